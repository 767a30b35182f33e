//! Frames that stop in flight. A camera can stop delivering without an error: a driver
//! that hangs, a cable half out, a simulator that stops sending the poses it renders
//! from. The camera then raises no "lost" event, and the pipeline has nothing to work on;
//! without GPS the autopilot has no position from mavloc and dead-reckons on its IMU
//! (0.3-1.7 m off after 4 s against PX4 SITL, `tools/sitl.py --camera-gap 4`). The ground
//! station is told once per silence, and again when frames come back, with how long they
//! were away.

use std::time::Duration;

use super::time::Mono;

#[derive(Debug, Default)]
pub struct FrameWatch {
    /// When the last frame reached the pipeline (used or skipped).
    last: Option<Mono>,
    /// Since when it is watching (in flight): a silence counts from then at the earliest,
    /// so frames that stopped on the ground are said a second after take-off, as missing
    /// for that second.
    since: Option<Mono>,
    /// The silence was said.
    warned: bool,
}

impl FrameWatch {
    /// A frame reached the pipeline at `now`; after a warning, the line saying frames
    /// came back.
    pub fn on_frame(&mut self, now: Mono) -> Option<String> {
        let back = std::mem::take(&mut self.warned).then(|| {
            let away = self.last.map_or(0.0, |t| now.saturating_sub(t).as_secs_f64());
            format!("camera frames again after {away:.1} s without")
        });
        self.last = Some(now);
        back
    }

    /// When [`FrameWatch::on_timeout`] has something to say, watching with `limit`.
    pub fn deadline(&self, limit: Duration) -> Option<Mono> {
        match (self.last, self.warned) {
            (Some(t), false) => Some(t.max(self.since.unwrap_or(t)) + limit),
            _ => None,
        }
    }

    /// `watching`: a pipeline runs on a camera that is up, in flight. The warning, once
    /// per silence of `limit` or longer.
    pub fn on_timeout(&mut self, now: Mono, watching: bool, limit: Duration) -> Option<Duration> {
        if !watching {
            self.since = None;
            return None;
        }
        let since = *self.since.get_or_insert(now);
        let silent = now.saturating_sub(self.last?.max(since));
        if self.warned || silent < limit {
            return None;
        }
        self.warned = true;
        Some(silent)
    }

    /// The camera went down or the pipeline stopped: that is said on its own, and the
    /// next frame starts a new watch.
    pub fn reset(&mut self) {
        *self = FrameWatch::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(s: f64) -> Mono {
        Mono::from_secs_f64(s)
    }

    #[test]
    fn a_silence_is_said_once_and_the_return_with_its_length() {
        let limit = Duration::from_secs(1);
        let mut w = FrameWatch::default();
        assert_eq!(w.on_timeout(at(5.0), true, limit), None, "no frame yet: nothing to miss");
        assert_eq!(w.on_frame(at(10.0)), None);
        assert_eq!(w.deadline(limit), Some(at(11.0)));
        assert_eq!(w.on_timeout(at(10.9), true, limit), None);
        assert_eq!(w.on_timeout(at(11.5), true, limit), Some(Duration::from_millis(1500)));
        assert_eq!(w.on_timeout(at(12.0), true, limit), None, "said once");
        assert_eq!(w.deadline(limit), None);
        assert_eq!(w.on_frame(at(12.6)).as_deref(), Some("camera frames again after 2.6 s without"));
        assert_eq!(w.on_frame(at(12.7)), None);
        w.reset();
        assert_eq!(w.on_timeout(at(20.0), true, limit), None, "the camera said it went down");
    }

    /// Frames that stopped on the ground are missed from the take-off on, not before.
    #[test]
    fn a_silence_counts_from_when_the_watch_began() {
        let limit = Duration::from_secs(1);
        let mut w = FrameWatch::default();
        w.on_frame(at(10.0));
        assert_eq!(w.on_timeout(at(14.0), false, limit), None);
        assert_eq!(w.on_timeout(at(15.0), true, limit), None, "just took off");
        assert_eq!(w.deadline(limit), Some(at(16.0)));
        assert_eq!(w.on_timeout(at(16.0), true, limit), Some(Duration::from_secs(1)));
        // Landed and off again: a new watch, a new silence.
        let mut w = FrameWatch::default();
        w.on_frame(at(10.0));
        w.on_timeout(at(10.5), true, limit);
        w.on_timeout(at(10.9), false, limit);
        assert_eq!(w.on_timeout(at(11.5), true, limit), None, "watching again from 11.5 s");
    }
}
