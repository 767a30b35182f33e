//! The telemetry streams mavloc asks the autopilot for (MAV_CMD_SET_MESSAGE_INTERVAL),
//! one request in flight at a time because PX4 acknowledges by command id only.
//! Requests that end unacknowledged or refused are reported once, in one notice.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;

/// Streams requested from the autopilot: (message id, name, interval in microseconds).
pub const STREAMS: &[(u32, &str, i32)] = &[
    (30, "ATTITUDE", 20_000),
    (32, "LOCAL_POSITION_NED", 20_000),
    (33, "GLOBAL_POSITION_INT", 100_000),
    (242, "HOME_POSITION", 1_000_000),
    (285, "GIMBAL_DEVICE_ATTITUDE_STATUS", 20_000),
    // Who holds the gimbal (gimbal::Gimbal yields to another controller): PX4 sends it
    // every 2 s unless asked.
    (281, "GIMBAL_MANAGER_STATUS", 500_000),
    (2, "SYSTEM_TIME", 1_000_000),
    (245, "EXTENDED_SYS_STATE", 200_000),
];

/// The simulator's ground truth (PX4 SITL streams SIH's true state as
/// HIL_STATE_QUATERNION when asked): asked for only when the sim camera renders from the
/// truth (`camera.sim_pose = "truth"`), at the camera's need, 30 Hz.
pub const TRUTH_STREAM: (u32, &str, i32) = (115, "HIL_STATE_QUATERNION", 33_333);

const TRIES: u32 = 5;
const RETRY: Duration = Duration::from_secs(1);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StreamState {
    /// Not yet asked (`tries == 0`) or asked and waiting for the ACK until `next`.
    Pending {
        tries: u32,
        next: Mono,
    },
    Accepted,
    Refused,
}

#[derive(Debug)]
pub struct Streams {
    /// What is asked for: [`STREAMS`], and [`TRUTH_STREAM`] when wanted.
    list: Vec<(u32, &'static str, i32)>,
    states: Vec<StreamState>,
    /// Whether requests may go out (the autopilot is present).
    active: bool,
    /// The one-line summary of failures is due once every stream has settled.
    reported: bool,
}

impl Default for Streams {
    fn default() -> Self {
        Streams::new(false)
    }
}

impl Streams {
    /// `truth`: also ask for the simulator's ground truth.
    pub fn new(truth: bool) -> Streams {
        let mut list = STREAMS.to_vec();
        if truth {
            list.push(TRUTH_STREAM);
        }
        Streams {
            states: vec![StreamState::Pending { tries: 0, next: Mono::ZERO }; list.len()],
            list,
            active: false,
            reported: false,
        }
    }

    pub fn states(&self) -> &[StreamState] {
        &self.states
    }

    /// Starts (or restarts, after a reboot) the requests.
    pub fn start(&mut self) {
        *self = Streams { active: true, ..Streams::new(self.list.contains(&TRUTH_STREAM)) };
    }

    pub fn stop(&mut self) {
        self.active = false;
    }

    fn in_flight(&self) -> Option<usize> {
        self.states.iter().position(|s| matches!(s, StreamState::Pending { tries, .. } if *tries > 0))
    }

    /// The next request to send, if one is due. `target` is the autopilot's system id.
    pub fn poll_transmit(&mut self, now: Mono, target: u8) -> Option<MavMessage> {
        if !self.active {
            return None;
        }
        let (i, tries) = match self.in_flight() {
            Some(i) => match self.states[i] {
                StreamState::Pending { tries, next } if next <= now => (i, tries),
                _ => return None,
            },
            None => (self.states.iter().position(|s| matches!(s, StreamState::Pending { .. }))?, 0),
        };
        if tries >= TRIES {
            self.states[i] = StreamState::Refused;
            return self.poll_transmit(now, target);
        }
        self.states[i] = StreamState::Pending { tries: tries + 1, next: now + RETRY };
        let (id, _, interval) = self.list[i];
        Some(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: id as f32,
            param2: interval as f32,
            command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
            target_system: target,
            target_component: 1,
            confirmation: tries.min(255) as u8,
            ..Default::default()
        }))
    }

    /// The autopilot's COMMAND_ACK for MAV_CMD_SET_MESSAGE_INTERVAL.
    pub fn on_ack(&mut self, result: MavResult) {
        if let Some(i) = self.in_flight() {
            self.states[i] = match result {
                MavResult::MAV_RESULT_ACCEPTED => StreamState::Accepted,
                MavResult::MAV_RESULT_IN_PROGRESS => self.states[i],
                _ => StreamState::Refused,
            };
        }
    }

    pub fn deadline(&self) -> Option<Mono> {
        if !self.active {
            return None;
        }
        match self.in_flight() {
            Some(i) => match self.states[i] {
                StreamState::Pending { next, .. } => Some(next),
                _ => None,
            },
            // A request not yet sent is not a timer: poll_transmit hands it out at once.
            None => None,
        }
    }

    /// Once every stream has settled, if any failed: a log line naming them, and a short
    /// line that fits one STATUSTEXT (a ground station shows split texts as pieces).
    pub fn poll_summary(&mut self) -> Option<(String, String)> {
        if !self.active
            || self.reported
            || self.states.iter().any(|s| matches!(s, StreamState::Pending { .. }))
        {
            return None;
        }
        self.reported = true;
        let failed: Vec<&str> = (0..self.list.len())
            .filter(|&i| self.states[i] == StreamState::Refused)
            .map(|i| self.list[i].1)
            .collect();
        (!failed.is_empty()).then(|| {
            (
                format!(
                    "autopilot refused or did not acknowledge these stream requests: {}",
                    failed.join(", ")
                ),
                format!("{} of {} streams not set up (see log)", failed.len(), self.list.len()),
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn requested(m: &MavMessage) -> u32 {
        match m {
            MavMessage::COMMAND_LONG(c) if c.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                c.param1 as u32
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn one_request_in_flight_each_acknowledged_in_turn() {
        let mut s = Streams::default();
        assert!(s.poll_transmit(Mono::ZERO, 1).is_none(), "inactive until the autopilot is found");
        s.start();
        let mut ids = Vec::new();
        let mut now = Mono::ZERO;
        while let Some(m) = s.poll_transmit(now, 1) {
            ids.push(requested(&m));
            assert!(s.poll_transmit(now, 1).is_none(), "one in flight");
            s.on_ack(MavResult::MAV_RESULT_ACCEPTED);
            now = now + Duration::from_millis(10);
        }
        assert_eq!(ids, STREAMS.iter().map(|s| s.0).collect::<Vec<_>>());
        assert_eq!(s.deadline(), None);
        assert_eq!(s.poll_summary(), None, "all accepted: nothing to report");
    }

    #[test]
    fn silence_is_retried_then_given_up_and_reported_once() {
        let mut s = Streams::default();
        s.start();
        let mut now = Mono::ZERO;
        let mut sent = 0;
        for _ in 0..200 {
            while s.poll_transmit(now, 1).is_some() {
                sent += 1;
            }
            match s.deadline() {
                Some(d) => now = d.max(now),
                None => break,
            }
        }
        assert_eq!(sent, TRIES as usize * STREAMS.len());
        let (line, short) = s.poll_summary().expect("reported");
        assert!(line.contains("ATTITUDE") && line.contains("EXTENDED_SYS_STATE"), "{line}");
        assert!(format!("mavloc: {short}").len() <= 50, "one STATUSTEXT: {short}");
        assert_eq!(s.poll_summary(), None, "once");
    }
}
