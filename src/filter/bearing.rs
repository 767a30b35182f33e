//! The area pipeline's per-landmark filter model (area seed sec. 5.1.2): the state is a
//! static landmark position in local NED (eq. 5.1-5.3, identity transition, no process
//! noise) and the measurement is the bearing from the camera to it (eq. 5.4-5.5), with
//! the yaw residual wrapped so a landmark due south does not flip between `+-pi`.

use nalgebra::{Matrix2, Rotation3, SMatrix, SVector, Vector2, Vector3};

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

/// Bearing `[yaw, pitch]` from a camera at `observer` to the landmark (eq. 5.5), in the
/// local frame turned by `frame`.
///
/// With the identity (`BearingModel::new`) this is the seed's eq. 5.5: yaw about local
/// down, pitch above the horizon. Those coordinates are singular straight down, where yaw
/// is undefined, and stretched near it: 1 deg of yaw is 0.1 deg of arc at pitch -84 deg.
/// A nadir photo puts most landmarks there, so the isotropic noise of eq. 5.6 is wrong and
/// the unscented transform of a spread-out prior folds across the pole. `about` measures
/// the same bearing in a frame whose "north" is the measured ray: the measurement is
/// `[0, 0]`, the singularity is 90 deg away from every sigma point that matters, and yaw
/// and pitch are both true angles of arc there, so eq. 5.6 holds as written whatever the
/// camera's tilt. Where the seed's camera looks near the horizon the two agree.
pub struct BearingModel {
    pub observer: Vec3,
    /// Local NED -> measurement frame.
    pub frame: Rotation3<f64>,
}

impl BearingModel {
    /// The seed's model: bearings in local NED.
    pub fn new(observer: Vec3) -> BearingModel {
        BearingModel { observer, frame: Rotation3::identity() }
    }

    /// Bearings measured about the measured direction `ray` (local NED, any length): use
    /// with the measurement [`BearingModel::ZERO`].
    pub fn about(observer: Vec3, ray: &Vec3) -> BearingModel {
        let frame = Rotation3::rotation_between(ray, &Vec3::x())
            // Only a ray due south has no unique shortest turn; half a turn about down.
            .unwrap_or_else(|| Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI));
        BearingModel { observer, frame }
    }

    /// The measurement that goes with [`BearingModel::about`].
    pub const ZERO: Vector2<f64> = Vector2::new(0.0, 0.0);

    /// Packs a bearing as a measurement vector.
    pub fn measurement(b: &Bearing) -> Vector2<f64> {
        Vector2::new(b.yaw, b.pitch)
    }

    /// A measurement in this model's frame as a bearing in local NED (for reports).
    pub fn to_local(&self, z: &Vector2<f64>) -> Bearing {
        let (cy, sy, cp, sp) = (z.x.cos(), z.x.sin(), z.y.cos(), z.y.sin());
        let d = self.frame.inverse() * Vec3::new(cp * cy, cp * sy, -sp);
        Bearing::from_direction(&d).unwrap_or(Bearing { yaw: 0.0, pitch: 0.0 })
    }
}

