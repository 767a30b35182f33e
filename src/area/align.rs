//! Photo alignment from tie points, before any landmark filter runs. A survey's attitude
//! tags can be too far off for the filters: the Seneca photos' tags put overlapping photos'
//! ground 13 m apart at 70 m (about 10 degrees), beyond the filters' gates, and nothing
//! converged; the DJI survey's gimbal tags were 2.4 to 5.0 degrees off (area issue
//! evidence). So the photos are first aligned to each other, as photogrammetry does:
//!
//! 1. SIFT in every photo; each photo and its nearest photos whose tagged ground
//!    footprints overlap are matched (Lowe's ratio test) and the matches verified by a fundamental matrix (MAGSAC++,
//!    which copes with the near-planar ground that makes plain RANSAC degenerate);
//! 2. verified matches are chained into tracks (a union-find over keypoints; a track
//!    seen twice in one photo is dropped);
//! 3. each track starts where its rays meet the ground plane, and the tracks and one
//!    rotation correction per photo are adjusted together ([`super::refine`]: the same
//!    bundle adjustment over attitudes, positions held at the GPS ones, each correction
//!    held towards zero by `area.align_prior_deg`), twice, the second time without the
//!    sightings the first left far off.
//!
//! The corrections then apply to every pose the filters see. Beyond the area seed (which
//! trusts its telemetry, sec. 6.10); the tie-point idea is aerial triangulation's.

use std::collections::{BTreeMap, HashMap};

use opencv::calib3d;
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;

use super::imageup::{self, on_ground, PhotoFeatures};
use super::rays::{triangulate, Ray};
use super::refine::{self, RefineParams};
use crate::geometry::{CameraPose, Intrinsics, Pixel, Vec3};
use mavloc_data::results::LandmarkRecord;

/// Keypoints per photo, and the width SIFT sees it at: more than the image-up check's
/// 1500 at 900 px, because tracks across three or more photos need repeated keypoints.
pub const FEATURES: i32 = 4000;
pub const WORK_WIDTH: f64 = 1600.0;
/// Each photo is matched with at most this many overlapping photos, the nearest: matching
/// every overlapping pair grows with the square of the survey (1630 pairs, 77 s, for 58
/// rendered photos around one lake).
const NEIGHBOURS: usize = 12;
/// A pair links its photos with at least this many verified matches.
const MIN_INLIERS: usize = 15;
/// The fundamental matrix's inlier threshold at the working width, pixels.
const EPIPOLAR_PX: f64 = 1.5;
/// A sighting this many pixel SDs off after the first adjustment is dropped.
const OUTLIER_SDS: f64 = 5.0;

/// One photo to align: its frame number, features (full-resolution pixels) and tagged pose.
pub struct Photo {
    pub frame: u64,
    pub features: PhotoFeatures,
    pub pose: CameraPose,
}

/// Matched keypoints chained across photos.
#[derive(Clone, Debug, Default)]
pub struct TiePoints {
    /// (frame, track id, full-resolution pixel).
    pub sightings: Vec<(u64, u64, Pixel)>,
    /// Each track's starting point: where its rays meet the ground plane, averaged.
    pub points: Vec<LandmarkRecord>,
    /// Photo pairs that linked (verified matches).
    pub pairs_linked: usize,
}

/// One photo's correction: a rotation (rotation vector in local NED, radians, applied as
/// [`refine::corrected`]) and then a shift of its position (local NED, m).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Correction {
    pub rotation: Vec3,
    pub shift: Vec3,
}

impl Correction {
    pub fn apply(&self, pose: &CameraPose) -> CameraPose {
        let p = refine::corrected(pose, &self.rotation);
        CameraPose { position: p.position + self.shift, ..p }
    }
}

/// What an alignment found.
#[derive(Clone, Debug)]
pub struct Alignment {
    /// Per photo (frame): its correction.
    pub corrections: BTreeMap<u64, Correction>,
    /// The tie points kept (outliers dropped) and their adjusted positions.
    pub ties: TiePoints,
    /// Median reprojection error of the tie points' sightings with the tagged and the
    /// aligned attitudes, full-resolution pixels.
    pub median_before_px: f64,
    pub median_after_px: f64,
    /// Sightings dropped as outliers after the first adjustment.
    pub dropped: usize,
    /// Linked pairs dropped as false links.
    pub dropped_pairs: usize,
}

