//! Cross-line agreement: a measure of a survey's poses that needs no ground truth. A
//! landmark photographed from two flight lines is triangulated from each line's rays alone;
//! with right poses the two points coincide, and the distance between them is what the two
//! lines' attitude and position errors make of it (issue #21: the Seneca survey before and
//! after refinement). Lines are split where the track turns.

use std::collections::BTreeMap;

use super::rays::{triangulate, Ray};
use crate::geometry::{CameraPose, Intrinsics, Pixel, Vec3};

/// A turn of more than this between consecutive legs starts a new line (degrees).
const TURN_DEG: f64 = 60.0;
/// The course is taken over at least this much ground (m): between video frames half a
/// metre apart, a position noise of 0.3 m turns the course every which way (a coastline
/// lap fell apart into 218-243 "lines"); photos of a survey are tens of metres apart.
const MIN_LEG_M: f64 = 5.0;
/// A line's own triangulation counts when it fixes the point this well (largest SD, m):
/// two photos a few tens of metres apart along a line do, a pair 3 m apart does not.
const MAX_SIGMA_M: f64 = 5.0;

/// Flight line of each frame (0, 1, ...), frames in order: where the course, taken over
/// legs of at least [`MIN_LEG_M`], turns by more than [`TURN_DEG`] from the leg before, a
/// new line starts. The first photo of a line is reached by the cross-over from the last
/// line, so a line of one frame joins the line after it.
pub fn flight_lines(positions: &BTreeMap<u64, Vec3>) -> BTreeMap<u64, usize> {
    use std::f64::consts::{PI, TAU};
    let frames: Vec<(u64, Vec3)> = positions.iter().map(|(f, p)| (*f, *p)).collect();
    let mut raw = vec![0usize; frames.len()];
    let mut line = 0;
    let mut last_course: Option<f64> = None;
    let mut anchor = frames.first().map(|f| f.1);
    for (i, (_, p)) in frames.iter().enumerate().skip(1) {
        let d = p - anchor.expect("frames after the first have an anchor");
        if d.x.hypot(d.y) >= MIN_LEG_M {
            let course = d.y.atan2(d.x);
            if let Some(c) = last_course {
                let turn = (course - c + PI).rem_euclid(TAU) - PI;
                if turn.abs().to_degrees() > TURN_DEG {
                    line += 1;
                }
            }
            last_course = Some(course);
            anchor = Some(*p);
        }
        raw[i] = line;
    }
    // Renumber, a one-frame line taking the next line's number.
    let mut out = BTreeMap::new();
    let mut next = 0;
    let mut i = 0;
    while i < frames.len() {
        let mut j = i;
        while j < frames.len() && raw[j] == raw[i] {
            j += 1;
        }
        let single = j - i == 1 && j < frames.len();
        for f in &frames[i..j] {
            out.insert(f.0, next);
        }
        if !single {
            next += 1;
        }
        i = j;
    }
    out
}

