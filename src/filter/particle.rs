//! A 2D particle filter for global x, y localisation (indoor seed sec. 3.3.4, Algorithm 2
//! and 3): motion step with Gaussian process noise (plus a displacement when the vehicle's
//! velocity is known), importance weights from a Gaussian mixture over the k nearest
//! neighbours' positions with rank-dependent covariances, resampling, and the discrete
//! maximum a posteriori estimate of Driessen and Boers.
//!
//! Deviations from the seed, deliberate:
//!
//! * Resampling is systematic (one random offset, `M` evenly spaced pointers) rather than
//!   the resampling wheel: both draw each particle with probability proportional to its
//!   weight, systematic resampling in O(M) with lower variance; the wheel is kept
//!   ([`resampling_wheel`]) and a test checks the two agree in distribution.
//! * The seed's MAP formula (sec. 3.3.4) omits the likelihood; Driessen and Boers' estimate
//!   is `argmax_i p(z_t | x_i) sum_j p(x_i | x_j^{t-1}) w_j^{t-1}`, which this implements.
//! * Particles are redrawn uniformly over the map when measurements become less likely
//!   than they have been (augmented MCL: short- and long-term averages of the likelihood,
//!   Thrun et al., Probabilistic Robotics, 8.3.5, here of its logarithm and at most
//!   `max_random` of the particles per frame), and all of them when no particle explains
//!   the measurement, so a kidnapped vehicle is found again while a tracked one keeps its
//!   spread honest.

use nalgebra::{Matrix2, Vector2};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// A 2D Gaussian with its inverse and normaliser precomputed.
#[derive(Clone, Copy, Debug)]
pub struct Gaussian2 {
    inv: Matrix2<f64>,
    norm: f64,
    chol: Matrix2<f64>,
}

impl Gaussian2 {
    /// `None` unless `cov` is symmetric positive definite.
    pub fn new(cov: &Matrix2<f64>) -> Option<Gaussian2> {
        let chol = nalgebra::Cholesky::new(*cov)?;
        let det = cov.determinant();
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        Some(Gaussian2 {
            inv: chol.inverse(),
            norm: 1.0 / (std::f64::consts::TAU * det.sqrt()),
            chol: chol.l(),
        })
    }

    /// Density of offset `d` from the mean.
    pub fn pdf(&self, d: &Vector2<f64>) -> f64 {
        self.norm * (-0.5 * d.dot(&(self.inv * d))).exp()
    }

    /// A sample of the zero-mean distribution.
    pub fn sample(&self, rng: &mut impl Rng) -> Vector2<f64> {
        let z = Vector2::new(rng.sample::<f64, _>(StandardNormal), rng.sample::<f64, _>(StandardNormal));
        self.chol * z
    }
}

/// Particles tried as the centre of the mode ([`ParticleFilter::mode_estimate`]): a mode
/// holding a tenth of the particles is missed with probability 0.9^32 = 3 %.
const MODE_CANDIDATES: usize = 32;

/// Tracking: measurements within this many recovery SDs of the mean may seed particles.
const TRACKING_REACH_SD: f64 = 1.5;
/// Tracking: the least share of particles renewed from the measurements each frame.
const TRACKING_RESET_SHARE: f64 = 0.01;

/// Particle filter over x, y within a rectangular map.
pub struct ParticleFilter {
    particles: Vec<Vector2<f64>>,
    weights: Vec<f64>,
    previous: Vec<Vector2<f64>>,
    previous_weights: Vec<f64>,
    min: Vector2<f64>,
    max: Vector2<f64>,
    /// Smoothing of the long- and short-term likelihood averages (augmented MCL).
    pub alpha_slow: f64,
    pub alpha_fast: f64,
    /// Most particles redrawn per update, as a fraction: one frame of wrong neighbours
    /// must not scatter a good track.
    pub max_random: f64,
    w_slow: f64,
    w_fast: f64,
    started: bool,
    rng: rand::rngs::StdRng,
    last_likelihood: Vec<f64>,
    last_displacement: Vector2<f64>,
    /// Where new particles come from: None, anywhere on the map (global localisation, the
    /// kidnapped robot); Some(sd), around the particles' mean (tracking: a vehicle
    /// cannot jump across the map between frames, but a look-alike place can lure
    /// uniform draws).
    local_recovery: Option<f64>,
    /// Tracking: whether renewed particles may start at measurements near the mean
    /// (sensor resetting), or only around the mean.
    sensor_resetting: bool,
    /// The weights are the likelihood raised to this power (1: the plain filter). Below 1
    /// for measurements correlated from frame to frame, each of which is then worth that
    /// share of an independent one (a tempered likelihood).
    pub likelihood_exponent: f64,
}

