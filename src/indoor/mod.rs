//! Indoor texton localisation (indoor seed `indoor-texton-thesis.txt`, ch. 3): global x, y
//! over a known floor from a downward camera.
//!
//! - [`textons`]: texton dictionary and histograms (sec. 3.3.1-3.3.2).
//! - [`derotate`]: downscaling and, beyond the seed, derotation by the camera attitude.
//! - [`flow`]: beyond the seed, the vehicle's velocity from consecutive frames (visual
//!   odometry), for the particles' motion and the autopilot.
//! - [`knn`]: the k nearest training histograms (sec. 3.3.3).
//! - [`model`]: the trained model file.
//! - [`localizer`]: the per-frame loop around the particle filter
//!   ([`crate::filter::particle`], sec. 3.3.4, Algorithm 2) with a velocity motion model.
//! - [`landing`]: the landing trigger (sec. 4.7); simulated landing approaches that close
//!   the loop through it are [`crate::simulated::approach`].
//! - [`offline`]: `mavloc indoor train` and `mavloc indoor run` over datasets.
//! - [`eval`]: `mavloc eval indoor` (ch. 4's measures).
//! - [`mapeval`]: the global loss of a floor image's views (sec. 3.4); the views are
//!   rendered by [`crate::simulated::mapeval`] (`mavloc indoor map-eval`).

pub mod derotate;
pub mod eval;
pub mod flow;
pub mod knn;
pub mod labelling;
pub mod landing;
pub mod localizer;
pub mod mapeval;
pub mod model;
pub mod offline;
pub mod textons;
