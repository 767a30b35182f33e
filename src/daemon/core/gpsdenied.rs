//! GPS-denied start-up (`indoor.gps_denied`): an autopilot with no GPS has no position
//! until an external one arrives and no global origin until one is given, and refuses to
//! arm without both. The order PX4 v1.16 needs (measured, `../shared/data/px4-sitl`):
//! vision estimates from power-on, then SET_GPS_GLOBAL_ORIGIN after about 5 s of them,
//! then arming once its pre-arm checks pass (about 4.5 s after the origin).
//!
//! Standing on the ground the downward camera sees a hand's width of floor the texton
//! model was never trained on, so while the vehicle is on the floor mavloc sends where
//! it stands, and that it is still: the pad (`indoor.pad_x_m/y_m`) until its first
//! estimate in the air, then where the particles last put it before touchdown. Off the
//! floor but below `indoor.min_height_m` (climbing, touching down) it cannot localise:
//! x and y go out with an SD of `BLIND_SD_M`, which EKF2 weighs at next to nothing, with
//! the camera's velocity when it has one, while z (the rangefinder's) stays tight. High
//! enough, the pipeline's estimates go out and these stop.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;
use super::{odometry, PositionEstimate, VelocityEstimate};
use crate::geometry::Geodetic;

/// Standing estimates go out at this rate (PX4's EKF2 wants vision at 30 Hz or so; a
/// gap of more than its timeout drops the position).
pub const GROUND_PERIOD: Duration = Duration::from_micros(33_333);
/// Vision this long before the origin: PX4 takes an origin only once its local position
/// from vision is up.
pub const ORIGIN_AFTER: Duration = Duration::from_secs(5);
/// The origin is resent this often until the autopilot echoes it (GPS_GLOBAL_ORIGIN).
const ORIGIN_RETRY: Duration = Duration::from_secs(3);
pub const ORIGIN_TRIES: u32 = 3;
/// The pad is placed by hand: a few centimetres.
const PAD_SD_M: f64 = 0.05;
/// x and y while off the floor and too low to localise: "somewhere near here". Sent
/// tight instead (the vehicle "stands" in the air), EKF2 explained the true drift of the
/// climb as an accelerometer bias and carried that wrong velocity (0.4 m/s) for seconds
/// after the camera saw again; measured against PX4 v1.16 SIH, the vehicle was lost.
/// Over a 3 s climb at 30 Hz this still weighs as one measurement of about 1 m SD.
pub const BLIND_SD_M: f64 = 10.0;
/// While the pipeline is silent in flight, the held estimates' period: under the 0.4 s
/// after which EKF2 stops fusing vision, and no faster, so that they weigh little.
const HOLD_PERIOD: Duration = Duration::from_millis(200);
/// The camera's velocity goes out with the next estimate off the floor if it is at most
/// this old (the camera runs at 15 Hz or so; older, the vehicle may be doing otherwise).
const VELOCITY_FRESH: Duration = Duration::from_millis(200);

/// Where the vehicle is, for the standing estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// On the floor: where it was last seen, to a few centimetres.
    Standing,
    /// Off the floor but too low (or too high) to localise: x and y loose, z tight.
    Blind,
    /// High enough: the pipeline's estimates go out, these stop.
    Seeing,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OriginState {
    /// Waiting for `ORIGIN_AFTER` of vision.
    Waiting,
    Sent {
        tries: u32,
        next: Mono,
    },
    /// The autopilot echoed ours.
    Confirmed,
    /// The autopilot had one already (GPS or an earlier peer): left alone.
    Autopilot(Geodetic),
    GaveUp,
}

/// What the core should say.
#[derive(Clone, Debug, PartialEq)]
pub enum Notice {
    OriginSent(Geodetic),
    OriginConfirmed,
    /// The autopilot reported an origin mavloc did not send; the distance to ours, m.
    OriginForeign(Geodetic, f64),
    OriginGaveUp,
}

#[derive(Debug)]
pub struct GpsDenied {
    origin: Option<Geodetic>,
    /// Where the vehicle stands: north, east, and the SD of each.
    standing: (f64, f64, f64),
    state: OriginState,
    vision_since: Option<Mono>,
    next_ground: Mono,
    phase: Phase,
    sent_ground: u64,
    notices: Vec<Notice>,
    floor: Option<(f64, f64)>,
    /// The camera's latest velocity, while too low to localise.
    velocity: Option<(Mono, VelocityEstimate)>,
    /// The pipeline fell silent in flight: the autopilot's own (north, east), to echo.
    holding: Option<(f64, f64)>,
    /// The autopilot was found flying ([`GpsDenied::forget_pad`]): no origin until it
    /// says the vehicle is on the ground ([`GpsDenied::on_ground`]), not merely low.
    found_flying: bool,
}