/// Centre of a photo's footprint on the plane `down` and the farthest its corners reach
/// from it (a corner above the horizon counts as three heights).
fn footprint(pose: &CameraPose, k: &Intrinsics, down: f64) -> Option<([f64; 2], f64)> {
    let centre = on_ground(pose, k, Pixel::new(k.cx, k.cy), down)?;
    let height = (down - pose.position.z).abs();
    let (w, h) = (k.width as f64 - 1.0, k.height as f64 - 1.0);
    let reach = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|&(u, v)| match on_ground(pose, k, Pixel::new(u, v), down) {
            Some(g) => (g[0] - centre[0]).hypot(g[1] - centre[1]).min(3.0 * height),
            None => 3.0 * height,
        })
        .fold(0.0, f64::max);
    Some((centre, reach))
}

/// A ratio-test match is kept only if the two tagged poses put it on the ground plane
/// within this many times what the attitude prior allows apart: `GATE` x tan(prior) x
/// the two photos' heights above the plane. Repeated ground fools the fundamental matrix:
/// over flat ground it is underdetermined (a homography and any epipole), so one pair's
/// matches can fit it twice over, and a ground that repeats turned half a turn (a tiled
/// texture mirrored both ways, rows of a field) links photos that never overlapped. On the
/// rendered three-line survey (`examples/tie_truth.rs`, poses 3 deg off) true matches
/// lay a median 0.7-12 m apart as tagged, false ones 35-68 m; the false links turned the
/// photos at one end of the block by 1.5-3 deg even from exact poses.
const GATE: f64 = 3.0;

/// Whether the tagged poses `a` and `b` put pixels `u` and `v` on the plane `down` within
/// the gate (above) of each other, the tags trusted to `gate_tan` (tangent of the prior).
fn on_same_ground(
    a: &CameraPose,
    b: &CameraPose,
    k: &Intrinsics,
    down: f64,
    gate_tan: f64,
    u: Pixel,
    v: Pixel,
) -> bool {
    let limit = GATE * gate_tan * ((down - a.position.z).abs() + (down - b.position.z).abs());
    match (on_ground(a, k, u, down), on_ground(b, k, v, down)) {
        (Some(ga), Some(gb)) => (ga[0] - gb[0]).hypot(ga[1] - gb[1]) <= limit,
        // A ray that misses the plane (an oblique camera's sky) cannot be gated here.
        _ => true,
    }
}

/// Verified matches of two photos, from their ratio-test matches `matched` (keypoint
/// indices in a, in b): those that the tagged poses put on the same ground within the
/// gate (above), and that fit one fundamental matrix.
fn verified(
    a: &Photo,
    b: &Photo,
    matched: Vec<(usize, usize)>,
    k: &Intrinsics,
    down: f64,
    gate_tan: f64,
    threshold_px: f64,
) -> opencv::Result<Vec<(usize, usize)>> {
    let (fa, fb) = (&a.features, &b.features);
    let m: Vec<(usize, usize)> = matched
        .into_iter()
        .filter(|&(i, j)| on_same_ground(&a.pose, &b.pose, k, down, gate_tan, fa.pixels()[i], fb.pixels()[j]))
        .collect();
    if m.len() < MIN_INLIERS {
        return Ok(Vec::new());
    }
    let pts = |f: &PhotoFeatures, pick: &dyn Fn(&(usize, usize)) -> usize| -> Vector<Point2f> {
        m.iter().map(|p| f.pixels()[pick(p)]).map(|p| Point2f::new(p.u as f32, p.v as f32)).collect()
    };
    let (pa, pb) = (pts(fa, &|p| p.0), pts(fb, &|p| p.1));
    let mut mask = Mat::default();
    let f =
        calib3d::find_fundamental_mat(&pa, &pb, calib3d::USAC_MAGSAC, threshold_px, 0.999, 2000, &mut mask)?;
    if f.empty() || mask.rows() as usize != m.len() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for (i, p) in m.iter().enumerate() {
        if *mask.at::<u8>(i as i32)? != 0 {
            out.push(*p);
        }
    }
    Ok(if out.len() >= MIN_INLIERS { out } else { Vec::new() })
}

