//! Time alignment: the stage between the sources (MAVLink telemetry, camera) and the
//! pipelines. It maps the autopilot's clock to the companion's monotonic clock, keeps a
//! short history of the vehicle pose and the gimbal attitude, and gives each frame the
//! pose interpolated at its capture time.
//!
//! Why it matters: area seed sec. 5.6.1 pairs each frame with the latest telemetry and
//! shows the cost (a gimbal that turns at 30 deg/s with 100 ms of lag puts bearings 3 deg
//! off, which the landmark filters then read as the world moving). Pure code: no clock of
//! its own, times are passed in, so the tests drive it with any timeline.
//!
//! Clock mapping, two estimators:
//! * TIMESYNC round trips (preferred): offset = tc1 - (ts1 + t_rx) / 2, valid to half the
//!   round-trip asymmetry; the estimate keeps the samples with the shortest round trips
//!   and fits a line through them, so a clock that runs at another rate is followed (PX4
//!   SIH's lockstep clock ran 1.07 % slow here: 10.7 ms a second, 320 ms over the 30 s
//!   window; taking the one shortest round trip of the window left frames aligned up to
//!   that far off and late by as much, 52-197 ms from capture to estimate from run to
//!   run). That rate changes with the machine's load (1.2-2.5 % slow from one 5 s stretch
//!   to the next), hence answers at 10 Hz and the line's level from the last 2 s of them,
//!   its rate from the whole window.
//! * Without TIMESYNC, the `time_boot_ms` stamps themselves: arrival = stamp + offset +
//!   delay with delay >= 0, so the smallest (arrival - stamp) over a sliding window is the
//!   offset plus the smallest delay seen (a lower-envelope estimate, robust to jitter).

use std::collections::VecDeque;

use mavloc_geometry::{body_rotation, CameraPose, GimbalAngles, GimbalChain, Mount, Rot3, Vec3};
use nalgebra::UnitQuaternion;

/// Autopilot boot times going back by more than this mean the autopilot rebooted.
const REBOOT_BACKSTEP_S: f64 = 1.0;
/// Sliding window of the lower-envelope estimator: long enough to see a quiet moment of
/// the link, short enough to follow crystal drift (100 ppm is 3 ms over 30 s).
const ENVELOPE_WINDOW_S: f64 = 30.0;
/// The TIMESYNC line's level comes from the answers of this last stretch (10 Hz), its
/// rate from all of the window (`ENVELOPE_WINDOW_S`): PX4 SITL's lockstep clock changes
/// its rate with the machine's load, 1.2-2.5 % slow from one 5 s stretch to the next
/// against PX4 v1.16 SIH. Fitted over that flight's logged offsets, a line through the
/// last 30 s was off by 18 ms (median, 47 ms at most) one second later. A line through
/// the last 5 s alone followed the changes, but its rate, from so short a span, swung
/// with the round trips' asymmetry (25 ms off a constant rate with round trips of up to
/// 100 ms, where the 30 s rate stays within 5 ms).
const TIMESYNC_LEVEL_S: f64 = 2.0;
/// At most this many answers kept: 30 s at 10 Hz.
const TIMESYNC_KEPT: usize = 320;

/// Which estimator the clock offset currently comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClockSource {
    None,
    Stamps,
    Timesync,
}

/// Autopilot time <-> local monotonic time, both in seconds.
#[derive(Clone, Debug)]
pub struct ClockSync {
    /// (local arrival, arrival - stamp) for the lower envelope.
    stamps: VecDeque<(f64, f64)>,
    /// (local time, round trip, offset local - autopilot) of recent TIMESYNC replies.
    syncs: VecDeque<(f64, f64, f64)>,
    /// The line fitted through `syncs` (`timesync_line`), refitted when they change: the
    /// mappings below run on every message and frame.
    line: Option<(f64, f64, f64)>,
    last_stamp: Option<f64>,
    /// Local arrival of the stamp that set `last_stamp`.
    last_arrival: Option<f64>,
}

/// The round-trip excess over the shortest at which a TIMESYNC sample's weight halves
/// twice: samples within it count nearly fully.
const RTT_SLACK_S: f64 = 0.001;
/// The fitted rate of one clock against the other is bounded: crystals differ by 100 ppm,
/// a simulator's lockstep clock by a few percent.
const MAX_RATE: f64 = 0.05;
/// Rates below this are not applied (see `timesync_line`).
const MIN_RATE: f64 = 1e-6;

/// A stamp further ahead of the last one than the local time elapsed since, plus this,
/// is not believed: the autopilot's clock cannot run faster than ours.
const FUTURE_JUMP_S: f64 = 5.0;

impl Default for ClockSync {
    fn default() -> Self {
        ClockSync::new()
    }
}

