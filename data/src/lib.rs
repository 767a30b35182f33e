//! mavloc's files, as plain data: what the simulator and the importer write and the
//! pipelines, `mavloc eval` and the daemon read. No simulator, OpenCV, tokio or MAVLink
//! here, so every layer may depend on this crate (the layering test in `tests/layers.rs`
//! of the `mavloc` package checks it).
//!
//! # Module map
//!
//! * [`atomic`]: the one atomic file writer (temporary in the same folder, fsync, rename,
//!   fsync of the folder; the temporary removed on failure).
//! * [`table`]: CSV tables through the `csv` crate with serde: header checks, errors that
//!   name file and line, fixed-decimal number formats, append-and-flush tables.
//! * [`dataset`]: the dataset format (frames, masks, `telemetry.jsonl`, `camera.toml`,
//!   ground truth): its records, [`Dataset::open`] and the writers.
//! * [`pngfile`]: 8-bit PNG files written whole (frames, masks, plots) and read back.
//! * [`results`]: result files of the pipelines: landmarks (CSV, PLY, GeoJSON, KML),
//!   border lines, indoor trajectories and landing trials.
//! * [`sets`]: result folders replaced as a unit (`results/area` a symlink to the newest
//!   complete set of the run), one folder per daemon run, tidied after a crash.
//! * [`state`]: state files that do not parse are moved aside (`NAME.corrupt-<stamp>`);
//!   UTC stamps for names.
//! * [`truth`]: the simulated vehicle's true track (`truth.csv`).
//! * `testing` (tests and the `test-util` feature only): a real full disk for tests.

pub mod atomic;
pub mod dataset;
pub mod geoid;
pub mod pngfile;
pub mod results;
pub mod sets;
pub mod staged;
pub mod state;
pub mod table;
#[cfg(any(test, feature = "test-util"))]
pub mod testing;
pub mod truth;

pub use atomic::write_atomic;
pub use dataset::{Dataset, SETTINGS_FILE};
