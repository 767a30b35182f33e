//! Evaluation as the area seed does it (ch. 6): each converged landmark's minimal distance
//! to the ground-truth border polyline, counted in the bands < 10 m, 10-20 m, > 20 m, with
//! the mean (tables 6.3, 6.5, 6.6); plus the fitted border line's mean and largest distance
//! to the ground truth; and, for a rendered dataset whose ground is known everywhere, each
//! landmark's height above the true surface at its north and east ([`AreaEvaluation::with_surface`]).
//! The distance to the border mixes where a landmark lies in the band beside the border
//! (up to the band's width, on a correct landmark) with its error; the height is its error
//! alone where the ground is level, and shows a map that floats as a whole.

use serde::Serialize;

use crate::geometry::Vec3;
use mavloc_data::results::LandmarkRecord;

/// The seed's table, and more.
#[derive(Clone, Debug, Serialize)]
pub struct AreaEvaluation {
    pub landmarks: usize,
    pub lt10: usize,
    pub from10to20: usize,
    pub gt20: usize,
    pub mean_m: f64,
    pub median_m: f64,
    pub max_m: f64,
    pub border_mean_m: f64,
    pub border_max_m: f64,
    pub frames_per_s: f64,
    /// Median height of the landmarks above the true surface, m (negative: below); only
    /// for datasets whose surface is known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_median_m: Option<f64>,
    /// Median of the absolute heights above the true surface, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub height_abs_median_m: Option<f64>,
    #[serde(skip)]
    pub distances: Vec<f64>,
}

/// Minimal distance from `p` to a set of polylines (infinite when there are none).
pub fn distance_to(lines: &[Vec<Vec3>], p: &Vec3) -> f64 {
    crate::geometry::nearest_on_polylines(lines, p).map_or(f64::INFINITY, |(_, d)| d)
}

fn stats(v: &[f64]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    (v.iter().sum::<f64>() / v.len() as f64, s[s.len() / 2], s[s.len() - 1])
}

/// Evaluates landmarks and border lines against the ground truth.
pub fn evaluate(
    landmarks: &[LandmarkRecord],
    truth: &[Vec<Vec3>],
    border: &[Vec<Vec3>],
    frames_per_s: f64,
) -> AreaEvaluation {
    let distances: Vec<f64> = landmarks.iter().map(|l| distance_to(truth, &l.position)).collect();
    let (mean_m, median_m, max_m) = stats(&distances);
    // The border line, sampled every metre.
    let mut border_d = Vec::new();
    for line in border {
        for w in line.windows(2) {
            let steps = ((w[1] - w[0]).norm().ceil() as usize).max(1);
            for s in 0..steps {
                let q = w[0] + (w[1] - w[0]) * (s as f64 / steps as f64);
                border_d.push(distance_to(truth, &q));
            }
        }
    }
    let (border_mean_m, _, border_max_m) = stats(&border_d);
    AreaEvaluation {
        landmarks: landmarks.len(),
        lt10: distances.iter().filter(|&&d| d < 10.0).count(),
        from10to20: distances.iter().filter(|&&d| (10.0..=20.0).contains(&d)).count(),
        gt20: distances.iter().filter(|&&d| d > 20.0).count(),
        mean_m,
        median_m,
        max_m,
        border_mean_m,
        border_max_m,
        frames_per_s,
        height_median_m: None,
        height_abs_median_m: None,
        distances,
    }
}

impl AreaEvaluation {
    /// With the landmarks' heights above the true surface, `surface_height(north, east)`
    /// (metres up).
    pub fn with_surface(
        mut self,
        landmarks: &[LandmarkRecord],
        surface_height: impl Fn(f64, f64) -> f64,
    ) -> Self {
        let h: Vec<f64> =
            landmarks.iter().map(|l| -l.position.z - surface_height(l.position.x, l.position.y)).collect();
        if !h.is_empty() {
            let abs: Vec<f64> = h.iter().map(|x| x.abs()).collect();
            self.height_median_m = Some(stats(&h).1);
            self.height_abs_median_m = Some(stats(&abs).1);
        }
        self
    }
}

