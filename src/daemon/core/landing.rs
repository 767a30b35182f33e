//! The landing command: MAV_CMD_NAV_LAND, retried once a second until the autopilot
//! acknowledges it, at most `TRIES` times.
//!
//! NAV_LAND rather than LANDING_TARGET: the trigger fires only once the vehicle is inside
//! the zone and the particles agree (indoor seed sec. 4.7), so "land where you are" is
//! the whole manoeuvre; LANDING_TARGET would need PX4's landing-target estimator fed with
//! a bearing to a pad, which the texton pipeline does not have.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;

pub const TRIES: u32 = 5;
const RETRY: Duration = Duration::from_secs(1);
/// After IN_PROGRESS the autopilot is working on it: wait longer before resending.
const IN_PROGRESS_WAIT: Duration = Duration::from_secs(5);

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
    GaveUp(u32),
}

#[derive(Debug)]
pub struct Landing {
    state: LandingState,
}

impl Default for Landing {
    fn default() -> Self {
        Landing { state: LandingState::Idle }
    }
}

impl Landing {
    pub fn state(&self) -> LandingState {
        self.state
    }

    /// Starts a landing unless one is in flight. Returns whether it started.
    pub fn request(&mut self, now: Mono) -> bool {
        if self.state != LandingState::Idle {
            return false;
        }
        self.state = LandingState::Pending { tries: 0, next: now };
        true
    }

    pub fn cancel(&mut self) {
        self.state = LandingState::Idle;
    }

    pub fn deadline(&self) -> Option<Mono> {
        match self.state {
            LandingState::Pending { next, .. } => Some(next),
            LandingState::Idle => None,
        }
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

    pub fn poll_transmit(&mut self, now: Mono, target: u8) -> Option<MavMessage> {
        let LandingState::Pending { tries, next } = self.state else { return None };
        if next > now || tries >= TRIES {
            return None;
        }
        self.state = LandingState::Pending { tries: tries + 1, next: now + RETRY };
        Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            // Yaw and position NaN: land here, keep the heading (PX4, ArduPilot).
            param4: f32::NAN,
            param5: f32::NAN,
            param6: f32::NAN,
            command: MavCmd::MAV_CMD_NAV_LAND,
            target_system: target,
            target_component: 1,
            confirmation: tries.min(255) as u8,
            ..Default::default()
        }))
    }

    pub fn on_ack(&mut self, now: Mono, result: MavResult) -> Option<LandingNotice> {
        let LandingState::Pending { tries, .. } = self.state else { return None };
        match result {
            MavResult::MAV_RESULT_ACCEPTED => {
                self.state = LandingState::Idle;
                Some(LandingNotice::Accepted)
            }
            MavResult::MAV_RESULT_IN_PROGRESS => {
                self.state = LandingState::Pending { tries, next: now + IN_PROGRESS_WAIT };
                None
            }
            other => {
                self.state = LandingState::Idle;
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
        assert!(l.request(Mono::from_millis(1000)));
        assert!(!l.request(Mono::from_millis(1000)), "one landing at a time");
        assert!(l.poll_transmit(Mono::from_millis(1000), 1).is_some());
        assert!(l.poll_transmit(Mono::from_millis(1500), 1).is_none());
        assert_eq!(l.deadline(), Some(Mono::from_millis(2000)));
        assert!(l.poll_transmit(Mono::from_millis(2000), 1).is_some());
        assert_eq!(
            l.on_ack(Mono::from_millis(2100), MavResult::MAV_RESULT_ACCEPTED),
            Some(LandingNotice::Accepted)
        );
        assert!(l.poll_transmit(Mono::from_millis(9000), 1).is_none());
        assert_eq!(l.deadline(), None);
    }

    #[test]
    fn gives_up_after_five_unanswered_tries() {
        let mut l = Landing::default();
        l.request(Mono::ZERO);
        let mut now = Mono::ZERO;
        let mut sent = 0;
        let mut notice = None;
        while let Some(d) = l.deadline() {
            now = d;
            notice = l.on_timeout(now).or(notice);
            sent += l.poll_transmit(now, 1).is_some() as u32;
        }
        assert_eq!(sent, TRIES);
        assert_eq!(notice, Some(LandingNotice::GaveUp(TRIES)));
        assert_eq!(now, Mono::from_millis(TRIES as u64 * 1000), "the last try gets its second");
    }
}
