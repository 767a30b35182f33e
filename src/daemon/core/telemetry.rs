//! The autopilot's telemetry, taken in for time alignment: attitude and position
//! (paired), the gimbal's attitude, home and the global position; the autopilot's boot
//! clock, whose running backwards means it rebooted.
//!
//! A reboot is believed only when the new timeline holds: [`REBOOT_CONFIRM`] stamps
//! consistent with one another over [`REBOOT_CONFIRM_S`], with no stamp of the old
//! timeline among them. Without signing anyone can send a frame as the autopilot; one
//! stamp of 0 would otherwise reset time alignment, streams and gimbal control and
//! warn of a reboot that never happened. A real autopilot that rebooted no longer speaks
//! on its old clock; a live one keeps doing so and so unmasks the claim.

use mavlink::dialects::common::*;

use super::time::Mono;
use crate::align::{AlignParams, Aligner, ClockSync, FixedMount, GimbalOffsets, GimbalSample, VehicleSample};
use crate::geometry::{Geodetic, LocalFrame, Vec3};
use crate::settings::Settings;
use mavloc_geometry::GimbalAngles;

/// A downward distance at or above this (cm), and above the sensor's maximum, is a
/// negative distance wrapped round in the u16 field: no rangefinder reads 600 m.
const WRAPPED_CM: u16 = 60_000;

pub fn align_params(s: &Settings) -> (AlignParams, FixedMount, GimbalOffsets) {
    let g = &s.gimbal;
    (
        AlignParams { use_gimbal: g.use_telemetry, ..AlignParams::default() },
        FixedMount {
            chain: g.chain,
            angles: GimbalAngles::from_degrees(g.mount_yaw_deg, g.mount_pitch_deg, g.mount_roll_deg),
        },
        GimbalOffsets {
            chain: g.chain,
            yaw: g.yaw_offset_deg.to_radians(),
            pitch: g.pitch_offset_deg.to_radians(),
            roll: g.roll_offset_deg.to_radians(),
        },
    )
}

/// A device's reports stamped with one time this long, in at least [`FROZEN_REPEATS`]
/// reports, come from a clock that stands still (some gimbals fill in no time at all).
const FROZEN_S: f64 = 0.5;
const FROZEN_REPEATS: u32 = 3;
/// Another gimbal's reports are taken once the one followed is silent this long.
const GIMBAL_SOURCE_HOLD: std::time::Duration = std::time::Duration::from_secs(2);

/// A MAVLink gimbal device's boot clock mapped onto the autopilot's, the way the
/// autopilot's is mapped onto mavloc's ([`ClockSync`]: the lower envelope of arrivals
/// against stamps; a backwards step is the device rebooting and starts it over). A clock
/// that stands still has no timing to give: its reports are placed at their arrival, and
/// when it moves again the mapping starts over, not skewed by the stamps it repeated.
#[derive(Debug, Default)]
struct DeviceClock {
    sync: ClockSync,
    /// The newest stamp, the arrival when it first came, and how often it came since.
    last: Option<(f64, f64, u32)>,
}

impl DeviceClock {
    /// The autopilot time of a report stamped `stamp` (device seconds) that arrived at
    /// autopilot time `arrival`; none for a stamp from the future.
    fn map(&mut self, stamp: f64, arrival: f64) -> Option<f64> {
        let frozen = |(_, since, n): (f64, f64, u32)| n >= FROZEN_REPEATS && arrival - since > FROZEN_S;
        match self.last {
            Some(l) if l.0 == stamp => {
                self.last = Some((l.0, l.1, l.2 + 1));
                return if frozen((l.0, l.1, l.2 + 1)) { Some(arrival) } else { self.sync.to_local(stamp) };
            }
            Some(l) if frozen(l) => self.sync = ClockSync::new(),
            _ => {}
        }
        if !self.sync.plausible(stamp, arrival) {
            return None;
        }
        self.sync.observe_stamp(stamp, arrival);
        self.last = Some((stamp, arrival, 1));
        self.sync.to_local(stamp)
    }
}

