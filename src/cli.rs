//! Command-line interface. Each subcommand's `--help` says what it does; those that later
//! work fills in say so when run instead of pretending.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// mavloc: localise an area's 3D border and a vehicle's indoor x, y from a drone's camera,
/// next to a PX4 autopilot over MAVLink.
#[derive(Debug, Parser)]
#[command(name = "mavloc", version, about, long_about = None, propagate_version = true)]
pub struct Cli {
    /// Configuration file (TOML). Default: /etc/mavloc/mavloc.toml if it exists, else the
    /// built-in defaults.
    #[arg(long, short = 'c', global = true, env = "MAVLOC_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,

    /// Override one configuration key, e.g. `--set area.l_max=300` (repeatable; wins over
    /// the file and MAVLOC_* variables).
    #[arg(long = "set", global = true, value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,

    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the daemon: MAVLink link, camera and the live pipeline (what systemd starts).
    Run(RunArgs),
    /// Run the end-to-end demonstration on simulated data and print a report.
    ///
    /// Exit status: 0 when the report says PASS, 2 when the demo ran to completion but the
    /// report says FAIL (an accuracy bar missed), 1 when it could not run (an error).
    Demo(DemoArgs),
    /// The simulated world: render datasets, run a simulated MAVLink vehicle.
    Sim {
        #[command(subcommand)]
        command: SimCommand,
    },
    /// Area pipeline offline: localise the 3D border of an area from a dataset.
    Area(AreaArgs),
    /// Indoor texton pipeline offline: train a model, run it, evaluate a floor texture.
    Indoor {
        #[command(subcommand)]
        command: IndoorCommand,
    },
    /// Evaluate results against a dataset's ground truth, as the seeds measure them.
    Eval {
        #[command(subcommand)]
        command: EvalCommand,
    },
    /// Check a configuration file or show the configuration in force.
    Config {
        #[command(subcommand)]
        command: ConfigCommand,
    },
    /// Values tuned over MAVLink (QGroundControl's parameter editor): list or reset them.
    Params {
        #[command(subcommand)]
        command: ParamsCommand,
    },
    /// Import real data into a dataset.
    Import {
        #[command(subcommand)]
        command: ImportCommand,
    },
    /// Estimate calibration constants from a flight.
    Calibrate {
        #[command(subcommand)]
        command: CalibrateCommand,
    },
}

#[derive(Debug, Subcommand)]
pub enum CalibrateCommand {
    /// The gimbal's static yaw, pitch and roll offsets (area seed sec. 6.11), by least
    /// squares over every sighting of the landmarks a dataset's flight converges on, or
    /// of a surveyed marker; prints them with their uncertainty and can write them into a
    /// configuration file.
    Gimbal(CalibrateGimbalArgs),
}

#[derive(Debug, Args)]
pub struct CalibrateGimbalArgs {
    /// Dataset folder of the flight (several lines or a turn help: along one straight line
    /// a roll offset is hard to tell from a sideways shift).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Folder for the area run the sightings come from (default: a temporary one).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// A surveyed marker's position, local NED metres of the dataset (north,east,down),
    /// with --marker-pixels: it anchors the estimate as the seed's reference marker does.
    #[arg(long, value_parser = parse_triple, allow_hyphen_values = true, value_name = "N,E,D", requires = "marker_pixels")]
    pub marker: Option<[f64; 3]>,
    /// CSV `frame,u,v`: where the marker is in each frame, full-resolution pixels.
    #[arg(long, requires = "marker")]
    pub marker_pixels: Option<PathBuf>,
    /// SD of the prior on each offset, degrees (it only keeps an unobservable one at 0).
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 10.0)]
    pub prior_deg: f64,
    /// The largest SD (degrees, over groups of frames) an offset may have to be reported as
    /// calibrated and written; above it the command exits 2 and writes nothing.
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 0.5)]
    pub max_sd_deg: f64,
    /// Write the offsets into this configuration file's [gimbal] section (other lines and
    /// comments kept).
    #[arg(long)]
    pub write: Option<PathBuf>,
}

