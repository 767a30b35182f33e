//! The daemon's own pulse: the HEARTBEAT period, the once-a-second report (counters to
//! the ground, `status.json`), and systemd's watchdog. The heartbeat's MAV_STATE is the
//! core's to compute; this module only says when.

use std::time::Duration;

use super::time::{earliest, Mono};

const REPORT_PERIOD: Duration = Duration::from_secs(1);

#[derive(Debug)]
pub struct Health {
    heartbeat_period: Duration,
    next_heartbeat: Mono,
    next_report: Mono,
    /// systemd's WatchdogSec / 3 when the watchdog is on.
    watchdog_period: Option<Duration>,
    next_watchdog: Mono,
    heartbeat_due: bool,
    report_due: bool,
    watchdog_due: bool,
}

impl Health {
    pub fn new(heartbeat_hz: f64, watchdog_period: Option<Duration>) -> Health {
        Health {
            heartbeat_period: Duration::from_secs_f64(1.0 / heartbeat_hz.max(0.01)),
            next_heartbeat: Mono::ZERO,
            next_report: Mono::ZERO + REPORT_PERIOD,
            watchdog_period,
            next_watchdog: Mono::ZERO,
            heartbeat_due: false,
            report_due: false,
            watchdog_due: false,
        }
    }

    pub fn deadline(&self) -> Option<Mono> {
        earliest([
            Some(self.next_heartbeat),
            Some(self.next_report),
            self.watchdog_period.map(|_| self.next_watchdog),
        ])
    }

    pub fn on_timeout(&mut self, now: Mono) {
        if self.next_heartbeat <= now {
            self.heartbeat_due = true;
            // From now, not from the missed slot: a stalled loop does not burst heartbeats.
            self.next_heartbeat = now + self.heartbeat_period;
        }
        if self.next_report <= now {
            self.report_due = true;
            self.next_report = now + REPORT_PERIOD;
        }
        if let Some(p) = self.watchdog_period {
            if self.next_watchdog <= now {
                self.watchdog_due = true;
                self.next_watchdog = now + p;
            }
        }
    }

    pub fn take_heartbeat(&mut self) -> bool {
        std::mem::take(&mut self.heartbeat_due)
    }

    pub fn take_report(&mut self) -> bool {
        std::mem::take(&mut self.report_due)
    }

    pub fn take_watchdog(&mut self) -> bool {
        std::mem::take(&mut self.watchdog_due)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heartbeat_report_and_watchdog_keep_their_periods() {
        let mut h = Health::new(1.0, Some(Duration::from_millis(3000)));
        let (mut hb, mut rep, mut wd) = (0, 0, 0);
        let mut now = Mono::ZERO;
        while now < Mono::from_millis(10_000) {
            h.on_timeout(now);
            hb += h.take_heartbeat() as u32;
            rep += h.take_report() as u32;
            wd += h.take_watchdog() as u32;
            let next = h.deadline().unwrap();
            assert!(next > now, "no spinning: the deadline moves past now");
            now = next;
        }
        assert_eq!((hb, rep, wd), (10, 9, 4));
    }
}