/// Over TIMESYNC samples (local time, round trip, offset), weighted by how short each
/// round trip is against the shortest: the weighted mean time and offset, the sums for the
/// slope (time spread, time-offset covariance), and the weights' sum.
fn weighted_line<'a>(syncs: impl Iterator<Item = &'a (f64, f64, f64)> + Clone) -> (f64, f64, f64, f64, f64) {
    let Some(best) = syncs.clone().min_by(|a, b| a.1.total_cmp(&b.1)) else {
        return (f64::NAN, f64::NAN, 0.0, 0.0, 0.0);
    };
    let (min_rtt, o_ref) = (best.1, best.2);
    let w = |rtt: f64| 1.0 / (rtt - min_rtt + RTT_SLACK_S).powi(2);
    let sw: f64 = syncs.clone().map(|s| w(s.1)).sum();
    let t0 = syncs.clone().map(|s| w(s.1) * s.0).sum::<f64>() / sw;
    // Offsets about the best sample's, so that equal offsets give exactly it back.
    let o0 = o_ref + syncs.clone().map(|s| w(s.1) * (s.2 - o_ref)).sum::<f64>() / sw;
    let stt: f64 = syncs.clone().map(|s| w(s.1) * (s.0 - t0).powi(2)).sum();
    let sto: f64 = syncs.map(|s| w(s.1) * (s.0 - t0) * (s.2 - o0)).sum();
    (t0, o0, stt, sto, sw)
}

impl ClockSync {
    pub fn new() -> ClockSync {
        ClockSync {
            stamps: VecDeque::new(),
            syncs: VecDeque::new(),
            line: None,
            last_stamp: None,
            last_arrival: None,
        }
    }

    /// Whether a stamp arriving at `arrival` can be true: not further ahead of the last
    /// one than the time that passed here (plus 5 s). A stamp from the future (a bad
    /// clock, a forged frame) would otherwise skew the offset and make the next true
    /// stamp look like a reboot; callers drop such messages.
    pub fn plausible(&self, stamp: f64, arrival: f64) -> bool {
        match (self.last_stamp, self.last_arrival) {
            (Some(last), Some(at)) => stamp <= last + (arrival - at).max(0.0) + FUTURE_JUMP_S,
            _ => true,
        }
    }

    /// Would this stamp say the autopilot rebooted (its boot clock ran backwards)?
    pub fn is_backstep(&self, stamp: f64) -> bool {
        matches!(self.last_stamp, Some(last) if stamp < last - REBOOT_BACKSTEP_S)
    }

    /// A telemetry stamp (autopilot seconds since boot) that arrived at local time
    /// `arrival`. Returns true when the stamp says the autopilot rebooted; the estimate is
    /// then reset.
    pub fn observe_stamp(&mut self, stamp: f64, arrival: f64) -> bool {
        let rebooted = matches!(self.last_stamp, Some(last) if stamp < last - REBOOT_BACKSTEP_S);
        if rebooted {
            self.stamps.clear();
            self.syncs.clear();
            self.line = None;
        }
        let newest = match self.last_stamp {
            Some(last) if !rebooted => last.max(stamp),
            _ => stamp,
        };
        if Some(newest) != self.last_stamp {
            self.last_arrival = Some(arrival);
        }
        self.last_stamp = Some(newest);
        let d = arrival - stamp;
        // Keep the lower envelope only: a sample above a later, smaller one can never be
        // the minimum again.
        while matches!(self.stamps.back(), Some(&(_, v)) if v >= d) {
            self.stamps.pop_back();
        }
        self.stamps.push_back((arrival, d));
        while matches!(self.stamps.front(), Some(&(t, _)) if t < arrival - ENVELOPE_WINDOW_S) {
            self.stamps.pop_front();
        }
        rebooted
    }

    /// A TIMESYNC reply: `sent` and `received` are local times of our request and of the
    /// reply, `remote` the autopilot's time in the reply.
    pub fn observe_timesync(&mut self, sent: f64, received: f64, remote: f64) {
        let rtt = received - sent;
        if !(0.0..1.0).contains(&rtt) {
            return;
        }
        let offset = (sent + received) / 2.0 - remote;
        self.syncs.push_back((received, rtt, offset));
        while matches!(self.syncs.front(), Some(&(t, _, _)) if t < received - ENVELOPE_WINDOW_S) {
            self.syncs.pop_front();
        }
        while self.syncs.len() > TIMESYNC_KEPT {
            self.syncs.pop_front();
        }
        self.line = self.timesync_line();
    }

