//! The landing command, retried once a second until the autopilot acknowledges it, at
//! most `TRIES` times.
//!
//! The trigger fires once the vehicle is inside the zone and the particles agree (indoor
//! seed sec. 4.7). "Land where you are" (MAV_CMD_NAV_LAND) then touches down anywhere in
//! the zone plus the drift of the descent (0.21 and 0.43 m from the commanded point in two
//! PX4 SITL flights). With a target (`indoor.landing_precision`) mavloc asks for PX4's
//! precision landing instead (MAV_CMD_NAV_LAND_LOCAL, id 23, which PX4 handles as
//! NAV_PRECLAND) and streams the zone's centre as LANDING_TARGET in the local frame
//! (PX4 takes `position_valid` targets in MAV_FRAME_LOCAL_NED as the target's position):
//! PX4 then flies over the centre and corrects all the way down. An autopilot that refuses
//! the precision landing gets the plain one.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;

pub const TRIES: u32 = 5;
const RETRY: Duration = Duration::from_secs(1);
/// After IN_PROGRESS the autopilot is working on it: wait longer before resending.
const IN_PROGRESS_WAIT: Duration = Duration::from_secs(5);
/// LANDING_TARGET rate while a precision landing runs (PX4 gives up on a target unseen
/// for PLD_BTOUT, 5 s by default).
const TARGET_PERIOD: Duration = Duration::from_millis(100);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LandingState {
    Idle,
    Pending { tries: u32, next: Mono },
}

/// How a landing ended, for the core to report.
#[derive(Clone, Debug, PartialEq)]
pub enum LandingNotice {
    Accepted,
    Refused(MavResult),
    /// The precision landing was refused: the plain one is sent instead.
    PlainInstead(MavResult),
    GaveUp(u32),
}

#[derive(Debug)]
pub struct Landing {
    state: LandingState,
    command: MavCmd,
    /// The zone's centre, local NED (m), streamed while `streaming`.
    target: Option<[f64; 3]>,
    streaming: bool,
    next_target: Mono,
}

impl Default for Landing {
    fn default() -> Self {
        Landing {
            state: LandingState::Idle,
            command: MavCmd::MAV_CMD_NAV_LAND,
            target: None,
            streaming: false,
            next_target: Mono::ZERO,
        }
    }
}

impl Landing {
    pub fn state(&self) -> LandingState {
        self.state
    }

    /// The command being sent: NAV_LAND, or NAV_LAND_LOCAL for a precision landing.
    pub fn command(&self) -> MavCmd {
        self.command
    }

    /// Whether the zone is being streamed as LANDING_TARGET.
    pub fn streaming(&self) -> bool {
        self.streaming
    }

    /// Starts a landing unless one is in flight; with `target` (local NED, m) a precision
    /// landing on it. Returns whether it started.
    pub fn request(&mut self, now: Mono, target: Option<[f64; 3]>) -> bool {
        if self.state != LandingState::Idle || self.streaming {
            return false;
        }
        self.state = LandingState::Pending { tries: 0, next: now };
        self.target = target;
        self.streaming = target.is_some();
        self.next_target = now;
        self.command =
            if target.is_some() { MavCmd::MAV_CMD_NAV_LAND_LOCAL } else { MavCmd::MAV_CMD_NAV_LAND };
        true
    }

    pub fn cancel(&mut self) {
        self.state = LandingState::Idle;
        self.streaming = false;
    }

    /// The vehicle is down (or disarmed): the target has done its work.
    pub fn landed(&mut self) {
        self.streaming = false;
    }

    pub fn deadline(&self) -> Option<Mono> {
        let command = match self.state {
            LandingState::Pending { next, .. } => Some(next),
            LandingState::Idle => None,
        };
        super::time::earliest([command, self.streaming.then_some(self.next_target)])
    }

