//! The area pipeline's per-landmark filter model (area seed sec. 5.1.2): the state is a
//! static landmark position in local NED (eq. 5.1-5.3, identity transition, no process
//! noise) and the measurement is the bearing from the camera to it (eq. 5.4-5.5), with
//! the yaw residual wrapped so a landmark due south does not flip between `+-pi`.

use nalgebra::{Matrix2, SMatrix, SVector, Vector2, Vector3};

use super::{MeasurementModel, ProcessModel};
use mavloc_geometry::{angle_diff, Bearing, Vec3};

/// Identity transition without noise: a landmark does not move (eq. 5.2-5.3).
pub struct StaticLandmark;

impl ProcessModel<3> for StaticLandmark {
    fn transition(&self, x: &SVector<f64, 3>, _dt: f64) -> SVector<f64, 3> {
        *x
    }
    fn noise(&self, _dt: f64) -> SMatrix<f64, 3, 3> {
        SMatrix::zeros()
    }
}

/// Bearing `[yaw, pitch]` from a camera at `observer` to the landmark (eq. 5.5).
pub struct BearingModel {
    pub observer: Vec3,
}

impl BearingModel {
    /// Packs a bearing as a measurement vector.
    pub fn measurement(b: &Bearing) -> Vector2<f64> {
        Vector2::new(b.yaw, b.pitch)
    }
}

impl MeasurementModel<3, 2> for BearingModel {
    fn measure(&self, x: &Vector3<f64>) -> Vector2<f64> {
        let d = x - self.observer;
        // A sigma point exactly at the camera has no bearing; the limit straight down is
        // as good as any and keeps the transform finite.
        let horizontal = d.x.hypot(d.y);
        Vector2::new(d.y.atan2(d.x), (-d.z).atan2(horizontal))
    }

    fn residual(&self, a: &Vector2<f64>, b: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(angle_diff(a.x, b.x), a.y - b.y)
    }
}

/// Measurement noise covariance for a bearing standard deviation in radians (eq. 5.6).
pub fn bearing_noise(sigma: f64) -> Matrix2<f64> {
    Matrix2::identity() * (sigma * sigma)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::{Ukf, UkfParams};
    use mavloc_geometry::bearing_between;
    use nalgebra::Matrix3;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Flies a circle of radius 40 m at 30 m above a landmark, measuring its bearing with
    /// 0.5 deg noise (seed table 6.2), from a first guess 20 m off.
    fn converge(seed: u64, landmark: Vec3, init_offset: Vec3) -> (Vec3, f64) {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let sigma = 0.5f64.to_radians();
        let noise = Normal::new(0.0, sigma).unwrap();
        let init = landmark + init_offset;
        let p0 = Matrix3::identity() * 20.0f64.powi(2);
        let mut ukf = Ukf::new(init, p0, UkfParams::default()).unwrap();
        let r = bearing_noise(sigma);
        for k in 0..120 {
            let t = k as f64 * 0.05; // about a third of the circle
            let observer = landmark + Vec3::new(40.0 * t.cos(), 40.0 * t.sin(), -30.0);
            let b = bearing_between(&observer, &landmark).unwrap();
            let z = Vector2::new(b.yaw + noise.sample(&mut rng), b.pitch + noise.sample(&mut rng));
            let model = BearingModel { observer };
            ukf.update(&model, &z, &r).unwrap();
        }
        (*ukf.state(), ukf.max_std())
    }

    #[test]
    fn static_target_converges_from_20_m_off() {
        for seed in 0..20 {
            let landmark = Vec3::new(12.0, -7.0, 1.5);
            let offset = Vec3::new(14.0, -14.0, 2.0); // |offset| = 19.9 m
            let (est, sd) = converge(seed, landmark, offset);
            let err = (est - landmark).norm();
            assert!(err < 0.5, "seed {seed}: error {err:.3} m");
            assert!(sd < 1.0, "seed {seed}: sigma_max {sd:.3} m");
        }
    }

    #[test]
    fn landmark_due_south_converges_across_the_yaw_wrap() {
        // Observer north of the landmark looking south: yaw near +-pi on every update.
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let sigma = 0.5f64.to_radians();
        let noise = Normal::new(0.0, sigma).unwrap();
        let landmark = Vec3::new(0.0, 0.0, 0.0);
        let mut ukf =
            Ukf::new(Vec3::new(-15.0, 12.0, 0.0), Matrix3::identity() * 400.0, UkfParams::default()).unwrap();
        for k in 0..200 {
            let east = -20.0 + 0.2 * k as f64;
            let observer = Vec3::new(30.0, east, -30.0);
            let b = bearing_between(&observer, &landmark).unwrap();
            let z = Vector2::new(b.yaw + noise.sample(&mut rng), b.pitch + noise.sample(&mut rng));
            ukf.update(&BearingModel { observer }, &z, &bearing_noise(sigma)).unwrap();
        }
        assert!((ukf.state() - landmark).norm() < 0.5, "{}", ukf.state());
    }

    #[test]
    fn residual_wraps_yaw_only() {
        let m = BearingModel { observer: Vec3::zeros() };
        let r = m.residual(&Vector2::new(3.1, 0.2), &Vector2::new(-3.1, 0.1));
        assert!((r.x - (6.2 - std::f64::consts::TAU)).abs() < 1e-12);
        assert!((r.y - 0.1).abs() < 1e-12);
    }
}
