//! The core's clock: plain data, never read from the OS inside the core.

use std::ops::{Add, Sub};
use std::time::Duration;

/// Microseconds since the shell started. The shell stamps every input with it, so the
/// core's behaviour is a function of its inputs alone (and tests run in simulated time).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Mono(pub u64);

impl Mono {
    pub const ZERO: Mono = Mono(0);

    pub fn from_secs_f64(s: f64) -> Mono {
        Mono((s.max(0.0) * 1e6).round() as u64)
    }

    pub fn from_millis(ms: u64) -> Mono {
        Mono(ms * 1000)
    }

    /// Seconds, the unit the aligner and the pipelines use.
    pub fn secs(self) -> f64 {
        self.0 as f64 / 1e6
    }

    pub fn saturating_sub(self, other: Mono) -> Duration {
        Duration::from_micros(self.0.saturating_sub(other.0))
    }
}

impl Add<Duration> for Mono {
    type Output = Mono;
    fn add(self, d: Duration) -> Mono {
        Mono(self.0.saturating_add(d.as_micros() as u64))
    }
}

impl Sub<Duration> for Mono {
    type Output = Mono;
    fn sub(self, d: Duration) -> Mono {
        Mono(self.0.saturating_sub(d.as_micros() as u64))
    }
}

/// The earliest of several optional deadlines.
pub fn earliest(deadlines: impl IntoIterator<Item = Option<Mono>>) -> Option<Mono> {
    deadlines.into_iter().flatten().min()
}
