//! mavloc's integration and end-to-end tests, in one binary: each file is a module, so
//! the OpenCV-linked test code is compiled and linked once, not once per file.
//!
//! * Pipelines on datasets: `area_pipeline`, `bearing_only`, `indoor_pipeline`,
//!   `indoor_labelling`,
//!   `sim_sift`, `mission_plans`, `import_photos`, `opencv_link`.
//! * The real binary: `cli` (commands, configuration errors); `realtime`, the tests that
//!   mostly wait on the wall clock, which `make test` runs in a process of its own beside
//!   the rest: `realtime::daemon_e2e` (the daemon over its links from pymavlink),
//!   `realtime::closed_loop` (live flights against the simulated vehicle),
//!   `realtime::systemd`.
//! * `twin`: the closed loop (vehicle, core, sim camera, live pipeline) in simulated time.
//! * Architecture: `layers` (which module may import which).
//!
//! Full-size runs are `#[ignore]`d here and run by `make check-long`.

mod area_pipeline;
mod bearing_only;
mod cli;
mod fixtures;
mod import_photos;
mod indoor_labelling;
mod indoor_pipeline;
mod install;
mod layers;
mod mission_plans;
mod opencv_link;
mod px4_replay;
mod realtime;
mod sim_sift;
mod twin;