impl GpsDenied {
    /// `origin` None: disabled (the autopilot has its own position).
    pub fn new(origin: Option<Geodetic>, pad: (f64, f64)) -> GpsDenied {
        GpsDenied {
            origin,
            standing: (pad.0, pad.1, PAD_SD_M),
            state: OriginState::Waiting,
            vision_since: None,
            next_ground: Mono::ZERO,
            phase: Phase::Seeing,
            sent_ground: 0,
            notices: Vec::new(),
            floor: None,
            velocity: None,
            holding: None,
            found_flying: false,
        }
    }

    pub fn enabled(&self) -> bool {
        self.origin.is_some()
    }

    pub fn origin_state(&self) -> OriginState {
        self.state
    }

    /// Standing estimates sent so far.
    pub fn sent_ground(&self) -> u64 {
        self.sent_ground
    }

    /// Whether the estimates it sends hold the height while the camera's frames stopped
    /// in flight (else they are for a vehicle standing or too low to localise).
    pub fn holding(&self) -> bool {
        self.holding.is_some()
    }

    /// Where the vehicle is taken to stand: north, east, SD (m).
    pub fn standing(&self) -> (f64, f64, f64) {
        self.standing
    }

    pub fn phase(&self) -> Phase {
        self.phase
    }

    /// `phase`: on the floor, off it but too low to localise, or high enough. Standing,
    /// the vehicle is where it was last seen, with that estimate's SD. (Letting the SD
    /// grow while on the floor was tried against PX4 SITL: EKF2 then drifted before
    /// lift-off and its controller pushed the vehicle 0.4 m/s the other way as it left
    /// the floor.) `floor`: where the floor is below it (local z, variance), if known,
    /// for the estimate's z.
    /// `holding`: high enough, in the air, but the pipeline has sent nothing for a while
    /// (the camera's frames stopped): where the autopilot itself puts the vehicle (north,
    /// east), echoed loosely with the floor's distance ([`GpsDenied::poll_transmit`]).
    pub fn set_state(&mut self, phase: Phase, floor: Option<(f64, f64)>, holding: Option<(f64, f64)>) {
        self.phase = phase;
        self.floor = floor;
        self.holding = holding.filter(|_| phase == Phase::Seeing);
    }

    /// The pipeline published an estimate from the air: it is where the vehicle will
    /// stand if it lands now.
    pub fn on_pipeline_estimate(&mut self, now: Mono, e: &PositionEstimate) {
        if !self.enabled() {
            return;
        }
        self.vision_since.get_or_insert(now);
        if self.phase == Phase::Seeing {
            let sd = e.cov[0][0].max(e.cov[1][1]).max(0.0).sqrt().max(PAD_SD_M);
            self.standing = (e.north, e.east, sd);
        }
    }

    /// The camera measured the velocity while too low to localise: it goes out with the
    /// next estimates off the floor.
    pub fn on_velocity(&mut self, now: Mono, v: &VelocityEstimate) {
        self.velocity = Some((now, *v));
    }

    /// Too low to localise, the particles carried on the camera's velocity put the vehicle
    /// at `e`: where it stands if it touches down now. (Taking the last fix above the blind
    /// heights instead, EKF2 settled up to 0.18 m off the truth on the floor after a descent
    /// that drifted, measured against PX4 v1.16 SIH.)
    pub fn on_coasted(&mut self, e: &PositionEstimate) {
        if self.enabled() && self.phase == Phase::Blind {
            let sd = e.cov[0][0].max(e.cov[1][1]).max(0.0).sqrt().max(PAD_SD_M);
            self.standing = (e.north, e.east, sd);
        }
    }

