//! The daemon's MAVLink logic without sockets, tasks or clocks (sans-I/O, in the manner
//! of quinn-proto and rustls): [`Input`]s in, messages and [`Action`]s out, time passed
//! in as [`Mono`]. The async shell ([`super::run`]) stamps inputs, drains the outputs
//! and sleeps until [`Core::poll_timeout`]; tests drive the same core in simulated time.
//!
//! One small module per concern, none referencing another; `Core::handle` routes and
//! forwards their notices (an autopilot reboot resets streams, timesync and gimbal):
//!
//! * [`autopilot`]: found, lost, armed, landed state.
//! * [`telemetry`]: attitude, position, gimbal, home, into the time aligner; reboots.
//! * [`streams`]: SET_MESSAGE_INTERVAL requests, one in flight.
//! * [`params`]: paced PARAM_VALUE output (lists, reads, set answers).
//! * [`commands`]: inbound COMMAND_LONG decisions and the final ACKs owed.
//! * [`timesync`]: TIMESYNC both ways.
//! * [`gimbal`]: gimbal-manager control shared with other controllers, rate-limited setpoints.
//! * [`landing`]: MAV_CMD_NAV_LAND (or PX4's precision landing on the zone) until
//!   acknowledged.
//! * [`gpsdenied`]: with no GPS, vision estimates from power-on and then the origin.
//! * [`events`]: the autopilot's EVENT messages (PX4's refusals) in words.
//! * [`framewatch`]: frames that stop in flight without the camera saying so.
//! * [`health`]: heartbeat, once-a-second report, watchdog.
//! * [`notes`]: STATUSTEXT, chunked and bounded.
//!
//! Output priority ([`Core::poll_transmit`]): ACKs and replies, heartbeat, status texts,
//! pipeline results, stream requests, timesync, landing, gimbal, parameters last.

pub mod autopilot;
pub mod commands;
pub mod events;
pub mod framewatch;
pub mod ftp;
pub mod gimbal;
pub mod gpsdenied;
pub mod health;
pub mod landing;
pub mod notes;
pub mod params;
pub mod streams;
pub mod telemetry;
pub mod time;
pub mod timesync;
pub mod waiting;

#[cfg(test)]
mod sim;
#[cfg(test)]
mod tests;

use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use mavlink::dialects::common::*;

use self::autopilot::{ApNotice, Autopilot};
use self::commands::{Decision, Owed, PipelineRequest};
use self::events::EventLog;
use self::gimbal::Gimbal;
use self::gpsdenied::GpsDenied;
use self::health::Health;
use self::landing::{Landing, LandingNotice};
use self::notes::{Notes, SenderLimit};

/// A sender not allowed to command mavloc is told DENIED at most this many times per
/// period (a ground station retries a command a few times), and all such senders together
/// at most `STRANGER_ACKS_ALL` times; the rest are counted in `commands_refused`.
const STRANGER_ACK_PERIOD: Duration = Duration::from_secs(1);
const STRANGER_ACKS_EACH: u32 = 5;
const STRANGER_ACKS_ALL: u32 = 20;
use self::params::ParamPacer;
use self::streams::Streams;
use self::telemetry::Telemetry;
use self::timesync::TimeSync;
use crate::align::Aligner;
use crate::geometry::Geodetic;
use crate::link::codec::{Auth, Frame};
use crate::link::params::{self as param_table, SetError, Wire};
use crate::link::transport::Outgoing;
use crate::settings::{GimbalAim, PipelineKind, Settings};

pub use self::commands::{CMD_PIPELINE, CMD_SNAPSHOT};
pub use self::streams::STREAMS;
pub use self::time::Mono;

/// ACTIVE needs a processed frame at least this recently.
const ACTIVE_WITHIN: Duration = Duration::from_secs(3);

/// Replies and pipeline results waiting to go out are bounded; past this the oldest
/// pipeline result is dropped (a newer estimate supersedes it), never an ACK.
const QUEUE_CAP: usize = 256;

/// What a pipeline reports after a frame, for the daemon to publish.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Report {
    /// Live counters, sent as NAMED_VALUE_FLOAT (names at most 10 characters).
    pub counters: Vec<(&'static str, f32)>,
    /// Newly converged area landmarks: local NED positions.
    pub new_landmarks: Vec<[f64; 3]>,
    /// The indoor estimate: x, y (local NED north, east), their covariance, time.
    pub position: Option<PositionEstimate>,
    /// The vehicle's velocity from the camera (indoor, [`crate::indoor::flow`]).
    pub velocity: Option<VelocityEstimate>,
    /// Too low to localise: where the particles, carried on the camera's velocity, put the
    /// vehicle. Not sent as a measurement; it is where the vehicle stands if it lands now.
    pub coasted: Option<PositionEstimate>,
    /// Human-readable events (STATUSTEXT, INFO).
    pub events: Vec<String>,
    /// What the ground should not miss (STATUSTEXT, WARNING; WARN in the log).
    pub warnings: Vec<Warning>,
    /// The landing trigger fired on this frame.
    pub landing_requested: bool,
    /// Where to point the camera to keep the target's border in view: earth-frame yaw and
    /// pitch, radians (area pipeline).
    pub aim: Option<(f64, f64)>,
    /// The frame went through the pipeline (false: skipped, e.g. no target mask or an
    /// unusable image). Only processed frames make the daemon ACTIVE.
    pub processed: bool,
}

/// A [`Report`]'s warning.
#[derive(Clone, Debug, PartialEq)]
pub enum Warning {
    /// A result write failed (a full disk, a read-only state folder): counted in
    /// [`Counters::result_writes_failed`], said at most every 10 s.
    WriteFailed(String),
    Other(String),
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PositionEstimate {
    pub autopilot_time: f64,
    pub north: f64,
    pub east: f64,
    pub down: f64,
    /// Covariance of (north, east), m^2.
    pub cov: [[f64; 2]; 2],
}

/// A velocity measured by the camera, in the body's front-right-down axes (m/s), and
/// the variance of each component. In body axes the autopilot's heading does not enter
/// the measurement (the camera sees the floor move past the body), so the autopilot can
/// correct its heading with it; in the local frame it would carry that heading's error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VelocityEstimate {
    pub body: [f64; 3],
    pub var: [f64; 3],
}

impl VelocityEstimate {
    /// Not measured on this frame: zero with a variance the autopilot weighs at nothing,
    /// sent rather than nothing so that its velocity fusion does not stop and restart.
    pub const UNMEASURED: VelocityEstimate =
        VelocityEstimate { body: [0.0; 3], var: [UNMEASURED_VARIANCE as f64; 3] };
    /// Standing on the floor: still, to a few centimetres a second.
    pub const STANDING: VelocityEstimate = VelocityEstimate { body: [0.0; 3], var: [0.05 * 0.05; 3] };
}

/// What happened on the pipeline worker. (A report is moved once per frame, 15 times a
/// second: boxing it to make the enum smaller would buy nothing.)
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
pub enum PipelineEvent {
    /// A frame's results; `capture` is the local capture time (seconds), `attitude` the
    /// vehicle's roll, pitch, yaw at capture.
    Report {
        capture: f64,
        attitude: (f64, f64, f64),
        report: Report,
    },
    /// The pipeline panicked, on a frame or outside one (`None`: after a landing), and
    /// was rebuilt.
    Panicked {
        frame: Option<u64>,
        message: String,
    },
    Failed(String),
    /// Writing the results failed outside a frame (when the pipeline stopped).
    WriteFailed(String),
    /// Something the pipeline did outside a frame (the map adjusted after landing).
    Note(String),
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CameraEvent {
    Up(String),
    Down {
        why: String,
        fatal: bool,
    },
    Ended(String),
    /// Frames the camera skipped as unusable so far (the new total).
    Unreadable(u64),
}

/// Counters the shell keeps (link and frame queues), handed in once a second.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ShellStats {
    /// Whether the link is open (a serial device present, a socket bound or connected).
    pub link_up: bool,
    pub link_in: u64,
    pub link_bad_frames: u64,
    /// Of the bad frames, those whose signature did not check.
    pub link_bad_signatures: u64,
    pub link_garbage_bytes: u64,
    pub frames_dropped: u64,
}

/// One input to the core, stamped with mavloc's clock.
#[derive(Debug)]
pub enum Input {
    /// A checked frame from the link, stamped on arrival by the reader.
    Mav {
        rx: Mono,
        frame: Frame,
    },
    Pipeline {
        now: Mono,
        event: PipelineEvent,
    },
    Camera {
        now: Mono,
        event: CameraEvent,
    },
    /// The shell finished work the core asked for under `token`.
    Done {
        now: Mono,
        token: u64,
        result: Result<(), String>,
    },
    Stats {
        now: Mono,
        stats: ShellStats,
    },
    /// The area pipeline's current result set (file names and contents), served over
    /// MAVLink FTP under `/mavloc/results/area/`; the shell reads each new set once.
    AreaResults {
        now: Mono,
        files: Vec<(String, Vec<u8>)>,
    },
}

/// Work for the pipeline worker.
#[derive(Clone, Debug, PartialEq)]
pub enum WorkerRequest {
    /// Start this pipeline (unless it already runs); answer `Done` with the token.
    Start {
        kind: PipelineKind,
        token: u64,
    },
    Stop,
    /// Results moved aside, the same pipeline started empty.
    Reset,
    /// Settings changed over MAVLink; hand them to the running pipeline.
    Apply(Box<Settings>),
    /// Adjust the area map now: at a touchdown ("landed") or asked by a command
    /// ("asked to").
    AdjustMap(&'static str),
}

/// Something the shell must do besides sending messages.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    Worker(WorkerRequest),
    /// Write status and results now; answer `Done` with the token.
    Snapshot {
        token: u64,
    },
    /// Persist the tuned parameters (`params.json`); answer `Done` with the token.
    SaveParams {
        token: u64,
        json: String,
    },
    /// Once a second: hand in [`ShellStats`] and rewrite `status.json`.
    Report,
    /// systemd's watchdog ping: the core's loop is alive.
    Watchdog,
}

/// Pipeline state as the daemon sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PipelineState {
    Stopped,
    Starting(PipelineKind),
    Running(PipelineKind),
    Failed(PipelineKind),
}

/// Where the area pipeline's current result set is served over MAVLink FTP.
pub const AREA_RESULTS_FTP: &str = "/mavloc/results/area";

