//! The seed's "previous method" (area seed sec. 2.1, eq. 2.7-2.10): intersect a pixel's
//! viewing ray with a horizontal ground plane of known height.
//!
//! Eq. 2.10 expands the intersection's scale factor `s` over the nine entries of the
//! rotation matrix. In the local frame the same thing is one line: the ray
//! `p + s d` meets the plane `down = g` at `s = (g - p_down) / d_down`, which needs only
//! the ray's direction in NED ([`crate::CameraPose::direction`]).

use crate::Vec3;

/// Point where the ray from `origin` along `direction` meets the horizontal plane
/// `down = ground_down` (local NED). `None` when the ray is parallel to the plane or
/// points away from it (the intersection would be behind the camera).
pub fn ground_plane_point(origin: &Vec3, direction: &Vec3, ground_down: f64) -> Option<Vec3> {
    let dz = direction.z;
    if dz.abs() < 1e-12 {
        return None;
    }
    let s = (ground_down - origin.z) / dz;
    if !s.is_finite() || s <= 0.0 {
        return None;
    }
    let p = origin + direction * s;
    p.iter().all(|c| c.is_finite()).then_some(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn straight_down_hits_below() {
        let p = ground_plane_point(&Vec3::new(1.0, 2.0, -30.0), &Vec3::new(0.0, 0.0, 1.0), 0.0);
        assert_eq!(p, Some(Vec3::new(1.0, 2.0, 0.0)));
    }

    #[test]
    fn rays_above_horizon_and_parallel_miss() {
        let o = Vec3::new(0.0, 0.0, -30.0);
        assert_eq!(ground_plane_point(&o, &Vec3::new(1.0, 0.0, -0.1), 0.0), None);
        assert_eq!(ground_plane_point(&o, &Vec3::new(1.0, 0.0, 0.0), 0.0), None);
    }

    #[test]
    fn forty_five_degrees() {
        let p = ground_plane_point(&Vec3::new(0.0, 0.0, -30.0), &Vec3::new(1.0, 0.0, 1.0), -5.0).unwrap();
        assert!((p - Vec3::new(25.0, 0.0, -5.0)).norm() < 1e-12);
    }
}
