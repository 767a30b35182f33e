//! The trained model file (`mavloc indoor train`): texton dictionary, training histograms
//! and positions, the per-rank measurement covariances `Sigma[j]` and the process noise
//! (indoor seed sec. 3.3.1-3.3.4).
//!
//! JSON with a format name and a version; a file of another version is refused with a
//! message saying which versions are involved, rather than read wrongly.

use std::path::Path;

use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};

use super::textons::Dictionary;

pub const MODEL_FORMAT: &str = "mavloc-indoor-model";
/// 2: canvases sampled bilinearly from the camera frame itself (no area downscale first),
/// as flight now gathers its patches; a version-1 model saw slightly smoother textures.
pub const MODEL_VERSION: u32 = 2;

/// How frames were turned into histograms; a run must do the same.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameParams {
    /// Frames are downscaled to this width.
    pub work_width: u32,
    /// Focal length at the working resolution, pixels (the scale textons were learned at).
    pub work_fx: f64,
    /// Frames derotated by the camera attitude before histograms.
    pub derotate: bool,
    /// Brightness and contrast normalised before histograms.
    pub normalise: bool,
    /// Frames were rescaled to the floor's scale as seen from this camera height (m), by
    /// the camera's height at each frame ([`crate::indoor::derotate`]). Absent: not
    /// rescaled (models trained before, or with `indoor.height_ref_m` negative).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_ref_m: Option<f64>,
}

/// Where the training labels came from and what training saw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingInfo {
    pub dataset: String,
    /// "telemetry" (simulated or motion-capture positions) or "homography".
    pub labelling: String,
    pub images: usize,
    /// Images rejected by the homography labelling (too few inliers).
    pub rejected: usize,
    /// Where the process noise came from.
    pub process_source: String,
    /// Leave-one-out RMS error of each rank's neighbour, metres.
    pub loo_rms_m: Vec<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Model {
    pub format: String,
    pub version: u32,
    pub frame: FrameParams,
    pub dictionary: Dictionary,
    /// Full-sampling histograms of the training images.
    pub histograms: Vec<Vec<f32>>,
    /// Their (x, y) = (north, east) positions, metres.
    pub positions: Vec<[f64; 2]>,
    /// `Sigma[j]` for neighbour rank `j` (nearest first): the covariance of the rank's
    /// errors when it is right.
    pub measurement_cov: Vec<[[f64; 2]; 2]>,
    /// Probability that rank `j` is right (otherwise it can be anywhere on the map).
    pub inlier_fraction: Vec<f64>,
    /// Process noise covariance per frame.
    pub process_cov: [[f64; 2]; 2],
    /// The map's extent: min and max (x, y) of the training positions.
    pub bounds: [[f64; 2]; 2],
    pub training: TrainingInfo,
}

pub fn to_matrix(m: &[[f64; 2]; 2]) -> Matrix2<f64> {
    Matrix2::new(m[0][0], m[0][1], m[1][0], m[1][1])
}

pub fn from_matrix(m: &Matrix2<f64>) -> [[f64; 2]; 2] {
    [[m[(0, 0)], m[(0, 1)]], [m[(1, 0)], m[(1, 1)]]]
}

impl Model {
    pub fn position(&self, i: usize) -> Vector2<f64> {
        Vector2::from(self.positions[i])
    }

    /// Area of the map, square metres (at least 1), for the outlier density.
    pub fn area(&self) -> f64 {
        let [min, max] = self.bounds;
        ((max[0] - min[0]) * (max[1] - min[1])).max(1.0)
    }