/// Counters reported to the ground and in `status.json`.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Counters {
    pub frames_processed: u64,
    /// Frames the pipeline was given but skipped (see [`Report::processed`]).
    pub frames_skipped: u64,
    pub frames_dropped: u64,
    /// Frames the camera source could not use (an unreadable or wrong-size file of a
    /// folder or dataset), each named in the log.
    pub frames_unreadable: u64,
    pub pipeline_panics: u64,
    pub commands_refused: u64,
    pub params_refused: u64,
    pub autopilot_reboots: u64,
    /// Parameter list and read requests refused (untrusted sender).
    pub param_requests_refused: u64,
    /// Log lines and STATUSTEXTs on a peer's behalf left out by the per-sender limit.
    pub peer_lines_suppressed: u64,
    /// Autopilot telemetry dropped for a stamp far ahead of its clock.
    pub telemetry_from_the_future: u64,
    /// The autopilot's attitude and position messages dropped for a NaN or infinite value.
    pub telemetry_not_finite: u64,
    /// Backwards steps of the autopilot's clock that its old timeline then disproved
    /// (a spoofed or garbled reboot; see `telemetry`).
    pub reboot_claims_rejected: u64,
    /// `gimbal.aim = "border"`: median angle between where mavloc pointed the gimbal and
    /// where the gimbal reports it looks, over the last minute of reports (degrees).
    pub gimbal_error_median_deg: Option<f64>,
    /// The same over every report while the vehicle was airborne since the start.
    pub gimbal_error_flight_median_deg: Option<f64>,
    pub statustext_dropped: u64,
    pub results_dropped: u64,
    /// Result writes that failed: checkpoints, snapshots, the write at stop. The results
    /// on disk are then older than the pipeline's.
    pub result_writes_failed: u64,
    /// `indoor.gps_denied`: estimates sent for the vehicle standing on the ground.
    pub standing_estimates_sent: u64,
    /// `indoor.gps_denied`: estimates holding the height while the camera's frames
    /// stopped in flight.
    pub held_estimates_sent: u64,
    /// EVENT messages from the autopilot (PX4's arming refusals and health reports).
    pub autopilot_events: u64,
    /// The autopilot's TIMESYNC requests answered. PX4 v1.16 maps mavloc's timestamps
    /// onto its clock only after 500 low-latency exchanges (its CONVERGENCE_WINDOW; at its
    /// 10 Hz, about 50 s); before that it stamps vision estimates on arrival.
    pub timesync_answered: u64,
    /// Median time from a frame's capture to its estimate going out, over the last 100
    /// estimates (ms): the delay EKF2 sees while it stamps on arrival (EKF2_EV_DELAY).
    pub vision_latency_median_ms: Option<f64>,
}

/// A failing result write is said at most this often (a full disk fails every write):
/// the rest are counted, and the next warning says how many.
const WRITE_WARNING_PERIOD: Duration = Duration::from_secs(10);

/// How often tuned parameters that could not be saved are saved again.
const PARAMS_RETRY: Duration = Duration::from_secs(10);
/// How often a second clock speaking as the autopilot is said (see `warn_of_a_second_clock`).
const CLASH_WARN_EVERY: Duration = Duration::from_secs(60);
/// Disproved reboot claims and stamps from the future that make a second clock worth
/// saying (see `warn_of_a_second_clock`).
const CLASH_MIN: u64 = 3;

/// The sim camera renders from the simulator's ground truth: ask for it.
/// The origin mavloc gives an autopilot with no GPS (`indoor.gps_denied`).
fn gps_origin(s: &Settings) -> Option<Geodetic> {
    match s.indoor.origin.as_slice() {
        [lat, lon, alt] if s.indoor.gps_denied => Some(Geodetic::new(*lat, *lon, *alt)),
        _ => None,
    }
}

fn wants_truth(s: &Settings) -> bool {
    s.camera.source == crate::settings::CameraSource::Sim
        && s.camera.sim_pose == crate::settings::SimPose::Truth
}

/// Why the shell owes a `Done`.
#[derive(Debug)]
enum Job {
    Start { kind: PipelineKind, requester: Option<(MavCmd, (u8, u8))> },
    Snapshot { ack_token: u64 },
    SaveParams { name: String },
}

pub struct Core {
    settings: Settings,
    /// Why no autopilot yet, said once the wait is long.
    waiting: waiting::Waiting,
    tuned: BTreeMap<String, f64>,
    /// Tuned parameters whose last save failed (a full disk): failed tries since the last
    /// good save, and when the next try is due. They are saved again until one succeeds
    /// (a value set on a full disk was lost at the next start even after space came back).
    params_unsaved: (u32, Mono),
    system_id: u8,
    component_id: u8,
    signing: bool,
    autopilot: Autopilot,
    telemetry: Telemetry,
    streams: Streams,
    timesync: TimeSync,
    params: ParamPacer,
    /// MAVLink FTP with the component metadata files; `metadata_general` is general.json.
    ftp: ftp::FtpServer,
    metadata_general: Vec<u8>,
    gimbal: Gimbal,
    landing: Landing,
    gps: GpsDenied,
    events: EventLog,
    /// The autopilot's pre-arm checks pass (SYS_STATUS), once it said.
    prearm_ok: Option<bool>,
    /// Capture-to-send delays of the last estimates (ms).
    latencies: VecDeque<f64>,
    health: Health,
    notes: Notes,
    /// Lines written on a peer's behalf, rate-limited per sender.
    peer_lines: SenderLimit,
    /// DENIED answers to commands from senders not allowed to command mavloc: each goes
    /// to every peer, so a stranger's flood would otherwise be reflected at the
    /// autopilot's link at its own rate (the audit's 5,000 commands got 5,000 answers).
    stranger_acks: SenderLimit,
    owed: Owed,
    jobs: BTreeMap<u64, Job>,
    next_job: u64,
    /// ACKs and direct replies.
    /// With the raw command id of an ACK to a command the dialect does not define.
    replies: VecDeque<(MavMessage, Option<u16>)>,
    /// Pipeline results (landmarks, position estimates, counters).
    results: VecDeque<MavMessage>,
    actions: VecDeque<Action>,
    heartbeat_requested: bool,
    pipeline: PipelineState,
    camera_live: bool,
    /// When the pipeline last processed a frame.
    last_processed: Option<Mono>,
    /// When the last vision message (ODOMETRY, VISION_POSITION_ESTIMATE) went out, and
    /// whether it carried a position and a velocity.
    last_vision_sent: Option<(Mono, bool, bool)>,
    /// When the pipeline last sent the autopilot anything of its own (an estimate, a
    /// velocity), or started: without GPS, a silence in flight is held ([`Core::holding`]).
    pipeline_vision_at: Option<Mono>,
    frame_watch: framewatch::FrameWatch,
    /// The newest time an input or timeout carried.
    now: Mono,
    counters: Counters,
    /// When a failed result write was last said, and how many failed since unsaid.
    write_warned: Option<Mono>,
    writes_failed_unsaid: u64,
    /// When a second clock speaking as the autopilot was last said, and the counts
    /// (reboot claims disproved, stamps from the future) already said.
    clash_warned: Option<Mono>,
    clash_said: (u64, u64),
    /// When the first of the counts not yet said came.
    clash_first: Option<Mono>,
    /// The downward rangefinder's reading the last time the vehicle stood (m): the
    /// floor, from where "off the floor" counts.
    ground_range: f64,
}

impl Core {
    /// `tuned` are the values already applied to `settings` from `params.json`;
    /// `watchdog` is systemd's ping period when its watchdog is on.
    pub fn new(
        settings: Settings,
        tuned: BTreeMap<String, f64>,
        signing: bool,
        watchdog: Option<Duration>,
    ) -> Core {
        let m = &settings.mavlink;
        let system_id = if m.system_id == 0 { m.autopilot_system_id } else { m.system_id };
        let metadata_files = crate::link::metadata::files(m.component_id);
        let mut core = Core {
            component_id: m.component_id,
            system_id,
            signing,
            autopilot: Autopilot::new(Duration::from_secs_f64(m.autopilot_timeout_s)),
            waiting: waiting::Waiting::default(),
            telemetry: Telemetry::new(&settings),
            streams: Streams::new(wants_truth(&settings)),
            timesync: TimeSync::default(),
            params: ParamPacer::new(param_table::PARAMS.len()),
            ftp: ftp::FtpServer::new(metadata_files.clone()),
            metadata_general: metadata_files[crate::link::metadata::GENERAL_PATH].clone(),
            gimbal: Gimbal::default(),
            landing: Landing::default(),
            gps: GpsDenied::new(gps_origin(&settings), (settings.indoor.pad_x_m, settings.indoor.pad_y_m)),
            events: EventLog::default(),
            prearm_ok: None,
            ground_range: 0.0,
            latencies: VecDeque::new(),
            health: Health::new(m.heartbeat_hz, watchdog),
            notes: Notes::default(),
            peer_lines: SenderLimit::default(),
            stranger_acks: SenderLimit::new(STRANGER_ACK_PERIOD, STRANGER_ACKS_EACH, STRANGER_ACKS_ALL),
            owed: Owed::default(),
            jobs: BTreeMap::new(),
            next_job: 0,
            replies: VecDeque::new(),
            results: VecDeque::new(),
            actions: VecDeque::new(),
            heartbeat_requested: false,
            pipeline: PipelineState::Stopped,
            camera_live: false,
            last_processed: None,
            last_vision_sent: None,
            pipeline_vision_at: None,
            frame_watch: Default::default(),
            now: Mono::ZERO,
            counters: Counters::default(),
            write_warned: None,
            writes_failed_unsaid: 0,
            clash_warned: None,
            clash_said: (0, 0),
            clash_first: None,
            tuned,
            params_unsaved: (0, Mono::ZERO),
            settings,
        };
        // Start the configured pipeline, as a drone would at boot.
        if core.settings.daemon.pipeline != PipelineKind::None {
            core.start_pipeline(core.settings.daemon.pipeline, None);
        }
        core
    }

    // ---- getters ----

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    pub fn system_id(&self) -> u8 {
        self.system_id
    }

    pub fn component_id(&self) -> u8 {
        self.component_id
    }