#[derive(Debug, Subcommand)]
pub enum ImportCommand {
    /// Geotagged drone photos to a dataset: DJI (EXIF GPS, XMP gimbal and flight attitude),
    /// senseFly (XMP position and attitude, camera fixed to the airframe), Parrot (EXIF GPS,
    /// XMP gimbal attitude, --ground-alt-m) or plain EXIF GPS (camera fixed to the
    /// airframe, heading from the track, --ground-alt-m).
    Photos {
        /// Folder of JPEG photos.
        dir: PathBuf,
        /// Dataset folder to write.
        #[arg(long)]
        out: PathBuf,
        /// Intrinsics (TOML: fx, fy, cx, cy) instead of the estimate from the focal length.
        #[arg(long)]
        calibration: Option<PathBuf>,
        /// Replace a non-empty output folder whole (an edited mavloc.toml in it is kept).
        #[arg(long)]
        force: bool,
        /// A camera fixed to the airframe (senseFly photos): its yaw, pitch, roll relative
        /// to the body in degrees (default 0,-90,0: straight down, image top to the nose).
        #[arg(long, value_parser = parse_triple, allow_hyphen_values = true, value_name = "YAW,PITCH,ROLL")]
        mount_deg: Option<[f64; 3]>,
        /// The ground's altitude in the photos' altitude datum (m). Needed by photos with
        /// no height above take-off (plain EXIF GPS, Parrot XMP); for those with one (DJI,
        /// senseFly) it is the take-off's altitude, replacing the tags' absolute altitude
        /// (barometric on some DJI models). Photos with no attitude tags at all are taken
        /// as from a camera fixed to a level airframe heading along its track.
        #[arg(long, value_parser = ground_altitude, allow_hyphen_values = true, value_name = "METRES")]
        ground_alt_m: Option<f64>,
        /// What the photos' absolute altitudes are heights above: `ellipsoid` (WGS84; the
        /// default for DJI, whose AbsoluteAltitude is geodetic height) or `sea-level` (the
        /// default for the others, as EXIF defines GPSAltitude). The dataset's are above sea
        /// level (EGM96).
        #[arg(long, value_parser = altitude_datum, value_name = "ellipsoid|sea-level")]
        altitude_datum: Option<crate::import::AltitudeDatum>,
    },
}

fn altitude_datum(s: &str) -> Result<crate::import::AltitudeDatum, String> {
    match s {
        "ellipsoid" => Ok(crate::import::AltitudeDatum::Ellipsoid),
        "sea-level" => Ok(crate::import::AltitudeDatum::SeaLevel),
        _ => Err(format!("`{s}`: ellipsoid or sea-level")),
    }
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// MAVLink connection, overriding `mavlink.connection`: serial:DEV:BAUD,
    /// udpin:HOST:PORT, udpout:HOST:PORT, tcpin:HOST:PORT or tcpout:HOST:PORT.
    #[arg(long, value_name = "ADDRESS")]
    pub mavlink: Option<String>,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Output folder for results, plots and logs.
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Seconds of coastline flight before the vehicle lands.
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 90.0)]
    pub coast_s: f64,
    /// Longest indoor flight, seconds (mavloc's landing normally ends it sooner).
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 60.0)]
    pub indoor_s: f64,
    /// Views of the floor rendered to train the indoor model.
    #[arg(long, default_value_t = 1000)]
    pub views: usize,
}