pub struct Telemetry {
    pub aligner: Aligner,
    /// Messages dropped for a stamp from the future (see `ClockSync::plausible`).
    pub implausible: u64,
    /// Of those, the flight controller's own (ATTITUDE, LOCAL_POSITION_NED,
    /// GLOBAL_POSITION_INT from component 1): a gimbal's clock is not the autopilot's.
    pub autopilot_from_the_future: u64,
    /// Reboot claims the old timeline disproved (see the module doc).
    pub reboot_claims_rejected: u64,
    /// The flight controller's ATTITUDE, LOCAL_POSITION_NED and HOME_POSITION refused for a
    /// value that is not a number (NaN or infinite): one would make every pose aligned
    /// near it NaN, or every result's position.
    pub not_finite: u64,
    /// A backwards step waiting for confirmation.
    candidate: Option<Candidate>,
    latest_attitude: Option<(f64, nalgebra::UnitQuaternion<f64>)>,
    pub home: Option<HOME_POSITION_DATA>,
    pub global: Option<GLOBAL_POSITION_INT_DATA>,
    /// The simulator's ground truth and when it arrived (PX4 SITL leaves its `time_usec`
    /// at 0, so arrival is the only time it has).
    pub truth: Option<(Mono, HIL_STATE_QUATERNION_DATA)>,
    /// The optical axis of the gimbal report just taken in (NED, unit), for the pointing
    /// statistics: none for a report that was refused (a bad quaternion, a stamp from
    /// the future), which must not count again the last good one.
    gimbal_report: Option<Vec3>,
    /// A MAVLink gimbal device's clock against the autopilot's (device stamp as the
    /// "autopilot" side, autopilot time at arrival as the "local" side).
    gimbal_clock: DeviceClock,
    /// The gimbal followed, (component, gimbal_device_id), and when it last reported.
    gimbal_source: Option<((u8, u8), Mono)>,
    /// Reports of other gimbals left out while it reports.
    pub other_gimbal_reports: u64,
    /// The downward rangefinder (DISTANCE_SENSOR, PITCH_270) and when: metres, 0 when
    /// it reads below its minimum (PX4 reports 0 standing on the ground).
    pub range_down: Option<(Mono, f64)>,
}

/// Stamps on a new timeline needed to believe a reboot...
pub const REBOOT_CONFIRM: u32 = 3;
/// ...spread over at least this long (PX4 streams attitude at 10-50 Hz after a boot).
pub const REBOOT_CONFIRM_S: f64 = 0.5;

/// A new timeline: its offset (arrival minus stamp), when it was first seen, how often.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    offset: f64,
    since: f64,
    count: u32,
}

/// The autopilot rebooted (its boot clock ran backwards).
#[derive(Debug, PartialEq, Eq)]
pub struct Rebooted;

impl Telemetry {
    /// The autopilot's latest attitude: roll, pitch, yaw (rad).
    pub fn attitude(&self) -> Option<(f64, f64, f64)> {
        self.latest_attitude.map(|(_, q)| q.euler_angles())
    }

    pub fn new(s: &Settings) -> Telemetry {
        let (ap, mount, offsets) = align_params(s);
        Telemetry {
            aligner: Aligner::new(ap, mount, offsets),
            implausible: 0,
            autopilot_from_the_future: 0,
            reboot_claims_rejected: 0,
            not_finite: 0,
            candidate: None,
            latest_attitude: None,
            home: None,
            global: None,
            truth: None,
            gimbal_report: None,
            gimbal_clock: DeviceClock::default(),
            gimbal_source: None,
            other_gimbal_reports: 0,
            range_down: None,
        }
    }

    pub fn reconfigure(&mut self, s: &Settings) {
        let (ap, mount, offsets) = align_params(s);
        self.aligner.set_params(ap, mount, offsets);
    }

    /// The WGS84 origin of the autopilot's local frame: HOME_POSITION gives both its
    /// geodetic and its local position, so origin = home moved back by its local offset.
    pub fn origin(&self) -> Option<Geodetic> {
        let h = self.home.as_ref()?;
        let home =
            Geodetic::new(h.latitude as f64 * 1e-7, h.longitude as f64 * 1e-7, h.altitude as f64 * 1e-3);
        home.validate().ok()?;
        // A local offset that is not a number would put every result at NaN degrees.
        let offset = Vec3::new(h.x as f64, h.y as f64, h.z as f64);
        if !offset.iter().all(|x| x.is_finite()) {
            return None;
        }
        let origin = LocalFrame::new(home).to_geodetic(&-offset);
        origin.validate().ok().map(|_| origin)
    }