impl ParticleFilter {
    /// `count` particles spread uniformly over `[min, max]` (global localisation).
    pub fn new(count: usize, min: Vector2<f64>, max: Vector2<f64>, seed: u64) -> ParticleFilter {
        let mut pf = ParticleFilter {
            particles: Vec::new(),
            weights: Vec::new(),
            previous: Vec::new(),
            previous_weights: Vec::new(),
            min,
            max,
            alpha_slow: 0.01,
            alpha_fast: 0.1,
            max_random: 0.1,
            w_slow: 0.0,
            w_fast: 0.0,
            started: false,
            rng: rand::rngs::StdRng::seed_from_u64(seed),
            last_likelihood: Vec::new(),
            last_displacement: Vector2::zeros(),
            local_recovery: None,
            sensor_resetting: true,
            likelihood_exponent: 1.0,
        };
        pf.particles = (0..count.max(1)).map(|_| pf.uniform()).collect();
        pf.weights = vec![1.0 / pf.particles.len() as f64; pf.particles.len()];
        pf.previous = pf.particles.clone();
        pf.previous_weights = pf.weights.clone();
        pf
    }

    /// Tracking instead of global localisation: new particles around the mean (SD, m).
    pub fn set_local_recovery(&mut self, sd_m: Option<f64>) {
        self.local_recovery = sd_m;
    }

    /// Global localisation again: every particle anywhere on the map, equal weights, the
    /// likelihood averages forgotten (they adapted to the lost track's low likelihood, so
    /// they would no longer call for random particles), no local recovery.
    pub fn restart_global(&mut self) {
        for i in 0..self.particles.len() {
            self.particles[i] = self.uniform();
        }
        let w = 1.0 / self.particles.len() as f64;
        self.weights.iter_mut().for_each(|x| *x = w);
        self.previous.clone_from(&self.particles);
        self.previous_weights.clone_from(&self.weights);
        self.started = false;
        self.local_recovery = None;
        self.sensor_resetting = true;
    }

    /// Tracking: renewed particles may start at measurements near the mean (true, the
    /// default), or only around the mean.
    pub fn set_sensor_resetting(&mut self, on: bool) {
        self.sensor_resetting = on;
    }

    /// A fresh particle: anywhere on the map; or, when tracking, where a measurement near
    /// the mean says (sensor resetting: one of `near`, within its rank's spread), else near
    /// the mean.
    fn fresh(&mut self, mean: Vector2<f64>, near: &[(Vector2<f64>, &Gaussian2)]) -> Vector2<f64> {
        let Some(sd) = self.local_recovery else { return self.uniform() };
        let p = if near.is_empty() {
            let g = Gaussian2::new(&(Matrix2::identity() * (sd * sd).max(1e-12)))
                .expect("a positive diagonal is positive definite");
            // Truncated at the reach: one particle drawn by chance onto a look-alike place
            // further out takes nearly all the weight in the next frame where the
            // neighbours point there, and with it the track.
            let reach = TRACKING_REACH_SD * sd;
            let mut d = g.sample(&mut self.rng);
            if d.norm() > reach {
                d *= reach / d.norm();
            }
            mean + d
        } else {
            let (z, g) = near[self.rng.random_range(0..near.len())];
            z + g.sample(&mut self.rng)
        };
        Vector2::new(p.x.clamp(self.min.x, self.max.x), p.y.clamp(self.min.y, self.max.y))
    }

    fn uniform(&mut self) -> Vector2<f64> {
        Vector2::new(
            self.rng.random_range(self.min.x..=self.max.x),
            self.rng.random_range(self.min.y..=self.max.y),
        )
    }

    pub fn particles(&self) -> &[Vector2<f64>] {
        &self.particles
    }

