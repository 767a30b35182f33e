//! A second opinion on a converged landmark, from its rays alone.
//!
//! The seed's convergence test (area sec. 5.5, eq. 5.21) trusts the UKF's covariance. A
//! bearing-only UKF started from a ground-plane guess 20 m long along the ray can be
//! overconfident: in straight flight a few sightings with little parallax pulled some live
//! demo landmarks 11-17 m up their rays while the filter claimed 0.35 m (the #20 tails).
//! So a landmark counts only if the rays that updated it, solved as one weighted least
//! squares problem (the linear triangulation of Hartley & Zisserman sec. 12.2, in its
//! perpendicular-distance form, weighted by range as a bearing error), also pin it down
//! to the convergence threshold and agree with the filter's position.
//!
//! Hand-written rather than through a solver crate: it is one 3x3 normal-equation solve
//! per check, iterated twice for the ranges.

use nalgebra::Matrix3;

use crate::geometry::Vec3;

/// Rays kept per landmark: the first and a ring of the most recent (the first gives the
/// longest baseline; the ring bounds memory and the check's cost).
pub const MAX_RAYS: usize = 48;

/// One sighting: the camera centre and the unit direction to the landmark (local NED).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

/// The rays a landmark was built from.
#[derive(Clone, Debug, Default)]
pub struct Rays {
    rays: Vec<Ray>,
    next: usize,
}

impl Rays {
    pub fn push(&mut self, r: Ray) {
        if self.rays.len() < MAX_RAYS {
            self.rays.push(r);
        } else {
            let slot = 1 + self.next % (MAX_RAYS - 1);
            self.rays[slot] = r;
            self.next += 1;
        }
    }

    pub fn len(&self) -> usize {
        self.rays.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }

    pub fn as_slice(&self) -> &[Ray] {
        &self.rays
    }
}

/// The rays' own solution near `start`.
#[derive(Clone, Copy, Debug)]
pub struct Triangulation {
    pub position: Vec3,
    /// Covariance of `position` from the bearing noise (m^2).
    pub covariance: Matrix3<f64>,
    /// Largest standard deviation (m): how well the rays alone fix the point.
    pub sigma_max: f64,
}

impl Triangulation {
    /// Mahalanobis distance of `p` from the rays' solution.
    pub fn mahalanobis(&self, p: &Vec3) -> f64 {
        let d = p - self.position;
        match self.covariance.try_inverse() {
            Some(inv) => (d.transpose() * inv * d)[0].max(0.0).sqrt(),
            None => f64::INFINITY,
        }
    }
}

/// The camera's position variance across a ray of unit direction `dir` (north, east,
/// down variances `position_var`, m^2), averaged over the two directions across it:
/// trace(P S) / 2 with P the projection across the ray and S diagonal.
pub fn across_variance(dir: &Vec3, position_var: &[f64; 3]) -> f64 {
    (0..3).map(|i| (1.0 - dir[i] * dir[i]) * position_var[i]).sum::<f64>() / 2.0
}