    /// The TIMESYNC offset as a line in local time: `(t0, offset at t0, rate)`. Both parts
    /// are least squares weighted by how short each round trip is (a reply's error is at
    /// most half its round trip's asymmetry, so the shortest dominate): the rate fitted
    /// over the whole window, where the others, spread over it, still show it; the level,
    /// with that rate, over the last `TIMESYNC_LEVEL_S`, so a rate that changes is
    /// followed. (The samples are few: no solver crate.)
    fn timesync_line(&self) -> Option<(f64, f64, f64)> {
        let newest = self.syncs.back()?.0;
        let (_, _, stt, sto, sw) = weighted_line(self.syncs.iter());
        // A rate needs samples spread in time (a weighted spread of about a second).
        let rate = if stt > 0.5 * sw { (sto / stt).clamp(-MAX_RATE, MAX_RATE) } else { 0.0 };
        // Under a part per million a fitted rate is rounding noise (3 us over the window):
        // dropped, so that the two mappings stay exact inverses of each other (a live test
        // pairing frames with poses by equal times took other pairs with a rate of 1e-16).
        let rate = if rate.abs() < MIN_RATE { 0.0 } else { rate };
        let recent = self.syncs.iter().filter(|s| s.0 >= newest - TIMESYNC_LEVEL_S);
        let (t1, o1, ..) = weighted_line(recent);
        Some((t1, o1, rate))
    }

    /// Local minus autopilot time now (at the newest sample), and where it came from.
    pub fn offset(&self) -> (Option<f64>, ClockSource) {
        if let Some(&(t, _, _)) = self.syncs.back() {
            return (self.offset_at(t), ClockSource::Timesync);
        }
        match self.stamps.front() {
            Some(&(_, d)) => (Some(d), ClockSource::Stamps),
            None => (None, ClockSource::None),
        }
    }

    /// Local minus autopilot time at local time `local`.
    fn offset_at(&self, local: f64) -> Option<f64> {
        match self.line {
            Some((t0, o0, rate)) => Some(o0 + rate * (local - t0)),
            None => self.stamps.front().map(|&(_, d)| d),
        }
    }

    pub fn to_local(&self, autopilot: f64) -> Option<f64> {
        match self.line {
            // local = autopilot + o0 + rate (local - t0), solved for local.
            Some((t0, o0, rate)) => Some((autopilot + o0 - rate * t0) / (1.0 - rate)),
            None => self.offset().0.map(|o| autopilot + o),
        }
    }

    pub fn to_autopilot(&self, local: f64) -> Option<f64> {
        self.offset_at(local).map(|o| local - o)
    }
}

/// Values that can be interpolated between two samples.
pub trait Interpolate: Clone {
    fn lerp(&self, other: &Self, s: f64) -> Self;
}

/// A bounded, time-ordered history of samples.
#[derive(Clone, Debug)]
pub struct History<T> {
    samples: VecDeque<(f64, T)>,
    span_s: f64,
}

/// Why a value is not available at a time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Missing {
    /// No sample yet.
    Empty,
    /// The time is after the newest sample: wait for telemetry to catch up.
    Ahead { newest: f64 },
    /// The time is before the oldest sample kept.
    TooOld { oldest: f64 },
    /// The neighbouring samples are too far apart to interpolate honestly.
    Gap { gap_s: f64 },
}

impl Missing {
    /// The case, without its numbers.
    pub fn name(&self) -> &'static str {
        match self {
            Missing::Empty => "Empty",
            Missing::Ahead { .. } => "Ahead",
            Missing::TooOld { .. } => "TooOld",
            Missing::Gap { .. } => "Gap",
        }
    }
}

impl<T: Interpolate> History<T> {
    pub fn new(span_s: f64) -> History<T> {
        History { samples: VecDeque::new(), span_s }
    }

    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    pub fn clear(&mut self) {
        self.samples.clear();
    }

    pub fn newest(&self) -> Option<(f64, &T)> {
        self.samples.back().map(|(t, v)| (*t, v))
    }

    /// Adds a sample; out-of-order samples are put in place (UDP may reorder).
    pub fn push(&mut self, t: f64, value: T) {
        let at = self.samples.iter().rposition(|(ts, _)| *ts <= t).map_or(0, |i| i + 1);
        if at > 0 && self.samples[at - 1].0 == t {
            self.samples[at - 1].1 = value;
        } else {
            self.samples.insert(at, (t, value));
        }
        let newest = self.samples.back().expect("just pushed").0;
        while matches!(self.samples.front(), Some((ts, _)) if *ts < newest - self.span_s) {
            self.samples.pop_front();
        }
    }

    /// The value at time `t`, interpolated between the samples around it. `max_gap_s`
    /// bounds the distance between those samples; `hold_s` lets a time slightly after
    /// the newest sample take that sample.
    pub fn at(&self, t: f64, max_gap_s: f64, hold_s: f64) -> Result<T, Missing> {
        let (&(t0, _), &(t1, ref v1)) = match (self.samples.front(), self.samples.back()) {
            (Some(a), Some(b)) => (a, b),
            _ => return Err(Missing::Empty),
        };
        if t > t1 {
            return if t - t1 <= hold_s { Ok(v1.clone()) } else { Err(Missing::Ahead { newest: t1 }) };
        }
        if t < t0 {
            return Err(Missing::TooOld { oldest: t0 });
        }
        let i = self.samples.partition_point(|(ts, _)| *ts <= t);
        if i == self.samples.len() {
            return Ok(v1.clone());
        }
        let (ta, a) = &self.samples[i - 1];
        let (tb, b) = &self.samples[i];
        let gap = tb - ta;
        if gap > max_gap_s {
            return Err(Missing::Gap { gap_s: gap });
        }
        Ok(a.lerp(b, if gap > 0.0 { (t - ta) / gap } else { 0.0 }))
    }
}

