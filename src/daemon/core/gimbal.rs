//! Pointing the camera (`gimbal.aim = "border"`): take gimbal-manager control with
//! MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, then send MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW with
//! an earth-frame yaw, at most 5 times a second; between sends only the newest aim is
//! kept. Control is released when the autopilot reboots or vanishes, and taken again.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;

pub const MIN_INTERVAL: Duration = Duration::from_millis(200);
/// GIMBAL_MANAGER_FLAGS_YAW_LOCK (16) | GIMBAL_MANAGER_FLAGS_YAW_IN_EARTH_FRAME (64): the
/// yaw is earth-fixed. PX4 v1.16's gimbal manager honours only YAW_LOCK and takes the yaw
/// relative to the vehicle otherwise (issue #18: median pointing error 15.7 degrees with
/// 64 alone); managers that follow the newer spec read YAW_IN_EARTH_FRAME. Both say the
/// same here.
const YAW_IN_EARTH_FRAME: f32 = 80.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Control {
    Released,
    /// CONFIGURE sent; setpoints follow (the manager acknowledges or refuses).
    Requested,
    InControl,
}

/// A setpoint is given this long to be reached before the gimbal's report is compared.
pub const SETTLE: Duration = Duration::from_millis(500);
/// The recent pointing error is over this long (the status's "last minute").
pub const RECENT: Duration = Duration::from_secs(60);
/// At most this many recent errors are kept (a minute at 100 Hz): an autopilot that
/// floods gimbal reports costs no more memory or sorting than that.
const RECENT_MAX: usize = 6000;
/// Resolution of the flight's error histogram, degrees (0..180).
const BIN_DEG: f64 = 0.01;

#[derive(Debug)]
pub struct Gimbal {
    control: Control,
    /// The recent setpoints: when sent, and the direction each asks for (unit, NED).
    pub sent: std::collections::VecDeque<(Mono, [f64; 3])>,
    /// Pointing errors (degrees) of reports against settled setpoints over the last
    /// [`RECENT`] (at most [`RECENT_MAX`]), with their times, the newest last.
    pub errors: std::collections::VecDeque<(Mono, f64)>,
    /// Every airborne report's error since the start, in [`BIN_DEG`] bins: the flight's
    /// median in constant memory (PX4 reports the gimbal at up to 70 Hz).
    flight: Vec<u64>,
    /// (yaw, pitch) radians, newest aim not yet sent.
    pending: Option<(f64, f64)>,
    next: Mono,
    refused_once: bool,
    /// A setpoint was accepted since the last refusal: a refusal now means the autopilot
    /// took the gimbal back (PX4's navigator does for RTL and landing), not that it has no
    /// gimbal manager.
    in_use: bool,
    /// A setpoint was ever accepted.
    ever_accepted: bool,
}

impl Default for Gimbal {
    fn default() -> Self {
        Gimbal {
            control: Control::Released,
            sent: Default::default(),
            errors: Default::default(),
            flight: vec![0; (180.0 / BIN_DEG) as usize + 1],
            pending: None,
            next: Mono::ZERO,
            refused_once: false,
            in_use: false,
            ever_accepted: false,
        }
    }
}

impl Gimbal {
    pub fn control(&self) -> Control {
        self.control
    }

    pub fn aim(&mut self, yaw: f64, pitch: f64) {
        self.pending = Some((yaw, pitch));
    }

    /// A gimbal report (optical axis, NED, unit) at `now`: its angle to the newest
    /// setpoint sent at least [`SETTLE`] before is kept for [`RECENT`] and, when the
    /// vehicle is `airborne`, counted in the flight's median (on the ground an autopilot
    /// holds the camera in its landing range whatever it is told: PX4's MNT_LND_P_*).
    pub fn on_report(&mut self, now: Mono, axis: [f64; 3], airborne: bool) {
        let Some(&(_, want)) = self.sent.iter().rev().find(|(t, _)| *t + SETTLE <= now) else { return };
        let dot: f64 = (0..3).map(|i| axis[i] * want[i]).sum();
        let error = dot.clamp(-1.0, 1.0).acos().to_degrees();
        tracing::trace!("gimbal report {axis:.3?} against setpoint {want:.3?}: {error:.2} deg");
        self.errors.push_back((now, error));
        while self.errors.front().is_some_and(|(t, _)| *t + RECENT < now) || self.errors.len() > RECENT_MAX {
            self.errors.pop_front();
        }
        if airborne {
            let last = self.flight.len() - 1;
            self.flight[((error / BIN_DEG).round() as usize).min(last)] += 1;
        }
    }