#[derive(Debug, Subcommand)]
pub enum SimCommand {
    /// Render a synthetic dataset (frames, masks, telemetry, ground truth, QGC plan) from
    /// a scenario: coastline, cliff, indoor-floor, or a scenario file.
    Render(Box<RenderArgs>),
    /// Write a scenario's mission as a QGroundControl .plan file (stdout without --out).
    Plan {
        /// Scenario name (coastline, cliff, indoor-floor) or path to a scenario TOML file.
        #[arg(long)]
        scenario: String,
        /// The .plan file to write (default: print it).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Write a north-up orthophoto of a scenario's ground (PNG), centred on the origin:
    /// the orthomap for `mavloc indoor train --orthomap`, or a floor for `indoor map-eval`.
    Orthophoto {
        /// Scenario name (coastline, cliff, indoor-floor) or path to a scenario TOML file.
        #[arg(long)]
        scenario: String,
        /// The PNG file to write.
        #[arg(long)]
        out: PathBuf,
        /// Half the side of the square, metres.
        #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 4.0)]
        half_extent_m: f64,
        /// Ground size of one pixel, metres.
        #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 0.01)]
        metres_per_px: f64,
    },
    /// Run a simulated MAVLink vehicle (PX4-like autopilot with a gimbal) that flies a
    /// scenario's mission; what mavloc talks to when no PX4 is installed.
    Vehicle {
        /// Scenario whose mission the vehicle flies: coastline, cliff, indoor-floor, or a
        /// scenario TOML file.
        #[arg(long)]
        scenario: String,
        /// Where to talk: udpout:HOST:PORT (to mavloc, as PX4's onboard link) or udpin:HOST:PORT.
        #[arg(long, default_value = "udpout:127.0.0.1:14540")]
        mavlink: String,
        /// The vehicle's MAVLink system id (PX4's default is 1).
        #[arg(long, default_value_t = 1)]
        system_id: u8,
        /// Land after this many seconds of mission and exit once on the ground (default: fly until stopped).
        #[arg(long, value_parser = positive, allow_hyphen_values = true)]
        duration: Option<f64>,
        /// Start this many seconds into the mission.
        #[arg(long, value_parser = non_negative, allow_hyphen_values = true, default_value_t = 0.0)]
        start: f64,
        /// Write the true state (t, north, east, down, roll, pitch, yaw, phase) to this CSV at 10 Hz.
        #[arg(long)]
        truth_log: Option<PathBuf>,
    },
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Scenario name (coastline, cliff, indoor-floor) or path to a scenario TOML file.
    #[arg(long)]
    pub scenario: String,
    /// Output folder; must be empty or absent unless --force.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the world and the noise (default: the scenario's).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Render at most this many frames (default: one lap of the mission).
    #[arg(long, value_parser = frame_count)]
    pub frames: Option<usize>,
    /// Image width in pixels (default: the scenario's; the field of view is kept).
    #[arg(long, requires = "height")]
    pub width: Option<u32>,
    /// Image height in pixels.
    #[arg(long, requires = "width")]
    pub height: Option<u32>,
    /// Record the true pose as the measured one (no noise, offsets, lag or drops).
    #[arg(long, conflicts_with_all = ["gimbal_sd_deg", "position_sd_m", "gimbal_offset_deg", "gimbal_lag_s", "drop_rate", "gimbal_drift_deg"])]
    pub no_noise: bool,
    /// Gimbal yaw and pitch noise SD, degrees (seed table 6.2: 0.5).
    #[arg(long, value_parser = non_negative, allow_hyphen_values = true)]
    pub gimbal_sd_deg: Option<f64>,
    /// Position noise SD north,east,down in metres (seed table 6.2: 0.5,0.5,2).
    #[arg(long, value_parser = parse_sd_triple, allow_hyphen_values = true, value_name = "N,E,D")]
    pub position_sd_m: Option<[f64; 3]>,
    /// Static gimbal offsets yaw,pitch,roll in degrees (seed sec. 6.10).
    #[arg(long, value_parser = parse_triple, allow_hyphen_values = true, value_name = "YAW,PITCH,ROLL")]
    pub gimbal_offset_deg: Option<[f64; 3]>,
    /// Gimbal telemetry lags the frames by this many seconds (seed sec. 5.6.1).
    #[arg(long, value_parser = number, allow_hyphen_values = true)]
    pub gimbal_lag_s: Option<f64>,
    /// SD of a slowly varying gimbal error yaw,pitch,roll in degrees (an autopilot's
    /// attitude estimate wanders; PX4 SIH's heading: 3 SD).
    #[arg(long, value_parser = parse_sd_triple, allow_hyphen_values = true, value_name = "YAW,PITCH,ROLL")]
    pub gimbal_drift_deg: Option<[f64; 3]>,
    /// Correlation time of that error, seconds (default 20).
    #[arg(long, value_parser = positive, allow_hyphen_values = true, requires = "gimbal_drift_deg")]
    pub gimbal_drift_tau_s: Option<f64>,
    /// Fraction of frames dropped, 0..1.
    #[arg(long, value_parser = fraction, allow_hyphen_values = true)]
    pub drop_rate: Option<f64>,
    /// Render this many random labelled views instead of the flight (indoor-floor only;
    /// indoor seed sec. 3.4.2).
    #[arg(long)]
    pub views: Option<usize>,
    /// Brightness offset for every frame of the flight, grey levels.
    #[arg(long, value_parser = number, allow_hyphen_values = true)]
    pub brightness: Option<f64>,
    /// Contrast factor for every frame of the flight.
    #[arg(long, value_parser = non_negative, allow_hyphen_values = true)]
    pub contrast: Option<f64>,
    /// Box-blur kernel for every frame of the flight, pixels (odd).
    #[arg(long)]
    pub blur_px: Option<u32>,
    /// Take the frames and masks from this dataset, rendered from the same scenario, seed
    /// and size, and draw only the telemetry anew with this render's noise (a noise study
    /// renders its flight once).
    #[arg(long, value_name = "DATASET")]
    pub frames_from: Option<std::path::PathBuf>,
    /// Overwrite a non-empty output folder.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Args)]
pub struct AreaArgs {
    /// Dataset folder (the simulation-world format, see README); its own settings
    /// (DATASET/mavloc.toml, e.g. from `mavloc import photos`) go over the config file.
    #[arg(long)]
    pub dataset: PathBuf,
    /// Output folder: landmarks.csv, landmarks.ply, area.geojson, area.kml, border.csv,
    /// summary.json (and trace.csv with --trace).
    #[arg(long)]
    pub out: PathBuf,
    /// `ukf` (the seed's method) or `ground-plane` (the previous method, sec. 2.1);
    /// default: `area.method` of the configuration.
    #[arg(long, value_parser = ["ukf", "ground-plane"])]
    pub method: Option<String>,
    /// Write every landmark update, and each landmark's first sighting, to trace.csv (seed fig. 6.2).
    #[arg(long)]
    pub trace: bool,
    /// Process at most this many frames.
    #[arg(long, value_parser = frame_count)]
    pub frames: Option<usize>,
    /// Write contact sheets of every frame beside its target mask (check the segmenter):
    /// masks.png, or masks-01.png, masks-02.png, ... 12 frames to a page.
    #[arg(long)]
    pub debug_masks: bool,
}

#[derive(Debug, Subcommand)]
pub enum IndoorCommand {
    /// Train a texton model from a dataset of labelled frames (`mavloc sim render
    /// --scenario indoor-floor --views N`, or a flight with motion-capture positions).
    Train(IndoorTrainArgs),
    /// Run a trained model over a dataset's flight: trajectory.csv and summary.json.
    Run(IndoorRunArgs),
    /// Simulated landing approaches to random zones (closed loop: localiser, guidance on
    /// the estimate, landing trigger): landings.csv, read by `mavloc eval indoor`.
    Landings(LandingsArgs),
    /// Evaluate how well a floor image suits texton localisation: the global loss L(D)
    /// over synthetic views of it, and a heat map of the per-view loss.
    MapEval(MapEvalArgs),
}

#[derive(Debug, Args)]
pub struct IndoorTrainArgs {
    /// Dataset folder of training frames.
    #[arg(long)]
    pub dataset: PathBuf,
    /// The model file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Label frames by homography against this orthomap image (north up) instead of the
    /// dataset's positions (indoor seed sec. 3.2).
    #[arg(long, requires = "map_metres_per_px")]
    pub orthomap: Option<PathBuf>,
    /// The orthomap's scale, metres per pixel.
    #[arg(long, value_parser = positive, allow_hyphen_values = true)]
    pub map_metres_per_px: Option<f64>,
    /// North, east of the orthomap's top-left pixel, metres (default: map centred on the
    /// origin).
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true)]
    pub map_origin: Option<[f64; 2]>,
    /// Frames with fewer RANSAC inliers than this are rejected.
    #[arg(long, default_value_t = 25)]
    pub min_inliers: usize,
    /// Seed of the random numbers (same seed, same result).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Debug, Args)]
pub struct IndoorRunArgs {
    /// Dataset folder of the flight (frames and telemetry; ground truth if it has one).
    #[arg(long)]
    pub dataset: PathBuf,
    /// The model file from `mavloc indoor train`.
    #[arg(long)]
    pub model: PathBuf,
    /// Output folder: trajectory.csv and summary.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Process at most this many frames.
    #[arg(long, value_parser = frame_count)]
    pub frames: Option<usize>,
    /// Ignore the telemetry's velocity (the velocity model then fits one to its estimates).
    #[arg(long)]
    pub no_velocity: bool,
    /// Move the particles with the velocity the camera measures from consecutive frames
    /// (as the daemon does without GPS) instead of the telemetry's; summary.json gives its
    /// error against the dataset's true velocity.
    #[arg(long, conflicts_with = "no_velocity")]
    pub camera_velocity: bool,
    /// Seed of the random numbers (same seed, same result).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Debug, Args)]
pub struct LandingsArgs {
    /// A model trained on the indoor-floor scenario.
    #[arg(long)]
    pub model: PathBuf,
    /// Output folder (e.g. the one of `mavloc indoor run`, for `mavloc eval indoor`).
    #[arg(long)]
    pub out: PathBuf,
    /// Landing approaches to fly, each to its own random zone.
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    /// Give up a trial after this long, seconds.
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 60.0)]
    pub max_s: f64,
    /// Seed of the random numbers (same seed, same result).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Debug, Args)]
pub struct MapEvalArgs {
    /// The floor image (north up).
    #[arg(long)]
    pub map: PathBuf,
    /// Its scale, metres per pixel.
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 0.005)]
    pub metres_per_px: f64,
    /// Synthetic views to generate.
    #[arg(long, default_value_t = 400)]
    pub views: usize,
    /// Heat map PNG to write.
    #[arg(long, default_value = "map-eval.png")]
    pub out: PathBuf,
    /// SD of the ideal similarity, metres (sigma_x = sigma_y, sec. 3.4.1).
    #[arg(long, value_parser = positive, allow_hyphen_values = true, default_value_t = 0.5)]
    pub sigma_m: f64,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    /// Seed of the random numbers (same seed, same result).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Area results: distances of landmarks and border line to the ground-truth border
    /// (seed tables 6.3/6.5/6.6).
    Area {
        /// The dataset the result was computed from (its ground_truth.csv is used).
        #[arg(long)]
        dataset: PathBuf,
        /// The output folder of `mavloc area`.
        #[arg(long)]
        result: PathBuf,
        /// Print one JSON object instead of the table.
        #[arg(long)]
        json: bool,
    },
    /// Indoor results: x, y error against ground truth (indoor seed ch. 4), lag, frames/s,
    /// landings; writes trajectory.png.
    Indoor {
        /// The flight dataset the result was computed from.
        #[arg(long)]
        dataset: PathBuf,
        /// The output folder of `mavloc indoor run`.
        #[arg(long)]
        result: PathBuf,
        /// Print one JSON object instead of the table.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Debug, Subcommand)]
pub enum ConfigCommand {
    /// Validate a configuration file (with the MAVLOC_* environment and --set applied) and
    /// the files it names, as `run` would; exits 78 and lists every problem, all in one
    /// pass, if it cannot run.
    Check {
        /// The file to check (default: --config, else /etc/mavloc/mavloc.toml).
        file: Option<PathBuf>,
    },
    /// Print the configuration in force, each value a layer set marked with that layer (`# from ...`).
    Show,
}

#[derive(Debug, Subcommand)]
pub enum ParamsCommand {
    /// List the tuned values, their configuration keys and whether each is in force.
    List,
    /// Print the table of every parameter (name, configuration key, type, unit, range,
    /// default, meaning) in Markdown, as the README has it.
    Doc,
    /// Forget a tuned value (or all of them): the configuration's value applies again
    /// from mavloc's next start.
    Reset {
        /// The parameter (e.g. IND_LAND_R); all of them when left out.
        name: Option<String>,
    },
}

/// Parses `a,b` into two numbers.
fn parse_pair(s: &str) -> Result<[f64; 2], String> {
    numbers(s, number)
}

/// Parses `a,b,c` into three numbers.
fn parse_triple(s: &str) -> Result<[f64; 3], String> {
    numbers(s, number)
}

/// Parses `a,b,c` into three numbers of 0 or more (standard deviations).
fn parse_sd_triple(s: &str) -> Result<[f64; 3], String> {
    numbers(s, non_negative)
}

/// `N` comma-separated numbers, each checked by `each`.
fn numbers<const N: usize>(s: &str, each: fn(&str) -> Result<f64, String>) -> Result<[f64; N], String> {
    let v = s.split(',').map(|p| each(p.trim())).collect::<Result<Vec<f64>, String>>()?;
    let count = match N {
        2 => "two".to_string(),
        3 => "three".to_string(),
        n => n.to_string(),
    };
    <[f64; N]>::try_from(v).map_err(|v| format!("expected {count} comma-separated numbers, got {}", v.len()))
}

/// A finite number: Rust's parser also takes `nan` and `inf`, which would reach datasets
/// and reports as `null` (a NaN mount angle made a dataset mavloc itself could not read).
fn number(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("`{s}` is not a finite number")),
        Err(_) => Err(format!("`{s}` is not a number")),
    }
}

