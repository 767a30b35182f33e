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

#[derive(Debug)]
pub struct Gimbal {
    control: Control,
    /// The recent setpoints: when sent, and the direction each asks for (unit, NED).
    pub sent: std::collections::VecDeque<(Mono, [f64; 3])>,
    /// Pointing errors (degrees) of reports against settled setpoints, the newest last.
    pub errors: std::collections::VecDeque<f64>,
    /// (yaw, pitch) radians, newest aim not yet sent.
    pending: Option<(f64, f64)>,
    next: Mono,
    refused_once: bool,
}

impl Default for Gimbal {
    fn default() -> Self {
        Gimbal {
            control: Control::Released,
            sent: Default::default(),
            errors: Default::default(),
            pending: None,
            next: Mono::ZERO,
            refused_once: false,
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
    /// setpoint sent at least [`SETTLE`] before is kept (the last 600, a minute at 10 Hz).
    pub fn on_report(&mut self, now: Mono, axis: [f64; 3]) {
        let Some(&(_, want)) = self.sent.iter().rev().find(|(t, _)| *t + SETTLE <= now) else { return };
        let dot: f64 = (0..3).map(|i| axis[i] * want[i]).sum();
        self.errors.push_back(dot.clamp(-1.0, 1.0).acos().to_degrees());
        if self.errors.len() > 600 {
            self.errors.pop_front();
        }
    }

    /// Median pointing error over the kept reports, degrees.
    pub fn median_error_deg(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.errors.iter().copied().collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
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

    /// The manager's answer to CONFIGURE or PITCHYAW. Returns a line to report the first
    /// time control is refused.
    pub fn on_ack(&mut self, command: MavCmd, result: MavResult) -> Option<String> {
        match result {
            MavResult::MAV_RESULT_ACCEPTED | MavResult::MAV_RESULT_IN_PROGRESS => {
                if command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE {
                    self.control = Control::InControl;
                }
                None
            }
            other => {
                // Take control again before the next setpoint.
                self.control = Control::Released;
                (!std::mem::replace(&mut self.refused_once, true)).then(|| {
                    format!("autopilot refused {command:?}: {other:?}; is it a gimbal manager (PX4: MNT_MODE_IN=4)?")
                })
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
}