    /// GPS_GLOBAL_ORIGIN from the autopilot.
    pub fn on_autopilot_origin(&mut self, o: Geodetic) -> Option<Notice> {
        let ours = self.origin?;
        let d = distance_m(&ours, &o);
        match self.state {
            // PX4 keeps float32 degrees: centimetres of rounding.
            OriginState::Waiting | OriginState::Sent { .. } | OriginState::GaveUp if d < 0.5 => {
                self.state = OriginState::Confirmed;
                Some(Notice::OriginConfirmed)
            }
            OriginState::Confirmed if d < 0.5 => None,
            OriginState::Autopilot(prev) if distance_m(&prev, &o) < 0.5 => None,
            _ => {
                self.state = OriginState::Autopilot(o);
                Some(Notice::OriginForeign(o, d))
            }
        }
    }

    /// The autopilot was found armed (mavloc started again in flight, after a crash): the
    /// vehicle is not on the pad, and where it will stand is unknown until the pipeline
    /// says (its estimates, or its particles carried on the camera's velocity). Until then
    /// the estimates for a vehicle on or near the floor go out with no x and y, which
    /// EKF2 drops, rather than the pad, metres off, to a few centimetres.
    pub fn forget_pad(&mut self) {
        self.standing = (f64::NAN, f64::NAN, PAD_SD_M);
        self.found_flying = true;
    }

    /// The autopilot says the vehicle is on the ground (its landed state, or disarmed).
    pub fn on_ground(&mut self) {
        self.found_flying = false;
    }

    /// Whether the origin may go out now: only while the vehicle stands.
    fn origin_may_go(&self) -> bool {
        self.phase == Phase::Standing && !self.found_flying
    }

    /// The autopilot rebooted or came back: its estimator starts over.
    pub fn restart(&mut self) {
        self.state = OriginState::Waiting;
        self.vision_since = None;
    }

    fn ground_due(&self) -> bool {
        // From the moment the pipeline pauses, with no wait for its last estimates: EKF2
        // stops fusing vision after 200 ms without a sample (EV_MAX_INTERVAL) and
        // restarts by resetting to the next one, which in the air is the loose one
        // (measured against PX4 SITL: its position went invalid mid-landing). An
        // estimate still in flight is older than these and EKF2 drops it.
        self.enabled() && (self.phase != Phase::Seeing || self.holding.is_some())
    }

    pub fn deadline(&self) -> Option<Mono> {
        if !self.enabled() {
            return None;
        }
        let ground = self.ground_due().then_some(self.next_ground);
        let origin = match self.state {
            OriginState::Waiting if self.origin_may_go() => self.vision_since.map(|t| t + ORIGIN_AFTER),
            OriginState::Sent { next, .. } => Some(next),
            _ => None,
        };
        super::time::earliest([ground, origin])
    }

    /// What happened that the core should say, oldest first.
    pub fn take_notice(&mut self) -> Option<Notice> {
        (!self.notices.is_empty()).then(|| self.notices.remove(0))
    }

