//! The typed configuration: every parameter of the daemon and both pipelines, with its
//! default. `config/mavloc.toml` documents the same keys one per line with units; a test
//! keeps the two in step.
//!
//! Defaults are the seeds' best values: area seed table 6.4 (band
//! 50 px, Mahalanobis 3.75, downscale 2), table 6.2 and eq. 5.6 (bearing noise 0.5 deg),
//! eq. 5.7 (UKF alpha 0.7, beta 2, kappa 0), sec. 5.4.1 (ratio test 0.5), sec. 5.2
//! (`10 L_max` features after the first frame); indoor seed sec. 3.3.1-3.3.4 and 4.7-4.8
//! (20 textons of 6x6 px, learning rate 0.02, 400 samples, landing radius and spread gate
//! 0.6 m). Where a seed leaves a value open (`L_max`, `T`, `k`), or where we measured
//! better (500 particles instead of the seed's 100; convergence 0.75 m instead of 0.5
//! since each sighting counts the position noise), the default is ours and
//! `config/mavloc.toml` says so.

use mavloc_geometry::GimbalChain;
use serde::{Deserialize, Serialize};

/// Everything mavloc can be configured with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Settings {
    pub daemon: Daemon,
    pub mavlink: Mavlink,
    pub camera: Camera,
    pub gimbal: Gimbal,
    pub area: Area,
    pub indoor: Indoor,
}

/// Which pipeline the daemon runs live.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PipelineKind {
    Area,
    Indoor,
    None,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Daemon {
    pub pipeline: PipelineKind,
    pub state_dir: String,
    pub log: String,
    pub max_frame_age_s: f64,
    /// The flight recorder's folder (`daemon::record`); empty = off.
    pub record: String,
    pub record_format: RecordFormat,
    /// Room the flight recorder leaves free on its disk (MB): below it, it stops, so the
    /// results and the state can still be written.
    pub record_reserve_mb: f64,
}

/// How the flight recorder stores frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RecordFormat {
    /// JPEG at quality 95: a fraction of PNG's size, and fast to encode.
    Jpg,
    /// Lossless PNG: a replay sees exactly the live pixels.
    Png,
}