    /// All particles drawn around a known position (tracking from a known start instead
    /// of global localisation), equal weights.
    pub fn reset_around(&mut self, centre: Vector2<f64>, sd_m: f64) {
        self.reset_mixed(centre, sd_m, 0.0);
    }

    /// Particles drawn around a position, and a share `anywhere` of them anywhere on the
    /// map (a prior that may be off: the filter's random particles come only when the
    /// likelihood drops, which it does not where every place looks as unlikely as the
    /// prior's), equal weights.
    pub fn reset_mixed(&mut self, centre: Vector2<f64>, sd_m: f64, anywhere: f64) {
        let g = Gaussian2::new(&(Matrix2::identity() * (sd_m * sd_m).max(1e-12)))
            .expect("a positive diagonal is positive definite");
        let n = self.particles.len();
        let far = ((n as f64 * anywhere.clamp(0.0, 1.0)).round() as usize).min(n);
        for i in 0..n {
            self.particles[i] = if i < far { self.uniform() } else { centre + g.sample(&mut self.rng) };
        }
        let w = 1.0 / self.particles.len() as f64;
        self.weights.iter_mut().for_each(|x| *x = w);
        self.previous = self.particles.clone();
        self.previous_weights = self.weights.clone();
    }

    /// Motion step: every particle moves by `displacement` plus process noise.
    pub fn predict(&mut self, displacement: Vector2<f64>, process: &Gaussian2) {
        self.previous.clone_from(&self.particles);
        self.previous_weights.clone_from(&self.weights);
        self.last_displacement = displacement;
        let n = self.particles.len();
        for i in 0..n {
            let noise = process.sample(&mut self.rng);
            let p = self.particles[i] + displacement + noise;
            self.particles[i] =
                Vector2::new(p.x.clamp(self.min.x, self.max.x), p.y.clamp(self.min.y, self.max.y));
        }
    }

    /// Measurement step: weights from the mixture over the neighbours' positions, rank `j`
    /// with covariance `ranks[j]` (Algorithm 2, lines 8-11), then systematic resampling.
    pub fn update(&mut self, neighbours: &[Vector2<f64>], ranks: &[Gaussian2]) {
        self.update_mixture(neighbours, ranks, None, 0.0);
    }

