//! Consistency checks a user can read: for each frame, the converged landmarks it matched,
//! reprojected with the frame's pose, against the pixels where they were seen. A wrong
//! focal length, a wrong yaw or a frame-convention error shows as large residuals rather
//! than as a quietly wrong map.
//!
//! Observations are every match a frame made to a landmark, accepted by the Mahalanobis
//! gate or not: a frame whose pose is badly wrong has its matches refused, and those
//! refusals are exactly what must show. A frame whose residuals drop by a factor of three
//! or more when its yaw is turned by 180 deg, to a fit as close as a recorded pose's error
//! allows, is reported as "yaw off by about 180 deg" (it happens in real DJI logs).

use std::collections::{BTreeMap, HashMap};

use mavloc_data::table::{self, fixed, Row};
use serde::{Deserialize, Serialize};

use crate::geometry::{CameraPose, Intrinsics, Pixel, Rot3, Vec3};
use mavloc_data::results::LandmarkRecord;

/// Residuals above this (pixels at full resolution) are worth a yaw check.
const SUSPECT_PX: f64 = 20.0;

/// Fewer sightings than this cannot tell a turned yaw from one bad match: on two recorded
/// PX4 SITL flights of about 1870 frames, one frame each, with a single sighting
/// reprojecting 73709 px and off-image, read 1793 and 7159 px turned, "three times better",
/// and was flagged, though neither gimbal ever turned.
const FLIP_MIN_LANDMARKS: usize = 3;

/// A turned pose must fit its sightings to within this share of the image width (full
/// resolution): a real half-turn leaves only the recorded attitude's error, a few degrees
/// (3 deg is 4 % of the width at a 75 deg field of view), while a frame that is wrong in
/// another way fits no better turned than a random pose.
const FLIP_FIT_OF_WIDTH: f64 = 0.05;

/// One frame's residuals, pixels at the frame's full resolution.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameResiduals {
    pub frame: u64,
    pub landmarks: usize,
    pub median_px: f64,
    pub p90_px: f64,
    /// Median with the yaw turned by 180 deg (computed for suspect frames).
    pub median_yaw180_px: Option<f64>,
    pub yaw_off_180: bool,
}

/// The `q` quantile of `v` (nearest rank; sorts `v`).
pub(crate) fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

fn errors(pose: &CameraPose, k: &Intrinsics, obs: &[(Vec3, Pixel)]) -> Vec<f64> {
    obs.iter()
        .map(|(p, seen)| match pose.project(k, p) {
            Some(px) => (px.u - seen.u).hypot(px.v - seen.v),
            None => f64::INFINITY, // behind the camera: as wrong as it gets
        })
        .collect()
}

/// Residuals per frame. `seen`: (frame, landmark id, pixel) of every match, in the
/// pipeline's pixels; `scale` turns them into full-resolution pixels; `poses` and `k` are
/// the pipeline's (processing resolution).
pub fn per_frame(
    seen: &[(u64, u64, Pixel)],
    landmarks: &[LandmarkRecord],
    poses: &BTreeMap<u64, CameraPose>,
    k: &Intrinsics,
    scale: f64,
) -> Vec<FrameResiduals> {
    let mut out = Vec::new();
    for (frame, obs) in by_frame(seen, landmarks) {
        let Some(pose) = poses.get(&frame) else { continue };
        let mut e: Vec<f64> = errors(pose, k, &obs).into_iter().map(|x| x * scale).collect();
        let median = quantile(&mut e, 0.5);
        let p90 = quantile(&mut e, 0.9);
        let (mut flipped, mut off) = (None, false);
        if median > SUSPECT_PX {
            let turned = CameraPose {
                position: pose.position,
                attitude: Rot3::from_axis_angle(&Vec3::z_axis(), std::f64::consts::PI) * pose.attitude,
            };
            let mut f: Vec<f64> = errors(&turned, k, &obs).into_iter().map(|x| x * scale).collect();
            let m = quantile(&mut f, 0.5);
            flipped = Some(m);
            let fits = m <= FLIP_FIT_OF_WIDTH * k.width as f64 * scale;
            off = obs.len() >= FLIP_MIN_LANDMARKS && fits && m * 3.0 <= median;
        }
        out.push(FrameResiduals {
            frame,
            landmarks: obs.len(),
            median_px: median,
            p90_px: p90,
            median_yaw180_px: flipped,
            yaw_off_180: off,
        });
    }
    out
}