/// Vehicle state from ATTITUDE and LOCAL_POSITION_NED.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleSample {
    pub position: Vec3,
    pub velocity: Vec3,
    pub attitude: UnitQuaternion<f64>,
}

impl Interpolate for VehicleSample {
    fn lerp(&self, o: &Self, s: f64) -> Self {
        VehicleSample {
            position: self.position.lerp(&o.position, s),
            velocity: self.velocity.lerp(&o.velocity, s),
            attitude: self.attitude.try_slerp(&o.attitude, s, 1e-9).unwrap_or(self.attitude),
        }
    }
}

/// Yaw reference of a gimbal attitude (gimbal protocol v2 flags).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum YawFrame {
    Earth,
    Vehicle,
}

/// Gimbal attitude from GIMBAL_DEVICE_ATTITUDE_STATUS: rotation "reference <- gimbal
/// FRD", the reference being NED (earth frame) or NED turned by the vehicle's heading.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GimbalSample {
    pub q: UnitQuaternion<f64>,
    pub frame: YawFrame,
}

impl Interpolate for GimbalSample {
    fn lerp(&self, o: &Self, s: f64) -> Self {
        if self.frame != o.frame {
            // The reference changed between samples: no meaningful midpoint.
            return if s < 0.5 { *self } else { *o };
        }
        GimbalSample { q: self.q.try_slerp(&o.q, s, 1e-9).unwrap_or(self.q), frame: self.frame }
    }
}

impl GimbalSample {
    /// From the message fields: `q` as (w, x, y, z) and the flag bits. Gimbal protocol v2:
    /// YAW_IN_EARTH_FRAME (64) or YAW_IN_VEHICLE_FRAME (32); older devices set neither and
    /// mean earth frame when YAW_LOCK (16) is set.
    pub fn from_status(q: [f32; 4], flags: u16) -> Option<GimbalSample> {
        let q = nalgebra::Quaternion::new(q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64);
        if !(q.norm() > 0.5 && q.norm() < 1.5) || q.coords.iter().any(|c| !c.is_finite()) {
            return None;
        }
        let frame = if flags & 64 != 0 {
            YawFrame::Earth
        } else if flags & 32 != 0 {
            YawFrame::Vehicle
        } else if flags & 16 != 0 {
            YawFrame::Earth
        } else {
            YawFrame::Vehicle
        };
        Some(GimbalSample { q: UnitQuaternion::from_quaternion(q), frame })
    }
}

/// How the camera is mounted when no gimbal reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FixedMount {
    pub chain: GimbalChain,
    pub angles: GimbalAngles,
}

/// Static corrections added to reported gimbal angles (area sec. 6.10-6.11).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GimbalOffsets {
    pub chain: GimbalChain,
    pub yaw: f64,
    pub pitch: f64,
    pub roll: f64,
}

impl GimbalOffsets {
    fn is_zero(&self) -> bool {
        self.yaw == 0.0 && self.pitch == 0.0 && self.roll == 0.0
    }
}

/// What a frame gets: the vehicle state and camera pose at its capture time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignedPose {
    /// Autopilot time of the capture, seconds since its boot.
    pub autopilot_time: f64,
    pub vehicle: VehicleSample,
    pub camera: CameraPose,
    /// Whether the camera attitude came from gimbal telemetry (else the fixed mount).
    pub from_gimbal: bool,
}

/// Why a frame cannot be aligned (yet).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlignError {
    /// The clock offset is not known yet.
    NoClock,
    /// Telemetry for the capture time has not arrived yet: try again shortly.
    Wait,
    /// The vehicle history cannot give the pose at that time.
    Vehicle(Missing),
    /// The gimbal history cannot give the attitude at that time.
    Gimbal(Missing),
}

impl AlignError {
    /// What went wrong without the numbers of this frame, to count drops by: the
    /// `Display` text carries times that change with every frame.
    pub fn kind(&self) -> String {
        match self {
            AlignError::NoClock | AlignError::Wait => self.to_string(),
            AlignError::Vehicle(m) => format!("no vehicle pose at the capture time ({})", m.name()),
            AlignError::Gimbal(m) => format!("no gimbal attitude at the capture time ({})", m.name()),
        }
    }
}

