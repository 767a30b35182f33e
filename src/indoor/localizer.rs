//! The per-frame indoor loop (indoor seed Algorithm 2 around sec. 3.3): random-sampling
//! histogram of the prepared frame, k nearest training histograms, particle filter motion
//! and measurement steps, MAP estimate and particle spread.
//!
//! Beyond the seed (its ch. 5: the estimate lagged the truth by about 6 frames because the
//! motion model is noise only): with [`MotionModel::Velocity`] the particles move by the
//! vehicle's velocity times the frame interval, from telemetry when the frame has it,
//! otherwise from a straight-line fit of the last second of estimates.

use std::collections::VecDeque;

use nalgebra::{Matrix2, Vector2};
use rand::SeedableRng;

use super::derotate::Canvas;
use super::knn::{Knn, Neighbour};
use super::model::{to_matrix, Model};
use super::textons::Classifier;
use crate::filter::particle::{Gaussian2, ParticleFilter};
use crate::settings::MotionModel;

/// Run-time parameters (from `[indoor]`).
#[derive(Clone, Debug)]
pub struct LocalizerParams {
    pub k: usize,
    pub particles: usize,
    pub samples: usize,
    pub motion: MotionModel,
    /// SD of the velocity the velocity model integrates, m/s.
    pub velocity_sigma_m_s: f64,
    pub seed: u64,
}

impl LocalizerParams {
    pub fn from_settings(s: &crate::settings::Indoor, seed: u64) -> LocalizerParams {
        LocalizerParams {
            k: s.k as usize,
            particles: s.particles as usize,
            samples: s.samples as usize,
            motion: s.motion_model,
            velocity_sigma_m_s: s.velocity_sigma_m_s,
            seed,
        }
    }
}

/// One frame's result.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    pub t: f64,
    /// MAP position (x, y) = (north, east), metres.
    pub position: Vector2<f64>,
    /// Particle SD in x and y, metres.
    pub spread: (f64, f64),
    /// Positions of the k nearest training samples, nearest first.
    pub neighbours: Vec<Vector2<f64>>,
    /// Velocity the motion step used (zero for the noise-only model).
    pub velocity: Vector2<f64>,
}

/// Smallest bandwidth of the MAP estimate's prior density, metres.
const MAP_BANDWIDTH_M: f64 = 0.05;
/// Frames further apart than this restart the velocity fit (a gap in the stream).
const MAX_GAP_S: f64 = 1.0;
/// Estimates the velocity fit uses, seconds back.
const VELOCITY_WINDOW_S: f64 = 1.0;
/// The velocity fit is trusted only while the particles agree this well, metres.
const VELOCITY_FIT_SPREAD_M: f64 = 0.5;

/// The indoor localiser: one per flight.
pub struct Localizer {
    params: LocalizerParams,
    classifier: Classifier,
    knn: Knn,
    positions: Vec<Vector2<f64>>,
    ranks: Vec<Gaussian2>,
    inlier: Vec<f64>,
    outlier_density: f64,
    process: Matrix2<f64>,
    pf: ParticleFilter,
    rng: rand::rngs::StdRng,
    scratch: Vec<f32>,
    found: Vec<Neighbour>,
    last_t: Option<f64>,
    history: VecDeque<(f64, Vector2<f64>)>,
    last_spread: (f64, f64),
}

/// Tracking from a known start: renewed particles within about this (SD, m) of the mean.
pub const TRACKING_RECOVERY_SD_M: f64 = 1.0;

