//! Unscented Kalman filter with Merwe scaled sigma points (area seed sec. 4.1.1,
//! eq. 4.1-4.10; Van der Merwe 2004) and the Mahalanobis gate of eq. 5.11.
//!
//! Differences from the seed's formulas, all deliberate:
//!
//! * eq. 4.5 writes `g(X_i - mu')`; the covariance uses `g(X_i) - mu'`.
//! * Measurement means and residuals go through [`MeasurementModel::residual`], so angle
//!   measurements (the area pipeline's bearings) average and subtract correctly across
//!   `+-pi`. The mean is taken as `Z_0 + sum W_i (Z_i - Z_0)`, which equals the weighted
//!   sum for plain vectors (the weights sum to 1) and stays on the right branch for angles.
//! * Numerical safety (seed sec. 5.6.2 lost runs to non-positive-definite covariances):
//!   covariances are symmetrised after every step; the matrix square root of eq. 4.1 is a
//!   Cholesky factor, and when Cholesky fails the covariance is repaired first by adding a
//!   growing multiple of its mean variance to the diagonal (1e-12 up to 1e-6), then by
//!   replacing it with its nearest positive semi-definite matrix (eigenvalues clamped at a
//!   small floor, Higham 1988), whose square root comes from the eigendecomposition. An
//!   update whose result is not finite is rolled back and reported as an error. No input
//!   makes the filter panic, and finite input never yields NaN state.

use nalgebra::{Cholesky, DMatrix, SMatrix, SVector, SymmetricEigen};
use serde::{Deserialize, Serialize};

use super::FilterError;

/// Largest state dimension the filter accepts: sigma points live in fixed stack arrays of
/// `2 * MAX_STATE + 1` entries because stable Rust cannot size an array `2 * N + 1`.
pub const MAX_STATE: usize = 15;
const MAX_SIGMA: usize = 2 * MAX_STATE + 1;

/// Merwe sigma-point parameters (seed eq. 4.3-4.4; the seed's tuned values, eq. 5.7, are
/// the default).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UkfParams {
    /// Spread of the sigma points around the mean, `0 < alpha <= 1`.
    pub alpha: f64,
    /// Prior knowledge of the distribution; 2 is optimal for a Gaussian.
    pub beta: f64,
    /// Secondary scaling, usually 0.
    pub kappa: f64,
}

impl Default for UkfParams {
    fn default() -> Self {
        UkfParams { alpha: 0.7, beta: 2.0, kappa: 0.0 }
    }
}

/// State transition `x[k+1] = f(x[k]) + w` (seed eq. 4.6).
pub trait ProcessModel<const N: usize> {
    /// Propagates a state over `dt` seconds.
    fn transition(&self, x: &SVector<f64, N>, dt: f64) -> SVector<f64, N>;
    /// Covariance of the process noise over `dt` seconds.
    fn noise(&self, dt: f64) -> SMatrix<f64, N, N>;
}

/// Measurement `z = h(x) + v` (seed eq. 4.7).
pub trait MeasurementModel<const N: usize, const M: usize> {
    /// Predicted measurement of a state.
    fn measure(&self, x: &SVector<f64, N>) -> SVector<f64, M>;
    /// `a - b` in measurement space; override to wrap angles.
    fn residual(&self, a: &SVector<f64, M>, b: &SVector<f64, M>) -> SVector<f64, M> {
        a - b
    }
}

/// A measurement predicted from the current state: what the gate and the update need.
#[derive(Clone, Debug)]
pub struct PredictedMeasurement<const N: usize, const M: usize> {
    /// Predicted mean `z_hat` (eq. 4.8).
    pub z: SVector<f64, M>,
    /// Innovation covariance `S`, measurement noise included (eq. 4.8).
    pub s: SMatrix<f64, M, M>,
    /// State-measurement cross covariance `T` (eq. 4.9).
    pub cross: SMatrix<f64, N, M>,
    s_chol: Cholesky<f64, nalgebra::Const<M>>,
}

impl<const N: usize, const M: usize> PredictedMeasurement<N, M> {
    /// Mahalanobis distance of an innovation `y = z - z_hat` (eq. 5.11), in standard
    /// deviations.
    pub fn mahalanobis(&self, y: &SVector<f64, M>) -> f64 {
        let solved = self.s_chol.solve(y);
        y.dot(&solved).max(0.0).sqrt()
    }
}