    /// Checks the parts agree with each other.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.dictionary.len();
        if n == 0 {
            return Err("the model has no textons".into());
        }
        let dim = self.dictionary.w * self.dictionary.h * 3;
        if self.dictionary.textons.iter().any(|t| t.len() != dim) {
            return Err(format!(
                "a texton does not have {dim} values ({}x{}x3)",
                self.dictionary.w, self.dictionary.h
            ));
        }
        if self.histograms.len() != self.positions.len() || self.histograms.is_empty() {
            return Err(format!(
                "{} histograms for {} positions; both must be equal and non-zero",
                self.histograms.len(),
                self.positions.len()
            ));
        }
        if let Some(i) = self.histograms.iter().position(|h| h.len() != n) {
            return Err(format!("histogram {i} has {} bins for {n} textons", self.histograms[i].len()));
        }
        if self.measurement_cov.is_empty() {
            return Err("the model has no measurement covariances".into());
        }
        if self.inlier_fraction.len() != self.measurement_cov.len()
            || self.inlier_fraction.iter().any(|p| !(0.0..=1.0).contains(p))
        {
            return Err(format!(
                "{} inlier fractions in [0, 1] are needed, one per measurement covariance",
                self.measurement_cov.len()
            ));
        }
        for (j, c) in self.measurement_cov.iter().enumerate() {
            if nalgebra::Cholesky::new(to_matrix(c)).is_none() {
                return Err(format!("measurement covariance of rank {} is not positive definite", j + 1));
            }
        }
        if nalgebra::Cholesky::new(to_matrix(&self.process_cov)).is_none() {
            return Err("the process covariance is not positive definite".into());
        }
        Ok(())
    }

    /// Writes the model atomically.
    pub fn save(&self, path: &Path) -> Result<(), String> {
        let json = serde_json::to_vec(self).map_err(|e| e.to_string())?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        }
        mavloc_data::write_atomic(path, &json).map_err(|e| format!("cannot write {}: {e}", path.display()))
    }

    /// Whether `path` holds a model this mavloc reads (`settings::check` before a run).
    pub fn check_file(path: &Path) -> Result<(), String> {
        Model::load(path).map(|_| ())
    }

    /// Reads a model, refusing other formats and versions with a clear message.
    pub fn load(path: &Path) -> Result<Model, String> {
        let bytes = std::fs::read(path).map_err(|e| format!("cannot read model {}: {e}", path.display()))?;
        Model::from_slice(&bytes).map_err(|e| format!("model {}: {e}", path.display()))
    }

    pub fn from_slice(bytes: &[u8]) -> Result<Model, String> {
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| format!("not a mavloc model (not JSON: {e})"))?;
        let format = value.get("format").and_then(|f| f.as_str());
        if format != Some(MODEL_FORMAT) {
            return Err(format!(
                "not a mavloc indoor model (format {format:?}, expected \"{MODEL_FORMAT}\")"
            ));
        }
        let version = value.get("version").and_then(|v| v.as_u64());
        if version != Some(MODEL_VERSION as u64) {
            return Err(format!(
                "model version {} but this mavloc reads version {MODEL_VERSION}; retrain it with `mavloc indoor train`",
                version.map_or("unknown".into(), |v| v.to_string())
            ));
        }
        let model: Model = serde_json::from_value(value).map_err(|e| format!("malformed model: {e}"))?;
        model.validate()?;
        Ok(model)
    }
}

