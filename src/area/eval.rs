//! Evaluation as the area seed does it (ch. 6): each converged landmark's minimal distance
//! to the ground-truth border polyline, counted in the bands < 10 m, 10-20 m, > 20 m, with
//! the mean (tables 6.3, 6.5, 6.6); plus the fitted border line's mean and largest distance
//! to the ground truth; and, for a rendered dataset whose ground is known everywhere, each
//! landmark's height above the true surface at its north and east ([`AreaEvaluation::with_surface`]).
//! The distance to the border mixes where a landmark lies in the band beside the border
//! (up to the band's width, on a correct landmark) with its error; the height is its error
//! alone where the ground is level, and shows a map that floats as a whole. With the run's
//! sightings (`trace.csv`) and a rendered dataset's true poses, each landmark is also set
//! against the point its own traced sightings fix from the true poses
//! ([`AreaEvaluation::with_true_rays`]): its error, wherever in the band it lies, as far
//! as those sightings are right (a landmark made of false matches is set against where
//! those false rays meet; since session 46 the trace holds each landmark's first sighting
//! too, so a landmark seen in two photos counts).

use std::collections::HashMap;

use serde::Serialize;

use super::rays::{self, Ray};
use crate::geometry::{Rot3, Vec3};

use mavloc_data::results::LandmarkRecord;

/// A landmark is set against its true-pose fix only where the true rays fix the point to
/// this SD (m) with a pixel of noise: rays with little parallax fix nothing to compare with.
pub const TRUE_FIX_MAX_SD_M: f64 = 0.25;

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
    /// Landmarks set against the point their sightings fix from the true poses, and
    /// their distance from it (mean, median, 95th percentile), m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_landmarks: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_mean_m: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_median_m: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_p95_m: Option<f64>,
    /// The error's mean vector (north, east, down), m: what moves the map as a whole, as a
    /// common error of the photos' positions or attitudes does; and the RMS of what is
    /// left about it, m, the map's shape error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_shift_m: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub true_fix_shape_rms_m: Option<f64>,
    /// Photos aligned by their tie points, set against their true attitudes: how many,
    /// the rotation they share (aligned against true, a rotation vector about north, east,
    /// down, degrees: what the photos' GPS positions leave open, turning the map as a
    /// whole) and the RMS of each photo's rest about it, degrees (how well they agree with
    /// each other).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aligned_photos: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aligned_common_deg: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aligned_rest_rms_deg: Option<f64>,
    /// The turn that best carries the photos' true positions onto their tagged ones
    /// (rotation vector, degrees): how the GPS positions alone turn the survey, to set
    /// beside `aligned_common_deg`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tagged_positions_turn_deg: Option<[f64; 3]>,
    #[serde(skip)]
    pub distances: Vec<f64>,
}

