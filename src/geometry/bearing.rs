//! Bearings: the area pipeline's measurement (area seed eq. 5.4-5.5).
//!
//! The seed writes `yaw = arctan(r_y / r_x)` and `pitch = -arctan(r_z / |r_xy|)`; plain
//! `arctan` loses the quadrant, so yaw uses `atan2` over the full circle. Angle residuals
//! must be wrapped ([`angle_diff`]) before any filter sees them, or a target due south
//! would jump between `+pi` and `-pi`.

use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

use crate::Vec3;

/// Direction from an observer to a target: azimuth from north (clockwise seen from above)
/// and elevation (negative below the horizon), radians.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct Bearing {
    pub yaw: f64,
    pub pitch: f64,
}

impl Bearing {
    /// Bearing of a direction vector in the local frame (needs no unit length).
    /// Returns `None` for the zero vector, whose direction is undefined.
    pub fn from_direction(d: &Vec3) -> Option<Bearing> {
        let horizontal = d.x.hypot(d.y);
        if !(horizontal > 0.0 || d.z != 0.0) || !d.iter().all(|c| c.is_finite()) {
            return None;
        }
        Some(Bearing { yaw: d.y.atan2(d.x), pitch: (-d.z).atan2(horizontal) })
    }

    /// Unit direction vector in the local frame.
    pub fn direction(&self) -> Vec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        Vec3::new(cp * cy, cp * sy, -sp)
    }

    /// Residual `self - other` with the yaw wrapped into `(-pi, pi]`.
    pub fn residual(&self, other: &Bearing) -> [f64; 2] {
        [angle_diff(self.yaw, other.yaw), self.pitch - other.pitch]
    }
}

/// Bearing from `observer` to `target`, both in the local frame (seed eq. 5.5).
/// `None` when the two coincide.
pub fn bearing_between(observer: &Vec3, target: &Vec3) -> Option<Bearing> {
    Bearing::from_direction(&(target - observer))
}

/// Wraps an angle into `(-pi, pi]`.
pub fn wrap_angle(a: f64) -> f64 {
    if !a.is_finite() {
        return a;
    }
    let mut w = a.rem_euclid(TAU); // [0, 2pi)
    if w > PI {
        w -= TAU;
    }
    w
}

/// `a - b` wrapped into `(-pi, pi]`.
pub fn angle_diff(a: f64, b: f64) -> f64 {
    wrap_angle(a - b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn cardinal_directions() {
        let o = Vec3::zeros();
        let north = bearing_between(&o, &Vec3::new(10.0, 0.0, 0.0)).unwrap();
        assert_eq!((north.yaw, north.pitch), (0.0, 0.0));
        let east_below = bearing_between(&o, &Vec3::new(0.0, 10.0, 10.0)).unwrap();
        assert!((east_below.yaw - PI / 2.0).abs() < 1e-15);
        assert!((east_below.pitch + PI / 4.0).abs() < 1e-15);
        let south = bearing_between(&o, &Vec3::new(-1.0, 0.0, 0.0)).unwrap();
        assert!((south.yaw.abs() - PI).abs() < 1e-15);
        assert!(bearing_between(&o, &o).is_none());
    }

    #[test]
    fn residual_wraps_across_south() {
        let a = Bearing { yaw: PI - 0.01, pitch: 0.0 };
        let b = Bearing { yaw: -PI + 0.01, pitch: 0.0 };
        assert!((a.residual(&b)[0] + 0.02).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn wrap_is_in_range_and_equivalent(a in -100.0f64..100.0) {
            let w = wrap_angle(a);
            prop_assert!(w > -PI && w <= PI);
            prop_assert!(((a - w) / TAU - ((a - w) / TAU).round()).abs() < 1e-9);
        }

        #[test]
        fn direction_round_trips(yaw in -PI..PI, pitch in -1.5f64..1.5) {
            let b = Bearing { yaw, pitch };
            let back = Bearing::from_direction(&(b.direction() * 7.5)).unwrap();
            prop_assert!(back.residual(&b)[0].abs() < 1e-9 && back.residual(&b)[1].abs() < 1e-9);
        }
    }
}
