//! The landing trigger (indoor seed sec. 4.7): land when the estimate is inside the landing
//! zone and the particles agree (spread below the gate in x and in y), for a number of
//! consecutive frames, never on a single frame. The seed landed on the first frame that
//! met its criterion and came down outside the zone in 2 of 6 tries.

use nalgebra::Vector2;

/// Trigger parameters (from `[indoor]` in the configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LandingZone {
    pub centre: Vector2<f64>,
    pub radius_m: f64,
    /// Largest particle standard deviation allowed, in x and in y.
    pub sigma_gate_m: f64,
    /// Consecutive frames the conditions must hold (at least 2).
    pub frames: u32,
}

/// Why the trigger is not firing, for logs and status messages.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Hold {
    /// The localiser has no position fix (searching): agreeing particles of a search may
    /// sit on a look-alike place.
    NoFix,
    OutsideZone,
    TooUncertain,
    /// Conditions met for this many consecutive frames so far.
    Settling(u32),
}

/// Counts consecutive frames that satisfy the landing conditions.
#[derive(Clone, Debug)]
pub struct LandingTrigger {
    zone: LandingZone,
    streak: u32,
    fired: bool,
}

impl LandingTrigger {
    pub fn new(zone: LandingZone) -> LandingTrigger {
        let frames = zone.frames.max(2);
        LandingTrigger { zone: LandingZone { frames, ..zone }, streak: 0, fired: false }
    }

    /// Feeds one frame's estimate and particle spread (x, y); `Ok(())` on the frame the
    /// trigger fires (once), otherwise why it holds.
    pub fn update(&mut self, estimate: Vector2<f64>, spread: (f64, f64)) -> Result<(), Hold> {
        let inside = (estimate - self.zone.centre).norm() <= self.zone.radius_m;
        let certain = spread.0 < self.zone.sigma_gate_m && spread.1 < self.zone.sigma_gate_m;
        if !(estimate.iter().all(|c| c.is_finite()) && inside) {
            self.streak = 0;
            return Err(Hold::OutsideZone);
        }
        if !certain {
            self.streak = 0;
            return Err(Hold::TooUncertain);
        }
        self.streak += 1;
        if self.streak >= self.zone.frames && !self.fired {
            self.fired = true;
            return Ok(());
        }
        Err(Hold::Settling(self.streak))
    }

    /// Feeds one frame of the localiser: its estimate if it is a position fix, else a
    /// frame that breaks the streak (a landing is triggered on a track only, not on
    /// particles that agree during a search).
    pub fn observe(&mut self, e: &super::localizer::Estimate) -> Result<(), Hold> {
        if e.fix {
            self.update(e.position, e.spread)
        } else {
            self.streak = 0;
            Err(Hold::NoFix)
        }
    }

    /// Whether it has fired.
    pub fn fired(&self) -> bool {
        self.fired
    }

    /// Arms it again (a new zone or a new attempt).
    pub fn reset(&mut self) {
        self.streak = 0;
        self.fired = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn zone(frames: u32) -> LandingTrigger {
        LandingTrigger::new(LandingZone {
            centre: Vector2::new(1.0, 2.0),
            radius_m: 0.6,
            sigma_gate_m: 0.6,
            frames,
        })
    }

    #[test]
    fn fires_after_consecutive_good_frames_and_only_once() {
        let mut t = zone(3);
        let here = Vector2::new(1.2, 2.1);
        assert_eq!(t.update(here, (0.2, 0.2)), Err(Hold::Settling(1)));
        assert_eq!(t.update(here, (0.2, 0.2)), Err(Hold::Settling(2)));
        assert_eq!(t.update(here, (0.2, 0.2)), Ok(()));
        assert!(t.fired());
        assert!(t.update(here, (0.2, 0.2)).is_err(), "fires once");
    }

    #[test]
    fn never_fires_on_a_single_frame() {
        let mut t = zone(1);
        assert_eq!(t.update(Vector2::new(1.0, 2.0), (0.1, 0.1)), Err(Hold::Settling(1)));
        assert_eq!(t.update(Vector2::new(1.0, 2.0), (0.1, 0.1)), Ok(()));
    }

    #[test]
    fn outside_the_zone_resets_the_streak() {
        let mut t = zone(2);
        assert!(t.update(Vector2::new(1.0, 2.0), (0.1, 0.1)).is_err());
        assert_eq!(t.update(Vector2::new(1.7, 2.0), (0.1, 0.1)), Err(Hold::OutsideZone));
        assert_eq!(t.update(Vector2::new(1.0, 2.0), (0.1, 0.1)), Err(Hold::Settling(1)));
    }

    #[test]
    fn a_frame_without_a_fix_resets_the_streak() {
        let mut t = zone(2);
        let frame = |fix| super::super::localizer::Estimate {
            t: 0.0,
            position: Vector2::new(1.0, 2.0),
            spread: (0.1, 0.1),
            neighbours: Vec::new(),
            velocity: Vector2::zeros(),
            fix,
        };
        assert_eq!(t.observe(&frame(true)), Err(Hold::Settling(1)));
        // Inside the zone and agreeing, but a search's particles: no fix, the streak ends.
        assert_eq!(t.observe(&frame(false)), Err(Hold::NoFix));
        assert_eq!(t.observe(&frame(true)), Err(Hold::Settling(1)));
        assert!(!t.fired());
    }

    #[test]
    fn uncertainty_in_either_axis_holds_it() {
        let mut t = zone(2);
        assert_eq!(t.update(Vector2::new(1.0, 2.0), (0.7, 0.1)), Err(Hold::TooUncertain));
        assert_eq!(t.update(Vector2::new(1.0, 2.0), (0.1, 0.65)), Err(Hold::TooUncertain));
        assert!(t.update(Vector2::new(f64::NAN, 2.0), (0.1, 0.1)).is_err());
        assert!(!t.fired());
    }
}