/// Weighted least-squares point closest to the rays, each ray's perpendicular offset
/// divided by its SD: the bearing SD (`sd_rad`) times its range, and the camera's position
/// noise across the ray (`position_var`, north, east, down variances, m^2, averaged over
/// the two directions across it). Without the position noise, rays from a short or
/// straight-down baseline looked like a fix: the position noise of each frame moves the
/// rays apart as parallax would (the demo's 12-15 m high landmarks, seen only during the
/// vertical landing descent with 0.5/0.5/2 m of noise per frame). Ranges are taken at
/// `start`, then once more at the first solution. `None` with fewer than two rays, a point
/// behind a camera or a singular system (parallel rays).
pub fn triangulate(
    rays: &[Ray],
    start: &Vec3,
    sd_rad: f64,
    position_var: &[f64; 3],
) -> Option<Triangulation> {
    if rays.len() < 2 || sd_rad.is_nan() || sd_rad <= 0.0 {
        return None;
    }
    let mut p = *start;
    let mut out = None;
    for _ in 0..2 {
        let mut a = Matrix3::zeros();
        let mut b = Vec3::zeros();
        for r in rays {
            let range = r.dir.dot(&(p - r.origin));
            if range.is_nan() || range <= 0.1 {
                return None;
            }
            let across = Matrix3::identity() - r.dir * r.dir.transpose();
            let w = 1.0 / ((range * sd_rad).powi(2) + across_variance(&r.dir, position_var));
            let perp = across * w;
            a += perp;
            b += perp * r.origin;
        }
        let cov = a.try_inverse()?;
        p = cov * b;
        let sigma_max = cov.symmetric_eigenvalues().max().max(0.0).sqrt();
        if !(p.iter().all(|v| v.is_finite()) && sigma_max.is_finite()) {
            return None;
        }
        out = Some(Triangulation { position: p, covariance: cov, sigma_max });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ray_to(origin: Vec3, p: &Vec3) -> Ray {
        Ray { origin, dir: (p - origin).normalize() }
    }

    proptest! {
        /// Exact rays from cameras along a line meet at the point, wherever it is.
        #[test]
        fn exact_rays_give_the_point(
            px in -50.0..50.0f64, py in -50.0..50.0f64, pz in -5.0..5.0f64,
            n in 2usize..20, spacing in 1.0..10.0f64,
        ) {
            let p = Vec3::new(px, py + 60.0, pz);
            let rays: Vec<Ray> =
                (0..n).map(|i| ray_to(Vec3::new(i as f64 * spacing, 0.0, -50.0), &p)).collect();
            let t = triangulate(&rays, &Vec3::new(px, py + 60.0, 0.0), 0.5f64.to_radians(), &[0.0; 3]).unwrap();
            prop_assert!((t.position - p).norm() < 1e-6, "{:?} vs {p:?}", t.position);
        }

        /// The claimed uncertainty shrinks with parallax: the same number of rays over a
        /// longer baseline fixes the point better.
        #[test]
        fn a_longer_baseline_fixes_the_point_better(n in 3usize..15, spacing in 0.2..3.0f64) {
            let p = Vec3::new(0.0, 60.0, 0.0);
            let sd = |s: f64| {
                let rays: Vec<Ray> = (0..n).map(|i| ray_to(Vec3::new(i as f64 * s, 0.0, -50.0), &p)).collect();
                triangulate(&rays, &p, 0.5f64.to_radians(), &[0.0; 3]).unwrap().sigma_max
            };
            prop_assert!(sd(spacing * 3.0) < sd(spacing));
        }
    }

    /// The tails' case: rays with a few metres of baseline at 60 m range leave the depth
    /// open far beyond half a metre, whatever a filter claims.
    #[test]
    fn little_parallax_leaves_the_depth_open() {
        let p = Vec3::new(0.0, 60.0, 0.0);
        let rays: Vec<Ray> = (0..6).map(|i| ray_to(Vec3::new(i as f64 * 0.8, 0.0, -50.0), &p)).collect();
        let t = triangulate(&rays, &p, 0.5f64.to_radians(), &[0.0; 3]).unwrap();
        assert!(t.sigma_max > 5.0, "{}", t.sigma_max);
        // and a point 12 m up the rays is well within it
        let up = p + (rays[0].origin - p).normalize() * 12.0;
        assert!(t.mahalanobis(&up) < 3.0, "{}", t.mahalanobis(&up));
    }

    #[test]
    fn the_ring_keeps_the_first_ray() {
        let mut rays = Rays::default();
        for i in 0..(MAX_RAYS * 3) {
            rays.push(Ray { origin: Vec3::new(i as f64, 0.0, 0.0), dir: Vec3::z() });
        }
        assert_eq!(rays.len(), MAX_RAYS);
        assert_eq!(rays.as_slice()[0].origin.x, 0.0);
        let newest = rays.as_slice().iter().map(|r| r.origin.x).fold(0.0, f64::max);
        assert_eq!(newest, (MAX_RAYS * 3 - 1) as f64);
    }

    /// The demo's tail (#20): a landmark seen only during a vertical landing descent, 7
    /// sightings over 1.4 m at 30 m range, with the seed's noise per frame (positions
    /// 0.5/0.5/2 m, bearings 0.5 deg). Counting the bearing noise alone, some draws fix the
    /// point to under a metre and are metres off; with the position noise counted none
    /// does.
    #[test]
    fn rays_from_a_noisy_descent_are_no_fix_once_the_position_noise_counts() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let (h, v, bearing) = (
            Normal::new(0.0, 0.5).unwrap(),
            Normal::new(0.0, 2.0).unwrap(),
            Normal::new(0.0, 0.5f64.to_radians()).unwrap(),
        );
        let truth = Vec3::new(80.9, -20.9, 0.0);
        let (mut fixed_alone, mut wrong_alone, mut fixed_with) = (0, 0, 0);
        for _ in 0..400 {
            let rays: Vec<Ray> = (0..7)
                .map(|k| {
                    let camera = Vec3::new(86.46, -19.12, -30.0 + k as f64 * 0.26);
                    let dir = (truth - camera).normalize()
                        + Vec3::new(
                            bearing.sample(&mut rng),
                            bearing.sample(&mut rng),
                            bearing.sample(&mut rng),
                        );
                    let noisy =
                        camera + Vec3::new(h.sample(&mut rng), h.sample(&mut rng), v.sample(&mut rng));
                    Ray { origin: noisy, dir: dir.normalize() }
                })
                .collect();
            let start = truth + Vec3::new(0.0, 0.0, -13.0);
            let sd = 0.5f64.to_radians();
            if let Some(t) = triangulate(&rays, &start, sd, &[0.0; 3]).filter(|t| t.sigma_max < 1.0) {
                fixed_alone += 1;
                wrong_alone += ((t.position - truth).norm() > 5.0) as usize;
            }
            fixed_with += triangulate(&rays, &start, sd, &[0.25, 0.25, 4.0])
                .is_some_and(|t| t.sigma_max < 1.0) as usize;
        }
        assert!(
            fixed_alone > 0 && wrong_alone * 10 >= fixed_alone * 8,
            "{fixed_alone} fixes, {wrong_alone} wrong"
        );
        assert_eq!(fixed_with, 0, "with the position noise counted");
    }
}