    /// Median pointing error over the last [`RECENT`], degrees.
    pub fn median_error_deg(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.errors.iter().map(|e| e.1).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }

    /// Median pointing error over every airborne report so far, degrees (to
    /// [`BIN_DEG`]).
    pub fn flight_median_error_deg(&self) -> Option<f64> {
        let total: u64 = self.flight.iter().sum();
        if total == 0 {
            return None;
        }
        let mut seen = 0;
        for (i, n) in self.flight.iter().enumerate() {
            seen += n;
            if 2 * seen > total {
                return Some(i as f64 * BIN_DEG);
            }
        }
        None
    }

    pub fn release(&mut self) {
        self.control = Control::Released;
        self.pending = None;
        self.sent.clear();
    }

    pub fn deadline(&self) -> Option<Mono> {
        self.pending.map(|_| self.next)
    }

    /// `me` is mavloc's (system, component): the manager's new primary controller.
    pub fn poll_transmit(&mut self, now: Mono, target: u8, me: (u8, u8)) -> Option<MavMessage> {
        let (yaw, pitch) = self.pending?;
        if now < self.next {
            return None;
        }
        let command = |command, p: [f32; 7]| {
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                param1: p[0],
                param2: p[1],
                param3: p[2],
                param4: p[3],
                param5: p[4],
                param6: p[5],
                param7: p[6],
                command,
                target_system: target,
                target_component: 1,
                confirmation: 0,
            })
        };
        if self.control == Control::Released {
            self.control = Control::Requested;
            // Primary control to us; secondary unchanged (-1); all gimbals (device id 0).
            return Some(command(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                [me.0 as f32, me.1 as f32, -1.0, -1.0, 0.0, 0.0, 0.0],
            ));
        }
        self.pending = None;
        self.next = now + MIN_INTERVAL;
        let (cp, sp) = (pitch.cos(), pitch.sin());
        self.sent.push_back((now, [cp * yaw.cos(), cp * yaw.sin(), -sp]));
        while self.sent.len() > 16 {
            self.sent.pop_front();
        }
        // Rates NaN: angles only.
        Some(command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [
                pitch.to_degrees() as f32,
                yaw.to_degrees() as f32,
                f32::NAN,
                f32::NAN,
                YAW_IN_EARTH_FRAME,
                0.0,
                0.0,
            ],
        ))
    }

    /// The manager's answer to CONFIGURE or PITCHYAW. Returns a line to report: the first
    /// refusal of a manager that never took a setpoint (likely no gimbal manager), and
    /// each time an autopilot that took setpoints starts refusing them (it points the
    /// camera itself); while it keeps refusing, nothing more.
    pub fn on_ack(&mut self, command: MavCmd, result: MavResult) -> Option<String> {
        match result {
            MavResult::MAV_RESULT_ACCEPTED | MavResult::MAV_RESULT_IN_PROGRESS => {
                if command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE {
                    self.control = Control::InControl;
                } else if command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW {
                    self.in_use = true;
                    self.ever_accepted = true;
                }
                None
            }
            other => {
                // Take control again before the next setpoint. The refused setpoints are
                // not where the gimbal was told to go: the autopilot points it (PX4's
                // navigator takes it back for the landing), and comparing its reports with
                // them would count the autopilot's choice as mavloc's pointing error.
                self.control = Control::Released;
                self.sent.clear();
                let first = !std::mem::replace(&mut self.refused_once, true);
                if std::mem::replace(&mut self.in_use, false) {
                    Some(format!(
                        "autopilot took the gimbal back ({command:?}: {other:?}): it points the camera itself \
                         (PX4 does in RTL and landing); mavloc asks for control again"
                    ))
                } else if first && !self.ever_accepted {
                    Some(format!(
                        "autopilot refused {command:?}: {other:?}; is it a gimbal manager (PX4: MNT_MODE_IN=4)?"
                    ))
                } else {
                    None
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn command(m: &MavMessage) -> (MavCmd, [f32; 2], f32) {
        match m {
            MavMessage::COMMAND_LONG(c) => (c.command, [c.param1, c.param2], c.param5),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn takes_control_once_then_at_most_5_hz_with_the_newest_aim() {
        let mut g = Gimbal::default();
        let me = (1, 191);
        let mut sent = Vec::new();
        for i in 0..10u64 {
            let now = Mono::from_millis(1000 + i * 100);
            g.aim(0.3 + i as f64 * 0.01, -0.5);
            while let Some(m) = g.poll_transmit(now, 1, me) {
                sent.push((now, command(&m)));
            }
        }
        assert_eq!(sent[0].1 .0, MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE);
        let setpoints: Vec<_> =
            sent.iter().filter(|s| s.1 .0 == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW).collect();
        assert_eq!(setpoints.len(), 5, "1 s at 5 Hz");
        for w in setpoints.windows(2) {
            assert!(w[1].0.saturating_sub(w[0].0) >= MIN_INTERVAL);
        }
        let (_, [p, y], flags) = setpoints[1].1;
        assert!((p - (-0.5f32).to_degrees()).abs() < 1e-4);
        assert!((y - 0.32f32.to_degrees()).abs() < 1e-3, "the aim of its own time, {y}");
        assert_eq!(flags, 80.0, "earth-frame yaw: YAW_LOCK for PX4, YAW_IN_EARTH_FRAME for the spec");
        // The held-back newest aim goes out at the next slot.
        assert_eq!(g.deadline(), Some(Mono::from_millis(2000)));
        assert!(g.poll_transmit(Mono::from_millis(2000), 1, me).is_some());
    }

    /// Reports are compared with the setpoint in force; once the autopilot refuses
    /// setpoints (it points the gimbal itself), its pointing is not counted as an error.
    #[test]
    fn pointing_errors_count_only_setpoints_the_autopilot_took() {
        let mut g = Gimbal::default();
        let me = (1, 191);
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::ZERO, 1, me); // CONFIGURE
        g.on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MavResult::MAV_RESULT_ACCEPTED);
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::from_millis(300), 1, me).unwrap();
        let axis = |pitch: f64| [pitch.cos(), 0.0, -pitch.sin()];
        // Before the setpoint has settled nothing is compared; after, the report is on it.
        g.on_report(Mono::from_millis(500), axis(0.0), true);
        assert!(g.errors.is_empty());
        g.on_report(Mono::from_millis(900), axis(-1.0), true);
        assert!(g.median_error_deg().unwrap() < 1e-6);
        // Refused: the autopilot levels the camera for its landing.
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::from_millis(1100), 1, me);
        g.on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, MavResult::MAV_RESULT_DENIED);
        for ms in [2000, 2500, 3000] {
            g.on_report(Mono::from_millis(ms), axis(0.0), true);
        }
        assert_eq!(g.errors.len(), 1, "{:?}", g.errors);
        // A wrong pointing under a setpoint in force does count (57 degrees off).
        g.aim(0.0, -1.0);
        while g.poll_transmit(Mono::from_millis(3100), 1, me).is_some() {}
        g.on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MavResult::MAV_RESULT_ACCEPTED);
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::from_millis(3400), 1, me).unwrap();
        g.on_report(Mono::from_millis(4000), axis(0.0), true);
        assert_eq!(g.errors.len(), 2);
        assert!((g.errors[1].1 - 57.3).abs() < 0.1, "{:?}", g.errors);
    }

    /// The recent median is over the last minute whatever the report rate (PX4 sends up
    /// to 70 a second); the flight's counts airborne reports only, all of them.
    #[test]
    fn the_recent_median_is_a_minute_and_the_flights_is_airborne() {
        let mut g = Gimbal::default();
        let me = (1, 191);
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::ZERO, 1, me);
        g.on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MavResult::MAV_RESULT_ACCEPTED);
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::ZERO, 1, me).unwrap();
        let off = |deg: f64| {
            let p = -1.0 - deg.to_radians();
            [p.cos(), 0.0, -p.sin()]
        };
        // 82 s airborne at 50 Hz: the first 42 s 3 degrees off, then 40 s 1 degree off.
        for i in 0..4100u64 {
            let deg = if i < 2100 { 3.0 } else { 1.0 };
            g.on_report(Mono::from_millis(1000 + i * 20), off(deg), true);
        }
        // Then 10 s on the ground, levelled by the autopilot (57 degrees off).
        for i in 0..500u64 {
            g.on_report(Mono::from_millis(83_000 + i * 20), off(57.3), false);
        }
        let flight = g.flight_median_error_deg().unwrap();
        assert!((flight - 3.0).abs() < 0.02, "flight median {flight}");
        // The last minute (33-93 s): 10 s at 3 degrees, 40 s at 1, 10 s on the ground.
        let recent = g.median_error_deg().unwrap();
        assert!((recent - 1.0).abs() < 0.02, "recent median {recent}");
        assert!(g.errors.len() <= 3001, "a minute of reports: {}", g.errors.len());
        // A flood is capped: 10 s at 1 kHz keeps the newest RECENT_MAX.
        for i in 0..10_000u64 {
            g.on_report(Mono::from_millis(93_000) + Duration::from_micros(i * 1000), off(2.0), true);
        }
        assert_eq!(g.errors.len(), RECENT_MAX);
        assert!(g.errors.iter().all(|e| (e.1 - 2.0).abs() < 1e-9));
    }

    #[test]
    fn a_refusal_is_reported_once_and_control_is_asked_again() {
        let mut g = Gimbal::default();
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::ZERO, 1, (1, 191));
        assert!(g
            .on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MavResult::MAV_RESULT_DENIED)
            .is_some());
        assert_eq!(g.control(), Control::Released);
        assert!(g
            .on_ack(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, MavResult::MAV_RESULT_DENIED)
            .is_none());
        let (c, _, _) = command(&g.poll_transmit(Mono::ZERO, 1, (1, 191)).unwrap());
        assert_eq!(c, MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE);
    }

    /// PX4 takes the gimbal for RTL after mavloc has pointed it for the whole mission (every
    /// SITL coastline flight): that is said as such, once per time it happens, not as a
    /// missing gimbal manager. Its loop of accepted CONFIGUREs and refused setpoints stays
    /// quiet.
    #[test]
    fn an_autopilot_taking_the_gimbal_back_is_told_from_one_without_a_manager() {
        let me = (1, 191);
        let yaw = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW;
        let configure = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE;
        let (ok, denied) = (MavResult::MAV_RESULT_ACCEPTED, MavResult::MAV_RESULT_DENIED);
        let mut g = Gimbal::default();
        let flight = |g: &mut Gimbal| {
            assert!(g.on_ack(configure, ok).is_none());
            for _ in 0..3 {
                assert!(g.on_ack(yaw, ok).is_none());
            }
            let said = g.on_ack(yaw, denied).expect("the first refusal after accepted setpoints is reported");
            assert!(said.contains("took the gimbal back") && !said.contains("MNT_MODE_IN"), "{said}");
            for _ in 0..10 {
                assert!(g.on_ack(configure, ok).is_none());
                assert!(g.on_ack(yaw, denied).is_none(), "refused again while the autopilot holds it");
            }
        };
        g.aim(0.0, -1.0);
        g.poll_transmit(Mono::ZERO, 1, me);
        flight(&mut g);
        // The next flight: pointed again, then taken back again, said again.
        flight(&mut g);
        // A manager that never took a setpoint: the configuration hint.
        let mut g = Gimbal::default();
        assert!(g.on_ack(configure, ok).is_none());
        let said = g.on_ack(yaw, denied).unwrap();
        assert!(said.contains("MNT_MODE_IN=4"), "{said}");
        assert!(g.on_ack(yaw, denied).is_none());
    }
}