    /// Why no autopilot yet, in short, while the link has been up for the wait (see
    /// [`waiting`]).
    pub fn autopilot_missing(&self) -> Option<&'static str> {
        self.waiting.note()
    }

    pub fn autopilot_found(&self) -> bool {
        self.autopilot.present()
    }

    pub fn autopilot(&self) -> &Autopilot {
        &self.autopilot
    }

    pub fn aligner(&self) -> &Aligner {
        &self.telemetry.aligner
    }

    /// Local time `local` (s) on the autopilot's clock as mavloc tracks it, in
    /// microseconds: the stamp of what the autopilot fuses (vision estimates, the landing
    /// target), on the clock the answers to its TIMESYNC requests carry (the same
    /// `to_autopilot`, in nanoseconds, in `TimeSync::on_timesync`). PX4 maps such stamps onto its
    /// clock with a filtered offset (Timesync.cpp: exponential smoothing with a slow
    /// skew term); stamped on mavloc's own clock, that offset drifts with the two clocks'
    /// rates, and against PX4 v1.16 SIH, whose lockstep clock ran 1.2-2.5 % slower than
    /// the wall clock, the filter lagged the observed offset by 40-78 ms in flight: EKF2
    /// took each vision estimate for one made that much later. On the autopilot's clock
    /// the offset PX4 observes stays near zero whatever the rates, and mavloc's clock
    /// model (`align::ClockSync`) follows the rate. Before any telemetry, mavloc's own:
    /// harmless with PX4, which takes a companion's stamps only once its TIMESYNC filter
    /// has converged (`Timesync::sync_stamp`; until then it stamps on arrival), and mavloc
    /// answers its requests only once it knows the autopilot's clock.
    fn autopilot_usec(&self, local: f64) -> u64 {
        let t = self.telemetry.aligner.clock.to_autopilot(local).unwrap_or(local);
        (t.max(0.0) * 1e6) as u64
    }

    /// `gimbal.aim = "border"`: the median angle between mavloc's setpoints and the
    /// gimbal's reports over the last minute (degrees).
    pub fn gimbal_error_median_deg(&self) -> Option<f64> {
        self.gimbal.median_error_deg()
    }

    /// The newest ground truth from the simulator (HIL_STATE_QUATERNION) and its arrival.
    pub fn truth(&self) -> Option<&(Mono, HIL_STATE_QUATERNION_DATA)> {
        self.telemetry.truth.as_ref()
    }

    /// The WGS84 origin of the autopilot's local frame, once HOME_POSITION arrived.
    pub fn origin(&self) -> Option<Geodetic> {
        self.telemetry.origin()
    }

    pub fn pipeline(&self) -> PipelineState {
        self.pipeline
    }

    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    pub fn streams(&self) -> &Streams {
        &self.streams
    }

    pub fn gimbal(&self) -> &Gimbal {
        &self.gimbal
    }

    #[cfg(test)]
    pub fn telemetry(&self) -> &Telemetry {
        &self.telemetry
    }

    /// Whether mavloc points the gimbal now: not without `gimbal.aim = "border"` or an
    /// autopilot, and not while the vehicle lands (the camera is levelled for the
    /// touchdown, as PX4's RTL and land modes do, and let go).
    fn gimbal_aim(&self) -> gimbal::Aim {
        if self.settings.gimbal.aim != GimbalAim::Border || !self.autopilot.present() {
            gimbal::Aim::Off
        } else if self.autopilot.landed_state() == Some(MavLandedState::MAV_LANDED_STATE_LANDING) {
            gimbal::Aim::Landing
        } else {
            gimbal::Aim::On
        }
    }

    /// The daemon stops: let go of the gimbal if mavloc holds it (sent by the next
    /// `poll_transmit`), so the ground station can point it without taking it first.
    pub fn shutting_down(&mut self) {
        self.gimbal.let_go();
    }

    pub fn set_event_metadata(&mut self, m: events::EventMetadata) {
        self.events.set_metadata(m);
    }

    pub fn gps_denied(&self) -> &GpsDenied {
        &self.gps
    }

    /// The newest EVENTs from the autopilot, in words where its metadata is at hand.
    pub fn autopilot_events(&self) -> &EventLog {
        &self.events
    }

    /// The autopilot's pre-arm checks (SYS_STATUS): None until it said.
    pub fn prearm_ok(&self) -> Option<bool> {
        self.prearm_ok
    }

    pub fn landing(&self) -> &Landing {
        &self.landing
    }

    pub fn tuned(&self) -> &BTreeMap<String, f64> {
        &self.tuned
    }

    /// PARAM_VALUEs owed but held back by pacing.
    pub fn params_queued(&self) -> usize {
        self.params.queued()
    }

    /// Final command ACKs owed.
    pub fn acks_owed(&self) -> usize {
        self.owed.len()
    }

    /// Live frames are not processed while the vehicle is on the ground: a downward
    /// camera sees the floor up close, and a landed vehicle needs no position from vision.
    pub fn on_ground(&self) -> bool {
        self.autopilot.on_ground()
    }

    /// MAV_STATE reflecting reality: ACTIVE only while a pipeline runs with camera and
    /// telemetry and has processed a frame within the last 3 s; STANDBY while idle,
    /// waiting or skipping every frame; CRITICAL when the pipeline failed.
    pub fn mav_state(&self) -> MavState {
        let producing = self.last_processed.is_some_and(|t| self.now.saturating_sub(t) <= ACTIVE_WITHIN);
        match self.pipeline {
            PipelineState::Failed(_) => MavState::MAV_STATE_CRITICAL,
            PipelineState::Running(_)
                if self.autopilot.present()
                    && self.camera_live
                    && producing
                    && self.telemetry.aligner.clock.offset().0.is_some() =>
            {
                MavState::MAV_STATE_ACTIVE
            }
            _ => MavState::MAV_STATE_STANDBY,
        }
    }

    // ---- inputs ----

    pub fn handle(&mut self, input: Input) {
        self.handle_input(input);
        self.update_gps_phase();
    }

    fn handle_input(&mut self, input: Input) {
        let at = match &input {
            Input::Mav { rx, .. } => *rx,
            Input::Pipeline { now, .. }
            | Input::Camera { now, .. }
            | Input::Done { now, .. }
            | Input::Stats { now, .. }
            | Input::AreaResults { now, .. } => *now,
        };
        self.now = self.now.max(at);
        match input {
            Input::Mav { rx, frame } => self.on_frame(rx, frame),
            Input::Pipeline { now, event } => self.on_pipeline(now, event),
            Input::Camera { event, .. } => self.on_camera(event),
            Input::Done { token, result, .. } => self.on_done(token, result),
            Input::Stats { now, stats } => self.on_stats(now, stats),
            Input::AreaResults { files, .. } => self.ftp.publish(AREA_RESULTS_FTP, files),
        }
    }

    /// Expires whatever is due; a no-op before every deadline.
    pub fn handle_timeout(&mut self, now: Mono) {
        self.now = self.now.max(now);
        if let Some(ApNotice::Lost) = self.autopilot.on_timeout(now) {
            let t = self.autopilot.timeout().as_secs_f64();
            self.notes.warn(&format!("autopilot lost (nothing from it for {t} s)"));
            self.streams.stop();
            self.timesync.stop();
            self.gimbal.release();
            self.landing.cancel();
            self.gps.restart();
            self.prearm_ok = None;
        }
        self.update_gps_phase();
        if let Some(line) = self.gimbal.on_timeout(now) {
            self.notes.warn(&line);
        }
        if let Some(LandingNotice::GaveUp(tries)) = self.landing.on_timeout(now) {
            let command = self.landing.command();
            self.notes.error(&format!("autopilot did not acknowledge {command:?} after {tries} tries"));
        }
        self.watch_frames(now);
        self.health.on_timeout(now);
        if self.health.take_report() {
            self.actions.push_back(Action::Report);
            // With the report's period: a retry of unsaved parameters once due (one at a
            // time: the next is due only after this one's answer or the period).
            if self.params_unsaved.0 > 0 && now >= self.params_unsaved.1 {
                self.params_unsaved.1 = now + PARAMS_RETRY;
                let json = serde_json::to_string_pretty(&self.tuned).expect("map serialises");
                let token = self.job(Job::SaveParams { name: "tuned parameters".into() });
                self.actions.push_back(Action::SaveParams { token, json });
            }
        }
        if self.health.take_watchdog() {
            self.actions.push_back(Action::Watchdog);
        }
    }

    /// How long frames may stop in flight before the ground station is told: the indoor
    /// pipeline runs at the camera's rate (15 Hz) in milliseconds a frame, and without GPS
    /// it is the autopilot's position; the area pipeline's frames take longer and it flies
    /// on nothing of it.
    fn frame_silence_limit(&self) -> Duration {
        match self.pipeline {
            PipelineState::Running(PipelineKind::Indoor) => Duration::from_secs(1),
            _ => Duration::from_secs(5),
        }
    }

    /// Frames are missed only from a running pipeline on a camera that is up, in flight.
    fn watching_frames(&self) -> bool {
        matches!(self.pipeline, PipelineState::Running(_)) && self.camera_live && self.autopilot.airborne()
    }

    fn watch_frames(&mut self, now: Mono) {
        let limit = self.frame_silence_limit();
        if let Some(silent) = self.frame_watch.on_timeout(now, self.watching_frames(), limit) {
            let blind = if self.pipeline == PipelineState::Running(PipelineKind::Indoor)
                && self.settings.indoor.gps_denied
            {
                ": the autopilot has no position from mavloc"
            } else {
                ""
            };
            self.notes.warn(&format!("no camera frame for {:.1} s in flight{blind}", silent.as_secs_f64()));
        }
    }

    /// The earliest time `handle_timeout` or `poll_transmit` has something to do.
    pub fn poll_timeout(&self) -> Option<Mono> {
        time::earliest([
            self.autopilot.deadline(),
            self.health.deadline(),
            self.streams.deadline(),
            self.timesync.deadline(),
            self.landing.deadline(),
            self.gps.deadline(),
            // When the pipeline's silence is to be held, without GPS (future only: a past
            // deadline not acted on would spin the shell).
            self.pipeline_vision_at.map(|t| t + HOLD_AFTER).filter(|d| *d > self.now && self.gps.enabled()),
            // Only while watching: a deadline past and not acted on would spin the shell.
            self.frame_watch.deadline(self.frame_silence_limit()).filter(|_| self.watching_frames()),
            self.gimbal.deadline(),
            self.params.deadline(),
            self.ftp.deadline(),
        ])
    }

    pub fn poll_action(&mut self) -> Option<Action> {
        self.actions.pop_front()
    }

    /// The next message to send, in priority order.
    pub fn poll_transmit(&mut self, now: Mono) -> Option<Outgoing> {
        let target = self.settings.mavlink.autopilot_system_id;
        if let Some((message, unknown_command)) = self.replies.pop_front() {
            return Some(Outgoing {
                system_id: self.system_id,
                component_id: self.component_id,
                message,
                unknown_command,
            });
        }
        // Letting go of the gimbal first: at shutdown there is one flush to send it in.
        let me = (self.system_id, self.component_id);
        if self.gimbal.letting_go() {
            if let Some(message) = self.gimbal.poll_transmit(now, target, me, self.gimbal_aim()) {
                return Some(Outgoing {
                    system_id: me.0,
                    component_id: me.1,
                    message,
                    unknown_command: None,
                });
            }
        }
        let message = self
            .poll_heartbeat()
            .or_else(|| {
                if let Some((line, short)) = self.streams.poll_summary() {
                    self.notes.warn_short(&line, &short);
                }
                self.notes.pop()
            })
            .or_else(|| self.results.pop_front())
            .or_else(|| {
                let present = self.autopilot.present();
                let attitude = self.telemetry.attitude();
                let stamp = self.autopilot_usec(now.secs());
                let m = self.gps.poll_transmit(now, present, target, attitude, stamp);
                if m.as_ref().is_some_and(|m| matches!(m, MavMessage::ODOMETRY(_))) {
                    match self.gps.holding() {
                        true => self.counters.held_estimates_sent += 1,
                        false => self.counters.standing_estimates_sent += 1,
                    }
                }
                self.say_gps_notices();
                m
            })
            .or_else(|| self.streams.poll_transmit(now, target))
            .or_else(|| self.timesync.poll_transmit(now, target))
            .or_else(|| {
                let stamp = self.autopilot_usec(now.secs());
                self.landing.poll_transmit(now, target, stamp)
            })
            .or_else(|| {
                let aim = self.gimbal_aim();
                self.gimbal.poll_transmit(now, target, (self.system_id, self.component_id), aim)
            })
            .or_else(|| self.ftp.poll(now).map(|(to, payload)| ftp_message(to, payload)))
            .or_else(|| self.params.poll(now).map(|i| self.param_value(i)))?;
        let message = self.vision_after_pause(now, message);
        Some(Outgoing {
            system_id: self.system_id,
            component_id: self.component_id,
            message,
            unknown_command: None,
        })
    }

    /// A vision message the first after a pause (`EV_PAUSE`) carries no placeholder
    /// velocity: an unmeasured one goes out as unknown (NaN), which EKF2 does not fuse.
    /// EKF2 stops fusing vision once its samples are 0.4 s apart (2 x EV_MAX_INTERVAL,
    /// PX4 v1.16 ev_control.cpp), and starting again with no other horizontal aiding it
    /// resets its velocity to the first one it gets, at 5 times its variance
    /// (ev_vel_control.cpp). The placeholder (zero, variance 1e4) weighs nothing while
    /// fusion runs, and after a 4 s camera gap against PX4 SITL it reset EKF2's velocity to
    /// zero at a 220 m/s SD: EKF2's position went invalid, and PX4's failsafe took the
    /// vehicle out of offboard and landed it where it was.
    ///
    /// The same holds for a position: a loose one (the "somewhere near here" of
    /// `gpsdenied::BLIND_SD_M`) would reset EKF2's position to it at its variance, which
    /// PX4 takes for an invalid position. It goes on only where EKF2 fuses positions
    /// already, and is dropped (x and y NaN: EKF2 drops a sample without all three)
    /// where it would start them.
    fn vision_after_pause(&mut self, now: Mono, mut m: MavMessage) -> MavMessage {
        if !matches!(m, MavMessage::ODOMETRY(_) | MavMessage::VISION_POSITION_ESTIMATE(_)) {
            return m;
        }
        // What EKF2 is fusing now (position, velocity), as far as the last sample tells.
        let (positions, velocities) = match self.last_vision_sent {
            Some((t, p, v)) if now.saturating_sub(t) < EV_PAUSE => (p, v),
            _ => (false, false),
        };
        if let MavMessage::ODOMETRY(o) = &mut m {
            if !velocities && o.velocity_covariance[0] >= UNMEASURED_VARIANCE {
                (o.vx, o.vy, o.vz) = (f32::NAN, f32::NAN, f32::NAN);
                for i in [0, 6, 11] {
                    o.velocity_covariance[i] = f32::NAN;
                }
            }
            if !positions && o.pose_covariance[0] >= LOOSE_VARIANCE {
                (o.x, o.y) = (f32::NAN, f32::NAN);
            }
        }
        let (p, v) = match &m {
            MavMessage::ODOMETRY(o) => {
                (o.x.is_finite() && o.y.is_finite() && o.z.is_finite(), o.vx.is_finite())
            }
            MavMessage::VISION_POSITION_ESTIMATE(e) => (e.x.is_finite() && e.y.is_finite(), false),
            _ => unreachable!("vision messages only"),
        };
        self.last_vision_sent = Some((now, p, v));
        m
    }

    fn poll_heartbeat(&mut self) -> Option<MavMessage> {
        let due = self.health.take_heartbeat() | std::mem::take(&mut self.heartbeat_requested);
        due.then(|| {
            MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
                autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                base_mode: MavModeFlag::empty(),
                system_status: self.mav_state(),
                mavlink_version: 3,
            })
        })
    }

    fn reply(&mut self, m: MavMessage) {
        // ACKs are never dropped; the cap holds only against a peer flooding requests.
        if self.replies.len() >= QUEUE_CAP * 4 {
            self.replies.pop_front();
        }
        self.replies.push_back((m, None));
    }

    /// An ACK to a command id the dialect does not define (the encoder writes `id`).
    fn reply_raw(&mut self, m: MavMessage, id: u16) {
        if self.replies.len() >= QUEUE_CAP * 4 {
            self.replies.pop_front();
        }
        self.replies.push_back((m, Some(id)));
    }

    fn result(&mut self, m: MavMessage) {
        if self.results.len() >= QUEUE_CAP {
            self.results.pop_front();
            self.counters.results_dropped += 1;
        }
        self.results.push_back(m);
    }

    fn job(&mut self, job: Job) -> u64 {
        self.next_job += 1;
        self.jobs.insert(self.next_job, job);
        self.next_job
    }

    // ---- frames ----

    fn is_autopilot_system(&self, f: &Frame) -> bool {
        f.header.system_id == self.settings.mavlink.autopilot_system_id as u32
    }

    fn is_autopilot(&self, f: &Frame) -> bool {
        self.is_autopilot_system(f) && f.header.component_id == 1
    }

    /// Commands and parameter sets: only from the ground station or the autopilot, and
    /// only signed when signing is on. Returns the reason for a refusal.
    fn trusted(&self, f: &Frame) -> Result<(), String> {
        let m = &self.settings.mavlink;
        let sys = f.header.system_id;
        if sys != m.gcs_system_id as u32 && sys != m.autopilot_system_id as u32 {
            return Err(format!("system {sys} is neither the ground station nor the autopilot"));
        }
        if self.signing && f.auth != Auth::Signed {
            return Err("unsigned, and signing is required".into());
        }
        Ok(())
    }

    /// A parameter request addressed to mavloc (LIST may be broadcast; READ by name too,
    /// when the name is mavloc's: [`Core::ours_by_name`]).
    fn addressed(&self, m: &MavMessage) -> bool {
        match m {
            MavMessage::PARAM_REQUEST_LIST(r) => self.for_us(r.target_system, r.target_component, true),
            MavMessage::PARAM_REQUEST_READ(r) => {
                self.for_us(r.target_system, r.target_component, false)
                    || (r.param_index < 0
                        && self.ours_by_name(r.target_system, r.target_component, &r.param_id))
            }
            _ => false,
        }
    }

    /// A read or set of one parameter by name sent to every component of this system
    /// (MAV_COMP_ID_ALL), as PX4 takes them: taken when the name is one of mavloc's, whose
    /// prefixes are its own (by index it would be anyone's index; an outside trial found
    /// these requests unanswered).
    fn ours_by_name(
        &self,
        target_system: u8,
        target_component: u8,
        id: &mavlink::types::CharArray<16>,
    ) -> bool {
        target_system == self.system_id
            && target_component == 0
            && param_name(id).is_some_and(|n| param_table::find(&n).is_some())
    }

    fn for_us(&self, target_system: u8, target_component: u8, allow_broadcast: bool) -> bool {
        (target_system == self.system_id || (allow_broadcast && target_system == 0))
            && (target_component == self.component_id || (allow_broadcast && target_component == 0))
    }

    /// Says when the autopilot's system id speaks on a second clock: flight-controller
    /// stamps from before its last one that no reboot followed, or from its future. Two
    /// vehicles (or a simulator and a vehicle) with the same MAV_SYS_ID on one network
    /// look like this, and so does a spoofer; either way the telemetry is screened (the
    /// stamps are dropped) but the user has to hear of it to fix the ids. A gimbal's
    /// clock does not count, nor stray messages (a duplicate that came late by another
    /// path): [`CLASH_MIN`] within a minute, said at most once a minute.
    fn warn_of_a_second_clock(&mut self, rx: Mono) {
        let now = (self.telemetry.reboot_claims_rejected, self.telemetry.autopilot_from_the_future);
        let (said_claims, said_future) = self.clash_said;
        let unsaid = (now.0 - said_claims) + (now.1 - said_future);
        if unsaid == 0 {
            return;
        }
        let first = *self.clash_first.get_or_insert(rx);
        if unsaid < CLASH_MIN {
            // Strays spread over more than a minute are not a second clock: forgotten.
            if rx.saturating_sub(first) > CLASH_WARN_EVERY {
                (self.clash_said, self.clash_first) = (now, None);
            }
            return;
        }
        if self.clash_warned.is_some_and(|t| rx.saturating_sub(t) < CLASH_WARN_EVERY) {
            return;
        }
        self.clash_warned = Some(rx);
        (self.clash_said, self.clash_first) = (now, None);
        let sys = self.settings.mavlink.autopilot_system_id;
        self.notes.warn_short(
            &format!(
                "a second clock speaks as the autopilot (system {sys}): {} of its reboot claims disproved, {} stamps from the future dropped; \
                 two vehicles or a simulator with the same MAV_SYS_ID on this network?",
                now.0 - said_claims,
                now.1 - said_future
            ),
            &format!("two clocks as system {sys}: same MAV_SYS_ID twice?"),
        );
    }

    fn on_frame(&mut self, rx: Mono, f: Frame) {
        // Our own messages echoed back by a router or PX4's forwarding.
        if f.header.system_id == self.system_id as u32 && f.header.component_id == self.component_id {
            return;
        }
        if self.signing && f.auth != Auth::Signed && !self.settings.mavlink.accept_unsigned_telemetry {
            if !self.autopilot.present() {
                self.waiting.unsigned();
            }
            return;
        }
        let from = (f.header.system_id as u8, f.header.component_id);
        if !self.autopilot.present() {
            self.waiting.heard(from);
        }
        if let Some(id) = f.unknown_command {
            let target = match &f.message {
                MavMessage::COMMAND_LONG(c) => (c.target_system, c.target_component),
                MavMessage::COMMAND_INT(c) => (c.target_system, c.target_component),
                _ => return,
            };
            // Addressed to mavloc: UNSUPPORTED, so the sender stops retrying. A broadcast
            // one is for whichever component knows it; silence is right there.
            if target == (self.system_id, self.component_id) {
                // The placeholder stands where the id goes (codec::PLACEHOLDER_COMMAND).
                let ack =
                    commands::ack(MavCmd::MAV_CMD_NAV_WAYPOINT, MavResult::MAV_RESULT_UNSUPPORTED, from);
                self.reply_raw(ack, id);
            }
            return;
        }
        if self.is_autopilot(&f) && !matches!(f.message, MavMessage::HEARTBEAT(_)) {
            self.autopilot.on_traffic(rx);
        }
        if self.is_autopilot_system(&f) {
            if self.telemetry.on_message(rx, &f.message, f.header.component_id).is_some() {
                self.on_reboot(rx);
            }
            self.warn_of_a_second_clock(rx);
            if let Some(axis) = self.telemetry.take_gimbal_report() {
                let airborne = !self.on_ground();
                self.gimbal.on_report(rx, [axis.x, axis.y, axis.z], airborne);
            }
        }
        match &f.message {
            MavMessage::HEARTBEAT(h)
                if self.is_autopilot(&f) && h.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID =>
            {
                let what = format!("{:?}, MAVLink {:?}", h.autopilot, f.version);
                if let Some(ApNotice::Found { sys, what }) = self.autopilot.on_heartbeat(rx, from.0, h, what)
                {
                    if self.settings.mavlink.system_id == 0 {
                        self.system_id = sys;
                    }
                    self.notes.info(&format!("autopilot found: system {sys} ({what})"));
                    self.waiting.found();
                    self.streams.start();
                    self.timesync.start(rx);
                    if self.gps.enabled() && self.autopilot.armed() && !self.autopilot.on_ground() {
                        // Found armed and not known to stand: mavloc started again in
                        // flight; the origin waits for the ground, and the pad is not
                        // where the vehicle is.
                        self.gps.forget_pad();
                        self.notes.info(
                            "no GPS: the autopilot is armed; vision estimates from now on, not the pad; the origin only once it stands",
                        );
                    } else if self.gps.enabled() {
                        let (n, e, _) = self.gps.standing();
                        self.notes.info(&format!(
                            "no GPS: vision estimates from now on, the pad (x {n:.2}, y {e:.2} m) while standing; the origin after {} s",
                            gpsdenied::ORIGIN_AFTER.as_secs()
                        ));
                    }
                }
                self.update_gps_phase();
                self.after_touchdown();
            }
            MavMessage::EXTENDED_SYS_STATE(e) if self.is_autopilot(&f) => {
                self.autopilot.on_landed_state(e.landed_state);
                self.update_gps_phase();
                self.after_touchdown();
                if e.landed_state == MavLandedState::MAV_LANDED_STATE_ON_GROUND {
                    self.landing.landed();
                }
            }
            MavMessage::SYS_STATUS(st) if self.is_autopilot(&f) => {
                // PX4 sets only the health bit (never present or enabled: measured on
                // v1.16 SITL), so the health bit is the verdict.
                let ok = st
                    .onboard_control_sensors_health
                    .contains(MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK);
                if self.prearm_ok != Some(ok) && (ok || self.prearm_ok.is_some()) {
                    let line =
                        if ok { "autopilot: pre-arm checks pass" } else { "autopilot: pre-arm checks fail" };
                    self.notes.info(line);
                }
                self.prearm_ok = Some(ok);
            }
            MavMessage::GPS_GLOBAL_ORIGIN(o) if self.is_autopilot_system(&f) => {
                let geo = Geodetic::new(
                    o.latitude as f64 * 1e-7,
                    o.longitude as f64 * 1e-7,
                    o.altitude as f64 * 1e-3,
                );
                if let Some(n) = self.gps.on_autopilot_origin(geo) {
                    self.say_gps_notice(n);
                }
            }
            MavMessage::EVENT(e) if self.is_autopilot_system(&f) => {
                self.counters.autopilot_events += 1;
                if let Some((level, line)) = self.events.on_event(rx, e) {
                    if level <= events::WARNING {
                        tracing::warn!("{line}");
                    } else {
                        tracing::info!("{line}");
                    }
                }
            }
            // Answers to mavloc's own commands only: an ACK the autopilot sends a ground
            // station (seen by a router's broadcast) says nothing about them.
            MavMessage::COMMAND_ACK(a)
                if self.is_autopilot(&f) && self.for_us(a.target_system, a.target_component, true) =>
            {
                self.on_autopilot_ack(rx, a)
            }
            MavMessage::GIMBAL_MANAGER_STATUS(g) if self.is_autopilot(&f) => {
                let me = (self.system_id, self.component_id);
                let primary = (g.primary_control_sysid, g.primary_control_compid);
                if let Some(line) = self.gimbal.on_manager_status(rx, primary, me, from.0) {
                    self.notes.info(&line);
                }
            }
            MavMessage::TIMESYNC(t) if self.is_autopilot_system(&f) => {
                let now_autopilot = self.telemetry.aligner.clock.to_autopilot(rx.secs());
                let (reply, sample) = self.timesync.on_timesync(rx, t, from, now_autopilot);
                if let Some(r) = reply {
                    self.counters.timesync_answered += 1;
                    self.reply(r);
                }
                if let Some(s) = sample {
                    self.telemetry.aligner.clock.observe_timesync(s.sent, s.received, s.remote);
                }
            }
            MavMessage::PARAM_REQUEST_LIST(_) | MavMessage::PARAM_REQUEST_READ(_)
                if self.addressed(&f.message) && self.trusted(&f).is_err() =>
            {
                // Only the ground station and the autopilot may have the list: a flood of
                // requests from anyone else costs a counter, not the link.
                self.counters.param_requests_refused += 1;
                if self.peer_lines.allow(from, rx) {
                    let why = self.trusted(&f).err().unwrap_or_default();
                    tracing::warn!("refused a parameter request from {}/{}: {why}", from.0, from.1);
                }
            }
            MavMessage::PARAM_REQUEST_LIST(r) if self.for_us(r.target_system, r.target_component, true) => {
                self.params.on_list();
            }
            MavMessage::PARAM_REQUEST_READ(r) if self.addressed(&f.message) => {
                let i = if r.param_index >= 0 {
                    Some(r.param_index as usize).filter(|&i| i < param_table::PARAMS.len())
                } else {
                    param_name(&r.param_id).and_then(|n| param_table::find(&n)).map(|(i, _)| i)
                };
                match i {
                    Some(i) => self.params.on_single(i),
                    None if self.peer_lines.allow(from, rx) => {
                        let id = param_name(&r.param_id).unwrap_or_else(|| "?".into());
                        self.notes.warn(&format!("no parameter {id} (index {})", r.param_index));
                    }
                    None => {}
                }
            }
            MavMessage::PARAM_SET(p)
                if self.for_us(p.target_system, p.target_component, false)
                    || self.ours_by_name(p.target_system, p.target_component, &p.param_id) =>
            {
                let name = param_name(&p.param_id).unwrap_or_default();
                self.param_set(rx, &f, &name, Wire { value: p.param_value, ty: p.param_type });
            }
            MavMessage::FILE_TRANSFER_PROTOCOL(m)
                if self.for_us(m.target_system, m.target_component, false) =>
            {
                // The files are public (parameter metadata) but the server's time is not:
                // only the peers allowed to command mavloc use it.
                if let Err(why) = self.trusted(&f) {
                    self.counters.commands_refused += 1;
                    if self.peer_lines.allow(from, rx) {
                        tracing::warn!("refused MAVLink FTP from {}/{}: {why}", from.0, from.1);
                    }
                    return;
                }
                if let Some(reply) = self.ftp.on_request(rx, from, &m.payload) {
                    self.reply(ftp_message(from, reply));
                }
            }
            MavMessage::COMMAND_LONG(c) if self.for_us(c.target_system, c.target_component, true) => {
                let broadcast = c.target_component == 0 || c.target_system == 0;
                self.on_command(rx, &f, c, broadcast);
            }
            // The same commands, with x and y as integers (MAVLink allows either).
            MavMessage::COMMAND_INT(c) if self.for_us(c.target_system, c.target_component, true) => {
                let broadcast = c.target_component == 0 || c.target_system == 0;
                let long = COMMAND_LONG_DATA {
                    param1: c.param1,
                    param2: c.param2,
                    param3: c.param3,
                    param4: c.param4,
                    param5: c.x as f32,
                    param6: c.y as f32,
                    param7: c.z,
                    command: c.command,
                    target_system: c.target_system,
                    target_component: c.target_component,
                    confirmation: 0,
                };
                self.on_command(rx, &f, &long, broadcast);
            }
            _ => {}
        }
    }

    fn on_reboot(&mut self, rx: Mono) {
        self.counters.autopilot_reboots += 1;
        self.notes.warn("autopilot rebooted; re-requesting its streams");
        if self.autopilot.present() {
            self.streams.start();
            self.timesync.start(rx);
        }
        self.gimbal.release();
        self.landing.cancel();
        self.gps.restart();
        self.prearm_ok = None;
    }

    /// The camera's height above the floor: the downward rangefinder when it spoke in the
    /// last second, else the autopilot's height (the local frame's z = 0 is the ground).
    pub fn height_above_floor(&self) -> Option<f64> {
        self.fresh_range().or_else(|| self.aligner().vehicle.newest().map(|(_, v)| -v.position.z))
    }

    /// Where the floor is below the camera, local z (down, m), and its variance: 0 while
    /// standing, else the downward rangefinder's distance turned vertical by the
    /// vehicle's tilt (a reading below its minimum is the floor). None without a fresh
    /// reading. It goes out as the vision estimate's z: the floor is the local frame's
    /// z = 0, the origin mavloc gives being on it.
    pub fn floor_down(&self) -> Option<(f64, f64)> {
        if self.standing() {
            return Some((0.0, RANGE_VARIANCE));
        }
        match self.fresh_range() {
            Some(m) => {
                let (roll, pitch, _) = self
                    .aligner()
                    .vehicle
                    .newest()
                    .map(|(_, v)| v.attitude.euler_angles())
                    .unwrap_or((0.0, 0.0, 0.0));
                Some((-(m * roll.cos() * pitch.cos()), RANGE_VARIANCE))
            }
            _ => None,
        }
    }

    fn update_gps_phase(&mut self) {
        if self.standing() {
            self.gps.on_ground();
            if let Some(h) = self.fresh_range() {
                self.ground_range = h;
            }
        }
        self.gps.set_state(self.gps_phase(), self.floor_down(), self.holding());
    }

    /// Without GPS in flight, the pipeline silent for `HOLD_AFTER`: where the autopilot
    /// itself puts the vehicle (north, east), for the held estimates.
    fn holding(&self) -> Option<(f64, f64)> {
        let silent = self.pipeline_vision_at.is_some_and(|t| self.now.saturating_sub(t) >= HOLD_AFTER);
        if !(silent
            && self.gps.enabled()
            && self.autopilot.airborne()
            && self.pipeline == PipelineState::Running(PipelineKind::Indoor))
        {
            return None;
        }
        let (_, v) = self.aligner().vehicle.newest()?;
        Some((v.position.x, v.position.y)).filter(|p| p.0.is_finite() && p.1.is_finite())
    }

    /// For the standing estimates: on the floor (the autopilot says so, or the camera
    /// has not left it), off it but too low (or too high) to localise, or in between.
    pub fn gps_phase(&self) -> gpsdenied::Phase {
        use gpsdenied::Phase;
        let lifted = self.height_above_floor().is_some_and(|h| h > self.ground_range + LIFT_OFF_M);
        if self.standing() || (self.outside_heights() && !lifted) {
            Phase::Standing
        } else if self.outside_heights() {
            Phase::Blind
        } else {
            Phase::Seeing
        }
    }

    fn fresh_range(&self) -> Option<f64> {
        match self.telemetry.range_down {
            Some((at, m)) if self.now.saturating_sub(at) <= Duration::from_secs(1) => Some(m),
            _ => None,
        }
    }

    /// No indoor localisation now: the vehicle stands, or the camera is lower than
    /// `indoor.min_height_m` (taking off, touching down, or a take-off PX4 has declared
    /// while the rangefinder still reads the ground) or higher than `indoor.max_height_m`.
    pub fn vision_paused(&self) -> bool {
        self.standing() || self.outside_heights()
    }

    /// The indoor pipeline runs and the camera is outside the heights it localises from:
    /// below `indoor.min_height_m`, or above `indoor.max_height_m` (there the view reaches
    /// past the floor the model knows: from 9 m over the simulated floor fixes were metres
    /// off, and against PX4 SITL its precision landing, its target lost, climbed to 9.5 m).
    /// Only the camera's velocity is measured then.
    pub fn outside_heights(&self) -> bool {
        let i = &self.settings.indoor;
        matches!(self.pipeline, PipelineState::Running(PipelineKind::Indoor))
            && self.height_above_floor().is_some_and(|h| h < i.min_height_m || h > i.max_height_m)
    }

    /// Standing on the ground, as far as the autopilot says: its landed state, or
    /// disarmed when it has not said one yet.
    fn standing(&self) -> bool {
        match self.autopilot.landed_state() {
            Some(s) => s == MavLandedState::MAV_LANDED_STATE_ON_GROUND,
            None => !self.autopilot.armed(),
        }
    }

    fn say_gps_notices(&mut self) {
        while let Some(n) = self.gps.take_notice() {
            self.say_gps_notice(n);
        }
    }

    fn say_gps_notice(&mut self, n: gpsdenied::Notice) {
        use gpsdenied::Notice;
        match n {
            Notice::OriginSent(o) => self.notes.info(&format!(
                "no GPS: sent the origin {:.7} {:.7} {:.2} m after {} s of vision",
                o.lat_deg,
                o.lon_deg,
                o.alt_m,
                gpsdenied::ORIGIN_AFTER.as_secs()
            )),
            Notice::OriginConfirmed => self.notes.info("no GPS: the autopilot took the origin"),
            Notice::OriginForeign(o, d) => self.notes.warn(&format!(
                "no GPS: the autopilot has another origin ({:.7} {:.7} {:.2} m, {d:.1} m from indoor.origin); not replacing it",
                o.lat_deg, o.lon_deg, o.alt_m
            )),
            Notice::OriginGaveUp => self.notes.error(&format!(
                "no GPS: the autopilot did not echo the origin after {} tries (GPS_GLOBAL_ORIGIN); it cannot arm without one",
                gpsdenied::ORIGIN_TRIES
            )),
        }
    }

    fn on_autopilot_ack(&mut self, now: Mono, a: &COMMAND_ACK_DATA) {
        match a.command {
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => self.streams.on_ack(a.result),
            MavCmd::MAV_CMD_NAV_LAND | MavCmd::MAV_CMD_NAV_LAND_LOCAL => {
                match self.landing.on_ack(now, a.command, a.result) {
                    Some(LandingNotice::Accepted) => {
                        self.notes.push(MavSeverity::MAV_SEVERITY_NOTICE, "autopilot accepted the landing")
                    }
                    Some(LandingNotice::PlainInstead(r)) => self.notes.warn(&format!(
                        "autopilot refused the precision landing ({r:?}); landing where the vehicle is"
                    )),
                    Some(LandingNotice::Refused(r)) => {
                        self.notes.error(&format!("autopilot refused the landing: {r:?}"))
                    }
                    _ => {}
                }
            }
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE | MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if let Some(line) = self.gimbal.on_ack(now, a.command, a.result) {
                    self.notes.warn(&line);
                }
            }
            _ => {}
        }
    }

    fn param_value(&self, i: usize) -> MavMessage {
        let def = &param_table::PARAMS[i];
        let w = param_table::encode(&self.settings, def);
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: w.value,
            param_count: param_table::PARAMS.len() as u16,
            param_index: i as u16,
            param_id: def.name.into(),
            param_type: w.ty,
        })
    }

    fn param_set(&mut self, rx: Mono, f: &Frame, name: &str, w: Wire) {
        let from = (f.header.system_id as u8, f.header.component_id);
        let index = param_table::find(name).map(|(i, _)| i);
        if let Err(why) = self.trusted(f) {
            self.counters.params_refused += 1;
            // Said, and answered with the unchanged value, once per sender per 10 s: a
            // flood of refused sets must not become a flood of answers.
            if self.peer_lines.allow(from, rx) {
                self.notes.warn(&format!("refused PARAM_SET {name}: {why}"));
                if let Some(i) = index {
                    self.params.on_single(i);
                }
            }
            return;
        }
        match param_table::set(&self.settings, name, w) {
            Ok((new, value)) => {
                let was = self.settings.daemon.pipeline;
                let pipeline_changed = new.daemon.pipeline != was;
                self.settings = new;
                self.telemetry.reconfigure(&self.settings);
                self.tuned.insert(name.to_string(), value);
                let json = serde_json::to_string_pretty(&self.tuned).expect("map serialises");
                let token = self.job(Job::SaveParams { name: name.to_string() });
                self.actions.push_back(Action::SaveParams { token, json });
                tracing::info!("parameter {name} = {value} (PARAM_SET from system {})", f.header.system_id);
                self.actions.push_back(Action::Worker(WorkerRequest::Apply(Box::new(self.settings.clone()))));
                // The pipeline set takes over from one running, starting or failed, and
                // from none (LOC_PIPELINE 0 stopped it); one stopped by command stays so.
                let takes_over = match self.pipeline {
                    PipelineState::Running(_) | PipelineState::Starting(_) | PipelineState::Failed(_) => true,
                    PipelineState::Stopped => was == PipelineKind::None,
                };
                if pipeline_changed && takes_over {
                    match self.settings.daemon.pipeline {
                        PipelineKind::None => self.stop_pipeline(),
                        k => self.start_pipeline(k, None),
                    }
                }
                self.params.on_single(index.expect("set succeeded, so it exists"));
            }
            Err(e) => {
                self.counters.params_refused += 1;
                if self.peer_lines.allow(from, rx) {
                    self.notes.warn(&format!("refused {e}"));
                }
                if let SetError::Refused { .. } = e {
                    self.params.on_single(index.expect("refused, so it exists"));
                }
            }
        }
    }

    fn on_command(&mut self, rx: Mono, f: &Frame, c: &COMMAND_LONG_DATA, broadcast: bool) {
        let from = (f.header.system_id as u8, f.header.component_id);
        let decision =
            commands::decide(c, broadcast, self.settings.daemon.pipeline, param_table::PARAMS.len());
        if decision == Decision::Ignore {
            return;
        }
        if let Err(why) = self.trusted(f) {
            self.counters.commands_refused += 1;
            if self.peer_lines.allow(from, rx) {
                tracing::warn!("refused command {} from {}/{}: {why}", c.command as u32, from.0, from.1);
            }
            if self.stranger_acks.allow(from, rx) {
                self.reply(commands::ack(c.command, MavResult::MAV_RESULT_DENIED, from));
            }
            return;
        }
        let ack = |core: &mut Core, r| core.reply(commands::ack(c.command, r, from));
        match decision {
            Decision::Ignore => {}
            Decision::Ack(r) => ack(self, r),
            Decision::SendHeartbeat => {
                ack(self, MavResult::MAV_RESULT_ACCEPTED);
                self.heartbeat_requested = true;
            }
            Decision::SendParam(i) => {
                ack(self, MavResult::MAV_RESULT_ACCEPTED);
                self.params.on_single(i);
            }
            Decision::SendMetadata => {
                ack(self, MavResult::MAV_RESULT_ACCEPTED);
                let general = &self.metadata_general;
                let uri =
                    format!("mftp://[;comp={}]{}", self.component_id, crate::link::metadata::GENERAL_PATH);
                let m = MavMessage::COMPONENT_METADATA(COMPONENT_METADATA_DATA {
                    time_boot_ms: (rx.secs() * 1000.0) as u32,
                    file_crc: crate::link::metadata::crc32(general),
                    uri: uri.as_str().into(),
                });
                self.reply(m);
            }
            Decision::Snapshot => {
                ack(self, MavResult::MAV_RESULT_IN_PROGRESS);
                if let Some(ack_token) = self.owed.owe(c.command, from) {
                    let token = self.job(Job::Snapshot { ack_token });
                    self.actions.push_back(Action::Snapshot { token });
                }
            }
            Decision::Pipeline(PipelineRequest::Start(PipelineKind::None)) => {
                self.notes.warn("no pipeline configured (LOC_PIPELINE = none)");
                ack(self, MavResult::MAV_RESULT_DENIED);
            }
            Decision::Pipeline(PipelineRequest::Start(k)) => self.start_pipeline(k, Some((c.command, from))),
            Decision::Pipeline(PipelineRequest::Stop) => {
                self.stop_pipeline();
                ack(self, MavResult::MAV_RESULT_ACCEPTED);
            }
            Decision::Pipeline(PipelineRequest::AdjustMap) => {
                let result = if self.pipeline != PipelineState::Running(PipelineKind::Area) {
                    self.notes.warn("the map is adjusted by the area pipeline, which is not running");
                    MavResult::MAV_RESULT_TEMPORARILY_REJECTED
                } else if self.settings.area.attitude_prior_deg <= 0.0 {
                    self.notes.warn("the map is not adjusted: area.attitude_prior_deg (AREA_ADJ_PRIOR) is 0");
                    MavResult::MAV_RESULT_DENIED
                } else {
                    self.actions.push_back(Action::Worker(WorkerRequest::AdjustMap("asked to")));
                    MavResult::MAV_RESULT_ACCEPTED
                };
                ack(self, result);
            }
            Decision::Pipeline(PipelineRequest::Reset) => match self.pipeline {
                PipelineState::Running(k) => {
                    self.actions.push_back(Action::Worker(WorkerRequest::Reset));
                    self.notes.info(&format!("{k:?} pipeline reset; earlier results kept aside"));
                    ack(self, MavResult::MAV_RESULT_ACCEPTED);
                }
                _ => ack(self, MavResult::MAV_RESULT_TEMPORARILY_REJECTED),
            },
        }
    }

    /// At a touchdown the area pipeline adjusts its map (`daemon::flightlog`), when
    /// `area.attitude_prior_deg` asks for it.
    fn after_touchdown(&mut self) {
        if self.autopilot.take_touchdown()
            && self.pipeline == PipelineState::Running(PipelineKind::Area)
            && self.settings.area.attitude_prior_deg > 0.0
        {
            self.actions.push_back(Action::Worker(WorkerRequest::AdjustMap("landed")));
        }
    }

    /// Asks the shell to start `kind`; the final ACK (if a command asked) comes with
    /// its `Done`, since only the shell can tell whether the model file exists.
    fn start_pipeline(&mut self, kind: PipelineKind, requester: Option<(MavCmd, (u8, u8))>) {
        if let PipelineKind::Indoor = kind {
            if self.settings.indoor.model.is_empty() {
                return self.start_failed(
                    kind,
                    requester,
                    "indoor.model is not set (train one with `mavloc indoor train`)",
                );
            }
        }
        if self.pipeline == PipelineState::Running(kind) {
            if let Some((cmd, to)) = requester {
                self.reply(commands::ack(cmd, MavResult::MAV_RESULT_ACCEPTED, to));
            }
            return;
        }
        self.pipeline = PipelineState::Starting(kind);
        let token = self.job(Job::Start { kind, requester });
        self.actions.push_back(Action::Worker(WorkerRequest::Start { kind, token }));
    }

    fn start_failed(&mut self, kind: PipelineKind, requester: Option<(MavCmd, (u8, u8))>, why: &str) {
        self.pipeline = PipelineState::Failed(kind);
        self.notes.error(&format!("cannot start the {kind:?} pipeline: {why}"));
        if let Some((cmd, to)) = requester {
            self.reply(commands::ack(cmd, MavResult::MAV_RESULT_DENIED, to));
        }
    }

    fn stop_pipeline(&mut self) {
        if let PipelineState::Running(k) | PipelineState::Failed(k) | PipelineState::Starting(k) =
            self.pipeline
        {
            self.actions.push_back(Action::Worker(WorkerRequest::Stop));
            self.pipeline = PipelineState::Stopped;
            self.frame_watch.reset();
            self.notes.info(&format!("{k:?} pipeline stopped; results written"));
        }
    }

    fn on_done(&mut self, token: u64, result: Result<(), String>) {
        let Some(job) = self.jobs.remove(&token) else {
            tracing::debug!("done for unknown token {token}");
            return;
        };
        match job {
            Job::Start { kind, requester } => {
                if self.pipeline != PipelineState::Starting(kind) {
                    // Stopped or replaced meanwhile: the newer request decides.
                    if let Some((cmd, to)) = requester {
                        self.reply(commands::ack(cmd, MavResult::MAV_RESULT_CANCELLED, to));
                    }
                    return;
                }
                match result {
                    Ok(()) => {
                        self.pipeline = PipelineState::Running(kind);
                        // A new pipeline's silence counts from its start: one started in
                        // the air (mavloc restarted in flight) has the height held until
                        // its first estimate, as a camera gap does.
                        self.pipeline_vision_at = Some(self.now);
                        let src = format!("{:?}", self.settings.camera.source).to_lowercase();
                        self.notes
                            .info(&format!("{kind:?} pipeline started; frames from camera source {src}"));
                        if let Some((cmd, to)) = requester {
                            self.reply(commands::ack(cmd, MavResult::MAV_RESULT_ACCEPTED, to));
                        }
                    }
                    Err(why) => self.start_failed(kind, requester, &why),
                }
            }
            Job::Snapshot { ack_token } => {
                let result = match &result {
                    Ok(()) => MavResult::MAV_RESULT_ACCEPTED,
                    Err(e) => {
                        self.counters.result_writes_failed += 1;
                        self.notes.error(&format!("snapshot failed: {e}"));
                        MavResult::MAV_RESULT_FAILED
                    }
                };
                if let Some((cmd, to, n)) = self.owed.settle(ack_token) {
                    for _ in 0..n {
                        self.reply(commands::ack(cmd, result, to));
                    }
                }
            }
            Job::SaveParams { name } => match result {
                Err(e) => {
                    if self.params_unsaved.0 == 0 {
                        self.notes.warn(&format!(
                            "{name} set but not saved: {e}; saving again every {} s",
                            PARAMS_RETRY.as_secs()
                        ));
                    }
                    self.params_unsaved = (self.params_unsaved.0 + 1, self.now + PARAMS_RETRY);
                }
                Ok(()) => {
                    if self.params_unsaved.0 > 0 {
                        self.notes.info(&format!(
                            "tuned parameters saved (after {} failed tries)",
                            self.params_unsaved.0
                        ));
                    }
                    self.params_unsaved.0 = 0;
                }
            },
        }
    }

    // ---- pipeline and camera ----

    fn on_pipeline(&mut self, now: Mono, event: PipelineEvent) {
        match event {
            PipelineEvent::Report { capture, attitude, report } => {
                if let Some(line) = self.frame_watch.on_frame(now) {
                    self.notes.info(&line);
                }
                self.publish(now, &report, capture, attitude)
            }
            PipelineEvent::Panicked { frame, message } => {
                self.counters.pipeline_panics += 1;
                let on = frame.map_or("outside a frame".to_string(), |f| format!("on frame {f}"));
                self.notes.error(&format!("pipeline panicked {on}: {message}; restarted"));
            }
            PipelineEvent::Failed(e) => {
                if let PipelineState::Running(k) | PipelineState::Starting(k) = self.pipeline {
                    self.pipeline = PipelineState::Failed(k);
                }
                self.notes.error(&format!("pipeline failed: {e}"));
            }
            PipelineEvent::WriteFailed(e) => self.write_failed(now, &e),
            PipelineEvent::Note(line) => self.notes.info(&line),
        }
    }

    /// A result write failed: counted always, said as a WARNING at most every
    /// [`WRITE_WARNING_PERIOD`].
    fn write_failed(&mut self, now: Mono, what: &str) {
        self.counters.result_writes_failed += 1;
        if self.write_warned.is_some_and(|t| now.saturating_sub(t) < WRITE_WARNING_PERIOD) {
            self.writes_failed_unsaid += 1;
            return;
        }
        let line = match std::mem::take(&mut self.writes_failed_unsaid) {
            0 => what.to_string(),
            n => format!("{what} ({n} more failed writes since the last warning)"),
        };
        self.notes.warn(&line);
        self.write_warned = Some(now);
    }

    fn on_camera(&mut self, event: CameraEvent) {
        match event {
            CameraEvent::Up(what) => {
                self.camera_live = true;
                self.notes.info(&format!("camera up: {what}"));
            }
            CameraEvent::Down { why, fatal } => {
                self.camera_live = false;
                self.frame_watch.reset();
                let what = if fatal { "camera failed" } else { "camera lost (retrying)" };
                self.notes.error(&format!("{what}: {why}"));
            }
            CameraEvent::Ended(what) => {
                self.camera_live = false;
                self.frame_watch.reset();
                self.notes.info(&format!("camera source ended: {what}"));
            }
            CameraEvent::Unreadable(n) => self.counters.frames_unreadable = n,
        }
    }

    fn on_stats(&mut self, now: Mono, s: ShellStats) {
        let m = &self.settings.mavlink;
        if let Some((log, short)) =
            self.waiting.on_stats(now, &s, &m.connection, m.autopilot_system_id, m.gcs_system_id)
        {
            self.notes.warn_short(&log, short);
        }
        self.counters.frames_dropped = s.frames_dropped;
        self.counters.peer_lines_suppressed = self.peer_lines.suppressed;
        self.counters.telemetry_from_the_future = self.telemetry.implausible;
        self.counters.telemetry_not_finite = self.telemetry.not_finite;
        self.counters.reboot_claims_rejected = self.telemetry.reboot_claims_rejected;
        self.counters.gimbal_error_median_deg = self.gimbal.median_error_deg();
        self.counters.gimbal_error_flight_median_deg = self.gimbal.flight_median_error_deg();
        self.counters.vision_latency_median_ms = {
            let mut v: Vec<f64> = self.latencies.iter().copied().collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied()
        };
        self.counters.statustext_dropped = self.notes.dropped;
        let ms = (now.0 / 1000) as u32;
        let values: [(&str, f32); 5] = [
            ("LINK_BAD", s.link_bad_frames as f32),
            ("LINK_JUNK", s.link_garbage_bytes as f32),
            ("LINK_IN", s.link_in as f32),
            ("FR_DONE", self.counters.frames_processed as f32),
            ("FR_DROP", self.counters.frames_dropped as f32),
        ];
        for (name, value) in values {
            self.result(MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
                time_boot_ms: ms,
                value,
                name: name.into(),
            }));
        }
    }

    /// Publishes what the pipeline found on one frame captured at local time `capture`
    /// (seconds on mavloc's monotonic clock), stamped on the autopilot's clock
    /// ([`Core::autopilot_usec`]), the clock mavloc's TIMESYNC answers carry.
    ///
    /// The indoor estimate goes out as ODOMETRY when the camera measured the velocity too
    /// (position in the local NED frame, velocity in body axes; PX4's EKF2 fuses the
    /// velocity with `EKF2_EV_CTRL` bit 2), else as VISION_POSITION_ESTIMATE (horizontal
    /// position, `EKF2_EV_CTRL` bit 0), each with its covariance. Too low to localise
    /// without GPS, the velocity goes out with the estimates for a vehicle off the floor.
    /// Area landmarks go out as DEBUG_VECT named `LMK` (north, east, down in metres,
    /// local NED of the autopilot), which QGroundControl's MAVLink inspector shows.
    fn publish(&mut self, now: Mono, report: &Report, capture: f64, attitude: (f64, f64, f64)) {
        if report.processed {
            self.counters.frames_processed += 1;
            self.last_processed = Some(now);
        } else {
            self.counters.frames_skipped += 1;
        }
        let usec = self.autopilot_usec(capture);
        for p in &report.new_landmarks {
            self.result(MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
                time_usec: usec,
                x: p[0] as f32,
                y: p[1] as f32,
                z: p[2] as f32,
                name: "LMK".into(),
            }));
        }
        if let Some(e) = &report.position {
            if self.latencies.len() >= 100 {
                self.latencies.pop_front();
            }
            self.latencies.push_back((now.secs() - capture) * 1e3);
            let (e, down_var) = match self.floor_down() {
                Some((down, var)) => (PositionEstimate { down, ..*e }, Some(var)),
                None => (*e, None),
            };
            self.result(match &report.velocity {
                Some(v) => odometry(Some(&e), v, usec, attitude, down_var),
                None => vision_position_estimate(&e, usec, attitude, down_var),
            });
            self.pipeline_vision_at = Some(now);
            self.gps.on_pipeline_estimate(now, &e);
        } else if let Some(v) = &report.velocity {
            if let Some(c) = &report.coasted {
                self.gps.on_coasted(c);
            }
            if self.gps.enabled() && self.gps.phase() != gpsdenied::Phase::Seeing {
                // Too low to localise: the velocity goes out with the estimates for a
                // vehicle off the floor ([`GpsDenied`]), one stream, not two.
                self.gps.on_velocity(now, v);
            } else {
                // No fix yet (or lost): the velocity alone still keeps EKF2's track honest.
                self.result(odometry(None, v, usec, attitude, None));
                self.pipeline_vision_at = Some(now);
            }
        }
        let ms = (capture.max(0.0) * 1e3) as u32;
        for &(name, value) in &report.counters {
            self.result(MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
                time_boot_ms: ms,
                value,
                name: name.into(),
            }));
        }
        for e in &report.events {
            self.notes.info(e);
        }
        for w in &report.warnings {
            match w {
                Warning::WriteFailed(e) => self.write_failed(now, e),
                Warning::Other(w) => self.notes.warn(w),
            }
        }
        if let Some((yaw, pitch)) = report.aim {
            if self.settings.gimbal.aim == GimbalAim::Border && self.autopilot.present() {
                self.gimbal.aim(yaw, pitch);
            }
        }
        if report.landing_requested {
            self.request_landing(now);
        }
    }

    /// The landing trigger fired: land if landing is enabled (IND_LAND_EN) and the
    /// vehicle is armed and in the air.
    fn request_landing(&mut self, now: Mono) {
        if !self.settings.indoor.landing_enabled {
            self.notes.info("landing trigger fired; landing is disabled (IND_LAND_EN 0)");
            return;
        }
        let a = &self.autopilot;
        if !a.present() || !a.armed() || !a.airborne() {
            let line = format!(
                "landing trigger fired, but the vehicle is not armed and in the air (armed {}, landed state {:?}); not landing",
                a.armed(),
                a.landed_state()
            );
            self.notes.warn(&line);
            return;
        }
        let i = &self.settings.indoor;
        // The floor is the local frame's z = 0 (its origin is on the floor).
        let target = i.landing_precision.then_some([i.landing_x_m, i.landing_y_m, 0.0]);
        if self.landing.request(now, target) {
            let line = match target {
                Some(t) => format!("landing requested: precision landing on x {:.2} y {:.2} m", t[0], t[1]),
                None => "landing requested: sending MAV_CMD_NAV_LAND".into(),
            };
            self.notes.push(MavSeverity::MAV_SEVERITY_NOTICE, &line);
        }
    }
}