/// A finite number above 0 (a scale, a duration, a standard deviation that divides).
fn positive(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| if v > 0.0 { Ok(v) } else { Err(format!("`{s}` must be above 0")) })
}

/// A finite number of 0 or more (a standard deviation, a factor).
fn non_negative(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| if v >= 0.0 { Ok(v) } else { Err(format!("`{s}` must be 0 or more")) })
}

/// A ground's altitude, within what a geodetic altitude may be ([-12000, 100000] m): out
/// of it, every photo was refused in turn as if its own altitude were wrong.
fn ground_altitude(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| {
        if (-12000.0..=100000.0).contains(&v) {
            Ok(v)
        } else {
            Err(format!("`{s}` m is no altitude of a ground: it must lie in [-12000, 100000] m"))
        }
    })
}

/// A count of frames, at least 1: `--frames 0` made an empty dataset, and `area` then
/// said no two photos shared a tie point.
fn frame_count(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("`0`: at least 1 frame (leave the option out for all of them)".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("`{s}` is not a whole number of frames")),
    }
}

/// A fraction, 0 to 1.
fn fraction(s: &str) -> Result<f64, String> {
    number(s).and_then(|v| {
        if (0.0..=1.0).contains(&v) {
            Ok(v)
        } else {
            Err(format!("`{s}` must be between 0 and 1"))
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// `nan` and `inf` parse as f64 but are not values: refused by every number argument,
    /// as are negative SDs and scales.
    #[test]
    fn number_arguments_refuse_what_is_not_a_value() {
        let parse =
            |args: &[&str]| Cli::try_parse_from(args.iter().copied()).map(|_| ()).map_err(|e| e.to_string());
        let render = ["mavloc", "sim", "render", "--scenario", "coastline", "--out", "x"];
        assert!(parse(&[&render[..], &["--gimbal-offset-deg", "1,-2,0.5"]].concat()).is_ok());
        for (bad, says) in [
            (&["--gimbal-offset-deg", "nan,0,0"][..], "`nan` is not a finite number"),
            (&["--gimbal-sd-deg", "nan"], "`nan` is not a finite number"),
            (&["--gimbal-sd-deg=-1"], "`-1` must be 0 or more"),
            // Written with a space, a negative number was taken for an unknown option.
            (&["--gimbal-sd-deg", "-1"], "`-1` must be 0 or more"),
            (&["--position-sd-m", "0.5,inf,2"], "`inf` is not a finite number"),
            (&["--drop-rate", "1.5"], "`1.5` must be between 0 and 1"),
            (&["--frames", "0"], "`0`: at least 1 frame"),
        ] {
            let e = parse(&[&render[..], bad].concat()).unwrap_err();
            assert!(e.contains(says), "{bad:?}: {e}");
        }
        let e =
            parse(&["mavloc", "import", "photos", "d", "--out", "o", "--ground-alt-m", "1e9"]).unwrap_err();
        assert!(e.contains("no altitude of a ground"), "{e}");
        assert!(parse(&["mavloc", "import", "photos", "d", "--out", "o", "--ground-alt-m", "-12"]).is_ok());
        let e = parse(&["mavloc", "import", "photos", "d", "--out", "o", "--mount-deg", "nan,-90,0"])
            .unwrap_err();
        assert!(e.contains("not a finite number"), "{e}");
        let e = parse(&["mavloc", "indoor", "map-eval", "--map", "m.png", "--sigma-m", "0"]).unwrap_err();
        assert!(e.contains("must be above 0"), "{e}");
        let e = parse(&["mavloc", "calibrate", "gimbal", "--dataset", "d", "--prior-deg", "0"]).unwrap_err();
        assert!(e.contains("must be above 0"), "{e}");
    }

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    /// Every argument of every subcommand says what it is for in `--help`.
    #[test]
    fn every_argument_has_help_text() {
        fn walk(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
            for arg in cmd.get_arguments() {
                let id = arg.get_id().as_str();
                if id != "help" && id != "version" && arg.get_help().is_none() {
                    missing.push(format!("{path} --{id}"));
                }
            }
            for sub in cmd.get_subcommands() {
                if sub.get_about().is_none() {
                    missing.push(format!("{path} {} (no about)", sub.get_name()));
                }
                walk(sub, &format!("{path} {}", sub.get_name()), missing);
            }
        }
        let mut missing = Vec::new();
        walk(&Cli::command(), "mavloc", &mut missing);
        assert!(missing.is_empty(), "arguments without help text: {missing:?}");
    }

    #[test]
    fn triples_parse() {
        assert_eq!(parse_triple("0,2,-1.5").unwrap(), [0.0, 2.0, -1.5]);
        assert!(parse_triple("1,2").unwrap_err().contains("three"));
        assert!(parse_triple("1,x,2").unwrap_err().contains("`x`"));
        let cli = Cli::try_parse_from([
            "mavloc",
            "sim",
            "render",
            "--scenario",
            "cliff",
            "--out",
            "o",
            "--gimbal-offset-deg",
            "0,-2,0",
        ])
        .unwrap();
        match cli.command {
            Command::Sim { command: SimCommand::Render(r) } => {
                assert_eq!(r.gimbal_offset_deg, Some([0.0, -2.0, 0.0]))
            }
            _ => panic!("wrong command"),
        }
    }
}