/// The rotation `r` that best carries the points `from` onto `to` about their centroids
/// (least squares, Kabsch's SVD solution); None for fewer than three points or points on
/// one line, whose turn about that line nothing fixes. Written here on nalgebra's SVD: the
/// crates we use have no point-set registration.
fn best_turn(pairs: &[(Vec3, Vec3)]) -> Option<Rot3> {
    if pairs.len() < 3 {
        return None;
    }
    let n = pairs.len() as f64;
    let (ca, cb) = pairs.iter().fold((Vec3::zeros(), Vec3::zeros()), |(a, b), (f, t)| (a + f / n, b + t / n));
    let h: nalgebra::Matrix3<f64> = pairs.iter().map(|(f, t)| (t - cb) * (f - ca).transpose()).sum();
    let svd = h.svd(true, true);
    // Singular values come largest first: a second one near zero is a line of points.
    if svd.singular_values[1] <= 1e-9 * svd.singular_values[0] {
        return None;
    }
    let (u, v_t) = (svd.u?, svd.v_t?);
    // A reflection is no turn: flip the least singular direction.
    let d = (u * v_t).determinant().signum();
    let r = u * nalgebra::Matrix3::from_diagonal(&Vec3::new(1.0, 1.0, d)) * v_t;
    Some(Rot3::from_matrix_unchecked(r))
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
        true_fix_landmarks: None,
        true_fix_mean_m: None,
        true_fix_median_m: None,
        true_fix_p95_m: None,
        true_fix_shift_m: None,
        true_fix_shape_rms_m: None,
        aligned_photos: None,
        aligned_common_deg: None,
        aligned_rest_rms_deg: None,
        tagged_positions_turn_deg: None,
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

    /// With the photos' aligned attitudes set against their true ones (`pairs`: true,
    /// aligned; rotations "NED <- camera") and the turn their tagged positions make
    /// against their true ones (`positions`: true, tagged); both as aligned or tagged
    /// against true. The errors are small, so
    /// their rotation vectors average.
    pub fn with_aligned_attitudes(mut self, pairs: &[(Rot3, Rot3)], positions: &[(Vec3, Vec3)]) -> Self {
        if pairs.is_empty() {
            return self;
        }
        // Both turns as the error is: the aligned attitudes and the tagged positions turned
        // against the truth, as the shift is the map's position less the true one.
        if let Some(r) = best_turn(positions) {
            let v = r.scaled_axis().map(f64::to_degrees);
            self.tagged_positions_turn_deg = Some([v.x, v.y, v.z]);
        }
        let v: Vec<Vec3> =
            pairs.iter().map(|(t, a)| (a * t.inverse()).scaled_axis().map(f64::to_degrees)).collect();
        let mean = v.iter().sum::<Vec3>() / v.len() as f64;
        let rest = v.iter().map(|x| (x - mean).norm_squared()).sum::<f64>() / v.len() as f64;
        self.aligned_photos = Some(v.len());
        self.aligned_common_deg = Some([mean.x, mean.y, mean.z]);
        self.aligned_rest_rms_deg = Some(rest.sqrt());
        self
    }

    /// With each landmark's distance from the point its own sightings fix when cast from
    /// the true poses (`rays`, by landmark id; least squares with `pixel_rad` of bearing
    /// noise, [`rays::triangulate`]). The distance to the border counts a correct landmark
    /// 2 m into the band as 2 m off; this does not. Landmarks whose true rays fix them no
    /// better than [`TRUE_FIX_MAX_SD_M`] are left out.
    pub fn with_true_rays(
        mut self,
        landmarks: &[LandmarkRecord],
        rays: &HashMap<u64, Vec<Ray>>,
        pixel_rad: f64,
    ) -> Self {
        let vectors: Vec<Vec3> = landmarks
            .iter()
            .filter_map(|l| {
                let r = rays.get(&l.id)?;
                let fix = rays::triangulate(r, &l.position, pixel_rad, &[0.0; 3])?;
                (fix.sigma_max <= TRUE_FIX_MAX_SD_M).then(|| l.position - fix.position)
            })
            .collect();
        let mut errors: Vec<f64> = vectors.iter().map(|v| v.norm()).collect();
        self.true_fix_landmarks = Some(errors.len());
        if !errors.is_empty() {
            let shift = vectors.iter().sum::<Vec3>() / vectors.len() as f64;
            let shape =
                vectors.iter().map(|v| (v - shift).norm_squared()).sum::<f64>() / vectors.len() as f64;
            self.true_fix_shift_m = Some([shift.x, shift.y, shift.z]);
            self.true_fix_shape_rms_m = Some(shape.sqrt());
            // The mean and median as the table's distances have them.
            let (mean, median, _) = stats(&errors);
            errors.sort_by(f64::total_cmp);
            self.true_fix_mean_m = Some(mean);
            self.true_fix_median_m = Some(median);
            self.true_fix_p95_m = Some(errors[((errors.len() - 1) as f64 * 0.95).round() as usize]);
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
        match (self.true_fix_landmarks, self.true_fix_mean_m, self.true_fix_median_m, self.true_fix_p95_m) {
            (Some(n), Some(mean), Some(median), Some(p95)) => {
                writeln!(
                    f,
                    "error against the true poses ({n} of {} landmarks, each against the point its sightings fix from the true poses): mean {mean:.2} m, median {median:.2} m, 95th percentile {p95:.2} m",
                    self.landmarks
                )?;
                if let (Some([n, e, d]), Some(rms)) = (self.true_fix_shift_m, self.true_fix_shape_rms_m) {
                    writeln!(
                        f,
                        "  of which the map as a whole is shifted by north {n:+.2} m, east {e:+.2} m, down {d:+.2} m; about that shift {rms:.2} m RMS"
                    )?;
                }
            }
            (Some(_), ..) => writeln!(
                f,
                "error against the true poses: no landmark's sightings fix it from the true poses"
            )?,
            _ => {}
        }
        if let (Some(n), Some([a, b, c]), Some(rms)) =
            (self.aligned_photos, self.aligned_common_deg, self.aligned_rest_rms_deg)
        {
            writeln!(
                f,
                "photos aligned against their true attitudes ({n}): turned together about north {a:+.3}, east {b:+.3}, down {c:+.3} deg; each about that {rms:.3} deg RMS"
            )?;
            if let Some([a, b, c]) = self.tagged_positions_turn_deg {
                writeln!(
                    f,
                    "  the photos' tagged positions against their true ones: turned about north {a:+.3}, east {b:+.3}, down {c:+.3} deg (what GPS leaves open)"
                )?;
            }
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

    /// A landmark 2 m into the band but exactly where its true rays meet has no error,
    /// though it is 2 m from the border; one 0.3 m off its rays' point has 0.3 m; one whose
    /// true rays are nearly parallel (no fix to judge by) is left out.
    #[test]
    fn the_error_against_the_true_poses_is_where_the_true_rays_meet() {
        let truth = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0)]];
        let on = Vec3::new(10.0, 2.0, 0.0);
        let off_point = Vec3::new(20.0, 2.0, 0.0);
        let far = Vec3::new(30.0, 2.0, 0.0);
        let ray = |from: Vec3, to: &Vec3| Ray { origin: from, dir: (to - from).normalize() };
        let cams =
            [Vec3::new(-20.0, -30.0, -40.0), Vec3::new(40.0, -30.0, -40.0), Vec3::new(10.0, 30.0, -40.0)];
        let mut rays = HashMap::new();
        rays.insert(0, cams.iter().map(|c| ray(*c, &on)).collect::<Vec<_>>());
        rays.insert(1, cams.iter().map(|c| ray(*c, &off_point)).collect());
        // Two rays from nearly one place: parallel to within a hair.
        rays.insert(
            2,
            vec![ray(Vec3::new(30.0, -30.0, -40.0), &far), ray(Vec3::new(30.01, -30.0, -40.0), &far)],
        );
        let mut l = [lm(on), lm(off_point + Vec3::new(0.0, 0.3, 0.0)), lm(far)];
        for (i, x) in l.iter_mut().enumerate() {
            x.id = i as u64;
        }
        let e = evaluate(&l, &truth, &[], 1.0);
        assert!(e.true_fix_landmarks.is_none() && !e.to_string().contains("true poses"));
        let e = e.with_true_rays(&l, &rays, 0.001);
        assert!((e.mean_m - 2.1).abs() < 1e-9, "2 m from the border on average: {}", e.mean_m);
        assert_eq!(e.true_fix_landmarks, Some(2), "the parallel pair fixes nothing");
        assert!((e.true_fix_mean_m.unwrap() - 0.15).abs() < 1e-6, "{:?}", e.true_fix_mean_m);
        assert!(e.to_string().contains("error against the true poses (2 of 3 landmarks"), "{e}");
        // Errors 0 and 0.3 m east: a common shift of 0.15 m east, 0.15 m RMS about it.
        let [n, east, d] = e.true_fix_shift_m.unwrap();
        assert!(n.abs() < 1e-6 && (east - 0.15).abs() < 1e-6 && d.abs() < 1e-6, "{:?}", e.true_fix_shift_m);
        assert!((e.true_fix_shape_rms_m.unwrap() - 0.15).abs() < 1e-6, "{:?}", e.true_fix_shape_rms_m);
        assert!(e.to_string().contains("east +0.15 m"), "{e}");
    }

    /// Three photos turned by one common 0.3 deg about north, two of them by another
    /// 0.01 deg about down and back: the common part and the rest come apart.
    #[test]
    fn aligned_attitudes_split_into_a_common_turn_and_each_photos_rest() {
        let deg = |x: f64, y: f64, z: f64| Rot3::new(Vec3::new(x, y, z).map(f64::to_radians));
        let truth = [deg(0.0, 180.0, 0.0), deg(0.0, 170.0, 10.0), deg(3.0, 175.0, -20.0)];
        let rests = [deg(0.0, 0.0, 0.01), deg(0.0, 0.0, -0.01), deg(0.0, 0.0, 0.0)];
        let common = deg(0.3, 0.0, 0.0);
        // aligned = common * rest * truth, so aligned * truth^-1 = common * rest.
        let pairs: Vec<(Rot3, Rot3)> = truth.iter().zip(rests).map(|(t, r)| (*t, common * r * t)).collect();
        // Tagged positions turned by 0.2 deg about down against the true ones, about their
        // centroid, and shifted: the turn is found, the shift is not a turn.
        let turn = deg(0.0, 0.0, 0.2);
        let truths = [Vec3::new(0.0, 0.0, -40.0), Vec3::new(60.0, 0.0, -40.0), Vec3::new(0.0, 60.0, -41.0)];
        let centroid = truths.iter().sum::<Vec3>() / 3.0;
        let positions: Vec<(Vec3, Vec3)> = truths
            .iter()
            .map(|t| (*t, turn * (t - centroid) + centroid + Vec3::new(0.3, -0.2, 0.1)))
            .collect();
        let e = evaluate(&[], &[vec![Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)]], &[], 1.0)
            .with_aligned_attitudes(&pairs, &positions);
        let [_, _, d] = e.tagged_positions_turn_deg.unwrap();
        assert!((d - 0.2).abs() < 1e-6, "{:?}", e.tagged_positions_turn_deg);
        let [n, east, d] = e.aligned_common_deg.unwrap();
        assert!((n - 0.3).abs() < 1e-4 && east.abs() < 1e-4 && d.abs() < 1e-4, "{:?}", e.aligned_common_deg);
        let rms = e.aligned_rest_rms_deg.unwrap();
        assert!((rms - (2.0f64 / 3.0).sqrt() * 0.01).abs() < 1e-4, "{rms}");
        assert!(e.to_string().contains("photos aligned against their true attitudes (3)"), "{e}");
    }

    /// Points on one line leave the turn about it open: no turn is claimed.
    #[test]
    fn points_on_one_line_have_no_best_turn() {
        let line: Vec<(Vec3, Vec3)> =
            (0..5).map(|i| (Vec3::new(i as f64, 0.0, 0.0), Vec3::new(i as f64 + 0.1, 0.0, 0.0))).collect();
        assert!(best_turn(&line).is_none());
        let mut plane = line.clone();
        plane.push((Vec3::new(0.0, 3.0, 0.0), Vec3::new(0.1, 3.0, 0.0)));
        assert!(best_turn(&plane).is_some_and(|r| r.angle() < 1e-9), "a shift alone is no turn");
    }

    #[test]
    fn no_landmarks_print_words_not_nan() {
        let e = evaluate(&[], &[vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(10.0, 0.0, 0.0)]], &[], 6.0);
        let text = e.to_string();
        assert!(text.contains("no landmarks") && !text.contains("NaN"), "{text}");
    }
}