/// Result of an update, for gating statistics and traces (seed fig. 6.2).
#[derive(Clone, Copy, Debug)]
pub struct UpdateReport<const M: usize> {
    /// Innovation `z - z_hat`.
    pub innovation: SVector<f64, M>,
    /// Predicted measurement before the update.
    pub predicted: SVector<f64, M>,
    /// Mahalanobis distance of the innovation.
    pub mahalanobis: f64,
}

/// Unscented Kalman filter over a state of dimension `N` (checked at compile time to be
/// between 1 and [`MAX_STATE`]).
#[derive(Clone, Debug)]
pub struct Ukf<const N: usize> {
    x: SVector<f64, N>,
    p: SMatrix<f64, N, N>,
    w: Weights,
}

#[derive(Clone, Copy, Debug)]
struct Weights {
    /// `sqrt(n + lambda)`, the sigma-point spread of eq. 4.1.
    spread: f64,
    mean0: f64,
    cov0: f64,
    /// Weight of every other sigma point, for mean and covariance alike.
    rest: f64,
}

impl Weights {
    fn new(n: usize, p: UkfParams) -> Result<Weights, FilterError> {
        let n = n as f64;
        let lambda = p.alpha * p.alpha * (n + p.kappa) - n; // eq. 4.3
        let scale = n + lambda;
        if !(p.alpha > 0.0 && p.alpha.is_finite() && p.beta.is_finite() && scale > 0.0 && scale.is_finite()) {
            return Err(FilterError::BadParameters(format!(
                "alpha={} beta={} kappa={} give n + lambda = {scale}, which must be positive",
                p.alpha, p.beta, p.kappa
            )));
        }
        Ok(Weights {
            spread: scale.sqrt(),
            mean0: lambda / scale,                                     // eq. 4.4
            cov0: lambda / scale + (1.0 - p.alpha * p.alpha + p.beta), // eq. 4.4
            rest: 1.0 / (2.0 * scale),                                 // eq. 4.4
        })
    }
}

impl<const N: usize> Ukf<N> {
    const DIMENSION_OK: () = assert!(N >= 1 && N <= MAX_STATE, "UKF state dimension out of range");

    /// A filter with mean `x`, covariance `p` and sigma-point parameters `params`.
    pub fn new(x: SVector<f64, N>, p: SMatrix<f64, N, N>, params: UkfParams) -> Result<Self, FilterError> {
        #[allow(clippy::let_unit_value)]
        let () = Self::DIMENSION_OK;
        if !all_finite(x.as_slice()) {
            return Err(FilterError::NonFinite("initial state"));
        }
        if !all_finite(p.as_slice()) {
            return Err(FilterError::NonFinite("initial covariance"));
        }
        let p = symmetrise(&p);
        if (0..N).any(|i| p[(i, i)] < 0.0) {
            return Err(FilterError::NotPositiveDefinite("initial covariance has a negative variance"));
        }
        Ok(Ukf { x, p, w: Weights::new(N, params)? })
    }

    /// State mean.
    pub fn state(&self) -> &SVector<f64, N> {
        &self.x
    }

    /// State covariance.
    pub fn covariance(&self) -> &SMatrix<f64, N, N> {
        &self.p
    }

    /// Largest standard deviation along the covariance's principal axes (seed eq. 5.21:
    /// the square root of the largest eigenvalue).
    pub fn max_std(&self) -> f64 {
        let (values, _) = eigen(&self.p);
        values.iter().fold(0.0f64, |m, &e| m.max(e)).sqrt()
    }

    /// Columns `U_i` of eq. 4.1: a square root of `(n + lambda) P`.
    fn sqrt_columns(&self) -> SMatrix<f64, N, N> {
        matrix_sqrt(&self.p) * self.w.spread
    }

    /// Sigma point `i` (eq. 4.2) given the scaled square root.
    fn sigma(&self, u: &SMatrix<f64, N, N>, i: usize) -> SVector<f64, N> {
        match i {
            0 => self.x,
            i if i <= N => self.x + u.column(i - 1),
            i => self.x - u.column(i - 1 - N),
        }
    }