fn find(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

/// The verified matches of one pair of photos (indices into the photo list).
#[derive(Clone, Debug)]
pub struct PairMatches {
    pub a: usize,
    pub b: usize,
    /// Keypoint indices (in a, in b).
    pub matches: Vec<(usize, usize)>,
}

/// Matches every pair of `photos` (poses and `k` at full resolution) whose footprints on
/// the plane `down` overlap, their attitude tags trusted to `prior_deg` (the gate above);
/// returns the pairs that linked and how many were tried.
pub fn match_pairs(
    photos: &[Photo],
    k: &Intrinsics,
    down: f64,
    prior_deg: f64,
) -> opencv::Result<(Vec<PairMatches>, usize)> {
    let gate_tan = prior_deg.to_radians().tan();
    let scale = (WORK_WIDTH / k.width as f64).min(1.0);
    let threshold = EPIPOLAR_PX / scale;
    let prints: Vec<_> = photos.iter().map(|p| footprint(&p.pose, k, down)).collect();
    // Each photo's overlapping neighbours, nearest footprint first; a pair is matched when
    // either photo has the other among its NEIGHBOURS nearest.
    let near = |i: usize| -> Vec<usize> {
        let Some((ca, ra)) = prints[i] else { return Vec::new() };
        let mut v: Vec<(f64, usize)> = (0..photos.len())
            .filter(|&j| j != i)
            .filter_map(|j| {
                let (cb, rb) = prints[j]?;
                let d = (ca[0] - cb[0]).hypot(ca[1] - cb[1]);
                // The tags may be degrees off: a fifth more reach than the footprints have.
                (d <= 1.2 * (ra + rb)).then_some((d, j))
            })
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v.into_iter().take(NEIGHBOURS).map(|(_, j)| j).collect()
    };
    let mut wanted = std::collections::BTreeSet::new();
    for i in 0..photos.len() {
        for j in near(i) {
            wanted.insert((i.min(j), i.max(j)));
        }
    }
    let tried = wanted.len();
    // The pairs grouped by their second photo, whose FLANN trees are built once for all
    // its pairs (building them is 40 % of a pair's matching); the groups in parallel. FLANN's trees and
    // MAGSAC draw from OpenCV's per-thread generator: seeded per photo and per pair, a
    // pair's matches do not depend on which thread ran what before.
    use rayon::prelude::*;
    let mut by_second: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for &(i, j) in &wanted {
        by_second.entry(j).or_default().push(i);
    }
    let groups: Vec<(usize, Vec<usize>)> = by_second.into_iter().collect();
    let verified: Vec<Vec<PairMatches>> = groups
        .par_iter()
        .map(|&(j, ref firsts)| {
            opencv::core::set_rng_seed(j as i32 * 7919 + 1)?;
            let mut index = imageup::FlannIndex::new(&photos[j].features)?;
            let mut out = Vec::new();
            for &i in firsts {
                opencv::core::set_rng_seed((i * 7919 + j) as i32 + 1)?;
                let matched = index.matched(&photos[i].features)?;
                let matches = verified(&photos[i], &photos[j], matched, k, down, gate_tan, threshold)?;
                if !matches.is_empty() {
                    out.push(PairMatches { a: i, b: j, matches });
                }
            }
            Ok(out)
        })
        .collect::<opencv::Result<_>>()?;
    let mut out: Vec<PairMatches> = verified.into_iter().flatten().collect();
    out.sort_by_key(|p| (p.a, p.b));
    Ok((out, tried))
}

/// Chains the pairs' matches into tracks; each starts where its rays meet the plane
/// `down`, averaged.
pub fn tracks(photos: &[Photo], pairs: &[PairMatches], k: &Intrinsics, down: f64) -> TiePoints {
    // Keypoint j of photo i is node offset[i] + j.
    let mut offset = Vec::with_capacity(photos.len());
    let mut nodes = 0;
    for p in photos {
        offset.push(nodes);
        nodes += p.features.pixels().len();
    }
    let mut parent: Vec<usize> = (0..nodes).collect();
    for p in pairs {
        for &(a, b) in &p.matches {
            let (x, y) = (find(&mut parent, offset[p.a] + a), find(&mut parent, offset[p.b] + b));
            parent[x] = y;
        }
    }
    let mut groups: BTreeMap<usize, Vec<(usize, usize)>> = BTreeMap::new();
    for (i, p) in photos.iter().enumerate() {
        for j in 0..p.features.pixels().len() {
            groups.entry(find(&mut parent, offset[i] + j)).or_default().push((i, j));
        }
    }
    let mut out = TiePoints { pairs_linked: pairs.len(), ..TiePoints::default() };
    for members in groups.values() {
        let mut seen_in: Vec<usize> = members.iter().map(|m| m.0).collect();
        seen_in.sort_unstable();
        seen_in.dedup();
        // A keypoint chain that meets one photo twice has joined two things.
        if seen_in.len() != members.len() || members.len() < 2 {
            continue;
        }
        let grounds: Vec<[f64; 2]> = members
            .iter()
            .filter_map(|&(i, j)| on_ground(&photos[i].pose, k, photos[i].features.pixels()[j], down))
            .collect();
        if grounds.is_empty() {
            continue;
        }
        let n = grounds.len() as f64;
        let start = Vec3::new(
            grounds.iter().map(|g| g[0]).sum::<f64>() / n,
            grounds.iter().map(|g| g[1]).sum::<f64>() / n,
            down,
        );
        let id = out.points.len() as u64;
        let frames: Vec<u64> = members.iter().map(|m| photos[m.0].frame).collect();
        out.points.push(LandmarkRecord {
            id,
            position: start,
            sigma_max_m: f64::NAN,
            observations: members.len() as u32,
            first_frame: *frames.iter().min().expect("a track has members"),
            last_frame: *frames.iter().max().expect("a track has members"),
        });
        for &(i, j) in members {
            out.sightings.push((photos[i].frame, id, photos[i].features.pixels()[j]));
        }
    }
    out
}

/// The median, NaN of nothing (a pair with no match left is then over any limit).
fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    super::residuals::quantile(&mut v, 0.5)
}