/// Sightings of converged landmarks grouped by frame: (landmark position, pixel).
fn by_frame(seen: &[(u64, u64, Pixel)], landmarks: &[LandmarkRecord]) -> BTreeMap<u64, Vec<(Vec3, Pixel)>> {
    let position: HashMap<u64, Vec3> = landmarks.iter().map(|l| (l.id, l.position)).collect();
    let mut out: BTreeMap<u64, Vec<(Vec3, Pixel)>> = BTreeMap::new();
    for (frame, id, px) in seen {
        if let Some(p) = position.get(id) {
            out.entry(*frame).or_default().push((*p, *px));
        }
    }
    out
}

/// Per frame, each converged landmark's sighting and where its estimate reprojects
/// (`None` behind the camera), in full-resolution pixels: what the contact sheet draws.
pub fn marks(
    seen: &[(u64, u64, Pixel)],
    landmarks: &[LandmarkRecord],
    poses: &BTreeMap<u64, CameraPose>,
    k: &Intrinsics,
    scale: f64,
) -> BTreeMap<u64, Vec<(Pixel, Option<Pixel>)>> {
    let full = |p: Pixel| Pixel::new(p.u * scale, p.v * scale);
    by_frame(seen, landmarks)
        .into_iter()
        .filter_map(|(frame, obs)| {
            let pose = poses.get(&frame)?;
            let drawn = obs.iter().map(|(p, px)| (full(*px), pose.project(k, p).map(full))).collect();
            Some((frame, drawn))
        })
        .collect()
}

/// A row of `residuals.csv`.
#[derive(Serialize, Deserialize)]
struct ResidualRow {
    frame: u64,
    landmarks: usize,
    #[serde(serialize_with = "fixed::dp2")]
    median_px: f64,
    #[serde(serialize_with = "fixed::dp2")]
    p90_px: f64,
    #[serde(serialize_with = "fixed::opt_dp2")]
    median_yaw180_px: Option<f64>,
    #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01")]
    yaw_off_180: bool,
}

impl Row for ResidualRow {
    const COLUMNS: &'static str = "frame,landmarks,median_px,p90_px,median_yaw180_px,yaw_off_180";
}