/// A MAVLink FTP payload to `to`.
fn ftp_message(to: (u8, u8), payload: [u8; ftp::PAYLOAD]) -> MavMessage {
    MavMessage::FILE_TRANSFER_PROTOCOL(FILE_TRANSFER_PROTOCOL_DATA {
        target_network: 0,
        target_system: to.0,
        target_component: to.1,
        payload,
    })
}

fn param_name(id: &mavlink::types::CharArray<16>) -> Option<String> {
    id.to_str().ok().map(|n| n.trim_end_matches('\0').to_string())
}

/// Variance of the floor's distance as the vision estimate's z: PX4's default
/// rangefinder noise (EKF2_RNG_NOISE, 0.1 m).
const RANGE_VARIANCE: f64 = 0.01;

/// Higher than this above the floor's reading, the vehicle has left the floor (a
/// rangefinder's noise is a centimetre or two; SIH's leaves 0 as the vehicle lifts).
const LIFT_OFF_M: f64 = 0.05;

/// A pause in the vision stream after which EKF2 starts its vision fusion again (0.4 s
/// in PX4 v1.16), with a margin for the link's jitter ([`Core::vision_after_pause`]).
const EV_PAUSE: Duration = Duration::from_millis(300);

/// A position this loose (m^2, an SD of 5 m) is "somewhere near here", not a measurement:
/// never the first of EKF2's vision fusion ([`Core::vision_after_pause`]).
const LOOSE_VARIANCE: f32 = 25.0;