impl std::fmt::Display for AreaEvaluation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.landmarks == 0 {
            // No distances to average: say so rather than print a table of NaN.
            writeln!(f, "no landmarks: nothing to compare with the ground truth")?;
        } else {
            writeln!(f, "landmarks  d < 10 m  10-20 m  d > 20 m  mean d to GT  median  max")?;
            writeln!(
                f,
                "{:>9}  {:>8}  {:>7}  {:>8}  {:>10.2} m  {:>4.2} m  {:.2} m",
                self.landmarks, self.lt10, self.from10to20, self.gt20, self.mean_m, self.median_m, self.max_m
            )?;
        }
        if self.border_mean_m.is_finite() {
            writeln!(
                f,
                "border line: mean {:.2} m, max {:.2} m from the ground truth",
                self.border_mean_m, self.border_max_m
            )?;
        } else {
            writeln!(f, "border line: none fitted")?;
        }
        if let (Some(h), Some(a)) = (self.height_median_m, self.height_abs_median_m) {
            writeln!(f, "height above the true surface: median {h:+.2} m, median of its size {a:.2} m")?;
        }
        writeln!(f, "speed: {:.1} frames/s", self.frames_per_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lm(p: Vec3) -> LandmarkRecord {
        LandmarkRecord {
            id: 0,
            position: p,
            sigma_max_m: 0.1,
            observations: 5,
            first_frame: 0,
            last_frame: 1,
        }
    }

    #[test]
    fn bands_and_mean_follow_the_seed() {
        let truth = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0)]];
        let l =
            [lm(Vec3::new(50.0, 3.0, 4.0)), lm(Vec3::new(10.0, 15.0, 0.0)), lm(Vec3::new(-30.0, 0.0, 0.0))];
        let e = evaluate(&l, &truth, &[], 12.0);
        assert_eq!((e.landmarks, e.lt10, e.from10to20, e.gt20), (3, 1, 1, 1));
        assert!((e.mean_m - (5.0 + 15.0 + 30.0) / 3.0).abs() < 1e-12);
        let border = vec![vec![Vec3::new(0.0, 1.0, 0.0), Vec3::new(100.0, 1.0, 0.0)]];
        let e = evaluate(&l, &truth, &border, 12.0);
        assert!((e.border_mean_m - 1.0).abs() < 1e-12 && (e.border_max_m - 1.0).abs() < 1e-12);
    }

    /// Heights are taken above the surface under each landmark (NED: up is -down), signed,
    /// and their size separately; without a surface nothing is reported.
    #[test]
    fn heights_are_measured_above_the_true_surface_under_each_landmark() {
        let truth = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0)]];
        // A slope rising 0.1 m per metre north; landmarks 2 m above, 1 m above, 3 m below.
        let l =
            [lm(Vec3::new(10.0, 0.0, -3.0)), lm(Vec3::new(20.0, 1.0, -3.0)), lm(Vec3::new(30.0, 2.0, 0.0))];
        let e = evaluate(&l, &truth, &[], 1.0);
        assert!(e.height_median_m.is_none() && !e.to_string().contains("true surface"));
        let e = e.with_surface(&l, |n, _| 0.1 * n);
        assert!((e.height_median_m.unwrap() - 1.0).abs() < 1e-12, "{:?}", e.height_median_m);
        assert!((e.height_abs_median_m.unwrap() - 2.0).abs() < 1e-12, "{:?}", e.height_abs_median_m);
        assert!(e.to_string().contains("median +1.00 m, median of its size 2.00 m"), "{e}");
    }

    #[test]
    fn no_landmarks_print_words_not_nan() {
        let e = evaluate(&[], &[vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(10.0, 0.0, 0.0)]], &[], 6.0);
        let text = e.to_string();
        assert!(text.contains("no landmarks") && !text.contains("NaN"), "{text}");
    }
}