/// Fits one rank's errors `T - P_j` as a mixture of a zero-mean Gaussian (the neighbour is
/// right, up to `Sigma`) and a uniform density `1 / area` (it is a look-alike elsewhere on
/// the map), by expectation-maximisation. Returns `(Sigma, inlier fraction)`.
///
/// Beyond the seed, which fitted one Gaussian to all errors: k-NN errors are heavy-tailed,
/// and one Gaussian wide enough for the look-alikes (metres) tells the filter nothing
/// about the neighbours that are right (decimetres).
pub fn fit_robust(errors: &[Vector2<f64>], area: f64) -> (Matrix2<f64>, f64) {
    let floor = Matrix2::identity() * 1e-4;
    if errors.is_empty() {
        return (Matrix2::identity(), 0.5);
    }
    let mut cov = Matrix2::identity() * 0.09;
    let mut pi = 0.5;
    let uniform = 1.0 / area.max(1e-6);
    for _ in 0..100 {
        let Some(g) = crate::filter::particle::Gaussian2::new(&cov) else { break };
        let (mut sum_r, mut acc) = (0.0, Matrix2::zeros());
        for d in errors {
            let a = pi * g.pdf(d);
            let r = a / (a + (1.0 - pi) * uniform);
            sum_r += r;
            acc += d * d.transpose() * r;
        }
        let new_pi = (sum_r / errors.len() as f64).clamp(1e-3, 1.0 - 1e-3);
        let new_cov = if sum_r > 1e-9 { acc / sum_r + floor } else { cov };
        let done = (new_pi - pi).abs() < 1e-6 && (new_cov - cov).norm() < 1e-9;
        (pi, cov) = (new_pi, new_cov);
        if done {
            break;
        }
    }
    (cov, pi)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn tiny() -> Model {
        Model {
            format: MODEL_FORMAT.into(),
            version: MODEL_VERSION,
            frame: FrameParams {
                work_width: 320,
                work_fx: 228.5,
                derotate: true,
                normalise: true,
                height_ref_m: None,
            },
            dictionary: Dictionary { w: 1, h: 1, textons: vec![vec![0.0; 3], vec![255.0; 3]] },
            histograms: vec![vec![1.0, 0.0], vec![0.0, 1.0]],
            positions: vec![[0.0, 0.0], [1.0, 1.0]],
            measurement_cov: vec![[[0.1, 0.0], [0.0, 0.1]]],
            inlier_fraction: vec![0.9],
            process_cov: [[0.01, 0.0], [0.0, 0.01]],
            bounds: [[0.0, 0.0], [1.0, 1.0]],
            training: TrainingInfo {
                dataset: "x".into(),
                labelling: "telemetry".into(),
                images: 2,
                rejected: 0,
                process_source: "configured".into(),
                loo_rms_m: vec![1.0],
            },
        }
    }

    #[test]
    fn round_trips_and_refuses_other_versions() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.json");
        let m = tiny();
        m.save(&path).unwrap();
        assert_eq!(Model::load(&path).unwrap(), m);

        let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        v["version"] = 99.into();
        let err = Model::from_slice(&serde_json::to_vec(&v).unwrap()).unwrap_err();
        assert!(err.contains("version 99") && err.contains("retrain"), "{err}");
        v["format"] = "something".into();
        assert!(Model::from_slice(&serde_json::to_vec(&v).unwrap()).unwrap_err().contains("not a mavloc"));
        assert!(Model::from_slice(b"\x00garbage").unwrap_err().contains("not JSON"));
    }

    #[test]
    fn robust_fit_separates_look_alikes_from_right_neighbours() {
        use rand::{Rng, SeedableRng};
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let normal = Normal::new(0.0, 0.2).unwrap();
        let errors: Vec<Vector2<f64>> = (0..4000)
            .map(|i| {
                if i % 10 < 7 {
                    Vector2::new(normal.sample(&mut rng), normal.sample(&mut rng))
                } else {
                    Vector2::new(rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0))
                }
            })
            .collect();
        let (cov, pi) = fit_robust(&errors, 64.0);
        assert!((pi - 0.7).abs() < 0.03, "{pi}");
        assert!((cov[(0, 0)].sqrt() - 0.2).abs() < 0.02 && (cov[(1, 1)].sqrt() - 0.2).abs() < 0.02, "{cov}");
        assert!(cov[(0, 1)].abs() < 0.01);
    }

    #[test]
    fn refuses_inconsistent_parts() {
        let mut m = tiny();
        m.histograms[1].push(0.0);
        assert!(m.validate().unwrap_err().contains("histogram 1"));
        let mut m = tiny();
        m.measurement_cov[0] = [[0.0, 0.0], [0.0, 0.0]];
        assert!(m.validate().unwrap_err().contains("rank 1"));
        let mut m = tiny();
        m.positions.pop();
        assert!(m.validate().is_err());
    }
}