impl Default for Daemon {
    fn default() -> Self {
        Daemon {
            pipeline: PipelineKind::Area,
            state_dir: "/var/lib/mavloc".into(),
            log: "info".into(),
            max_frame_age_s: 0.5,
            record: String::new(),
            record_format: RecordFormat::Jpg,
            record_reserve_mb: 256.0,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Mavlink {
    pub connection: String,
    pub system_id: u8,
    pub component_id: u8,
    pub autopilot_system_id: u8,
    pub gcs_system_id: u8,
    pub heartbeat_hz: f64,
    pub autopilot_timeout_s: f64,
    pub signing_key: String,
    pub accept_unsigned_telemetry: bool,
    /// PX4's event metadata (`all_events.json` from its build's `events/` folder): the
    /// autopilot's EVENTs (arming refusals) in words. Empty: a few known by heart.
    pub px4_events: String,
}

impl Default for Mavlink {
    fn default() -> Self {
        Mavlink {
            connection: "udpin:127.0.0.1:14540".into(),
            system_id: 0,
            component_id: 191,
            autopilot_system_id: 1,
            gcs_system_id: 255,
            heartbeat_hz: 1.0,
            autopilot_timeout_s: 3.0,
            px4_events: String::new(),
            signing_key: String::new(),
            accept_unsigned_telemetry: true,
        }
    }
}

/// Where frames come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraSource {
    V4l2,
    File,
    Dataset,
    Sim,
    None,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Camera {
    pub source: CameraSource,
    pub device: String,
    pub path: String,
    pub scenario: String,
    pub width: u32,
    pub height: u32,
    pub fps: f64,
    pub pixel_format: String,
    pub hfov_deg: f64,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Vec<f64>,
    /// `file` / `dataset`: true = at the recorded rate (frames the pipeline cannot keep up
    /// with are dropped), false = as fast as the pipeline takes them, none dropped.
    pub realtime: bool,
    /// `sim`: render from the received pose perturbed by the scenario's noise.
    pub sim_noise: bool,
    /// `sim`: the pose frames are rendered from.
    pub sim_pose: SimPose,
}

/// Where the sim camera takes its pose from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SimPose {
    /// The telemetry mavloc receives (perturbed by the scenario's noise with `sim_noise`):
    /// what the built-in vehicle's tests fly.
    Telemetry,
    /// The simulator's ground truth (HIL_STATE_QUATERNION, which PX4 SITL streams when
    /// asked): the camera sees where the vehicle *is*, not where its estimator believes it
    /// is, so mavloc cannot merely confirm the estimate. For PX4 SITL.
    Truth,
}

impl Default for Camera {
    fn default() -> Self {
        Camera {
            source: CameraSource::Sim,
            device: "/dev/video0".into(),
            path: String::new(),
            scenario: "coastline".into(),
            width: 1920,
            height: 1080,
            fps: 6.0,
            pixel_format: "MJPG".into(),
            hfov_deg: 90.0,
            fx: 0.0,
            fy: 0.0,
            cx: -1.0,
            cy: -1.0,
            distortion: vec![0.0; 5],
            realtime: true,
            sim_noise: true,
            sim_pose: SimPose::Telemetry,
        }
    }
}

impl Camera {
    /// Intrinsics from the explicit values, or from the field of view where they are
    /// left at their "derive" defaults (fx/fy 0, cx/cy -1).
    pub fn intrinsics(&self) -> mavloc_geometry::Intrinsics {
        let mut k =
            mavloc_geometry::Intrinsics::from_hfov(self.width, self.height, self.hfov_deg.to_radians());
        if self.fx > 0.0 {
            k.fx = self.fx;
        }
        if self.fy > 0.0 {
            k.fy = self.fy;
        } else if self.fx > 0.0 {
            k.fy = self.fx;
        }
        if self.cx >= 0.0 {
            k.cx = self.cx;
        }
        if self.cy >= 0.0 {
            k.cy = self.cy;
        }
        k
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Gimbal {
    pub chain: GimbalChain,
    pub aim: GimbalAim,
    pub use_telemetry: bool,
    pub mount_yaw_deg: f64,
    pub mount_pitch_deg: f64,
    pub mount_roll_deg: f64,
    pub yaw_offset_deg: f64,
    pub pitch_offset_deg: f64,
    pub roll_offset_deg: f64,
}

impl Default for Gimbal {
    fn default() -> Self {
        Gimbal {
            chain: GimbalChain::YawPitchRoll,
            aim: GimbalAim::Mission,
            use_telemetry: true,
            mount_yaw_deg: 0.0,
            mount_pitch_deg: -90.0,
            mount_roll_deg: 0.0,
            yaw_offset_deg: 0.0,
            pitch_offset_deg: 0.0,
            roll_offset_deg: 0.0,
        }
    }
}

/// Who points the gimbal.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GimbalAim {
    /// The mission's region-of-interest items or the gimbal's own pointing.
    Mission,
    /// mavloc takes gimbal-manager control and keeps the segmented border in view.
    Border,
}

/// Area localisation method.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AreaMethod {
    /// The seed's method: SIFT landmarks, one UKF each.
    Ukf,
    /// The seed's previous method (sec. 2.1): border pixels onto a ground plane.
    GroundPlane,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Area {
    pub method: AreaMethod,
    pub downscale: u32,
    pub band_px: u32,
    pub l_max: u32,
    pub turnover: u32,
    pub feature_factor: u32,
    pub ratio_test: f64,
    pub mahalanobis_max: f64,
    pub convergence_m: f64,
    pub min_observations: u32,
    pub bearing_noise_deg: f64,
    /// SD of the vehicle's reported position per frame, north, east, down (m): each
    /// sighting's noise and the convergence check's rays count it beside the bearing noise.
    pub position_noise_m: Vec<f64>,
    pub ukf_alpha: f64,
    pub ukf_beta: f64,
    pub ukf_kappa: f64,
    pub ukf_iterations: u32,
    pub init_sigma_m: f64,
    pub ground_down_m: f64,
    pub max_descriptors: u32,
    /// SD of the recorded attitude, degrees: the prior of the attitude refinement run
    /// after the landmark filters (`area::refine`): offline, and live after each
    /// touchdown (`daemon::flightlog`); 0 = no refinement.
    pub attitude_prior_deg: f64,
    /// Live, with `attitude_prior_deg > 0`: adjust the map in flight too, first once this
    /// many frames are logged, then each time the logged frames have doubled; the static
    /// gimbal offset each adjustment finds is applied to the frames after it. 0 = only
    /// after each touchdown and on command.
    pub adjust_first_frames: u32,
    /// SD of the recorded attitude, degrees, for aligning the photos to each other by
    /// their tie points before the landmark filters run (`area::align`); 0 = off.
    pub align_prior_deg: f64,
    /// SD of the recorded positions for the same alignment, metres (each photo's
    /// position shift is estimated with it); 0 = positions held as recorded.
    pub align_shift_m: f64,
    /// Bearing noise of the landmark filters once the alignment has reached at least half
    /// the photos (the others are left out), degrees: its poses fit thousands of tie
    /// points, the tags did not; 0 = the same as `bearing_noise_deg`.
    pub aligned_bearing_noise_deg: f64,
    /// Sightings a landmark needs once the alignment has reached at least half the photos;
    /// 0 = the same as `min_observations`.
    pub aligned_min_observations: u32,
    /// How features are matched to landmarks: `global` (the seed's, every feature of the
    /// frame) or `guided` (only inside each landmark's predicted gate).
    pub matching: AreaMatching,
    pub segmenter: Segmenter,
    pub hsv_low: Vec<f64>,
    pub hsv_high: Vec<f64>,
}

/// How a frame's features are matched to the landmarks (`area.matching`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AreaMatching {
    /// The seed's (sec. 5.4): every landmark against every feature of the frame.
    #[default]
    Global,
    /// Only inside the gate where each landmark's filter predicts it.
    Guided,
}

/// Where target masks come from (`area.segmenter`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Segmenter {
    /// The dataset's `masks/` (rendered or made elsewhere); the sim camera's own.
    Masks,
    /// Open water, by local smoothness and colour.
    Water,
    /// A box in HSV (`hsv_low` .. `hsv_high`).
    Hsv,
    /// Learned from the masks the user made for some frames (`mavloc area` only).
    Learned,
}

impl Default for Area {
    fn default() -> Self {
        Area {
            method: AreaMethod::Ukf,
            downscale: 2,
            band_px: 50,
            l_max: 400,
            turnover: 40,
            feature_factor: 10,
            ratio_test: 0.5,
            mahalanobis_max: 3.75,
            convergence_m: 0.75,
            min_observations: 3,
            bearing_noise_deg: 0.5,
            position_noise_m: vec![0.5, 0.5, 2.0],
            ukf_alpha: 0.7,
            ukf_beta: 2.0,
            ukf_kappa: 0.0,
            ukf_iterations: 1,
            init_sigma_m: 20.0,
            ground_down_m: 0.0,
            max_descriptors: 8,
            attitude_prior_deg: 0.0,
            adjust_first_frames: 0,
            align_prior_deg: 0.0,
            align_shift_m: 5.0,
            aligned_bearing_noise_deg: 0.0,
            aligned_min_observations: 0,
            matching: AreaMatching::Global,
            segmenter: Segmenter::Masks,
            hsv_low: vec![90.0, 60.0, 30.0],
            hsv_high: vec![130.0, 255.0, 255.0],
        }
    }
}

/// How the texton dictionary is learned.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DictionaryMethod {
    /// The seed's winner-take-all competitive learning (sec. 3.3.1).
    Competitive,
    KMeans,
}