    fn weight_mean(&self, i: usize) -> f64 {
        if i == 0 {
            self.w.mean0
        } else {
            self.w.rest
        }
    }

    fn weight_cov(&self, i: usize) -> f64 {
        if i == 0 {
            self.w.cov0
        } else {
            self.w.rest
        }
    }

    /// Prediction step (eq. 4.6 through the unscented transform, eq. 4.1-4.5).
    pub fn predict<P: ProcessModel<N>>(&mut self, model: &P, dt: f64) -> Result<(), FilterError> {
        let u = self.sqrt_columns();
        let mut pts = [SVector::<f64, N>::zeros(); MAX_SIGMA];
        let count = 2 * N + 1;
        let mut mean = SVector::<f64, N>::zeros();
        for (i, pt) in pts.iter_mut().enumerate().take(count) {
            *pt = model.transition(&self.sigma(&u, i), dt);
            mean += *pt * self.weight_mean(i);
        }
        let mut cov = model.noise(dt);
        for (i, pt) in pts.iter().enumerate().take(count) {
            let d = pt - mean;
            cov += d * d.transpose() * self.weight_cov(i);
        }
        if !all_finite(mean.as_slice()) || !all_finite(cov.as_slice()) {
            return Err(FilterError::NonFinite("predicted state"));
        }
        self.x = mean;
        self.p = repair_psd(&symmetrise(&cov));
        Ok(())
    }

    /// The unscented transform of `h` about mean `x` and covariance `p` (eq. 4.8-4.9
    /// without the noise): predicted mean, its covariance and the cross covariance.
    #[allow(clippy::type_complexity)]
    fn unscented_measurement<const M: usize, H: MeasurementModel<N, M>>(
        &self,
        model: &H,
        x: &SVector<f64, N>,
        p: &SMatrix<f64, N, N>,
    ) -> (SVector<f64, M>, SMatrix<f64, M, M>, SMatrix<f64, N, M>) {
        let u = matrix_sqrt(p) * self.w.spread;
        let count = 2 * N + 1;
        let point = |i: usize| match i {
            0 => *x,
            i if i <= N => x + u.column(i - 1),
            i => x - u.column(i - 1 - N),
        };
        let mut zs = [SVector::<f64, M>::zeros(); MAX_SIGMA];
        for (i, z) in zs.iter_mut().enumerate().take(count) {
            *z = model.measure(&point(i));
        }
        let z0 = zs[0];
        let mut offset = SVector::<f64, M>::zeros();
        for (i, z) in zs.iter().enumerate().take(count).skip(1) {
            offset += model.residual(z, &z0) * self.weight_mean(i);
        }
        let z_hat = z0 + offset;
        let mut s = SMatrix::<f64, M, M>::zeros();
        let mut cross = SMatrix::<f64, N, M>::zeros();
        for (i, z) in zs.iter().enumerate().take(count) {
            let dz = model.residual(z, &z_hat);
            let dx = point(i) - x;
            let w = self.weight_cov(i);
            s += dz * dz.transpose() * w;
            cross += dx * dz.transpose() * w;
        }
        (z_hat, s, cross)
    }

    /// Predicted measurement, innovation covariance and cross covariance (eq. 4.8-4.9),
    /// with measurement noise covariance `r`.
    pub fn predict_measurement<const M: usize, H: MeasurementModel<N, M>>(
        &self,
        model: &H,
        r: &SMatrix<f64, M, M>,
    ) -> Result<PredictedMeasurement<N, M>, FilterError> {
        let (z_hat, s, cross) = self.unscented_measurement(model, &self.x, &self.p);
        let s = symmetrise(&(s + r));
        if !all_finite(z_hat.as_slice()) || !all_finite(s.as_slice()) || !all_finite(cross.as_slice()) {
            return Err(FilterError::NonFinite("predicted measurement"));
        }
        // A factor with a vanishing pivot would overflow the gain: treat it as singular.
        let s_chol = Cholesky::new(s)
            .filter(|c| c.l_dirty().diagonal().iter().all(|&d| d > 1e-150))
            .ok_or(FilterError::NotPositiveDefinite("innovation covariance"))?;
        Ok(PredictedMeasurement { z: z_hat, s, cross, s_chol })
    }