    /// Measurement step with a robust mixture: rank `j` is right with probability
    /// `inlier[j]` (Gaussian `ranks[j]` about the neighbour) and otherwise anywhere on the
    /// map (density `outlier_density`). The seed's model is `inlier = 1`.
    pub fn update_mixture(
        &mut self,
        neighbours: &[Vector2<f64>],
        ranks: &[Gaussian2],
        inlier: Option<&[f64]>,
        outlier_density: f64,
    ) {
        let n = self.particles.len();
        let pi = |j: usize| inlier.and_then(|w| w.get(j)).copied().unwrap_or(1.0);
        let floor: f64 =
            (0..neighbours.len().min(ranks.len())).map(|j| (1.0 - pi(j)) * outlier_density).sum();
        self.last_likelihood = self
            .particles
            .iter()
            .map(|x| {
                floor
                    + neighbours
                        .iter()
                        .zip(ranks)
                        .enumerate()
                        .map(|(j, (z, g))| pi(j) * g.pdf(&(z - x)))
                        .sum::<f64>()
            })
            .collect();
        let total: f64 = self.last_likelihood.iter().sum();
        if !(total.is_finite() && total > 0.0) {
            // Nothing explains the measurement: start again over the whole map (or,
            // tracking, around where the particles were).
            let mean = self.mean();
            for i in 0..n {
                self.particles[i] = self.fresh(mean, &[]);
            }
            self.weights = vec![1.0 / n as f64; n];
            return;
        }
        // Averages of the log of the mean likelihood: an arithmetic average is pulled up by
        // the rare frames whose neighbours all agree, and then every ordinary frame looks
        // like a kidnapping.
        let log_mean = (total / n as f64).ln();
        if !self.started {
            (self.w_slow, self.w_fast, self.started) = (log_mean, log_mean, true);
        }
        self.w_slow += self.alpha_slow * (log_mean - self.w_slow);
        self.w_fast += self.alpha_fast * (log_mean - self.w_fast);
        let p_random = (1.0 - (self.w_fast - self.w_slow).exp()).clamp(0.0, self.max_random);
        self.weights = if self.likelihood_exponent == 1.0 {
            self.last_likelihood.iter().map(|l| l / total).collect()
        } else {
            // Relative to the largest likelihood, which is positive here (the total is).
            let max = self.last_likelihood.iter().copied().fold(0.0, f64::max);
            let mut tempered: Vec<f64> =
                self.last_likelihood.iter().map(|l| (l / max).powf(self.likelihood_exponent)).collect();
            let sum: f64 = tempered.iter().sum();
            tempered.iter_mut().for_each(|w| *w /= sum);
            tempered
        };
        let picks = systematic(&self.weights, self.rng.random::<f64>());
        let (old, old_l) = (self.particles.clone(), self.last_likelihood.clone());
        self.particles = picks.iter().map(|&i| old[i]).collect();
        self.last_likelihood = picks.iter().map(|&i| old_l[i]).collect();
        self.weights = vec![1.0 / n as f64; n];
        let mean = self.mean();
        // Tracking: the neighbours within reach of the estimate, and always a few fresh
        // particles among them. A filter that starts (or gets) off by more than its
        // measurement spread otherwise never sees its likelihood drop below its own
        // running average, and stays off while the camera sees the right place
        // (measured against PX4 SITL: 0.6 m off after the take-off, then lost).
        let near: Vec<(Vector2<f64>, &Gaussian2)> = match self.local_recovery {
            Some(sd) if self.sensor_resetting => neighbours
                .iter()
                .zip(ranks)
                .filter(|(z, _)| (*z - mean).norm() <= TRACKING_REACH_SD * sd)
                .map(|(z, g)| (*z, g))
                .collect(),
            _ => Vec::new(),
        };
        let p_random =
            if self.local_recovery.is_some() { p_random.max(TRACKING_RESET_SHARE) } else { p_random };
        for i in 0..n {
            if p_random > 0.0 && self.rng.random::<f64>() < p_random {
                self.particles[i] = self.fresh(mean, &near);
                self.last_likelihood[i] = 0.0;
            }
        }
    }

    /// Driessen and Boers' MAP estimate: the particle maximising its likelihood times the
    /// predicted density from the previous particle set.
    pub fn map_estimate(&self, process: &Gaussian2) -> Vector2<f64> {
        let mut best = (f64::NEG_INFINITY, self.particles[0]);
        for (i, x) in self.particles.iter().enumerate() {
            let prior: f64 = self
                .previous
                .iter()
                .zip(&self.previous_weights)
                .map(|(p, w)| w * process.pdf(&(x - p - self.last_displacement)))
                .sum();
            let score = prior * self.last_likelihood.get(i).copied().unwrap_or(1.0);
            if score > best.0 {
                best = (score, *x);
            }
        }
        best.1
    }

    /// The posterior's mode in O(M) (the MAP estimate above is O(M^2): 250 000 kernel
    /// evaluations per frame at 500 particles, more than the rest of the frame together).
    /// Of `MODE_CANDIDATES` particles spread over the set, the one with the most weight
    /// within `radius`; then the weighted mean of the particles within `radius` of that
    /// point, twice (mean shift with a flat kernel). After resampling the particles are
    /// distributed as the posterior, so the weight in a disk is its mass there: a look-alike
    /// place holding fewer particles does not pull the estimate, as it pulls the mean.
    pub fn mode_estimate(&self, radius: f64) -> Vector2<f64> {
        let n = self.particles.len();
        let r2 = radius * radius;
        let mass = |c: &Vector2<f64>| -> f64 {
            self.particles
                .iter()
                .zip(&self.weights)
                .filter(|(p, _)| (*p - c).norm_squared() <= r2)
                .map(|(_, w)| w)
                .sum()
        };
        let step = n.div_ceil(MODE_CANDIDATES).max(1);
        let mut best = (f64::NEG_INFINITY, self.particles[0]);
        for c in self.particles.iter().step_by(step) {
            let m = mass(c);
            if m > best.0 {
                best = (m, *c);
            }
        }
        let mut centre = best.1;
        for _ in 0..2 {
            let (mut sum, mut total) = (Vector2::zeros(), 0.0);
            for (p, w) in self.particles.iter().zip(&self.weights) {
                if (p - centre).norm_squared() <= r2 {
                    sum += p * *w;
                    total += w;
                }
            }
            if total > 0.0 {
                centre = sum / total;
            }
        }
        centre
    }

