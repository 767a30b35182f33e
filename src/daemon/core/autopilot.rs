//! Is the autopilot there? Found on its first heartbeat, lost after
//! `mavlink.autopilot_timeout_s` without one, rebooted when its boot clock runs backwards
//! (reported by the telemetry module, forwarded here by the core).

use std::time::Duration;

use mavlink::dialects::common::{MavLandedState, MavModeFlag, HEARTBEAT_DATA};

use super::time::Mono;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ApState {
    Absent,
    Present { sys: u8, last_seen: Mono },
    Lost { since: Mono },
}

/// What changed, for the core to route to the other modules.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ApNotice {
    Found { sys: u8, what: String },
    Lost,
}

#[derive(Debug)]
pub struct Autopilot {
    state: ApState,
    timeout: Duration,
    armed: bool,
    landed: Option<MavLandedState>,
    /// In the air since the last touchdown.
    flew: bool,
    /// A touchdown not yet taken ([`Autopilot::take_touchdown`]).
    touchdown: bool,
}

impl Autopilot {
    pub fn new(timeout: Duration) -> Autopilot {
        Autopilot {
            state: ApState::Absent,
            timeout,
            armed: false,
            landed: None,
            flew: false,
            touchdown: false,
        }
    }

    pub fn state(&self) -> ApState {
        self.state
    }

    pub fn present(&self) -> bool {
        matches!(self.state, ApState::Present { .. })
    }

    pub fn armed(&self) -> bool {
        self.armed
    }

    pub fn landed_state(&self) -> Option<MavLandedState> {
        self.landed
    }

    pub fn on_ground(&self) -> bool {
        self.landed == Some(MavLandedState::MAV_LANDED_STATE_ON_GROUND)
    }

    pub fn airborne(&self) -> bool {
        self.landed == Some(MavLandedState::MAV_LANDED_STATE_IN_AIR)
    }

    /// A heartbeat from the autopilot's system and component.
    pub fn on_heartbeat(&mut self, now: Mono, sys: u8, h: &HEARTBEAT_DATA, what: String) -> Option<ApNotice> {
        let armed = h.base_mode.contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
        // An autopilot that never says its landed state: disarming is the touchdown.
        if self.landed.is_none() && self.armed && !armed {
            self.touchdown = true;
        }
        self.armed = armed;
        let found = !self.present();
        self.state = ApState::Present { sys, last_seen: now };
        found.then_some(ApNotice::Found { sys, what })
    }

    /// Any other message from the autopilot while it is present: it is still there. A
    /// flood on the link makes the kernel drop datagrams at random, and three heartbeats in
    /// a row can go while its telemetry at tens of messages a second comes through (an
    /// outside trial: "autopilot lost" under 50 000 datagrams/s). Finding it still takes
    /// a heartbeat, which says what it is.
    pub fn on_traffic(&mut self, now: Mono) {
        if let ApState::Present { last_seen, .. } = &mut self.state {
            *last_seen = now;
        }
    }

    /// The autopilot's landed state. A touchdown is on the ground after it was in the
    /// air (PX4 passes through `LANDING` on the way down; a first `ON_GROUND` after
    /// mavloc starts, or one repeated, is none).
    pub fn on_landed_state(&mut self, s: MavLandedState) {
        if s == MavLandedState::MAV_LANDED_STATE_IN_AIR {
            self.flew = true;
        }
        self.landed = Some(s);
        if s == MavLandedState::MAV_LANDED_STATE_ON_GROUND && self.flew {
            self.flew = false;
            self.touchdown = true;
        }
    }

    /// Whether the vehicle has touched down since the last call: by its landed state, or
    /// by disarming when it never says one.
    pub fn take_touchdown(&mut self) -> bool {
        std::mem::take(&mut self.touchdown)
    }

    pub fn deadline(&self) -> Option<Mono> {
        match self.state {
            ApState::Present { last_seen, .. } => Some(last_seen + self.timeout),
            _ => None,
        }
    }

    /// A no-op before the deadline.
    pub fn on_timeout(&mut self, now: Mono) -> Option<ApNotice> {
        match self.deadline() {
            Some(d) if d <= now => {
                self.state = ApState::Lost { since: now };
                self.armed = false;
                Some(ApNotice::Lost)
            }
            _ => None,
        }
    }

    pub fn timeout(&self) -> Duration {
        self.timeout
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn found_once_lost_after_the_timeout_and_found_again() {
        let mut a = Autopilot::new(Duration::from_secs(3));
        let hb = HEARTBEAT_DATA::default();
        assert!(matches!(
            a.on_heartbeat(Mono::from_millis(0), 1, &hb, "px4".into()),
            Some(ApNotice::Found { sys: 1, .. })
        ));
        assert_eq!(a.on_heartbeat(Mono::from_millis(1000), 1, &hb, "px4".into()), None);
        assert_eq!(a.deadline(), Some(Mono::from_millis(4000)));
        assert_eq!(a.on_timeout(Mono::from_millis(3999)), None, "no-op before the deadline");
        assert_eq!(a.on_timeout(Mono::from_millis(4000)), Some(ApNotice::Lost));
        assert_eq!(a.deadline(), None);
        assert_eq!(a.on_timeout(Mono::from_millis(9000)), None, "lost once");
        assert!(a.on_heartbeat(Mono::from_millis(9000), 1, &hb, "px4".into()).is_some());
    }

    /// Its other messages keep a present autopilot present when its heartbeats are lost;
    /// they do not find a lost one.
    #[test]
    fn other_messages_keep_the_autopilot_but_do_not_find_it() {
        let mut a = Autopilot::new(Duration::from_secs(3));
        a.on_heartbeat(Mono::from_millis(0), 1, &HEARTBEAT_DATA::default(), "px4".into());
        for ms in (100..10_000).step_by(100) {
            a.on_traffic(Mono::from_millis(ms));
            assert_eq!(a.on_timeout(Mono::from_millis(ms)), None, "{ms} ms: no heartbeat since 0");
        }
        assert_eq!(a.on_timeout(Mono::from_millis(12_900)), Some(ApNotice::Lost));
        a.on_traffic(Mono::from_millis(13_000));
        assert!(!a.present(), "found only by a heartbeat");
    }
}