impl std::fmt::Display for AlignError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            AlignError::NoClock => write!(f, "autopilot clock not synchronised yet"),
            AlignError::Wait => write!(f, "telemetry for the capture time not arrived yet"),
            AlignError::Vehicle(m) => write!(f, "no vehicle pose at the capture time ({m:?})"),
            AlignError::Gimbal(m) => write!(f, "no gimbal attitude at the capture time ({m:?})"),
        }
    }
}

/// Parameters of the aligner.
#[derive(Clone, Copy, Debug)]
pub struct AlignParams {
    /// History kept, seconds.
    pub span_s: f64,
    /// Largest gap between two samples that is interpolated across.
    pub max_gap_s: f64,
    /// A capture this little after the newest sample takes that sample instead of waiting.
    /// 0 by default: holding is exactly the stale pairing this stage exists to avoid; the
    /// daemon waits (boundedly) for telemetry to catch up instead.
    pub hold_s: f64,
    /// Use gimbal telemetry (else the fixed mount).
    pub use_gimbal: bool,
}

impl Default for AlignParams {
    fn default() -> Self {
        AlignParams { span_s: 5.0, max_gap_s: 0.5, hold_s: 0.0, use_gimbal: true }
    }
}

/// The time-alignment stage.
pub struct Aligner {
    pub clock: ClockSync,
    pub vehicle: History<VehicleSample>,
    pub gimbal: History<GimbalSample>,
    params: AlignParams,
    mount: FixedMount,
    offsets: GimbalOffsets,
    /// Local time the gimbal last reported, to fall back to the mount when it stops.
    gimbal_seen: Option<f64>,
}

impl Aligner {
    pub fn new(params: AlignParams, mount: FixedMount, offsets: GimbalOffsets) -> Aligner {
        Aligner {
            clock: ClockSync::new(),
            vehicle: History::new(params.span_s),
            gimbal: History::new(params.span_s),
            params,
            mount,
            offsets,
            gimbal_seen: None,
        }
    }

    pub fn set_params(&mut self, params: AlignParams, mount: FixedMount, offsets: GimbalOffsets) {
        self.params = params;
        self.mount = mount;
        self.offsets = offsets;
    }

    /// The autopilot rebooted: its clock and everything stamped with it is void.
    pub fn reset(&mut self) {
        self.clock = ClockSync::new();
        self.vehicle.clear();
        self.gimbal.clear();
        self.gimbal_seen = None;
    }

    pub fn push_vehicle(&mut self, stamp: f64, sample: VehicleSample) {
        self.vehicle.push(stamp, sample);
    }

    pub fn push_gimbal(&mut self, stamp: f64, sample: GimbalSample, local_now: f64) {
        self.gimbal.push(stamp, sample);
        self.gimbal_seen = Some(local_now);
    }

    /// The newest autopilot time with telemetry for a whole pose at local time `now`:
    /// the vehicle's newest sample, or the gimbal's when that is older (a gimbal device's
    /// clock, mapped onto the autopilot's, can put its report a hair before the
    /// vehicle's sent at the same moment). Where a pose can be had now, for the sim
    /// camera.
    pub fn newest_complete(&self, now: f64) -> Option<f64> {
        let (v, _) = self.vehicle.newest()?;
        match self.gimbal.newest() {
            Some((g, _)) if self.gimbal_live(now) => Some(v.min(g)),
            _ => Some(v),
        }
    }

    /// Whether gimbal telemetry is in use at local time `now` (reported within 2 s).
    pub fn gimbal_live(&self, now: f64) -> bool {
        self.params.use_gimbal && matches!(self.gimbal_seen, Some(t) if now - t < 2.0)
    }

    /// The pose at local capture time `capture`, seen from local time `now`.
    pub fn align(&self, capture: f64, now: f64) -> Result<AlignedPose, AlignError> {
        let t = self.clock.to_autopilot(capture).ok_or(AlignError::NoClock)?;
        let p = &self.params;
        let vehicle = match self.vehicle.at(t, p.max_gap_s, p.hold_s) {
            Ok(v) => v,
            Err(Missing::Ahead { .. }) => return Err(AlignError::Wait),
            Err(m) => return Err(AlignError::Vehicle(m)),
        };
        let (roll, pitch, yaw) = vehicle.attitude.euler_angles();
        let body = body_rotation(roll, pitch, yaw);
        let (camera, from_gimbal) = if self.gimbal_live(now) {
            let g = match self.gimbal.at(t, p.max_gap_s, p.hold_s) {
                Ok(g) => g,
                Err(Missing::Ahead { .. }) => return Err(AlignError::Wait),
                Err(m) => return Err(AlignError::Gimbal(m)),
            };
            (self.gimbal_pose(vehicle.position, yaw, &g), true)
        } else {
            let pose = CameraPose::from_gimbal(
                vehicle.position,
                self.mount.chain,
                self.mount.angles,
                Mount::Body { attitude: body },
            );
            (pose, false)
        };
        Ok(AlignedPose { autopilot_time: t, vehicle, camera, from_gimbal })
    }