/// `residuals.csv`.
pub fn csv(rows: &[FrameResiduals]) -> String {
    let rows: Vec<ResidualRow> = rows
        .iter()
        .map(|r| ResidualRow {
            frame: r.frame,
            landmarks: r.landmarks,
            median_px: r.median_px,
            p90_px: r.p90_px,
            median_yaw180_px: r.median_yaw180_px,
            yaw_off_180: r.yaw_off_180,
        })
        .collect();
    table::to_string(&rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{GimbalAngles, GimbalChain, Mount};

    /// A camera 40 m up looking nearly level along `yaw` (radians).
    fn pose(yaw: f64) -> CameraPose {
        CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -40.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles { yaw, pitch: -1.2, roll: 0.0 },
            Mount::Earth,
        )
    }

    /// A landmark on the ground at (`x`, `y`).
    fn landmark(id: u64, x: f64, y: f64) -> LandmarkRecord {
        LandmarkRecord {
            id,
            position: Vec3::new(x, y, 0.0),
            sigma_max_m: 0.2,
            observations: 3,
            first_frame: 0,
            last_frame: 1,
        }
    }

    #[test]
    fn a_yaw_off_by_half_a_turn_is_named_and_a_good_pose_is_quiet() {
        let k = Intrinsics::from_hfov(800, 600, 1.2);
        let truth = pose(0.3);
        let landmarks: Vec<LandmarkRecord> =
            (0..20).map(|i| landmark(i, 20.0 + i as f64, -10.0 + 1.3 * i as f64)).collect();
        let seen: Vec<(u64, u64, Pixel)> = landmarks
            .iter()
            .flat_map(|l| {
                let px = truth.project(&k, &l.position).unwrap();
                [(0, l.id, px), (1, l.id, px)]
            })
            .collect();
        // Frame 0 recorded right; frame 1's recorded yaw is half a turn off.
        let poses = BTreeMap::from([(0, truth), (1, pose(0.3 + std::f64::consts::PI))]);
        let r = per_frame(&seen, &landmarks, &poses, &k, 2.0);
        assert_eq!(r.len(), 2);
        assert!(r[0].median_px < 1e-6 && !r[0].yaw_off_180, "{:?}", r[0]);
        assert!(r[1].median_px > 100.0 && r[1].yaw_off_180, "{:?}", r[1]);
        assert!(r[1].median_yaw180_px.unwrap() < 1e-6);
        assert!(csv(&r).lines().nth(2).unwrap().ends_with(",1"));
    }

    /// What the recorded PX4 flights showed: a frame with one sighting far off (a bad match
    /// near the image plane) that reads "better" turned, but only from absurd to absurd, and
    /// a frame of several sightings that a half turn brings nowhere near a fit. Neither is a
    /// turned yaw.
    #[test]
    fn one_bad_sighting_or_a_turn_that_fits_nothing_is_not_a_half_turn() {
        let k = Intrinsics::from_hfov(800, 600, 1.2);
        let truth = pose(0.3);
        let turned = pose(0.3 + std::f64::consts::PI);
        // Frame 0: one landmark seen where the turned pose puts it, 30 px off.
        let lone = landmark(0, 25.0, 5.0);
        let at = turned.project(&k, &lone.position).unwrap();
        let mut seen = vec![(0, 0, Pixel::new(at.u + 30.0, at.v))];
        // Frame 1: ten landmarks, each sighting where the turned pose puts it, shifted by
        // 100 px (an eighth of the width): a sixth of the recorded pose's error, still no fit.
        let many: Vec<LandmarkRecord> =
            (1..11).map(|i| landmark(i, 20.0 + i as f64, -8.0 + i as f64)).collect();
        for l in &many {
            let p = turned.project(&k, &l.position).unwrap();
            seen.push((1, l.id, Pixel::new(p.u + 100.0, p.v)));
        }
        let mut all = vec![lone];
        all.extend(many);
        let poses = BTreeMap::from([(0, truth), (1, truth)]);
        let r = per_frame(&seen, &all, &poses, &k, 1.0);
        assert_eq!(r.len(), 2);
        for f in &r {
            let turned_px = f.median_yaw180_px.expect("suspect, so checked");
            assert!(turned_px * 3.0 <= f.median_px, "turned reads better: {f:?}");
            assert!(!f.yaw_off_180, "not a half turn: {f:?}");
        }
        // The same ten sightings exactly where the turned pose puts them: a half turn.
        for s in seen.iter_mut().filter(|s| s.0 == 1) {
            s.2.u -= 100.0;
        }
        assert!(per_frame(&seen, &all, &poses, &k, 1.0)[1].yaw_off_180);
        // 30 px off it in the pipeline's pixels, at half the frame's resolution: 60 px of
        // the full 1600 px width, within its 5 % (80 px), though not within 5 % of 800.
        for s in seen.iter_mut().filter(|s| s.0 == 1) {
            s.2.u += 30.0;
        }
        let half = per_frame(&seen, &all, &poses, &k, 2.0);
        assert!((half[1].median_yaw180_px.unwrap() - 60.0).abs() < 1e-6, "{:?}", half[1]);
        assert!(half[1].yaw_off_180, "{:?}", half[1]);
    }
}