impl MeasurementModel<3, 2> for BearingModel {
    fn measure(&self, x: &Vector3<f64>) -> Vector2<f64> {
        let d = self.frame * (x - self.observer);
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
    use std::f64::consts::{FRAC_PI_2, PI, TAU};

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
            let model = BearingModel::new(observer);
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
            ukf.update(&BearingModel::new(observer), &z, &bearing_noise(sigma)).unwrap();
        }
        assert!((ukf.state() - landmark).norm() < 0.5, "{}", ukf.state());
    }

    proptest::proptest! {
        /// About its own ray a measurement is zero, converts back to the local bearing, and
        /// a small turn of the target by `e` radians off the ray reads as an arc of `e`.
        #[test]
        fn bearings_about_the_ray_are_arcs(
            yaw in -PI..PI, pitch in -FRAC_PI_2 + 1e-6..FRAC_PI_2 - 1e-6, range in 1.0f64..200.0,
            off in 1e-4f64..0.05, dir in 0.0..TAU,
        ) {
            let observer = Vec3::new(3.0, -4.0, -40.0);
            let ray = Vec3::new(pitch.cos() * yaw.cos(), pitch.cos() * yaw.sin(), -pitch.sin());
            let m = BearingModel::about(observer, &ray);
            let z = m.measure(&(observer + ray * range));
            proptest::prop_assert!(z.norm() < 1e-9, "{z}");
            let b = m.to_local(&BearingModel::ZERO);
            proptest::prop_assert!(angle_diff(b.yaw, yaw).abs() * pitch.cos() < 1e-9);
            proptest::prop_assert!((b.pitch - pitch).abs() < 1e-9);
            // Turn the ray by `off` about an axis across it.
            let a = ray.cross(&Vec3::z()).try_normalize(1e-9).unwrap_or(Vec3::y());
            let axis = nalgebra::Unit::new_normalize(
                nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(ray), dir) * a,
            );
            let turned = nalgebra::Rotation3::from_axis_angle(&axis, off) * ray;
            let z = m.measure(&(observer + turned * range));
            // Yaw and pitch are arcs to first order about the ray; the rest is O(off^3).
            proptest::prop_assert!((z.norm() - off).abs() < off.powi(3), "{} vs {off}", z.norm());
        }
    }

    /// Three nadir photos 14 m apart from 40 m, landmarks anywhere in the view, 1 px of
    /// noise (0.05 deg, isotropic in arc as pixel noise is), each landmark started on the
    /// ground plane with 20 m SD along the first ray as the area pipeline does. Bearings
    /// about the ray with the iterated update recover what the photos can tell, with an
    /// honest SD; a single unscented update from that wide a prior keeps metres of it.
    #[test]
    fn nadir_photos_triangulate_landmarks_with_the_iterated_update_about_the_ray() {
        let sigma = 0.05f64.to_radians();
        let stats = |iterations: u32| {
            let (mut errors, mut sds, mut consistent) = (Vec::new(), Vec::new(), 0);
            for seed in 0..100u64 {
                let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
                let u = rand_distr::Uniform::new(-25.0, 25.0).unwrap();
                let truth =
                    Vec3::new(10.0 + u.sample(&mut rng), 10.0 + u.sample(&mut rng), 0.1 * u.sample(&mut rng));
                let (e, sd) = three_nadir_photos(truth, sigma, iterations, &mut rng);
                consistent += usize::from(e < 3.0 * sd);
                errors.push(e);
                sds.push(sd);
            }
            errors.sort_by(f64::total_cmp);
            sds.sort_by(f64::total_cmp);
            (errors[50], errors[90], sds[50], consistent)
        };
        let (median, p90, sd, consistent) = stats(8);
        assert!(median < 0.25 && p90 < 0.5, "iterated: error median {median:.3} m, p90 {p90:.3} m");
        assert!(consistent >= 97, "iterated: {consistent}/100 within 3 SD (median SD {sd:.3} m)");
        let (median1, _, sd1, consistent1) = stats(1);
        assert!(sd1 > 5.0 * sd && median1 > 5.0 * median, "plain: error {median1:.3} m, SD {sd1:.3} m");
        assert!(consistent1 >= 97, "plain: {consistent1}/100 within 3 SD");
    }

    fn three_nadir_photos(truth: Vec3, sigma: f64, iterations: u32, rng: &mut impl rand::Rng) -> (f64, f64) {
        let r = bearing_noise(sigma);
        let noise = Normal::new(0.0, sigma).unwrap();
        let first = Vec3::new(0.0, 0.0, -40.0);
        let d = (truth - first).normalize();
        let start = first + d * (-first.z / d.z);
        let p0 = Matrix3::identity() * 0.3f64.powi(2) + d * d.transpose() * (20.0f64.powi(2) - 0.09);
        let mut ukf = Ukf::new(start, p0, UkfParams::default()).unwrap();
        for k in 1..3 {
            let observer = Vec3::new(10.0 * k as f64, 10.0 * k as f64, -40.0);
            // Pixel noise is isotropic in arc: draw it about the true ray.
            let about_truth = BearingModel::about(observer, &(truth - observer));
            let noisy = about_truth.to_local(&Vector2::new(noise.sample(rng), noise.sample(rng)));
            let model = BearingModel::about(observer, &noisy_direction(&noisy));
            let pred = ukf.predict_measurement(&model, &r).unwrap();
            ukf.update_iterated(&model, &pred, &BearingModel::ZERO, &r, iterations).unwrap();
        }
        ((ukf.state() - truth).norm(), ukf.max_std())
    }

    fn noisy_direction(b: &Bearing) -> Vec3 {
        Vec3::new(b.pitch.cos() * b.yaw.cos(), b.pitch.cos() * b.yaw.sin(), -b.pitch.sin())
    }

    #[test]
    fn residual_wraps_yaw_only() {
        let m = BearingModel::new(Vec3::zeros());
        let r = m.residual(&Vector2::new(3.1, 0.2), &Vector2::new(-3.1, 0.1));
        assert!((r.x - (6.2 - std::f64::consts::TAU)).abs() < 1e-12);
        assert!((r.y - 0.1).abs() < 1e-12);
    }
}