impl Localizer {
    pub fn new(model: &Model, params: LocalizerParams) -> Result<Localizer, String> {
        model.validate()?;
        let knn = Knn::new(&model.histograms)?;
        let k = params.k.max(1);
        // Ranks beyond those the model fitted reuse the last one.
        let ranks = (0..k)
            .map(|j| {
                let c = model.measurement_cov[j.min(model.measurement_cov.len() - 1)];
                Gaussian2::new(&to_matrix(&c))
                    .ok_or_else(|| format!("measurement covariance {j} is singular"))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let [min, max] = model.bounds;
        let pf =
            ParticleFilter::new(params.particles.max(1), Vector2::from(min), Vector2::from(max), params.seed);
        Ok(Localizer {
            classifier: model.dictionary.classifier(),
            knn,
            positions: model.positions.iter().map(|p| Vector2::from(*p)).collect(),
            ranks,
            inlier: (0..k).map(|j| model.inlier_fraction[j.min(model.inlier_fraction.len() - 1)]).collect(),
            outlier_density: 1.0 / model.area(),
            process: to_matrix(&model.process_cov),
            pf,
            rng: rand::rngs::StdRng::seed_from_u64(params.seed ^ 0x7e77),
            scratch: Vec::new(),
            found: Vec::new(),
            last_t: None,
            history: VecDeque::new(),
            last_spread: (f64::INFINITY, f64::INFINITY),
            params: LocalizerParams { k, ..params },
        })
    }

    /// The motion step's displacement and noise for a frame `dt` after the last one.
    fn motion(&self, dt: f64, velocity: Option<Vector2<f64>>) -> (Vector2<f64>, Matrix2<f64>) {
        match self.params.motion {
            MotionModel::Noise => (Vector2::zeros(), self.process),
            MotionModel::Velocity => {
                if let Some(v) = velocity.filter(|v| v.iter().all(|c| c.is_finite())) {
                    let sd = self.params.velocity_sigma_m_s * dt;
                    // A floor keeps the particles from collapsing onto a few copies.
                    let var = sd * sd + 1e-6;
                    (v * dt, Matrix2::identity() * var)
                } else {
                    (self.fitted_velocity() * dt, self.process)
                }
            }
        }
    }

    /// Least-squares velocity over the last second of estimates, zero until they agree.
    fn fitted_velocity(&self) -> Vector2<f64> {
        if self.history.len() < 3 || self.last_spread.0.max(self.last_spread.1) > VELOCITY_FIT_SPREAD_M {
            return Vector2::zeros();
        }
        let n = self.history.len() as f64;
        let tm = self.history.iter().map(|(t, _)| t).sum::<f64>() / n;
        let pm = self.history.iter().map(|(_, p)| p).sum::<Vector2<f64>>() / n;
        let (mut num, mut den) = (Vector2::zeros(), 0.0);
        for (t, p) in &self.history {
            num += (p - pm) * (t - tm);
            den += (t - tm) * (t - tm);
        }
        if den > 1e-9 {
            num / den
        } else {
            Vector2::zeros()
        }
    }

    /// Processes one prepared frame taken at `t` seconds, with the vehicle's horizontal
    /// velocity (north, east) when telemetry has it.
    pub fn step(&mut self, t: f64, canvas: &Canvas, velocity: Option<Vector2<f64>>) -> Estimate {
        let h = self.classifier.histogram_random(
            &canvas.img,
            Some(&canvas.mask),
            self.params.samples,
            &mut self.rng,
        );
        self.step_histogram(t, &h, velocity)
    }

    /// The same from a ready histogram.
    pub fn step_histogram(&mut self, t: f64, histogram: &[f32], velocity: Option<Vector2<f64>>) -> Estimate {
        let dt = match self.last_t {
            Some(last) if t > last && t - last <= MAX_GAP_S => t - last,
            Some(_) => {
                self.history.clear();
                0.0
            }
            None => 0.0,
        };
        self.last_t = Some(t);
        let (displacement, process) = self.motion(dt, velocity);
        let process_g = Gaussian2::new(&process).unwrap_or_else(|| {
            Gaussian2::new(&(Matrix2::identity() * 1e-4)).expect("a positive diagonal is positive definite")
        });
        self.pf.predict(displacement, &process_g);
        self.knn.nearest(histogram, self.params.k, None, &mut self.scratch, &mut self.found);
        let neighbours: Vec<Vector2<f64>> = self.found.iter().map(|n| self.positions[n.index]).collect();
        // An empty histogram (nothing valid in view) carries no measurement.
        if histogram.iter().any(|v| *v > 0.0) {
            let n = neighbours.len();
            self.pf.update_mixture(
                &neighbours,
                &self.ranks[..n],
                Some(&self.inlier[..n]),
                self.outlier_density,
            );
        }
        // The MAP's prior is a kernel density over the previous particles; with the
        // velocity model's millimetre process noise it would reward a particle for sitting
        // on a previous one by chance, so its bandwidth has a floor.
        let kde = process + Matrix2::identity() * (MAP_BANDWIDTH_M * MAP_BANDWIDTH_M);
        let position = match Gaussian2::new(&kde) {
            Some(g) => self.pf.map_estimate(&g),
            None => self.pf.map_estimate(&process_g),
        };
        let spread = self.pf.spread();
        self.last_spread = spread;
        self.history.push_back((t, position));
        while self.history.front().is_some_and(|(t0, _)| t - t0 > VELOCITY_WINDOW_S) {
            self.history.pop_front();
        }
        Estimate {
            t,
            position,
            spread,
            neighbours,
            velocity: if dt > 0.0 { displacement / dt } else { Vector2::zeros() },
        }
    }

    /// Applies what can change mid-flight (motion model, its SD, samples per histogram);
    /// false when `p` also changes k or the particle count, which need a new localiser.
    pub fn set_params(&mut self, p: &LocalizerParams) -> bool {
        self.params.motion = p.motion;
        self.params.velocity_sigma_m_s = p.velocity_sigma_m_s;
        self.params.samples = p.samples;
        p.k == self.params.k && p.particles == self.params.particles
    }

    pub fn particles(&self) -> &[Vector2<f64>] {
        self.pf.particles()
    }

    /// Starts tracking from a known position (a GPS-denied take-off from a known pad)
    /// instead of searching the whole floor.
    /// From then on it tracks: particles that renew themselves do so near the estimate
    /// (`TRACKING_RECOVERY_SD_M`), never across the map, where a look-alike place could
    /// take the estimate metres away in one frame (measured against PX4 SITL: 6 m).
    pub fn start_at(&mut self, centre: Vector2<f64>, sd_m: f64) {
        self.pf.reset_around(centre, sd_m);
        self.pf.set_local_recovery(Some(TRACKING_RECOVERY_SD_M));
        self.history.clear();
        self.last_t = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::indoor::model::tests::tiny;

    fn params(motion: MotionModel) -> LocalizerParams {
        LocalizerParams { k: 1, particles: 200, samples: 10, motion, velocity_sigma_m_s: 0.05, seed: 1 }
    }

    #[test]
    fn converges_on_the_matching_training_sample() {
        let mut loc = Localizer::new(&tiny(), params(MotionModel::Noise)).unwrap();
        let mut e = None;
        for i in 0..30 {
            e = Some(loc.step_histogram(i as f64 / 15.0, &[0.0, 1.0], None));
        }
        let e = e.unwrap();
        assert!((e.position - Vector2::new(1.0, 1.0)).norm() < 0.2, "{e:?}");
        assert_eq!(e.neighbours, vec![Vector2::new(1.0, 1.0)]);
    }

    #[test]
    fn velocity_model_moves_particles_by_the_telemetry_velocity() {
        let mut loc = Localizer::new(&tiny(), params(MotionModel::Velocity)).unwrap();
        let (d, q) = loc.motion(0.1, Some(Vector2::new(1.0, -2.0)));
        assert!((d - Vector2::new(0.1, -0.2)).norm() < 1e-12);
        assert!(q[(0, 0)] < 1e-4);
        // Without telemetry and before the estimates agree, no displacement is invented.
        let (d, _) = loc.motion(0.1, None);
        assert_eq!(d, Vector2::zeros());
        // A steady track gives its velocity back.
        loc.last_spread = (0.1, 0.1);
        for i in 0..15 {
            let t = i as f64 / 15.0;
            loc.history.push_back((t, Vector2::new(0.5 * t, 0.2)));
        }
        assert!((loc.fitted_velocity() - Vector2::new(0.5, 0.0)).norm() < 1e-9);
        let noise = Localizer::new(&tiny(), params(MotionModel::Noise)).unwrap();
        assert_eq!(noise.motion(0.1, Some(Vector2::new(1.0, 1.0))).0, Vector2::zeros());
    }
}
