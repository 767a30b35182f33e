//! TIMESYNC with the autopilot: mavloc asks ten times a second (at most 10 requests
//! remembered) to learn the offset between its clock and the autopilot's, and answers the
//! autopilot's own requests so PX4 can map mavloc's timestamps onto its clock (without
//! that, PX4 stamps vision estimates on arrival).

use std::time::Duration;

use mavlink::dialects::common::{MavMessage, TIMESYNC_DATA};

use super::time::Mono;

/// As often as PX4 asks (its Timesync runs at 10 Hz): the clock model takes its level from
/// the last 2 s of answers and its rate from 30 s (`align::ClockSync`), and PX4 SITL's
/// lockstep clock changes its rate with the machine's load from one second to the next.
const PERIOD: Duration = Duration::from_millis(100);
/// A second of requests: the clock model takes round trips of up to a second.
const IN_FLIGHT: usize = 10;
/// How far before the request's own stamp mavloc's idea of the autopilot's clock may put
/// its arrival and still answer: the clock model's error (milliseconds, tens in SITL).
const ANSWER_EARLY_S: f64 = 0.1;

/// A round trip: when the request left, when the answer arrived (both mavloc's clock,
/// seconds), and the autopilot's clock in between (seconds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub sent: f64,
    pub received: f64,
    pub remote: f64,
}

#[derive(Debug, Default)]
pub struct TimeSync {
    active: bool,
    next: Mono,
    /// ts1 (ns) of our requests in flight, and when each left.
    sent: Vec<(i64, Mono)>,
}

impl TimeSync {
    pub fn start(&mut self, now: Mono) {
        *self = TimeSync { active: true, next: now, sent: Vec::new() };
    }

    pub fn stop(&mut self) {
        self.active = false;
        self.sent.clear();
    }

    pub fn in_flight(&self) -> usize {
        self.sent.len()
    }

    pub fn deadline(&self) -> Option<Mono> {
        self.active.then_some(self.next)
    }

    pub fn poll_transmit(&mut self, now: Mono, target: u8) -> Option<MavMessage> {
        if !self.active || now < self.next {
            return None;
        }
        self.next = now + PERIOD;
        let ts1 = now.0 as i64 * 1000;
        if self.sent.len() >= IN_FLIGHT {
            self.sent.remove(0);
        }
        self.sent.push((ts1, now));
        Some(MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 0, ts1, target_system: target, target_component: 1 }))
    }

    /// A TIMESYNC from the autopilot received at `rx`: either its request (answered with
    /// `now_autopilot`, the arrival on the autopilot's clock as mavloc tracks it, in
    /// seconds: the clock mavloc stamps what it sends the autopilot in) or its answer to
    /// one of ours (a clock sample). A request is not answered while mavloc does not know
    /// that clock, nor when the arrival it knows is not just after the request's own
    /// stamp (its `ts1`, the autopilot's clock when it asked): an autopilot that has just
    /// rebooted asks at 10 Hz from its boot, before mavloc believes the reboot (a few
    /// stamps over half a second), and PX4 takes its first answer as the offset outright.
    pub fn on_timesync(
        &mut self,
        rx: Mono,
        t: &TIMESYNC_DATA,
        from: (u8, u8),
        now_autopilot: Option<f64>,
    ) -> (Option<MavMessage>, Option<Sample>) {
        if t.tc1 == 0 {
            let asked = t.ts1 as f64 * 1e-9;
            // An answer of 0 would read as a request.
            let reply = now_autopilot
                .filter(|&a| a > 0.0 && (-ANSWER_EARLY_S..=1.0).contains(&(a - asked)))
                .map(|a| {
                    MavMessage::TIMESYNC(TIMESYNC_DATA {
                        tc1: (a * 1e9) as i64,
                        ts1: t.ts1,
                        target_system: from.0,
                        target_component: from.1,
                    })
                });
            return (reply, None);
        }
        match self.sent.iter().position(|&(ts1, _)| ts1 == t.ts1) {
            Some(i) => {
                let (_, sent) = self.sent.remove(i);
                (None, Some(Sample { sent: sent.secs(), received: rx.secs(), remote: t.tc1 as f64 * 1e-9 }))
            }
            None => (None, None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ten_times_a_second_and_the_answer_gives_a_sample_taken_at_arrival() {
        let mut t = TimeSync::default();
        assert!(t.poll_transmit(Mono::ZERO, 1).is_none());
        t.start(Mono::from_millis(100));
        let Some(MavMessage::TIMESYNC(req)) = t.poll_transmit(Mono::from_millis(100), 1) else { panic!() };
        assert!(t.poll_transmit(Mono::from_millis(160), 1).is_none());
        assert_eq!(t.deadline(), Some(Mono::from_millis(200)));
        let answer = TIMESYNC_DATA { tc1: 5_000_000_000, ts1: req.ts1, ..Default::default() };
        let (reply, sample) = t.on_timesync(Mono::from_millis(140), &answer, (1, 1), Some(5.02));
        assert!(reply.is_none());
        assert_eq!(sample, Some(Sample { sent: 0.1, received: 0.14, remote: 5.0 }));
        assert_eq!(t.in_flight(), 0);
        // The autopilot's own request, stamped 6.895 s on its clock, is answered with the
        // arrival on that clock, and not at all while that clock is unknown.
        let request = TIMESYNC_DATA { tc1: 0, ts1: 6_895_000_000, ..Default::default() };
        let (reply, _) = t.on_timesync(Mono::from_millis(2000), &request, (1, 1), Some(6.9));
        let Some(MavMessage::TIMESYNC(r)) = reply else { panic!() };
        assert_eq!((r.tc1, r.ts1), (6_900_000_000, 6_895_000_000));
        assert_eq!(t.on_timesync(Mono::from_millis(2000), &request, (1, 1), None), (None, None));
    }

    /// Just rebooted, an autopilot asks at 10 Hz from its boot while mavloc still maps
    /// arrivals onto the old boot's clock (it believes a reboot after a few stamps over
    /// half a second): an answer from that clock would be PX4's first offset, taken
    /// outright. Only an arrival just after the request's own stamp is answered, and
    /// never with 0, which would read as a request.
    #[test]
    fn a_request_from_another_clock_than_the_one_tracked_is_not_answered() {
        let mut t = TimeSync::default();
        let asked_at = |s: f64| TIMESYNC_DATA { tc1: 0, ts1: (s * 1e9) as i64, ..Default::default() };
        let rx = Mono::from_millis(500_000);
        // 0.3 s after the reboot, the old boot's clock says 412 s.
        assert_eq!(t.on_timesync(rx, &asked_at(0.3), (1, 1), Some(412.0)), (None, None));
        // An arrival 0.2 s before it was asked, and one at 0.
        assert_eq!(t.on_timesync(rx, &asked_at(412.0), (1, 1), Some(411.8)), (None, None));
        assert_eq!(t.on_timesync(rx, &asked_at(0.0), (1, 1), Some(0.0)), (None, None));
        // Within the clock model's error either way, answered.
        assert!(t.on_timesync(rx, &asked_at(412.0), (1, 1), Some(411.95)).0.is_some());
        assert!(t.on_timesync(rx, &asked_at(412.0), (1, 1), Some(412.3)).0.is_some());
    }

    #[test]
    fn unanswered_requests_are_bounded() {
        let mut t = TimeSync::default();
        t.start(Mono::ZERO);
        for s in 0..100 {
            t.poll_transmit(Mono::from_millis(s * 100), 1);
        }
        assert_eq!(t.in_flight(), IN_FLIGHT);
    }
}