    /// The camera's optical axis (gimbal FRD x) in NED, from a gimbal report; a yaw
    /// relative to the vehicle is turned by the vehicle's latest heading.
    fn earth_direction(&self, s: &GimbalSample) -> Option<Vec3> {
        let forward = s.q * Vec3::x();
        match s.frame {
            crate::align::YawFrame::Earth => Some(forward),
            crate::align::YawFrame::Vehicle => {
                let (_, q) = self.latest_attitude?;
                let yaw = q.euler_angles().2;
                Some(nalgebra::UnitQuaternion::from_axis_angle(&Vec3::z_axis(), yaw) * forward)
            }
        }
    }

    /// Screens a stamp for a reboot claim: false while a backwards step waits for
    /// confirmation (the sample is not used), true for the old timeline and for the stamp
    /// that confirms the new one.
    fn reboot_holds(&mut self, stamp: f64, now: f64) -> bool {
        if !self.aligner.clock.is_backstep(stamp) {
            if self.candidate.take().is_some() {
                self.reboot_claims_rejected += 1;
            }
            return true;
        }
        let offset = now - stamp;
        match &mut self.candidate {
            // Consistent with the candidate timeline (within a second of its offset).
            Some(c) if (c.offset - offset).abs() < 1.0 => {
                c.count += 1;
                if c.count >= REBOOT_CONFIRM && now - c.since >= REBOOT_CONFIRM_S {
                    self.candidate = None;
                    return true;
                }
                false
            }
            other => {
                if other.is_some() {
                    self.reboot_claims_rejected += 1;
                }
                *other = Some(Candidate { offset, since: now, count: 1 });
                false
            }
        }
    }

    fn stamp(&mut self, stamp: f64, rx: Mono) -> Option<Rebooted> {
        let now = rx.secs();
        if self.aligner.clock.observe_stamp(stamp, now) {
            self.aligner.reset();
            self.gimbal_clock = DeviceClock::default();
            // reset() cleared the clock; keep this stamp.
            self.aligner.clock.observe_stamp(stamp, now);
            return Some(Rebooted);
        }
        None
    }

    /// The optical axis of the gimbal report the last message brought, if it was one
    /// and was taken in (see `gimbal_report`).
    pub fn take_gimbal_report(&mut self) -> Option<Vec3> {
        self.gimbal_report.take()
    }

