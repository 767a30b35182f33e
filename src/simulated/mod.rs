//! Experiments that run a pipeline against the simulator: the sim-facing layer beside
//! [`crate::demo`], so the pipelines themselves (`area`, `indoor`) never depend on the
//! simulator.
//!
//! * [`approach`]: simulated landing approaches (`mavloc indoor landings`).
//! * [`mapeval`]: map evaluation from rendered views of a floor image (`mavloc indoor
//!   map-eval`).
//! * [`surface`]: the true ground of a rendered dataset (`mavloc eval area`).

pub mod approach;
pub mod mapeval;
pub mod surface;