    /// Gives up after `TRIES` unanswered sends; a no-op before the deadline.
    pub fn on_timeout(&mut self, now: Mono) -> Option<LandingNotice> {
        match self.state {
            LandingState::Pending { tries, next } if next <= now && tries >= TRIES => {
                self.state = LandingState::Idle;
                Some(LandingNotice::GaveUp(tries))
            }
            _ => None,
        }
    }

    /// `stamp`: `now` on the autopilot's clock (us), the landing target's `time_usec`.
    pub fn poll_transmit(&mut self, now: Mono, target: u8, stamp: u64) -> Option<MavMessage> {
        if let (true, Some(p)) = (self.streaming && self.next_target <= now, self.target) {
            self.next_target = now + TARGET_PERIOD;
            return Some(MavMessage::LANDING_TARGET(LANDING_TARGET_DATA {
                time_usec: stamp,
                frame: MavFrame::MAV_FRAME_LOCAL_NED,
                x: p[0] as f32,
                y: p[1] as f32,
                z: p[2] as f32,
                q: [1.0, 0.0, 0.0, 0.0],
                mavtype: LandingTargetType::LANDING_TARGET_TYPE_VISION_OTHER,
                position_valid: MavBool::MAV_BOOL_TRUE,
                ..Default::default()
            }));
        }
        let LandingState::Pending { tries, next } = self.state else { return None };
        if next > now || tries >= TRIES {
            return None;
        }
        self.state = LandingState::Pending { tries: tries + 1, next: now + RETRY };
        Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            // Yaw and position NaN: land here, keep the heading (PX4, ArduPilot). For the
            // precision landing the target comes as LANDING_TARGET.
            param4: f32::NAN,
            param5: f32::NAN,
            param6: f32::NAN,
            param7: f32::NAN,
            command: self.command,
            target_system: target,
            target_component: 1,
            confirmation: tries.min(255) as u8,
            ..Default::default()
        }))
    }

    /// The autopilot's answer to `command`; answers to another command are not ours.
    pub fn on_ack(&mut self, now: Mono, command: MavCmd, result: MavResult) -> Option<LandingNotice> {
        let LandingState::Pending { tries, .. } = self.state else { return None };
        if command != self.command {
            return None;
        }
        match result {
            MavResult::MAV_RESULT_ACCEPTED => {
                self.state = LandingState::Idle;
                Some(LandingNotice::Accepted)
            }
            MavResult::MAV_RESULT_IN_PROGRESS => {
                self.state = LandingState::Pending { tries, next: now + IN_PROGRESS_WAIT };
                None
            }
            other if self.command == MavCmd::MAV_CMD_NAV_LAND_LOCAL => {
                self.command = MavCmd::MAV_CMD_NAV_LAND;
                self.streaming = false;
                self.state = LandingState::Pending { tries: 0, next: now };
                Some(LandingNotice::PlainInstead(other))
            }
            other => {
                self.state = LandingState::Idle;
                self.streaming = false;
                Some(LandingNotice::Refused(other))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn retried_once_a_second_until_acknowledged() {
        let mut l = Landing::default();
        assert!(l.request(Mono::from_millis(1000), None));
        assert!(!l.request(Mono::from_millis(1000), None), "one landing at a time");
        assert!(l.poll_transmit(Mono::from_millis(1000), 1, 0).is_some());
        assert!(l.poll_transmit(Mono::from_millis(1500), 1, 0).is_none());
        assert_eq!(l.deadline(), Some(Mono::from_millis(2000)));
        assert!(l.poll_transmit(Mono::from_millis(2000), 1, 0).is_some());
        assert_eq!(
            l.on_ack(Mono::from_millis(2100), MavCmd::MAV_CMD_NAV_LAND, MavResult::MAV_RESULT_ACCEPTED),
            Some(LandingNotice::Accepted)
        );
        assert!(l.poll_transmit(Mono::from_millis(9000), 1, 0).is_none());
        assert_eq!(l.deadline(), None);
    }

    #[test]
    fn gives_up_after_five_unanswered_tries() {
        let mut l = Landing::default();
        l.request(Mono::ZERO, None);
        let mut now = Mono::ZERO;
        let mut sent = 0;
        let mut notice = None;
        while let Some(d) = l.deadline() {
            now = d;
            notice = l.on_timeout(now).or(notice);
            sent += l.poll_transmit(now, 1, 0).is_some() as u32;
        }
        assert_eq!(sent, TRIES);
        assert_eq!(notice, Some(LandingNotice::GaveUp(TRIES)));
        assert_eq!(now, Mono::from_millis(TRIES as u64 * 1000), "the last try gets its second");
    }

    #[test]
    fn a_precision_landing_streams_the_zone_and_falls_back_to_a_plain_one_when_refused() {
        let mut l = Landing::default();
        assert!(l.request(Mono::ZERO, Some([2.5, 1.0, 0.0])));
        let mut targets = 0;
        let mut commands = Vec::new();
        let mut now = Mono::ZERO;
        while now <= Mono::from_millis(1000) {
            while let Some(m) = l.poll_transmit(now, 1, 0) {
                match m {
                    MavMessage::LANDING_TARGET(t) => {
                        assert_eq!((t.x, t.y, t.position_valid), (2.5, 1.0, MavBool::MAV_BOOL_TRUE));
                        assert_eq!(t.frame, MavFrame::MAV_FRAME_LOCAL_NED);
                        targets += 1;
                    }
                    MavMessage::COMMAND_LONG(c) => commands.push(c.command),
                    _ => panic!(),
                }
            }
            now = now + Duration::from_millis(50);
        }
        assert_eq!(targets, 11, "10 Hz for a second, the first at once");
        assert_eq!(commands, [MavCmd::MAV_CMD_NAV_LAND_LOCAL, MavCmd::MAV_CMD_NAV_LAND_LOCAL]);
        assert_eq!(l.on_ack(now, MavCmd::MAV_CMD_NAV_LAND, MavResult::MAV_RESULT_DENIED), None, "not ours");
        assert_eq!(
            l.on_ack(now, MavCmd::MAV_CMD_NAV_LAND_LOCAL, MavResult::MAV_RESULT_UNSUPPORTED),
            Some(LandingNotice::PlainInstead(MavResult::MAV_RESULT_UNSUPPORTED))
        );
        assert!(!l.streaming());
        let Some(MavMessage::COMMAND_LONG(c)) = l.poll_transmit(now, 1, 0) else { panic!() };
        assert_eq!(c.command, MavCmd::MAV_CMD_NAV_LAND);
        assert_eq!(
            l.on_ack(now, MavCmd::MAV_CMD_NAV_LAND, MavResult::MAV_RESULT_ACCEPTED),
            Some(LandingNotice::Accepted)
        );
    }

    #[test]
    fn the_target_streams_after_the_accept_until_the_vehicle_is_down() {
        let mut l = Landing::default();
        l.request(Mono::ZERO, Some([0.0, 0.0, 0.0]));
        assert!(matches!(l.poll_transmit(Mono::ZERO, 1, 0), Some(MavMessage::LANDING_TARGET(_))));
        assert!(matches!(l.poll_transmit(Mono::ZERO, 1, 0), Some(MavMessage::COMMAND_LONG(_))));
        l.on_ack(Mono::ZERO, MavCmd::MAV_CMD_NAV_LAND_LOCAL, MavResult::MAV_RESULT_ACCEPTED);
        assert!(matches!(
            l.poll_transmit(Mono::from_millis(5000), 1, 0),
            Some(MavMessage::LANDING_TARGET(_))
        ));
        assert!(!l.request(Mono::from_millis(5000), None), "one landing at a time");
        l.landed();
        assert_eq!(l.poll_transmit(Mono::from_millis(9000), 1, 0), None);
        assert_eq!(l.deadline(), None);
    }
}