    /// The next message, if due; `present`: the autopilot is there to hear it;
    /// `attitude`: its latest (roll, pitch, yaw), echoed as the pipeline's estimates echo it;
    /// `stamp`: `now` on the autopilot's clock (us), the messages' `time_usec`.
    pub fn poll_transmit(
        &mut self,
        now: Mono,
        present: bool,
        target: u8,
        attitude: Option<(f64, f64, f64)>,
        stamp: u64,
    ) -> Option<MavMessage> {
        let origin = self.origin?;
        if !present {
            return None;
        }
        match self.state {
            // Only while the vehicle stands (found flying: once the autopilot says it is on
            // the ground, not in the last decimetres of a descent). One in the air has an
            // origin already (it could not have armed without), and a new one moves its
            // local frame under it (PX4 v1.16 `setLatLonOrigin` shifts the local position by
            // the origins' difference): mavloc started again in flight (a crash, systemd's
            // restart) sent it mid-flight before this.
            OriginState::Waiting
                if self.origin_may_go() && self.vision_since.is_some_and(|t| t + ORIGIN_AFTER <= now) =>
            {
                self.state = OriginState::Sent { tries: 1, next: now + ORIGIN_RETRY };
                self.notices.push(Notice::OriginSent(origin));
                return Some(set_origin(&origin, target, stamp));
            }
            OriginState::Sent { tries, next } if next <= now && tries >= ORIGIN_TRIES => {
                self.state = OriginState::GaveUp;
                self.notices.push(Notice::OriginGaveUp);
            }
            OriginState::Sent { tries, next } if next <= now => {
                self.state = OriginState::Sent { tries: tries + 1, next: now + ORIGIN_RETRY };
                return Some(set_origin(&origin, target, stamp));
            }
            _ => {}
        }
        if self.ground_due() && self.next_ground <= now {
            // Keep the cadence when polled late (by less than a period).
            let next = self.next_ground + GROUND_PERIOD;
            self.next_ground = if next > now { next } else { now + GROUND_PERIOD };
            if let Some((north, east)) = self.holding {
                // The camera's frames stopped in flight. EKF2 has its height from vision
                // only (EKF2_HGT_REF 3): in a 4 s gap against PX4 SITL it held a height the
                // vehicle sank 0.36 m from, below the heights the camera localises from,
                // where the loose estimates then restarted EKF2's vision fusion with a
                // reset to them and its position went invalid. So the floor's distance
                // goes on, with x and y where the autopilot itself puts the vehicle (no
                // innovation: it tells EKF2 nothing of where it is) at `BLIND_SD_M`, and
                // no velocity; at 5 Hz, under EKF2's 0.4 s timeout, so that 4 s of them
                // weigh as one position of 2 m SD. (EKF2 drops a sample without all three
                // coordinates.)
                self.next_ground = now + HOLD_PERIOD;
                let (down, _) = self.floor?;
                let e = PositionEstimate {
                    autopilot_time: f64::NAN,
                    north,
                    east,
                    down,
                    cov: [[BLIND_SD_M * BLIND_SD_M, 0.0], [0.0, BLIND_SD_M * BLIND_SD_M]],
                };
                let attitude = attitude.unwrap_or((0.0, 0.0, 0.0));
                let unknown = VelocityEstimate { body: [f64::NAN; 3], var: [f64::NAN; 3] };
                return Some(odometry(Some(&e), &unknown, stamp, attitude, self.floor.map(|f| f.1)));
            }
            self.vision_since.get_or_insert(now);
            self.sent_ground += 1;
            let (north, east, sd) = self.standing;
            let sd = if self.phase == Phase::Blind { BLIND_SD_M } else { sd };
            let e = PositionEstimate {
                autopilot_time: f64::NAN,
                north,
                east,
                down: self.floor.map_or(0.0, |f| f.0),
                cov: [[sd * sd, 0.0], [0.0, sd * sd]],
            };
            // Standing, the vehicle is still. In the air the camera's velocity, while
            // fresh, keeps EKF2 from drifting on its IMU alone until the camera is high
            // enough to localise (measured against PX4 v1.16 SIH: a 0.5 m drift in a 4 s
            // blind climb, and its heading pulled 30 degrees off by the correction after).
            // Each of the camera's velocities goes out once: sent again, the autopilot would
            // count one measurement twice.
            let v = match (self.phase, self.velocity.take()) {
                (Phase::Standing, _) => VelocityEstimate::STANDING,
                (_, Some((t, v))) if now.saturating_sub(t) <= VELOCITY_FRESH => v,
                _ => VelocityEstimate::UNMEASURED,
            };
            // The attitude is echoed, not measured: EKF2 turns the vision frame by how far the
            // attitude sent is from its own (ev_control.cpp), so a level one would tilt it.
            let attitude = attitude.unwrap_or((0.0, 0.0, 0.0));
            return Some(odometry(Some(&e), &v, stamp, attitude, self.floor.map(|f| f.1)));
        }
        None
    }
}

// The message MAVLink now marks superseded by MAV_CMD_DO_SET_GLOBAL_ORIGIN: PX4 v1.16
// handles the message and not the command.
#[allow(deprecated)]
fn set_origin(o: &Geodetic, target: u8, stamp: u64) -> MavMessage {
    MavMessage::SET_GPS_GLOBAL_ORIGIN(SET_GPS_GLOBAL_ORIGIN_DATA {
        latitude: (o.lat_deg * 1e7).round() as i32,
        longitude: (o.lon_deg * 1e7).round() as i32,
        altitude: (o.alt_m * 1e3).round() as i32,
        target_system: target,
        time_usec: stamp,
    })
}

/// Flat-earth distance: the two points are metres apart at most for it to matter.
fn distance_m(a: &Geodetic, b: &Geodetic) -> f64 {
    let r = 6_371_000.0;
    let dn = (a.lat_deg - b.lat_deg).to_radians() * r;
    let de = (a.lon_deg - b.lon_deg).to_radians() * r * a.lat_deg.to_radians().cos();
    let du = a.alt_m - b.alt_m;
    (dn * dn + de * de + du * du).sqrt()
}