/// Without GPS, the pipeline silent this long in flight (the camera's frames stopped)
/// has the height held ([`Core::holding`]): under the 0.4 s after which EKF2 stops fusing
/// vision, over the 67 ms between frames.
const HOLD_AFTER: Duration = Duration::from_millis(250);

/// Variance reported for what the pipeline does not measure (z, attitude): large enough
/// that EKF2 would never lean on it, finite so nothing downstream divides by infinity.
const UNMEASURED_VARIANCE: f32 = 1.0e4;

/// ODOMETRY for an indoor estimate with the camera's velocity (body axes); `e` None: the
/// velocity alone (position NaN, which PX4 reads as "no position"). Position, z and the
/// echoed attitude as in [`vision_position_estimate`].
pub fn odometry(
    e: Option<&PositionEstimate>,
    v: &VelocityEstimate,
    usec: u64,
    attitude: (f64, f64, f64),
    down_var: Option<f64>,
) -> MavMessage {
    let (x, y, z, pose_covariance) = match e {
        Some(e) => (e.north as f32, e.east as f32, e.down as f32, pose_covariance(e, down_var)),
        None => (f32::NAN, f32::NAN, f32::NAN, [f32::NAN; 21]),
    };
    let q = nalgebra::UnitQuaternion::from_euler_angles(attitude.0, attitude.1, attitude.2);
    // Upper triangle of the 6x6 (vx, vy, vz, roll, pitch, yaw rates) covariance; the
    // rates are not measured (NaN, as MAVLink says for unknown).
    let mut velocity_covariance = [0f32; 21];
    velocity_covariance[0] = v.var[0] as f32;
    velocity_covariance[6] = v.var[1] as f32;
    velocity_covariance[11] = v.var[2] as f32;
    for i in [15, 18, 20] {
        velocity_covariance[i] = f32::NAN;
    }
    MavMessage::ODOMETRY(ODOMETRY_DATA {
        time_usec: usec,
        x,
        y,
        z,
        q: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
        vx: v.body[0] as f32,
        vy: v.body[1] as f32,
        vz: v.body[2] as f32,
        rollspeed: f32::NAN,
        pitchspeed: f32::NAN,
        yawspeed: f32::NAN,
        pose_covariance,
        velocity_covariance,
        frame_id: MavFrame::MAV_FRAME_LOCAL_NED,
        child_frame_id: MavFrame::MAV_FRAME_BODY_FRD,
        reset_counter: 0,
        estimator_type: MavEstimatorType::MAV_ESTIMATOR_TYPE_VISION,
        quality: 0,
    })
}