    /// Iterated update (iterated posterior linearisation, Garcia-Fernandez et al. 2015):
    /// the plain update of [`Ukf::update_predicted`] linearises `h` statistically over
    /// the prior's sigma points. When the prior is much wider than what one measurement
    /// leaves (a new landmark's depth, 20 m, seen from a second photo 15 m away), that
    /// average slope is far from the slope where the landmark is, and the update keeps
    /// most of the prior's uncertainty. Each further iteration fits the linear model
    /// `z = A x + b + e` (with `e` the fit's residual covariance) over sigma points of
    /// the current posterior and redoes the Kalman update from the prior with it.
    /// `iterations = 1` is exactly the plain update; iteration stops early once the mean
    /// moves less than 1 mm-equivalent (1e-3 of the state's units).
    pub fn update_iterated<const M: usize, H: MeasurementModel<N, M>>(
        &mut self,
        model: &H,
        pred: &PredictedMeasurement<N, M>,
        z: &SVector<f64, M>,
        r: &SMatrix<f64, M, M>,
        iterations: u32,
    ) -> Result<UpdateReport<M>, FilterError> {
        let (x0, p0) = (self.x, self.p);
        let report = self.update_predicted(model, pred, z)?;
        for _ in 1..iterations.max(1) {
            let (xj, pj) = (self.x, self.p);
            let (z_bar, phi, psi) = self.unscented_measurement(model, &xj, &pj);
            // A = Psi^T Pj^-1; Omega = Phi - A Pj A^T (the fit's residual covariance).
            let Some(pj_chol) = Cholesky::new(pj) else { break };
            let a: SMatrix<f64, M, N> = pj_chol.solve(&psi).transpose();
            let omega = symmetrise(&(phi - a * pj * a.transpose()));
            let s = symmetrise(&(a * p0 * a.transpose() + omega + r));
            let Some(s_chol) = Cholesky::new(s) else { break };
            let k: SMatrix<f64, N, M> = s_chol.solve(&(a * p0)).transpose();
            // z - (A x0 + b) with b = z_bar - A xj, the angle part wrapped.
            let y = model.residual(z, &z_bar) - a * (x0 - xj);
            let x = x0 + k * y;
            let p = repair_psd(&symmetrise(&(p0 - k * s * k.transpose())));
            if !all_finite(x.as_slice()) || !all_finite(p.as_slice()) {
                break;
            }
            let moved = (x - xj).amax();
            self.x = x;
            self.p = p;
            if moved < 1e-3 {
                break;
            }
        }
        Ok(report)
    }

    /// Update with measurement `z` from an already predicted measurement (eq. 4.9-4.10),
    /// so a caller can gate on [`PredictedMeasurement::mahalanobis`] first without
    /// recomputing the sigma points.
    pub fn update_predicted<const M: usize, H: MeasurementModel<N, M>>(
        &mut self,
        model: &H,
        pred: &PredictedMeasurement<N, M>,
        z: &SVector<f64, M>,
    ) -> Result<UpdateReport<M>, FilterError> {
        if !all_finite(z.as_slice()) {
            return Err(FilterError::NonFinite("measurement"));
        }
        let y = model.residual(z, &pred.z);
        // K = T S^-1, computed as (S^-1 T^T)^T with the Cholesky factor (S is symmetric).
        let k: SMatrix<f64, N, M> = pred.s_chol.solve(&pred.cross.transpose()).transpose();
        let x = self.x + k * y;
        let p = repair_psd(&symmetrise(&(self.p - k * pred.s * k.transpose())));
        if !all_finite(x.as_slice()) || !all_finite(p.as_slice()) {
            return Err(FilterError::NonFinite("updated state"));
        }
        self.x = x;
        self.p = p;
        Ok(UpdateReport { innovation: y, predicted: pred.z, mahalanobis: pred.mahalanobis(&y) })
    }

    /// Predicts the measurement and updates with `z` in one call.
    pub fn update<const M: usize, H: MeasurementModel<N, M>>(
        &mut self,
        model: &H,
        z: &SVector<f64, M>,
        r: &SMatrix<f64, M, M>,
    ) -> Result<UpdateReport<M>, FilterError> {
        let pred = self.predict_measurement(model, r)?;
        self.update_predicted(model, &pred, z)
    }
}