/// Reprojection error of each sighting (NaN where the point falls behind the camera).
fn errors(
    sightings: &[(u64, u64, Pixel)],
    points: &HashMap<u64, Vec3>,
    poses: &BTreeMap<u64, CameraPose>,
    k: &Intrinsics,
) -> Vec<f64> {
    sightings
        .iter()
        .map(|&(f, id, px)| match poses[&f].project(k, &points[&id]) {
            Some(p) => (p.u - px.u).hypot(p.v - px.v),
            None => f64::NAN,
        })
        .collect()
}

/// A linked pair whose matches reproject this many pixel SDs off (median) after an
/// adjustment is taken for a false link (repeated texture: rows of a field) and dropped.
const PAIR_REJECT_SDS: f64 = 3.0;
/// Rounds of adjusting and dropping false pairs.
const PAIR_ROUNDS: usize = 4;

/// Median over a pair's matches of the larger reprojection error of the point its two
/// rays meet at, with the poses `aligned`.
fn pair_fit(
    photos: &[Photo],
    p: &PairMatches,
    aligned: &BTreeMap<u64, CameraPose>,
    k: &Intrinsics,
    down: f64,
) -> f64 {
    let (pa, pb) = (&aligned[&photos[p.a].frame], &aligned[&photos[p.b].frame]);
    let e: Vec<f64> = p
        .matches
        .iter()
        .filter_map(|&(x, y)| {
            let (u, v) = (photos[p.a].features.pixels()[x], photos[p.b].features.pixels()[y]);
            let ga = on_ground(pa, k, u, down)?;
            let gb = on_ground(pb, k, v, down)?;
            let start = Vec3::new((ga[0] + gb[0]) / 2.0, (ga[1] + gb[1]) / 2.0, down);
            let rays = [
                Ray { origin: pa.position, dir: pa.direction(k, u) },
                Ray { origin: pb.position, dir: pb.direction(k, v) },
            ];
            let x = triangulate(&rays, &start, 1e-3, &[0.0; 3])?.position;
            let (ra, rb) = (pa.project(k, &x)?, pb.project(k, &x)?);
            Some((ra.u - u.u).hypot(ra.v - u.v).max((rb.u - v.u).hypot(rb.v - v.v)))
        })
        .collect();
    median(e)
}