    fn gimbal_pose(&self, position: Vec3, vehicle_yaw: f64, g: &GimbalSample) -> CameraPose {
        let mount = match g.frame {
            YawFrame::Earth => Mount::Earth,
            YawFrame::Vehicle => Mount::VehicleHeading { vehicle_yaw },
        };
        let r: Rot3 = g.q.to_rotation_matrix();
        if self.offsets.is_zero() {
            let attitude = match mount {
                Mount::VehicleHeading { vehicle_yaw } => {
                    Rot3::from_axis_angle(&Vec3::z_axis(), vehicle_yaw) * r
                }
                _ => r,
            };
            return CameraPose { position, attitude };
        }
        let chain = self.offsets.chain;
        let a = chain.angles(&r);
        let a = GimbalAngles {
            yaw: a.yaw + self.offsets.yaw,
            pitch: a.pitch + self.offsets.pitch,
            roll: a.roll + self.offsets.roll,
        };
        CameraPose::from_gimbal(position, chain, a, mount)
    }
}

#[cfg(test)]
mod tests {
    /// Drops are counted by kind: two frames too old for the history, at different times,
    /// are one kind, though their messages differ by the times in them.
    #[test]
    fn an_alignment_errors_kind_leaves_out_this_frames_numbers() {
        use super::{AlignError, Missing};
        let a = AlignError::Vehicle(Missing::TooOld { oldest: 1712.34 });
        let b = AlignError::Vehicle(Missing::TooOld { oldest: 1713.01 });
        assert_ne!(a.to_string(), b.to_string());
        assert_eq!(a.kind(), b.kind());
        assert_eq!(a.kind(), "no vehicle pose at the capture time (TooOld)");
        assert_eq!(
            AlignError::Gimbal(Missing::Empty).kind(),
            "no gimbal attitude at the capture time (Empty)"
        );
        assert_ne!(a.kind(), AlignError::Vehicle(Missing::Gap { gap_s: 0.6 }).kind());
    }

    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};

    fn vehicle_at(t: f64) -> VehicleSample {
        // Flying east at 5 m/s, yawing at 0.2 rad/s.
        VehicleSample {
            position: Vec3::new(0.0, 5.0 * t, -30.0),
            velocity: Vec3::new(0.0, 5.0, 0.0),
            attitude: UnitQuaternion::from_euler_angles(0.0, 0.0, 0.2 * t),
        }
    }

    /// A gimbal sweeping its yaw at 30 deg/s (the seed's worst case), pitched down 60 deg.
    fn gimbal_at(t: f64) -> GimbalSample {
        let r = GimbalChain::YawPitchRoll.rotation(GimbalAngles {
            yaw: (30.0 * t).to_radians(),
            pitch: -60f64.to_radians(),
            roll: 0.0,
        });
        GimbalSample { q: UnitQuaternion::from_rotation_matrix(&r), frame: YawFrame::Earth }
    }

    fn aligner() -> Aligner {
        Aligner::new(
            AlignParams::default(),
            FixedMount {
                chain: GimbalChain::YawPitchRoll,
                angles: GimbalAngles::from_degrees(0.0, -90.0, 0.0),
            },
            GimbalOffsets { chain: GimbalChain::YawPitchRoll, yaw: 0.0, pitch: 0.0, roll: 0.0 },
        )
    }

    fn angle_between(a: &Rot3, b: &Rot3) -> f64 {
        (a.transpose() * b).angle()
    }

    #[test]
    fn lower_envelope_finds_the_offset_through_jitter() {
        let mut c = ClockSync::new();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let offset = 1234.5; // local = autopilot + offset
        for i in 0..500 {
            let stamp = i as f64 * 0.02;
            let delay = 0.002 + rng.random::<f64>().powi(3) * 0.2;
            c.observe_stamp(stamp, stamp + offset + delay);
        }
        let (o, src) = c.offset();
        assert_eq!(src, ClockSource::Stamps);
        assert!((o.unwrap() - offset - 0.002).abs() < 0.003, "{o:?}");
    }

    #[test]
    fn timesync_wins_and_uses_the_shortest_round_trip() {
        let mut c = ClockSync::new();
        c.observe_stamp(10.0, 110.5);
        // Replies with asymmetric delays: the 2 ms round trip bounds the error by 1 ms.
        c.observe_timesync(100.0, 100.2, 0.0 + 100.05 - 90.0); // rtt 200 ms, skewed
        c.observe_timesync(101.0, 101.002, 101.001 - 90.0); // rtt 2 ms
        let (o, src) = c.offset();
        assert_eq!(src, ClockSource::Timesync);
        assert!((o.unwrap() - 90.0).abs() < 0.001);
    }

    proptest! {
        /// An autopilot clock running at another rate (a simulator's lockstep clock, 1 %
        /// slow against PX4 SIH here) is followed: a minute of 10 Hz TIMESYNC with round
        /// trips of up to 100 ms, each way's delay drawn on its own, maps times both ways to
        /// within 5 ms, where the one shortest round trip of the window was up to the whole
        /// window's drift off.
        #[test]
        fn timesync_follows_a_clock_that_runs_at_another_rate(
            rate in -0.03f64..0.03, offset in -1000.0f64..1000.0, seed in 0u64..1000,
        ) {
            let mut c = ClockSync::new();
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            // autopilot = (local - offset) * (1 + rate)
            let ap = |local: f64| (local - offset) * (1.0 + rate);
            for i in 0..600 {
                let sent = 5000.0 + i as f64 * 0.1;
                let (up, down) = (0.0002 + rng.random::<f64>().powi(4) * 0.05, 0.0002 + rng.random::<f64>().powi(4) * 0.05);
                c.observe_timesync(sent, sent + up + down, ap(sent + up));
            }
            let now = 5060.0;
            let err = c.to_autopilot(now).unwrap() - ap(now);
            prop_assert_eq!(c.offset().1, ClockSource::Timesync);
            prop_assert!(err.abs() < 0.005, "to_autopilot off by {:.1} ms", err * 1e3);
            let back = c.to_local(ap(now)).unwrap() - now;
            prop_assert!(back.abs() < 0.005, "to_local off by {:.1} ms", back * 1e3);
        }
    }

    /// PX4 SITL's lockstep clock changes its rate with the machine's load: against PX4
    /// v1.16 SIH it ran 1.2-2.5 % slow from one 5 s stretch to the next. A clock that
    /// switches between those rates every 5 s (answers at 10 Hz, round trips under 2 ms)
    /// is followed to within 8.4 ms until the next answer, 6.8 ms at the median. Asked
    /// once a second, as before, with the line through 30 s of answers: 20.9 and 9.8 ms.
    /// (A line through the last 5 s alone: 11.6 and 6.3 ms, but its rate swings with the
    /// round trips, which `timesync_follows_a_clock_that_runs_at_another_rate` catches.)
    #[test]
    fn timesync_follows_a_clock_whose_rate_changes_with_the_load() {
        let mut c = ClockSync::new();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        // The autopilot's clock, integrated: 1.2 % slow, then 2.5 %, every 5 s in turn.
        let rate = |local: f64| if ((local / 5.0) as u64).is_multiple_of(2) { 0.988 } else { 0.975 };
        let (mut ap, mut local) = (100.0, 0.0);
        let mut errors = Vec::new();
        for _ in 0..900 {
            let (up, down) = (0.0002 + rng.random::<f64>() * 0.0008, 0.0002 + rng.random::<f64>() * 0.0008);
            let remote = ap + up * rate(local);
            c.observe_timesync(local, local + up + down, remote);
            ap += 0.1 * rate(local);
            local += 0.1;
            if local > 10.0 {
                errors.push((c.to_autopilot(local).unwrap() - ap).abs() * 1e3);
            }
        }
        errors.sort_by(f64::total_cmp);
        let (median, worst) = (errors[errors.len() / 2], errors[errors.len() - 1]);
        assert!(worst < 12.0 && median < 8.5, "off by {median:.1} ms at the median, {worst:.1} ms at worst");
    }

    #[test]
    fn a_reboot_resets_the_clock() {
        let mut c = ClockSync::new();
        assert!(!c.observe_stamp(500.0, 1000.0));
        assert!(c.observe_stamp(0.5, 1001.0));
        // A stamp from the future is not plausible; the next true one is no reboot.
        assert!(c.plausible(1.5, 1002.0) && c.plausible(6.0, 1002.0) && !c.plausible(7.0, 1002.0));
        assert!(!c.plausible(5000.0, 1002.0));
        assert!(!c.observe_stamp(1.5, 1002.0));
        assert!((c.offset().0.unwrap() - 1000.5).abs() < 1e-9);
    }

    /// A frame gets the pose at its capture time, not the latest telemetry's, with a
    /// gimbal that reports 120 ms late and jittery arrival.
    #[test]
    fn frames_get_the_pose_at_capture_time_despite_lag_and_jitter() {
        let mut a = aligner();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let offset = 50.0;
        // Telemetry at 50 Hz over 4 s, arriving with 1-30 ms jitter; the gimbal's status
        // arrives 120 ms after its stamp.
        let mut arrivals: Vec<(f64, bool, f64)> = Vec::new();
        for i in 0..200 {
            let t = i as f64 * 0.02;
            arrivals.push((t + offset + 0.001 + rng.random::<f64>() * 0.029, false, t));
            arrivals.push((t + offset + 0.12 + rng.random::<f64>() * 0.01, true, t));
        }
        arrivals.sort_by(|x, y| x.0.total_cmp(&y.0));
        let capture_stamp = 2.013; // a frame captured between samples
        let capture = capture_stamp + offset;
        let mut naive_error = None;
        let mut result = Err(AlignError::NoClock);
        for &(arrival, is_gimbal, t) in &arrivals {
            if is_gimbal {
                a.push_gimbal(t, gimbal_at(t), arrival);
            } else {
                a.clock.observe_stamp(t, arrival);
                a.push_vehicle(t, vehicle_at(t));
            }
            if arrival > capture && naive_error.is_none() {
                // What pairing with the latest gimbal sample would have given.
                let (_, g) = a.gimbal.newest().unwrap();
                let truth = gimbal_at(capture_stamp).q.to_rotation_matrix();
                naive_error = Some(angle_between(&g.q.to_rotation_matrix(), &truth));
            }
            if arrival > capture {
                result = a.align(capture, arrival);
                if result.is_ok() {
                    break;
                }
                assert_eq!(result.unwrap_err(), AlignError::Wait, "the lagging gimbal means wait");
            }
        }
        let pose = result.expect("aligned once the gimbal caught up");
        let truth = gimbal_at(capture_stamp).q.to_rotation_matrix();
        let err = angle_between(&pose.camera.attitude, &truth);
        assert!(err < 0.05f64.to_radians(), "aligned attitude error {} deg", err.to_degrees());
        assert!(naive_error.unwrap() > 2.0f64.to_radians(), "latest-sample pairing error is degrees");
        // Position is interpolated too: 5 m/s east, a few mm at most from the clock error.
        assert!((pose.vehicle.position - vehicle_at(capture_stamp).position).norm() < 0.02);
        assert!(pose.from_gimbal);
    }

    #[test]
    fn vehicle_frame_yaw_adds_the_heading_and_no_gimbal_uses_the_mount() {
        let mut a = aligner();
        a.clock.observe_stamp(0.0, 0.0);
        let heading = 0.7;
        for i in 0..10 {
            let t = i as f64 * 0.1;
            a.push_vehicle(
                t,
                VehicleSample {
                    position: Vec3::zeros(),
                    velocity: Vec3::zeros(),
                    attitude: UnitQuaternion::from_euler_angles(0.0, 0.0, heading),
                },
            );
        }
        // Without gimbal telemetry: the fixed mount, straight down.
        let p = a.align(0.45, 0.5).unwrap();
        assert!(!p.from_gimbal);
        let down = p.camera.attitude * Vec3::x();
        assert!((down - Vec3::z()).norm() < 1e-9);
        // A gimbal reporting level, yaw 0 in the vehicle frame: looks along the heading.
        for i in 0..10 {
            let t = i as f64 * 0.1;
            a.push_gimbal(t, GimbalSample { q: UnitQuaternion::identity(), frame: YawFrame::Vehicle }, 0.5);
        }
        let p = a.align(0.45, 0.5).unwrap();
        let fwd = p.camera.attitude * Vec3::x();
        assert!((fwd - Vec3::new(heading.cos(), heading.sin(), 0.0)).norm() < 1e-9);
    }

    #[test]
    fn flags_pick_the_yaw_frame() {
        let q = [1.0, 0.0, 0.0, 0.0];
        assert_eq!(GimbalSample::from_status(q, 64).unwrap().frame, YawFrame::Earth);
        assert_eq!(GimbalSample::from_status(q, 32).unwrap().frame, YawFrame::Vehicle);
        assert_eq!(GimbalSample::from_status(q, 16).unwrap().frame, YawFrame::Earth);
        assert_eq!(GimbalSample::from_status(q, 0).unwrap().frame, YawFrame::Vehicle);
        assert!(GimbalSample::from_status([f32::NAN, 0.0, 0.0, 0.0], 64).is_none());
        assert!(GimbalSample::from_status([0.0; 4], 64).is_none());
    }

    proptest! {
        /// Interpolating samples of a linear signal gives the signal, whatever the order
        /// samples arrive in; times outside the history are refused, not extrapolated.
        #[test]
        fn history_interpolates_linear_signals(
            times in proptest::collection::vec(0.0f64..4.0, 2..60),
            q in 0.0f64..1.0,
        ) {
            #[derive(Clone, Debug)]
            struct S(f64);
            impl Interpolate for S {
                fn lerp(&self, o: &Self, s: f64) -> Self { S(self.0 + (o.0 - self.0) * s) }
            }
            let mut h = History::new(10.0);
            for &t in &times {
                h.push(t, S(3.0 * t + 1.0));
            }
            let lo = times.iter().cloned().fold(f64::INFINITY, f64::min);
            let hi = times.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let t = lo + q * (hi - lo);
            let v = h.at(t, 10.0, 0.0).unwrap();
            prop_assert!((v.0 - (3.0 * t + 1.0)).abs() < 1e-9);
            prop_assert_eq!(h.at(hi + 1.0, 10.0, 0.0).unwrap_err(), Missing::Ahead { newest: hi });
            prop_assert!(h.at(lo - 1.0, 10.0, 0.0).is_err());
        }
    }
}