/// For each landmark seen from two or more lines with at least two sightings on each:
/// the distance between its points triangulated from each line alone (every pair of
/// lines), metres. `sd_rad`: the bearing SD the triangulation weighs with.
pub fn disagreement(
    sightings: &[(u64, u64, Pixel)],
    poses: &BTreeMap<u64, CameraPose>,
    k: &Intrinsics,
    lines: &BTreeMap<u64, usize>,
    landmarks: &BTreeMap<u64, Vec3>,
    sd_rad: f64,
) -> Vec<f64> {
    // landmark -> line -> rays
    let mut rays: BTreeMap<u64, BTreeMap<usize, Vec<Ray>>> = BTreeMap::new();
    for &(f, id, px) in sightings {
        let (Some(pose), Some(&line)) = (poses.get(&f), lines.get(&f)) else { continue };
        if !landmarks.contains_key(&id) {
            continue;
        }
        let ray = Ray { origin: pose.position, dir: pose.direction(k, px) };
        rays.entry(id).or_default().entry(line).or_default().push(ray);
    }
    let mut out = Vec::new();
    for (id, by_line) in &rays {
        let start = landmarks[id];
        let points: Vec<Vec3> = by_line
            .values()
            .filter(|r| r.len() >= 2)
            .filter_map(|r| triangulate(r, &start, sd_rad, &[0.0; 3]))
            .filter(|t| t.sigma_max <= MAX_SIGMA_M)
            .map(|t| t.position)
            .collect();
        for i in 0..points.len() {
            for j in i + 1..points.len() {
                out.push((points[i] - points[j]).norm());
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::area::refine::corrected;
    use crate::geometry::{GimbalAngles, GimbalChain, Mount};

    fn nadir(position: Vec3) -> CameraPose {
        let a = GimbalAngles { yaw: 0.0, pitch: -90f64.to_radians(), roll: 0.0 };
        CameraPose::from_gimbal(position, GimbalChain::YawPitchRoll, a, Mount::Earth)
    }

    #[test]
    fn lines_split_where_the_track_turns() {
        // North along y = 0, a turn, south along y = 30, a turn, north along y = 60.
        let mut positions = BTreeMap::new();
        let mut f = 0;
        for (y, dir) in [(0.0, 1.0), (30.0, -1.0), (60.0, 1.0)] {
            for i in 0..5 {
                let x = if dir > 0.0 { i as f64 * 20.0 } else { 80.0 - i as f64 * 20.0 };
                positions.insert(f, Vec3::new(x, y, -70.0));
                f += 1;
            }
        }
        let lines = flight_lines(&positions);
        let got: Vec<usize> = lines.values().copied().collect();
        assert_eq!(got, vec![0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2, 2, 2, 2]);
    }

    /// A video flight: frames 0.5 m apart with 0.3 m of position noise along a straight
    /// track, then a turn: two lines, not hundreds.
    #[test]
    fn a_noisy_video_track_keeps_its_lines() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let noise = Normal::new(0.0, 0.3).unwrap();
        let mut positions = BTreeMap::new();
        for i in 0..200u64 {
            let (x, y) = if i < 100 { (i as f64 * 0.5, 0.0) } else { (50.0, (i - 100) as f64 * 0.5) };
            positions.insert(i, Vec3::new(x + noise.sample(&mut rng), y + noise.sample(&mut rng), -30.0));
        }
        let lines = flight_lines(&positions);
        assert_eq!(lines.values().max(), Some(&1), "two lines");
        assert_eq!(lines[&50], 0);
        assert_eq!(lines[&180], 1);
    }

    /// Two lines see the same points: exact poses agree to nothing; one line's photos all
    /// turned by a degree put its points about a degree's worth of range away.
    #[test]
    fn lines_agree_with_right_poses_and_disagree_with_a_rotated_line() {
        let k = Intrinsics { width: 1000, height: 750, fx: 900.0, fy: 900.0, cx: 499.5, cy: 374.5 };
        let mut poses = BTreeMap::new();
        let mut lines = BTreeMap::new();
        for i in 0..4u64 {
            poses.insert(i, nadir(Vec3::new(i as f64 * 15.0, 0.0, -70.0)));
            lines.insert(i, 0);
            poses.insert(10 + i, nadir(Vec3::new(i as f64 * 15.0, 30.0, -70.0)));
            lines.insert(10 + i, 1);
        }
        let points: BTreeMap<u64, Vec3> = (0..20)
            .map(|j| (j, Vec3::new(10.0 + (j % 5) as f64 * 6.0, 8.0 + (j / 5) as f64 * 4.0, 0.0)))
            .collect();
        let mut sightings = Vec::new();
        for (&f, p) in &poses {
            for (&j, x) in &points {
                if let Some(px) = p.project(&k, x).filter(|px| k.contains(*px)) {
                    sightings.push((f, j, px));
                }
            }
        }
        let d = disagreement(&sightings, &poses, &k, &lines, &points, 0.01);
        assert!(d.len() >= 15, "{} landmarks seen from both lines", d.len());
        assert!(d.iter().all(|&m| m < 1e-6), "exact poses: {d:?}");
        // Line 1's recorded attitude a degree off about north: its points move ~1.2 m.
        let turned: BTreeMap<u64, CameraPose> = poses
            .iter()
            .map(|(&f, p)| {
                (f, if f >= 10 { corrected(p, &Vec3::new(1f64.to_radians(), 0.0, 0.0)) } else { *p })
            })
            .collect();
        let mut d = disagreement(&sightings, &turned, &k, &lines, &points, 0.01);
        d.sort_by(f64::total_cmp);
        let median = d[d.len() / 2];
        assert!(median > 0.8 && median < 2.0, "a degree at 70 m: median {median:.2} m");
    }
}