/// The upper triangle of the 6x6 (x, y, z, roll, pitch, yaw) covariance, row-major, as
/// MAVLink defines it, for an indoor estimate. `down_var`: z is measured (the camera's
/// distance to the floor) with this variance; None: z is not measured.
fn pose_covariance(e: &PositionEstimate, down_var: Option<f64>) -> [f32; 21] {
    let mut covariance = [0f32; 21];
    covariance[0] = e.cov[0][0] as f32;
    covariance[1] = e.cov[0][1] as f32;
    covariance[6] = e.cov[1][1] as f32;
    for i in [11, 15, 18, 20] {
        covariance[i] = UNMEASURED_VARIANCE;
    }
    if let Some(v) = down_var {
        covariance[11] = v as f32;
        // The attitude is the autopilot's own, echoed, and EKF2 never fuses roll or pitch
        // from vision; but PX4 v1.16 floors the height's variance with the roll/pitch
        // variance (ev_height_control.cpp), so "unmeasured" there would void z.
        for i in [15, 18] {
            covariance[i] = v as f32;
        }
    }
    covariance
}

/// VISION_POSITION_ESTIMATE for an indoor estimate, its covariance from [`pose_covariance`].
pub fn vision_position_estimate(
    e: &PositionEstimate,
    usec: u64,
    attitude: (f64, f64, f64),
    down_var: Option<f64>,
) -> MavMessage {
    let covariance = pose_covariance(e, down_var);
    MavMessage::VISION_POSITION_ESTIMATE(VISION_POSITION_ESTIMATE_DATA {
        usec,
        x: e.north as f32,
        y: e.east as f32,
        z: e.down as f32,
        roll: attitude.0 as f32,
        pitch: attitude.1 as f32,
        yaw: attitude.2 as f32,
        covariance,
        reset_counter: 0,
    })
}
