//! mavloc: a MAVLink companion-computer daemon that localises, from a drone's camera and
//! telemetry, the 3D border of an area (lake, fire, flood) and the vehicle's own x, y over
//! a known indoor floor.
//!
//! # Module map
//!
//! * [`geometry`] (crate `mavloc-geometry`, sources in `src/geometry/`): frames (WGS84,
//!   local NED, body, gimbal, camera), gimbal kinematic chains, pinhole camera, pixel <->
//!   bearing, the ground-plane projection (the area seed's previous method), geodesy.
//!   It is its own crate so the simulator (`sim/`) shares it without a dependency cycle.
//! * [`data`] (crate `mavloc-data`, sources in `data/`): the files: dataset format, result
//!   files, CSV tables and the one atomic writer. The simulator writes datasets through it,
//!   the pipelines and the importer read them through it.
//! * [`area`]: the area pipeline (seed 1): band, SIFT, landmark library with one UKF each,
//!   the ground-plane baseline, border-line fit, evaluation, dataset runner.
//! * [`indoor`]: the indoor pipeline (seed 2): textons, k-NN, particle filter, landing
//!   trigger, training and offline runs.
//! * [`output`]: result files (formats in [`data`]) and plots.
//! * [`filter`]: a generic unscented Kalman filter (const-generic dimensions, models as
//!   traits, numerically guarded), the static-landmark bearing model, and the 2D particle
//!   filter of the indoor pipeline.
//! * [`settings`]: the layered, validated configuration (`config/mavloc.toml`).
//! * [`lens`]: whether a lens distortion model can be undone over a whole image.
//! * [`link`]: the MAVLink side: addresses, framing, signing, parameters, transports.
//! * [`camera`]: frame sources (V4L2, file, dataset replay, the simulated camera).
//! * [`align`]: time alignment of frames with the autopilot's telemetry.
//! * [`daemon`]: `mavloc run`, wiring link -> alignment -> pipeline worker -> outputs.
//! * [`import`]: geotagged drone photos (EXIF, DJI XMP) to a dataset.
//! * [`demo`]: the end-to-end demonstration `make demo` runs (vehicle + daemon, live).
//! * [`simulated`]: pipelines run against the simulator (landing approaches, map
//!   evaluation from rendered views).
//! * [`imaging`]: OpenCV image helpers below the pipelines and the frame sources, and the
//!   one image reader (plain PNGs through [`data::pngfile`], the rest through OpenCV).
//! * [`logging`]: tracing set-up (plain lines for journald, colour on a terminal).
//! * [`cli`]: command-line definitions.
//! * [`commands`]: one module per subcommand, each a function from the parsed arguments
//!   to an exit code; `main.rs` only parses and dispatches to them.
//!
//! Data flows one way: sources (link, camera) -> time alignment -> pipeline -> outputs.
//! Pipelines are plain synchronous libraries with no tokio or MAVLink inside, and they do
//! not depend on the simulator: only `demo`, `simulated`, the sim camera
//! (`camera::sim`), the daemon's use of it and the `sim` commands (`commands::sim`) do
//! (`tests/layers.rs` checks this).

pub use mavloc_data as data;
pub use mavloc_geometry as geometry;

pub mod align;
pub mod area;
pub mod camera;
pub mod cli;
pub mod commands;
pub mod daemon;
pub mod demo;
pub mod filter;
pub mod imaging;
pub mod import;
pub mod indoor;
pub mod lens;
pub mod link;
pub mod logging;
pub mod output;
pub mod settings;
pub mod simulated;