/// Eigenvalues and eigenvectors (as columns) of a symmetric matrix. Goes through a
/// dynamic matrix because nalgebra's eigen solver needs typenum bounds that a plain
/// const generic `N` does not carry; it runs only for `max_std` and the rare repair path.
fn eigen<const N: usize>(p: &SMatrix<f64, N, N>) -> (SVector<f64, N>, SMatrix<f64, N, N>) {
    let eig = SymmetricEigen::new(DMatrix::from_column_slice(N, N, p.as_slice()));
    (
        SVector::<f64, N>::from_column_slice(eig.eigenvalues.as_slice()),
        SMatrix::<f64, N, N>::from_column_slice(eig.eigenvectors.as_slice()),
    )
}

fn all_finite(v: &[f64]) -> bool {
    v.iter().all(|c| c.is_finite())
}

fn symmetrise<const N: usize>(p: &SMatrix<f64, N, N>) -> SMatrix<f64, N, N> {
    (p + p.transpose()) * 0.5
}

/// A matrix square root `L` with `L L^T = P` for a symmetric `P`, following the fallback
/// chain of the module doc. Never fails for finite input.
fn matrix_sqrt<const N: usize>(p: &SMatrix<f64, N, N>) -> SMatrix<f64, N, N> {
    if let Some(c) = Cholesky::new(*p) {
        return c.l();
    }
    let scale = (p.trace() / N as f64).abs().max(f64::MIN_POSITIVE);
    let mut jitter = 1e-12;
    while jitter <= 1e-6 {
        let jittered = p + SMatrix::<f64, N, N>::identity() * (jitter * scale);
        if let Some(c) = Cholesky::new(jittered) {
            return c.l();
        }
        jitter *= 100.0;
    }
    let (values, mut l) = eigen(p);
    let floor = scale * 1e-12;
    for (j, &e) in values.iter().enumerate() {
        let s = if e.is_finite() { e.max(floor).sqrt() } else { floor.sqrt() };
        l.column_mut(j).scale_mut(s);
    }
    l
}