/// Aligns the photos from the verified matches of their pairs: one rotation correction
/// per photo, the tags trusted to `prior_deg`. Pairs whose matches the adjustment cannot
/// explain are dropped, worst first, and the adjustment redone; then single sightings far
/// off. `None` when no two photos share a tie point.
pub fn align(
    photos: &[Photo],
    mut pairs: Vec<PairMatches>,
    k: &Intrinsics,
    down: f64,
    prior_deg: f64,
    shift_m: f64,
) -> Option<Alignment> {
    let poses: BTreeMap<u64, CameraPose> = photos.iter().map(|p| (p.frame, p.pose)).collect();
    // A SIFT keypoint is good to about a pixel at the width SIFT saw.
    let pixel_sd = 1.0 / (WORK_WIDTH / k.width as f64).min(1.0);
    // Tie points start on the ground plane, hundreds of pixels off: nothing is an outlier
    // before the first adjustment (they are dropped after it, below).
    let params = RefineParams {
        pixel_sd,
        shift_prior_m: shift_m,
        outlier_sds: f64::INFINITY,
        ..RefineParams::new(prior_deg)
    };
    let correction = |r: &refine::Refined, f: &u64| Correction {
        rotation: r.corrections[f],
        shift: r.shifts.get(f).copied().unwrap_or_default(),
    };
    let solved = |r: &refine::Refined| -> (HashMap<u64, Vec3>, BTreeMap<u64, CameraPose>) {
        let points = r.landmarks.iter().map(|l| (l.id, l.position)).collect();
        let aligned = poses.iter().map(|(f, p)| (*f, correction(r, f).apply(p))).collect();
        (points, aligned)
    };
    let mut dropped: Vec<PairMatches> = Vec::new();
    let (mut ties, mut result, mut before) = (TiePoints::default(), None, f64::NAN);
    for round in 0..PAIR_ROUNDS {
        let t = tracks(photos, &pairs, k, down);
        if t.points.is_empty() {
            return None;
        }
        if round == 0 {
            let start = t.points.iter().map(|l| (l.id, l.position)).collect();
            before = median(
                errors(&t.sightings, &start, &poses, k).into_iter().filter(|e| e.is_finite()).collect(),
            );
        }
        let r = refine::refine(&t.sightings, &t.points, &poses, k, &params);
        let (_, aligned) = solved(&r);
        let errs: Vec<f64> = pairs.iter().map(|p| pair_fit(photos, p, &aligned, k, down)).collect();
        ties = t;
        result = Some(r);
        let limit = PAIR_REJECT_SDS * pixel_sd;
        // A pair with no match left (NaN) counts as over the limit.
        let over = |e: f64| e.is_nan() || e > limit;
        let bad = errs.iter().filter(|e| over(**e)).count();
        if bad == 0 || round + 1 == PAIR_ROUNDS {
            break;
        }
        // Worst first: a false pair bends its neighbours too, so drop the worse half of
        // those over the limit and look again; a true pair dropped this way is taken
        // back below.
        let mut order: Vec<usize> = (0..pairs.len()).filter(|&i| over(errs[i])).collect();
        order.sort_by(|&x, &y| errs[y].total_cmp(&errs[x]));
        let drop: std::collections::HashSet<usize> = order.into_iter().take(bad.div_ceil(2)).collect();
        let (out, keep): (Vec<_>, Vec<_>) =
            pairs.into_iter().enumerate().partition(|(i, _)| drop.contains(i));
        dropped.extend(out.into_iter().map(|(_, p)| p));
        pairs = keep.into_iter().map(|(_, p)| p).collect();
    }
    // Take back the dropped pairs that fit the aligned poses: each match triangulated
    // from its two rays reprojects within the limit (median).
    if let Some(r) = &result {
        let (_, aligned) = solved(r);
        let limit = PAIR_REJECT_SDS * pixel_sd;
        let (back, out): (Vec<_>, Vec<_>) =
            dropped.into_iter().partition(|p| pair_fit(photos, p, &aligned, k, down) <= limit);
        if !back.is_empty() {
            pairs.extend(back);
            let t = tracks(photos, &pairs, k, down);
            result = Some(refine::refine(&t.sightings, &t.points, &poses, k, &params));
            ties = t;
        }
        dropped = out;
    }
    let first = result?;
    let (points, aligned) = solved(&first);
    // Drop single sightings the adjustment could not explain (a wrong match that passed
    // the epipolar test lies along its epipolar line), then adjust again from the tags.
    let err = errors(&ties.sightings, &points, &aligned, k);
    let kept: Vec<(u64, u64, Pixel)> = ties
        .sightings
        .iter()
        .zip(&err)
        .filter(|(_, e)| e.is_finite() && **e <= OUTLIER_SDS * pixel_sd)
        .map(|(s, _)| *s)
        .collect();
    let dropped_pairs = dropped.len();
    let dropped = ties.sightings.len() - kept.len();
    let mut count: HashMap<u64, usize> = HashMap::new();
    for s in &kept {
        *count.entry(s.1).or_default() += 1;
    }
    let sightings: Vec<_> = kept.into_iter().filter(|s| count[&s.1] >= 2).collect();
    let start: Vec<LandmarkRecord> =
        first.landmarks.iter().filter(|l| count.get(&l.id).is_some_and(|&c| c >= 2)).cloned().collect();
    if start.is_empty() {
        return None;
    }
    let second = refine::refine(&sightings, &start, &poses, k, &params);
    let (points, aligned) = solved(&second);
    let after =
        median(errors(&sightings, &points, &aligned, k).into_iter().filter(|e| e.is_finite()).collect());
    Some(Alignment {
        corrections: poses.keys().map(|f| (*f, correction(&second, f))).collect(),
        ties: TiePoints { sightings, points: second.landmarks, pairs_linked: pairs.len() },
        median_before_px: before,
        median_after_px: after,
        dropped,
        dropped_pairs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::area::crosslines;
    use crate::geometry::{GimbalAngles, GimbalChain, Mount, Rot3};

    fn nadir(north: f64, east: f64, yaw_deg: f64) -> CameraPose {
        let a = GimbalAngles { yaw: yaw_deg.to_radians(), pitch: -90f64.to_radians(), roll: 0.0 };
        CameraPose::from_gimbal(Vec3::new(north, east, -70.0), GimbalChain::YawPitchRoll, a, Mount::Earth)
    }

    /// The match gate keeps every true match of a survey whose tags are up to 8 deg off
    /// (trusted to 5 deg) and drops every match between photos that never overlapped
    /// (ground repeated half a turn: pixel (u, v) of one photo matched to (2 cx - u,
    /// 2 cy - v) of another, as rotation-invariant SIFT matches a point-mirrored copy).
    #[test]
    fn the_match_gate_keeps_what_the_tags_allow_and_drops_ground_seen_elsewhere() {
        let (k, _, tagged, photos, pairs, linked) = survey(0.3);
        let tan = 5f64.to_radians().tan();
        let mut kept = 0;
        for p in &pairs[..linked] {
            for &(x, y) in &p.matches {
                let (u, v) = (photos[p.a].features.pixels()[x], photos[p.b].features.pixels()[y]);
                assert!(
                    on_same_ground(&tagged[p.a], &tagged[p.b], &k, 0.0, tan, u, v),
                    "pair {}-{}",
                    p.a,
                    p.b
                );
                kept += 1;
            }
        }
        assert!(kept > 1000, "{kept} true matches");
        // Line 0's first photo and line 2's last: 90 m across and 100 m along apart.
        let (a, b) = (0, 17);
        let twins: Vec<_> = photos[a]
            .features
            .pixels()
            .iter()
            .map(|u| (*u, Pixel::new(2.0 * k.cx - u.u, 2.0 * k.cy - u.v)))
            .collect();
        assert!(twins.len() > 100);
        for (u, v) in twins {
            assert!(!on_same_ground(&tagged[a], &tagged[b], &k, 0.0, tan, u, v), "{u:?} - {v:?}");
        }
    }

    /// A survey the tie points see exactly: three lines of nadir photos 70 m up (the middle
    /// one flown back) over uneven ground, each photo's attitude tagged up to 8 degrees off
    /// and its position `position_err_m` off in each axis (at most), and two pairs linked
    /// by false matches (repeated texture). The truth, the tagged poses, the photos, the
    /// pairs and how many of them are true.
    #[allow(clippy::type_complexity)]
    fn survey(
        position_err_m: f64,
    ) -> (Intrinsics, Vec<CameraPose>, Vec<CameraPose>, Vec<Photo>, Vec<PairMatches>, usize) {
        let k = Intrinsics { width: 1200, height: 900, fx: 900.0, fy: 900.0, cx: 599.5, cy: 449.5 };
        let mut truth = Vec::new();
        let mut tagged = Vec::new();
        let mut rng = 7u64;
        let mut noise = || {
            // xorshift: a fixed draw, -1..1.
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng % 20001) as f64 / 10000.0 - 1.0
        };
        for (line, east) in [0.0, 45.0, 90.0].into_iter().enumerate() {
            for i in 0..6 {
                let (north, yaw) =
                    if line == 1 { (100.0 - i as f64 * 20.0, 180.0) } else { (i as f64 * 20.0, 0.0) };
                let pose = nadir(north, east, yaw);
                let err = Vec3::new(noise(), noise(), noise()) * 8f64.to_radians() / 3f64.sqrt();
                let moved = if position_err_m > 0.0 {
                    Vec3::new(noise(), noise(), noise()) * position_err_m
                } else {
                    Vec3::zeros()
                };
                truth.push(pose);
                tagged.push(CameraPose {
                    attitude: Rot3::new(-err) * pose.attitude,
                    position: pose.position + moved,
                });
            }
        }
        // Ground points on a 5 m grid, heights up to 4 m: each photo's keypoints are the
        // points in its view, and every pair of photos matches what both see.
        let mut pixels: Vec<Vec<Pixel>> = vec![Vec::new(); truth.len()];
        let mut index: Vec<HashMap<usize, usize>> = vec![HashMap::new(); truth.len()];
        let mut g = 0;
        for gn in -30..=26 {
            for ge in -12..=21 {
                let p =
                    Vec3::new(gn as f64 * 5.0, ge as f64 * 5.0, -4.0 * ((gn * 7 + ge * 3) % 5) as f64 / 4.0);
                for (i, pose) in truth.iter().enumerate() {
                    if let Some(px) = pose
                        .project(&k, &p)
                        .filter(|px| px.u >= 0.0 && px.v >= 0.0 && px.u < 1200.0 && px.v < 900.0)
                    {
                        index[i].insert(g, pixels[i].len());
                        pixels[i].push(px);
                    }
                }
                g += 1;
            }
        }
        let mut pairs = Vec::new();
        for a in 0..truth.len() {
            for b in a + 1..truth.len() {
                let mut matches: Vec<(usize, usize)> =
                    index[a].iter().filter_map(|(g, &x)| Some((x, *index[b].get(g)?))).collect();
                matches.sort_unstable();
                if matches.len() >= MIN_INLIERS {
                    pairs.push(PairMatches { a, b, matches });
                }
            }
        }
        let linked = pairs.len();
        // False links: photo 2 to photo 15 and photo 8 to photo 16, keypoints paired
        // by index (they see different ground).
        for (a, b) in [(2, 15), (8, 16)] {
            let n = pixels[a].len().min(pixels[b].len()).min(60);
            pairs.push(PairMatches { a, b, matches: (0..n).map(|i| (i, i)).collect() });
        }
        let photos: Vec<Photo> = tagged
            .iter()
            .zip(pixels)
            .enumerate()
            .map(|(i, (pose, px))| Photo {
                frame: i as u64,
                features: PhotoFeatures::from_pixels(px),
                pose: *pose,
            })
            .collect();
        (k, truth, tagged, photos, pairs, linked)
    }

    /// Three lines of nadir photos (the middle one flown back) over uneven ground, each
    /// photo's attitude tagged up to 8 degrees off, and two pairs linked by false matches
    /// (repeated texture): the false pairs are dropped, every photo's error is found, and
    /// the lines, which disagree by metres as tagged, agree after alignment.
    #[test]
    fn tie_points_recover_each_photos_attitude_error_and_the_lines_agree() {
        let (k, truth, tagged, photos, pairs, linked) = survey(0.0);
        let a = align(&photos, pairs, &k, 0.0, 10.0, 0.0).expect("tie points");
        assert_eq!(a.dropped_pairs, 2, "the two false links");
        assert_eq!(a.ties.pairs_linked, linked);
        for (f, pose) in truth.iter().enumerate() {
            let got = a.corrections[&(f as u64)].apply(&tagged[f]);
            let off = (got.attitude * pose.attitude.inverse()).angle().to_degrees();
            assert!(off < 0.05, "frame {f}: {off:.3} deg from the truth");
        }
        assert!(a.median_after_px < 1e-3, "exact sightings reproject: {}", a.median_after_px);
        assert!(a.median_before_px > 20.0, "tagged attitudes: {}", a.median_before_px);
        let tagged: BTreeMap<u64, CameraPose> = photos.iter().map(|p| (p.frame, p.pose)).collect();
        let lines = crosslines::flight_lines(&tagged.iter().map(|(f, p)| (*f, p.position)).collect());
        assert_eq!(lines.values().max(), Some(&2));
        let start: BTreeMap<u64, Vec3> = a.ties.points.iter().map(|l| (l.id, l.position)).collect();
        let aligned: BTreeMap<u64, CameraPose> =
            tagged.iter().map(|(f, p)| (*f, a.corrections[f].apply(p))).collect();
        let m = |poses| median(crosslines::disagreement(&a.ties.sightings, poses, &k, &lines, &start, 1e-3));
        let (before, after) = (m(&tagged), m(&aligned));
        assert!(before > 2.0 && after < 0.01, "lines apart by {before:.2} m as tagged, {after:.4} m aligned");
    }

    /// Over flat ground a photo turned by an angle and one moved by its height times
    /// that angle see nearly the same image, so the shift prior, not the tie points,
    /// decides between them. Positions good to 0.5 m in each axis, attitudes up to 8 deg
    /// off, ground with 4 m of relief (which tells them apart a little): with the shift
    /// prior at the positions' noise the photos are found within 0.2 m and 0.25 deg
    /// (median); with 5 m they keep three times the attitude error (0.38 m, 0.79 deg).
    #[test]
    fn the_shift_prior_keeps_photos_from_moving_where_they_turned() {
        let (k, truth, tagged, photos, pairs, _) = survey(0.5);
        let found = |shift_m: f64| {
            let a = align(&photos, pairs.clone(), &k, 0.0, 10.0, shift_m).expect("tie points");
            let (mut moved, mut turned): (Vec<f64>, Vec<f64>) = truth
                .iter()
                .enumerate()
                .map(|(f, pose)| {
                    let got = a.corrections[&(f as u64)].apply(&tagged[f]);
                    (
                        (got.position - pose.position).norm(),
                        (got.attitude * pose.attitude.inverse()).angle().to_degrees(),
                    )
                })
                .unzip();
            (median(std::mem::take(&mut moved)), median(std::mem::take(&mut turned)))
        };
        let (tight_m, tight_deg) = found(0.5);
        let (loose_m, loose_deg) = found(5.0);
        println!("shift prior 0.5 m: photos {tight_m:.2} m, {tight_deg:.2} deg from the truth; 5 m: {loose_m:.2} m, {loose_deg:.2} deg");
        assert!(tight_m < 0.3 && tight_deg < 0.4, "{tight_m:.2} m, {tight_deg:.2} deg");
        assert!(
            loose_deg > 2.0 * tight_deg && loose_m > tight_m,
            "the failure this guards against: {loose_deg:.2} deg and {loose_m:.2} m against {tight_deg:.2} deg and {tight_m:.2} m"
        );
    }
}