    /// A message from the autopilot's system, from `component` (1: the flight controller
    /// itself).
    pub fn on_message(&mut self, rx: Mono, m: &MavMessage, component: u8) -> Option<Rebooted> {
        let flight_controller = component == 1;
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        let numbers = match m {
            MavMessage::ATTITUDE(a) => finite(&[a.roll, a.pitch, a.yaw]),
            MavMessage::LOCAL_POSITION_NED(p) => finite(&[p.x, p.y, p.z, p.vx, p.vy, p.vz]),
            // The home's local offset places the results (`origin`); a bad one is refused
            // so the last good home stands.
            MavMessage::HOME_POSITION(h) => finite(&[h.x, h.y, h.z]),
            _ => true,
        };
        if flight_controller && !numbers {
            self.not_finite += 1;
            return None;
        }
        let stamp_ms = match m {
            MavMessage::ATTITUDE(a) => Some(a.time_boot_ms),
            MavMessage::LOCAL_POSITION_NED(p) => Some(p.time_boot_ms),
            MavMessage::GLOBAL_POSITION_INT(g) => Some(g.time_boot_ms),
            _ => None,
        };
        if let Some(ms) = stamp_ms.filter(|_| flight_controller) {
            let (stamp, now) = (ms as f64 * 1e-3, rx.secs());
            if !self.aligner.clock.plausible(stamp, now) {
                self.implausible += 1;
                self.autopilot_from_the_future += 1;
                return None;
            }
            if !self.reboot_holds(stamp, now) {
                return None;
            }
        }
        match m {
            MavMessage::ATTITUDE(a) if flight_controller => {
                let stamp = a.time_boot_ms as f64 * 1e-3;
                let r = self.stamp(stamp, rx);
                let q =
                    nalgebra::UnitQuaternion::from_euler_angles(a.roll as f64, a.pitch as f64, a.yaw as f64);
                self.latest_attitude = Some((stamp, q));
                r
            }
            MavMessage::LOCAL_POSITION_NED(p) if flight_controller => {
                let stamp = p.time_boot_ms as f64 * 1e-3;
                let r = self.stamp(stamp, rx);
                // Position and attitude come at the same rate from the same estimator;
                // pair the position with the latest attitude.
                if let Some((_, q)) = self.latest_attitude {
                    self.aligner.push_vehicle(
                        stamp,
                        VehicleSample {
                            position: nalgebra::Vector3::new(p.x as f64, p.y as f64, p.z as f64),
                            velocity: nalgebra::Vector3::new(p.vx as f64, p.vy as f64, p.vz as f64),
                            attitude: q,
                        },
                    );
                }
                r
            }
            MavMessage::GLOBAL_POSITION_INT(g) if flight_controller => {
                let r = self.stamp(g.time_boot_ms as f64 * 1e-3, rx);
                self.global = Some(g.clone());
                r
            }
            MavMessage::HIL_STATE_QUATERNION(h) if flight_controller => {
                self.truth = Some((rx, h.clone()));
                None
            }
            MavMessage::DISTANCE_SENSOR(d)
                if d.orientation == MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270 =>
            {
                // PX4 SIH sends a distance below the floor (the vehicle settling into
                // the ground) wrapped round to 655 m: that is the floor, not "no reading".
                // Taken as none, the height fell back to the autopilot's, made of mavloc's
                // own z, and against PX4 SITL a vehicle that had settled 0.3 m into SIH's
                // ground had its ground-level frames localised: EKF2 drifted, PX4 never
                // saw the landing. Any other reading above the maximum is no reading.
                let wrapped = d.current_distance >= WRAPPED_CM && d.current_distance > d.max_distance;
                if wrapped {
                    self.range_down = Some((rx, 0.0));
                } else if d.current_distance <= d.max_distance || d.max_distance == 0 {
                    let m = d.current_distance as f64 * 0.01;
                    let below = d.current_distance <= d.min_distance;
                    self.range_down = Some((rx, if below { 0.0 } else { m }));
                }
                None
            }
            MavMessage::HOME_POSITION(h) if flight_controller => {
                self.home = Some(h.clone());
                None
            }
            MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(g) => {
                // One gimbal: the first to report, until it falls silent. Two on one
                // vehicle (each on its own clock) would be mixed into one history.
                let source = (component, g.gimbal_device_id);
                match self.gimbal_source {
                    Some((s, last)) if s != source && rx.saturating_sub(last) < GIMBAL_SOURCE_HOLD => {
                        if self.other_gimbal_reports == 0 {
                            tracing::warn!(
                                "gimbal reports of component {} (device {}) left out: mavloc follows the gimbal of component {} (device {}) while it reports",
                                source.0, source.1, s.0, s.1
                            );
                        }
                        self.other_gimbal_reports += 1;
                        return None;
                    }
                    Some((s, _)) if s != source => self.gimbal_clock = DeviceClock::default(),
                    _ => {}
                }
                let s = GimbalSample::from_status(g.q, g.flags.bits())?;
                let now = rx.secs();
                let stamp = if flight_controller {
                    // The autopilot's own gimbal driver (PX4 with MNT_MODE_OUT = AUX):
                    // its clock. One stamp from the future would have made the history
                    // drop every true report after it (5 s behind the newest) and
                    // stopped the area pipeline for good.
                    let stamp = g.time_boot_ms as f64 * 1e-3;
                    if !self.aligner.clock.plausible(stamp, now) {
                        self.implausible += 1;
                        return None;
                    }
                    stamp
                } else {
                    // A MAVLink gimbal device (component 154): its own boot clock, which
                    // PX4 forwards as it is (a gimbal powered up 3 s after the autopilot
                    // gave no aligned frame at all). Mapped onto the autopilot's clock the
                    // way the autopilot's is onto ours: by the lower envelope of its
                    // arrivals (on the autopilot's clock) against its stamps.
                    let arrival = self.aligner.clock.to_autopilot(now)?;
                    match self.gimbal_clock.map(g.time_boot_ms as f64 * 1e-3, arrival) {
                        Some(t) => t,
                        None => {
                            self.implausible += 1;
                            return None;
                        }
                    }
                };
                self.gimbal_source = Some((source, rx));
                self.aligner.push_gimbal(stamp, s, now);
                self.gimbal_report = self.earth_direction(&s);
                None
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reports every 20 ms from `from` to `to` (autopilot seconds), each arriving 3 ms
    /// after it was sent plus up to 4 ms of jitter, stamped by `device`; the mapped
    /// times' largest error against the true sending times.
    fn worst_error(c: &mut DeviceClock, from: f64, to: f64, device: impl Fn(f64) -> f64) -> f64 {
        let mut worst: f64 = 0.0;
        let mut t = from;
        let mut i = 0u32;
        while t < to {
            let jitter = 0.004 * ((i * 7919) % 13) as f64 / 13.0;
            let mapped = c.map(device(t), t + 0.003 + jitter).expect("mapped");
            worst = worst.max((mapped - t).abs());
            t += 0.02;
            i += 1;
        }
        worst
    }

    /// A gimbal device's clock, whatever its offset to the autopilot's, maps onto it
    /// within the link's latency; a stamp from the future is refused; a reboot of the
    /// device (its clock back to 0) starts the mapping over.
    #[test]
    fn a_gimbal_devices_clock_maps_onto_the_autopilots() {
        let mut c = DeviceClock::default();
        // Booted 3 s after the autopilot, ms stamps.
        let behind = |t: f64| ((t - 3.0) * 1000.0).floor() / 1000.0;
        assert!(worst_error(&mut c, 3.5, 20.0, behind) < 0.009);
        assert_eq!(c.map(700.0, 20.0), None, "600 s ahead");
        assert!(worst_error(&mut c, 20.0, 25.0, behind) < 0.009, "the mapping survives the forged stamp");
        let rebooted = |t: f64| t - 24.9;
        assert!(worst_error(&mut c, 25.0, 30.0, rebooted) < 0.009);
    }

    /// Two gimbals on one vehicle are not mixed: the first to report is followed while
    /// it reports; the other's reports are left out, and taken once the first has been
    /// silent for 2 s.
    #[test]
    fn one_gimbal_is_followed_while_it_reports() {
        let mut t = Telemetry::new(&Settings::default());
        let report = |device: u8, ms: u32| {
            MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
                time_boot_ms: ms,
                q: [1.0, 0.0, 0.0, 0.0],
                flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME,
                gimbal_device_id: device,
                ..Default::default()
            })
        };
        let taken = |t: &mut Telemetry, device: u8, ms: u32| {
            t.on_message(Mono::from_millis(ms as u64), &report(device, ms), 1);
            t.take_gimbal_report().is_some()
        };
        for ms in (1000..3000).step_by(20) {
            assert!(taken(&mut t, 1, ms));
            assert!(!taken(&mut t, 2, ms + 10), "the second gimbal is left out");
        }
        assert_eq!(t.other_gimbal_reports, 100);
        assert!(!taken(&mut t, 2, 4900), "1.9 s after the first's last report");
        assert!(taken(&mut t, 2, 5100), "2.1 s after: the first is gone");
        assert!(!taken(&mut t, 1, 5200), "now the second is followed");
    }

    /// Some gimbals fill in no time at all: reports with one stamp are placed at their
    /// arrival. A clock that stood still at first (0 until it starts) does not skew the
    /// mapping once it runs.
    #[test]
    fn a_gimbal_clock_that_stands_still_gives_the_arrival() {
        let mut c = DeviceClock::default();
        let mut last = 0.0;
        for i in 0..100 {
            let arrival = 1.0 + i as f64 * 0.02;
            last = c.map(0.0, arrival).unwrap();
        }
        assert!((last - 2.98).abs() < 1e-9, "{last}");
        let mut c = DeviceClock::default();
        let clamped = |t: f64| ((t - 2.0) * 1000.0).floor().max(0.0) / 1000.0;
        worst_error(&mut c, 0.5, 2.0, clamped);
        assert!(worst_error(&mut c, 2.5, 10.0, clamped) < 0.009);
    }
}