/// Returns `p` if it has a Cholesky factor, else its nearest positive semi-definite matrix
/// with eigenvalues floored at a tiny fraction of its mean variance.
fn repair_psd<const N: usize>(p: &SMatrix<f64, N, N>) -> SMatrix<f64, N, N> {
    if Cholesky::new(*p).is_some() {
        return *p;
    }
    let (values, v) = eigen(p);
    let scale = (p.trace() / N as f64).abs().max(f64::MIN_POSITIVE);
    let floor = scale * 1e-12;
    let clamped = values.map(|e| if e.is_finite() { e.max(floor) } else { floor });
    symmetrise(&(v * SMatrix::<f64, N, N>::from_diagonal(&clamped) * v.transpose()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
    use proptest::prelude::*;

    /// Linear models to compare against a textbook Kalman filter.
    struct Linear<const N: usize> {
        f: SMatrix<f64, N, N>,
        q: SMatrix<f64, N, N>,
    }
    impl<const N: usize> ProcessModel<N> for Linear<N> {
        fn transition(&self, x: &SVector<f64, N>, _dt: f64) -> SVector<f64, N> {
            self.f * x
        }
        fn noise(&self, _dt: f64) -> SMatrix<f64, N, N> {
            self.q
        }
    }
    struct LinearH<const N: usize, const M: usize>(SMatrix<f64, M, N>);
    impl<const N: usize, const M: usize> MeasurementModel<N, M> for LinearH<N, M> {
        fn measure(&self, x: &SVector<f64, N>) -> SVector<f64, M> {
            self.0 * x
        }
    }

    fn spd3(a: [f64; 9], d: [f64; 3]) -> Matrix3<f64> {
        let m = Matrix3::from_row_slice(&a);
        m * m.transpose() + Matrix3::from_diagonal(&Vector3::from(d))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// With linear models the unscented transform is exact: the UKF equals the KF.
        #[test]
        fn linear_ukf_matches_kalman_filter(
            f in prop::array::uniform9(-1.2f64..1.2),
            a in prop::array::uniform9(-2.0f64..2.0),
            qa in prop::array::uniform9(-0.5f64..0.5),
            h in prop::array::uniform6(-2.0f64..2.0),
            x0 in prop::array::uniform3(-10.0f64..10.0),
            zs in prop::collection::vec(prop::array::uniform2(-10.0f64..10.0), 1..6),
            alpha in 0.3f64..1.0,
        ) {
            let f = Matrix3::from_row_slice(&f);
            let q = spd3(qa, [0.01, 0.01, 0.01]);
            let hm = SMatrix::<f64, 2, 3>::from_row_slice(&h);
            let r = Matrix2::new(0.3, 0.05, 0.05, 0.2);
            let p0 = spd3(a, [0.1, 0.1, 0.1]);
            let params = UkfParams { alpha, beta: 2.0, kappa: 0.0 };
            let mut ukf = Ukf::new(Vector3::from(x0), p0, params).unwrap();
            let (mut x, mut p) = (Vector3::from(x0), p0);
            for z in zs {
                let z = Vector2::from(z);
                ukf.predict(&Linear { f, q }, 1.0).unwrap();
                x = f * x;
                p = f * p * f.transpose() + q;
                ukf.update(&LinearH(hm), &z, &r).unwrap();
                let s = hm * p * hm.transpose() + r;
                let k = p * hm.transpose() * s.try_inverse().unwrap();
                x += k * (z - hm * x);
                p = (Matrix3::identity() - k * hm) * p;
                p = (p + p.transpose()) * 0.5;
                let tol = 1e-9 * (1.0 + x.amax() + p.amax());
                prop_assert!((ukf.state() - x).amax() < tol, "{} vs {}", ukf.state(), x);
                prop_assert!((ukf.covariance() - p).amax() < tol, "{} vs {}", ukf.covariance(), p);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(100))]
        /// With a linear model the statistical linearisation is exact wherever it is done,
        /// so iterating changes nothing: any iteration count gives the plain update.
        #[test]
        fn iterated_update_equals_plain_update_for_linear_models(
            a in prop::array::uniform9(-2.0f64..2.0),
            h in prop::array::uniform6(-2.0f64..2.0),
            x0 in prop::array::uniform3(-10.0f64..10.0),
            z in prop::array::uniform2(-10.0f64..10.0),
            iterations in 1u32..6,
        ) {
            let p0 = spd3(a, [0.1, 0.1, 0.1]);
            let hm = LinearH(SMatrix::<f64, 2, 3>::from_row_slice(&h));
            let r = Matrix2::new(0.3, 0.05, 0.05, 0.2);
            let z = Vector2::from(z);
            let mut plain = Ukf::new(Vector3::from(x0), p0, UkfParams::default()).unwrap();
            let mut iterated = plain.clone();
            plain.update(&hm, &z, &r).unwrap();
            let pred = iterated.predict_measurement(&hm, &r).unwrap();
            iterated.update_iterated(&hm, &pred, &z, &r, iterations).unwrap();
            let tol = 1e-8 * (1.0 + plain.state().amax() + plain.covariance().amax());
            prop_assert!((plain.state() - iterated.state()).amax() < tol);
            prop_assert!((plain.covariance() - iterated.covariance()).amax() < tol);
        }
    }

    /// Iterations re-linearise about the posterior: `z = x^2` measured precisely far
    /// inside a wide prior. The plain update's slope is the average over the prior's
    /// sigma points; the iterated update ends at the posterior mode (found here by
    /// Newton's method) with the variance the local slope gives.
    #[test]
    fn iterated_update_reaches_the_posterior_mode_of_a_nonlinear_measurement() {
        struct Square;
        impl MeasurementModel<1, 1> for Square {
            fn measure(&self, x: &SVector<f64, 1>) -> SVector<f64, 1> {
                x.map(|v| v * v)
            }
        }
        let (x0, p0, z, r) = (10.0, 25.0, 16.0, 0.01);
        // Newton on the MAP cost (x - x0)^2 / p0 + (x^2 - z)^2 / r.
        let mut x: f64 = x0;
        for _ in 0..100 {
            let grad = (x - x0) / p0 + 4.0 * x * (x * x - z) / r;
            let hess = 1.0 / p0 + (12.0 * x * x - 4.0 * z) / r;
            x -= grad / hess;
        }
        let laplace = 1.0 / (1.0 / p0 + 4.0 * x * x / r);
        let v = |a: f64| SVector::<f64, 1>::new(a);
        let m = |a: f64| SMatrix::<f64, 1, 1>::new(a);
        let mut plain = Ukf::new(v(x0), m(p0), UkfParams::default()).unwrap();
        let mut iterated = plain.clone();
        plain.update(&Square, &v(z), &m(r)).unwrap();
        let pred = iterated.predict_measurement(&Square, &m(r)).unwrap();
        iterated.update_iterated(&Square, &pred, &v(z), &m(r), 10).unwrap();
        let (xi, pi) = (iterated.state()[0], iterated.covariance()[(0, 0)]);
        assert!((xi - x).abs() < 1e-3, "iterated {xi} vs mode {x}");
        assert!((pi / laplace - 1.0).abs() < 0.05, "iterated variance {pi} vs {laplace}");
        assert!((plain.state()[0] - x).abs() > 0.3, "plain {} vs mode {x}", plain.state()[0]);
    }

    #[test]
    fn mahalanobis_matches_hand_computation() {
        let ukf =
            Ukf::new(Vector2::new(0.0, 0.0), Matrix2::new(4.0, 0.0, 0.0, 1.0), UkfParams::default()).unwrap();
        let h = LinearH::<2, 2>(Matrix2::identity());
        let pred = ukf.predict_measurement(&h, &Matrix2::zeros()).unwrap();
        // S = P; y = (2, 1): d^2 = 4/4 + 1/1 = 2.
        assert!((pred.mahalanobis(&Vector2::new(2.0, 1.0)) - 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_input_without_panicking() {
        let p = Matrix2::identity();
        assert!(Ukf::new(Vector2::new(f64::NAN, 0.0), p, UkfParams::default()).is_err());
        assert!(Ukf::new(Vector2::zeros(), Matrix2::new(-1.0, 0.0, 0.0, 1.0), UkfParams::default()).is_err());
        let bad = UkfParams { alpha: 0.0, ..UkfParams::default() };
        assert!(matches!(Ukf::new(Vector2::zeros(), p, bad), Err(FilterError::BadParameters(_))));
        let mut ukf = Ukf::new(Vector2::zeros(), p, UkfParams::default()).unwrap();
        let h = LinearH::<2, 2>(Matrix2::identity());
        let before = *ukf.state();
        assert!(ukf.update(&h, &Vector2::new(f64::INFINITY, 0.0), &Matrix2::identity()).is_err());
        assert_eq!(*ukf.state(), before, "a refused update leaves the state alone");
        // A singular innovation covariance is refused, not divided by.
        let zero = Ukf::new(Vector2::zeros(), Matrix2::zeros(), UkfParams::default()).unwrap();
        assert!(zero.predict_measurement(&h, &Matrix2::zeros()).is_err());
    }

    #[test]
    fn near_singular_and_slightly_indefinite_covariances_survive() {
        // Eigenvalues 1e3, 1e-14 and -1e-10: what round-off leaves after many updates.
        let v = nalgebra::Rotation3::from_euler_angles(0.3, -0.7, 1.1).into_inner();
        let p = v * Matrix3::from_diagonal(&Vector3::new(1e3, 1e-14, -1e-10)) * v.transpose();
        let mut ukf = Ukf::new(Vector3::new(1.0, 2.0, 3.0), p, UkfParams::default())
            .expect("a covariance indefinite by round-off is repaired, not refused");
        let h = LinearH::<3, 2>(SMatrix::<f64, 2, 3>::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0));
        let r = Matrix2::identity() * 0.01;
        for k in 0..50 {
            let z = Vector2::new(1.0 + 0.01 * k as f64, 2.0);
            ukf.update(&h, &z, &r).unwrap();
            assert!(all_finite(ukf.state().as_slice()) && all_finite(ukf.covariance().as_slice()));
            assert!(Cholesky::new(*ukf.covariance()).is_some() || ukf.max_std() < 1e-3);
        }
        // The square root of an indefinite matrix still reproduces its PSD part.
        let l = matrix_sqrt(&p);
        assert!(all_finite(l.as_slice()));
        assert!((l * l.transpose() - p).amax() < 1e-6);
    }
}