    /// Weighted mean of the particles.
    pub fn mean(&self) -> Vector2<f64> {
        self.particles.iter().zip(&self.weights).map(|(p, w)| p * *w).sum()
    }

    /// Standard deviation of the particles in x and in y (the seed's uncertainty).
    pub fn spread(&self) -> (f64, f64) {
        let m = self.mean();
        let var =
            self.particles.iter().zip(&self.weights).fold(Vector2::zeros(), |acc: Vector2<f64>, (p, w)| {
                let d = p - m;
                acc + Vector2::new(d.x * d.x, d.y * d.y) * *w
            });
        (var.x.sqrt(), var.y.sqrt())
    }
}

/// Systematic resampling: indices drawn with probability proportional to `weights`
/// (normalised), using one random offset `u` in [0, 1).
pub fn systematic(weights: &[f64], u: f64) -> Vec<usize> {
    let n = weights.len();
    let total: f64 = weights.iter().sum();
    let mut out = Vec::with_capacity(n);
    let mut cumulative = 0.0;
    let mut i = 0;
    for m in 0..n {
        let pointer = (u + m as f64) / n as f64 * total;
        while i + 1 < n && cumulative + weights[i] < pointer {
            cumulative += weights[i];
            i += 1;
        }
        out.push(i);
    }
    out
}