/// Particle-filter motion model.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionModel {
    /// The seed's: Gaussian process noise only.
    Noise,
    /// Displacement from velocity (telemetry, else recent estimates) plus noise.
    Velocity,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Indoor {
    pub model: String,
    pub textons: u32,
    pub patch_w: u32,
    pub patch_h: u32,
    pub dictionary: DictionaryMethod,
    pub learning_rate: f64,
    pub samples: u32,
    pub work_width: u32,
    pub k: u32,
    pub particles: u32,
    pub motion_model: MotionModel,
    pub process_sigma_m: f64,
    pub velocity_sigma_m_s: f64,
    pub derotate: bool,
    pub normalise: bool,
    pub landing_enabled: bool,
    pub landing_x_m: f64,
    pub landing_y_m: f64,
    pub landing_radius_m: f64,
    pub landing_sigma_gate_m: f64,
    pub landing_frames: u32,
    /// Land on the zone's centre with the autopilot's precision landing (PX4: the
    /// zone streamed as LANDING_TARGET) rather than where the vehicle is when the
    /// trigger fires.
    pub landing_precision: bool,
    /// The autopilot has no other position source (no GPS): send vision estimates from
    /// power-on (the pad while standing), then the origin, so it can arm.
    pub gps_denied: bool,
    /// Frames taken lower than this above the floor (the downward rangefinder, else the
    /// autopilot's height) are not localised: the model never saw the floor that close.
    pub min_height_m: f64,
    /// Frames taken higher than this above the floor are not localised either: their view
    /// reaches past the floor the model knows, or sees it too coarsely. On the simulated
    /// floor (trained at 0.8-1.2 m, rescaled to 1 m) the fixes were 0.04 m RMS off from 1 to
    /// 3 m up, 0.09 m from 5 m, and 4.3 m (up to 7.2 m) from 9 m; PX4's precision landing,
    /// its landing target lost, climbs to 10 m to search (`PLD_SRCH_ALT`).
    pub max_height_m: f64,
    /// Frames are rescaled to the floor's scale as seen from this camera height (m), by
    /// the camera's height at each frame (0 = off). Set at training; runs take the
    /// model's.
    pub height_ref_m: f64,
    /// Where the vehicle stands before its first fix in the air, in the floor's frame.
    pub pad_x_m: f64,
    pub pad_y_m: f64,
    /// The WGS84 point of the floor's (0, 0): latitude, longitude (degrees), altitude
    /// (m), sent as SET_GPS_GLOBAL_ORIGIN when `gps_denied`. Empty: not set.
    pub origin: Vec<f64>,
}

impl Default for Indoor {
    fn default() -> Self {
        Indoor {
            model: String::new(),
            textons: 20,
            patch_w: 6,
            patch_h: 6,
            dictionary: DictionaryMethod::Competitive,
            learning_rate: 0.02,
            samples: 400,
            work_width: 320,
            k: 5,
            particles: 500,
            motion_model: MotionModel::Velocity,
            process_sigma_m: 0.0,
            velocity_sigma_m_s: 0.1,
            derotate: true,
            normalise: true,
            landing_enabled: false,
            landing_x_m: 0.0,
            landing_y_m: 0.0,
            landing_radius_m: 0.6,
            landing_sigma_gate_m: 0.6,
            landing_frames: 5,
            landing_precision: true,
            gps_denied: false,
            min_height_m: 0.5,
            max_height_m: 3.0,
            height_ref_m: 0.0,
            pad_x_m: 0.0,
            pad_y_m: 0.0,
            origin: Vec::new(),
        }
    }
}