/// The seed's resampling wheel (Algorithm 3), for comparison.
pub fn resampling_wheel(weights: &[f64], rng: &mut impl Rng) -> Vec<usize> {
    let n = weights.len();
    let max = weights.iter().cloned().fold(0.0, f64::max);
    let mut i = rng.random_range(0..n);
    let mut beta = 0.0;
    (0..n)
        .map(|_| {
            beta += rng.random::<f64>() * 2.0 * max;
            while beta > weights[i] {
                beta -= weights[i];
                i = (i + 1) % n;
            }
            i
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g(sd: f64) -> Gaussian2 {
        Gaussian2::new(&(Matrix2::identity() * sd * sd)).unwrap()
    }

    /// A tempered likelihood (exponent 1/3) counts a measurement as a third of one: the
    /// posterior of a Gaussian prior (SD 1 m) and measurement (SD 0.316 m) is about
    /// 1/sqrt(1 + 10) = 0.30 m wide in full, 1/sqrt(1 + 3.3) = 0.48 m tempered.
    #[test]
    fn a_tempered_likelihood_narrows_the_particles_less() {
        let spread_after = |exponent: f64| {
            let mut pf = ParticleFilter::new(4000, Vector2::new(-5.0, -5.0), Vector2::new(5.0, 5.0), 3);
            pf.reset_around(Vector2::zeros(), 1.0);
            pf.set_sensor_resetting(false);
            pf.likelihood_exponent = exponent;
            pf.update(&[Vector2::new(0.5, 0.0)], &[g(0.1f64.sqrt())]);
            pf.spread().0
        };
        let (full, tempered) = (spread_after(1.0), spread_after(1.0 / 3.0));
        assert!((full - 0.30).abs() < 0.04, "full {full:.3}");
        assert!((tempered - 0.48).abs() < 0.05, "tempered {tempered:.3}");
    }

    #[test]
    fn gaussian_density_integrates_to_one() {
        let gauss = Gaussian2::new(&Matrix2::new(0.09, 0.02, 0.02, 0.04)).unwrap();
        let h = 0.01;
        let mut sum = 0.0;
        for i in -150..150 {
            for j in -150..150 {
                sum += gauss.pdf(&Vector2::new(i as f64 * h, j as f64 * h)) * h * h;
            }
        }
        assert!((sum - 1.0).abs() < 1e-3, "{sum}");
        assert!(Gaussian2::new(&Matrix2::new(1.0, 2.0, 2.0, 1.0)).is_none(), "indefinite refused");
    }

    #[test]
    fn systematic_and_wheel_draw_in_proportion_to_weight() {
        let w = [0.1, 0.0, 0.6, 0.3];
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let (mut a, mut b) = ([0usize; 4], [0usize; 4]);
        for _ in 0..2000 {
            for i in systematic(&w, rng.random()) {
                a[i] += 1;
            }
            for i in resampling_wheel(&w, &mut rng) {
                b[i] += 1;
            }
        }
        let total = 8000.0;
        for k in 0..4 {
            assert!((a[k] as f64 / total - w[k]).abs() < 0.01, "systematic {a:?}");
            assert!((b[k] as f64 / total - w[k]).abs() < 0.02, "wheel {b:?}");
        }
        assert_eq!(a[1] + b[1], 0, "zero weight is never drawn");
    }

    #[test]
    fn global_localisation_converges_and_resolves_an_ambiguity() {
        // The truth walks east; k-NN gives the truth plus a decoy somewhere else each time
        // (look-alike places). The mixture carries both; only the truth is consistent with
        // the motion, so the particles gather there.
        let mut pf = ParticleFilter::new(300, Vector2::new(-4.0, -4.0), Vector2::new(4.0, 4.0), 1);
        let process = g(0.1);
        let ranks = [g(0.3), g(0.5)];
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let mut truth = Vector2::new(-3.0, 0.0);
        for _ in 0..40 {
            let step = Vector2::new(0.1, 0.0);
            truth += step;
            pf.predict(step, &process);
            let noisy = truth + g(0.2).sample(&mut rng);
            let decoy = Vector2::new(rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0));
            pf.update(&[noisy, decoy], &ranks);
        }
        let est = pf.map_estimate(&process);
        assert!((est - truth).norm() < 0.5, "estimate {est:?} vs truth {truth:?}");
        let (sx, sy) = pf.spread();
        assert!(sx < 0.6 && sy < 0.6, "a tracked vehicle has a tight spread: {sx} {sy}");
    }

    #[test]
    fn kidnapped_vehicle_is_found_again() {
        let mut pf = ParticleFilter::new(200, Vector2::new(-4.0, -4.0), Vector2::new(4.0, 4.0), 3);
        let process = g(0.05);
        let ranks = [g(0.2)];
        for _ in 0..20 {
            pf.predict(Vector2::zeros(), &process);
            pf.update(&[Vector2::new(-3.0, -3.0)], &ranks);
        }
        // Kidnapped to the far corner: measurements now say (3, 3).
        for _ in 0..30 {
            pf.predict(Vector2::zeros(), &process);
            pf.update(&[Vector2::new(3.0, 3.0)], &ranks);
        }
        let est = pf.map_estimate(&process);
        assert!((est - Vector2::new(3.0, 3.0)).norm() < 0.4, "{est:?}");
        let (sx, sy) = pf.spread();
        assert!(sx < 1.5 && sy < 1.5, "spread {sx} {sy}");
    }

    #[test]
    fn robust_mixture_keeps_a_track_through_a_wrong_frame_and_recovers_from_a_kidnap() {
        let mut pf = ParticleFilter::new(200, Vector2::new(-4.0, -4.0), Vector2::new(4.0, 4.0), 5);
        let process = g(0.02);
        let ranks = [g(0.15)];
        let at = |pf: &mut ParticleFilter, z: Vector2<f64>| {
            pf.predict(Vector2::zeros(), &process);
            pf.update_mixture(&[z], &ranks, Some(&[0.9]), 1.0 / 64.0);
        };
        for _ in 0..40 {
            at(&mut pf, Vector2::new(-3.0, -3.0));
        }
        // One look-alike frame: the track stays.
        at(&mut pf, Vector2::new(2.0, 1.0));
        at(&mut pf, Vector2::new(-3.0, -3.0));
        assert!((pf.map_estimate(&process) - Vector2::new(-3.0, -3.0)).norm() < 0.2);
        assert!(pf.spread().0 < 0.8, "{:?}", pf.spread());
        // Kidnapped: the measurements now say (3, 3), frame after frame.
        for _ in 0..60 {
            at(&mut pf, Vector2::new(3.0, 3.0));
        }
        let est = pf.map_estimate(&process);
        assert!((est - Vector2::new(3.0, 3.0)).norm() < 0.3, "{est:?}");
    }
}
