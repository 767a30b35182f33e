//! Which way up is each photo? Overlapping photos must see the same ground where their
//! poses say they do. For each pair of consecutive photos, SIFT matches are projected
//! through both tagged poses onto the ground plane: with the right poses a match lands on
//! one spot from both photos (metres apart at most, from attitude and height errors);
//! with one photo turned half a turn about its optical axis (a reverse line whose
//! recorded yaw is 180 degrees off, area issue evidence: 177-179 degrees on a DJI
//! survey's middle line) the two spots are two baselines apart. Each pair votes for the
//! combination of "as tagged" and "turned" that makes its spots agree best, and a photo
//! is turned if most of its pairs say so. This runs before any landmark exists, so a
//! reverse line is found even when nothing would converge on it.
//!
//! Turning an image half a turn about its optical axis maps pixel (u, v) to
//! (2 cx - u, 2 cy - v); for a nadir camera that is its yaw + 180 degrees.

use opencv::core::{self, Mat, Vector};
use opencv::features2d::{BFMatcher, FlannBasedMatcher, SIFT};
use opencv::imgproc;
use opencv::prelude::*;

use crate::geometry::{CameraPose, Intrinsics, Pixel};

/// Features per photo, at about `WORK_WIDTH` pixels wide.
const FEATURES: i32 = 1500;
const WORK_WIDTH: f64 = 900.0;
/// A pair with fewer ratio-test matches than this does not vote.
const MIN_MATCHES: usize = 20;

/// One photo's keypoints (full-resolution pixels) and descriptors.
pub struct PhotoFeatures {
    pixels: Vec<Pixel>,
    descriptors: Mat,
}

/// SIFT on a downscaled grey copy; pixels in full-resolution coordinates.
pub fn features(bgr: &Mat) -> opencv::Result<PhotoFeatures> {
    features_sized(bgr, FEATURES, WORK_WIDTH)
}

/// The `imread` flags for JPEG's scaled decoding (1/2, 1/4 or 1/8 of each side, done in
/// its DCT) that still give at least the features' width from a photo `full_width` pixels
/// wide, and that factor: a 12 MP photo decoded at a quarter is several times quicker to
/// read than decoded whole and resized (the README, "Which way up").
pub fn reduced_read(full_width: u32) -> (i32, u32) {
    use opencv::imgcodecs::{
        IMREAD_COLOR, IMREAD_REDUCED_COLOR_2, IMREAD_REDUCED_COLOR_4, IMREAD_REDUCED_COLOR_8,
    };
    [(IMREAD_REDUCED_COLOR_8, 8), (IMREAD_REDUCED_COLOR_4, 4), (IMREAD_REDUCED_COLOR_2, 2)]
        .into_iter()
        .find(|&(_, f)| full_width as f64 / f as f64 >= WORK_WIDTH)
        .unwrap_or((IMREAD_COLOR, 1))
}

/// [`features`] of a photo of `full` (width, height) pixels decoded at `1 / factor` of
/// each side ([`reduced_read`]), its pixels in the photo's full resolution: libjpeg makes
/// the decoded image `ceil(full / factor)` wide and high, its pixel `i` the mean of the
/// photo's pixels `factor i .. factor (i + 1)`, so its centre is `(i + 0.5) factor - 0.5`.
/// `None` when the decoded image is not that size (an EXIF orientation turned it, or it is
/// no JPEG): read it whole then.
pub fn features_of_reduced(
    bgr: &Mat,
    full: (u32, u32),
    factor: u32,
) -> opencv::Result<Option<PhotoFeatures>> {
    let expected = (full.0.div_ceil(factor) as i32, full.1.div_ceil(factor) as i32);
    if (bgr.cols(), bgr.rows()) != expected {
        return Ok(None);
    }
    let mut f = features(bgr)?;
    let s = factor as f64;
    for p in &mut f.pixels {
        *p = Pixel::new((p.u + 0.5) * s - 0.5, (p.v + 0.5) * s - 0.5);
    }
    Ok(Some(f))
}

/// [`features`] with `count` keypoints on a copy `width` pixels wide (never enlarged).
pub fn features_sized(bgr: &Mat, count: i32, width: f64) -> opencv::Result<PhotoFeatures> {
    let mut grey = Mat::default();
    imgproc::cvt_color(bgr, &mut grey, imgproc::COLOR_BGR2GRAY, 0)?;
    let scale = (width / grey.cols() as f64).min(1.0);
    let mut small = Mat::default();
    imgproc::resize(&grey, &mut small, core::Size::new(0, 0), scale, scale, imgproc::INTER_AREA)?;
    let mut sift = SIFT::create(count, 3, 0.04, 10.0, 1.6)?;
    let mut keypoints = Vector::new();
    let mut descriptors = Mat::default();
    sift.detect_and_compute(&small, &core::no_array(), &mut keypoints, &mut descriptors, false)?;
    let pixels = keypoints
        .iter()
        .map(|k| Pixel::new((k.pt().x as f64 + 0.5) / scale - 0.5, (k.pt().y as f64 + 0.5) / scale - 0.5))
        .collect();
    Ok(PhotoFeatures { pixels, descriptors })
}

impl PhotoFeatures {
    /// The keypoints, full-resolution pixels.
    pub fn pixels(&self) -> &[Pixel] {
        &self.pixels
    }

    /// Keypoints without descriptors (tests that give the matches themselves).
    #[cfg(test)]
    pub fn from_pixels(pixels: Vec<Pixel>) -> PhotoFeatures {
        PhotoFeatures { pixels, descriptors: Mat::default() }
    }
}

/// Pixel pairs (a, b) of ratio-test matches.
fn matches(a: &PhotoFeatures, b: &PhotoFeatures) -> opencv::Result<Vec<(Pixel, Pixel)>> {
    Ok(matched(a, b)?.into_iter().map(|(i, j)| (a.pixels[i], b.pixels[j])).collect())
}

/// Keypoint index pairs (in a, in b) of ratio-test matches (Lowe's 0.75), exhaustive.
pub fn matched(a: &PhotoFeatures, b: &PhotoFeatures) -> opencv::Result<Vec<(usize, usize)>> {
    if a.pixels.len() < 2 || b.pixels.len() < 2 {
        return Ok(Vec::new());
    }
    let matcher = BFMatcher::create(core::NORM_L2, false)?;
    let mut knn = Vector::<Vector<core::DMatch>>::new();
    matcher.knn_train_match(&a.descriptors, &b.descriptors, &mut knn, 2, &core::no_array(), false)?;
    ratio_test(&knn)
}

/// One photo's descriptors in FLANN's randomised k-d trees (OpenCV's defaults), built once
/// and matched against every overlapping photo ([`FlannIndex::matched`]): building the
/// trees is 40 % of a pair's matching (42 of 107 ms for two DJI photos, `benches/area.rs`,
/// area_align_*), and a survey photo is in up to a dozen pairs.
pub struct FlannIndex {
    matcher: FlannBasedMatcher,
    len: usize,
}

impl FlannIndex {
    /// Indexes `f`'s descriptors. The trees draw from OpenCV's per-thread generator:
    /// seed it first for the same trees on every run.
    pub fn new(f: &PhotoFeatures) -> opencv::Result<FlannIndex> {
        let mut matcher = FlannBasedMatcher::new_def()?;
        if f.pixels.len() >= 2 {
            use opencv::features2d::FlannBasedMatcherTrait;
            FlannBasedMatcherTrait::add(&mut matcher, &Vector::<Mat>::from_iter([f.descriptors.clone()]))?;
            FlannBasedMatcherTrait::train(&mut matcher)?;
        }
        Ok(FlannIndex { matcher, len: f.pixels.len() })
    }

    /// Keypoint index pairs (in `a`, in the indexed photo) of ratio-test matches (Lowe's
    /// 0.75), through the trees: approximate nearest neighbours, where [`matched`] is
    /// exhaustive (4000 keypoints a photo: 62 ms a query of built trees, 254 ms
    /// exhaustive, the same bench).
    pub fn matched(&mut self, a: &PhotoFeatures) -> opencv::Result<Vec<(usize, usize)>> {
        if a.pixels.len() < 2 || self.len < 2 {
            return Ok(Vec::new());
        }
        let mut knn = Vector::<Vector<core::DMatch>>::new();
        self.matcher.knn_match(&a.descriptors, &mut knn, 2, &core::no_array(), false)?;
        ratio_test(&knn)
    }
}

fn ratio_test(knn: &Vector<Vector<core::DMatch>>) -> opencv::Result<Vec<(usize, usize)>> {
    let mut out = Vec::new();
    for pair in knn.iter() {
        if pair.len() == 2 {
            let (m1, m2) = (pair.get(0)?, pair.get(1)?);
            if m1.distance < 0.75 * m2.distance {
                out.push((m1.query_idx as usize, m1.train_idx as usize));
            }
        }
    }
    Ok(out)
}

/// Where a pixel's ray meets the horizontal plane `down`, if it does (north, east).
pub fn on_ground(pose: &CameraPose, k: &Intrinsics, px: Pixel, down: f64) -> Option<[f64; 2]> {
    let d = pose.direction(k, px);
    let t = (down - pose.position.z) / d.z;
    (d.z > 1e-3 && t > 0.0).then(|| [pose.position.x + t * d.x, pose.position.y + t * d.y])
}

/// The pixel seen by a camera turned half a turn about its optical axis.
fn turned(k: &Intrinsics, px: Pixel) -> Pixel {
    Pixel::new(2.0 * k.cx - px.u, 2.0 * k.cy - px.v)
}

/// One consecutive pair's vote.
#[derive(Clone, Debug, PartialEq)]
pub struct PairVote {
    pub a: usize,
    pub b: usize,
    pub matches: usize,
    /// Median ground disagreement (m) for (a turned?, b turned?) = (no,no), (no,yes),
    /// (yes,no), (yes,yes).
    pub median_m: [f64; 4],
}

impl PairVote {
    /// The best combination, (a turned, b turned), if it is clearly the best: its
    /// disagreement under half the next best's (a pair whose poses are poor for every
    /// combination does not vote).
    pub fn best(&self) -> Option<(bool, bool)> {
        let mut order = [0usize, 1, 2, 3];
        order.sort_by(|&x, &y| self.median_m[x].total_cmp(&self.median_m[y]));
        let (i, next) = (order[0], order[1]);
        (self.median_m[i] < 0.5 * self.median_m[next]).then_some((i >= 2, i % 2 == 1))
    }
}

/// The vote of photos `a` and `b` (indices into the caller's list).
pub fn vote(
    a: (usize, &PhotoFeatures, &CameraPose),
    b: (usize, &PhotoFeatures, &CameraPose),
    k: &Intrinsics,
    ground_down: f64,
) -> opencv::Result<Option<PairVote>> {
    let pairs = matches(a.1, b.1)?;
    if pairs.len() < MIN_MATCHES {
        return Ok(None);
    }
    let mut median_m = [f64::INFINITY; 4];
    for (i, (ta, tb)) in [(false, false), (false, true), (true, false), (true, true)].into_iter().enumerate()
    {
        let mut d: Vec<f64> = pairs
            .iter()
            .filter_map(|&(pa, pb)| {
                let pa = if ta { turned(k, pa) } else { pa };
                let pb = if tb { turned(k, pb) } else { pb };
                let ga = on_ground(a.2, k, pa, ground_down)?;
                let gb = on_ground(b.2, k, pb, ground_down)?;
                Some((ga[0] - gb[0]).hypot(ga[1] - gb[1]))
            })
            .collect();
        if d.len() >= MIN_MATCHES {
            d.sort_by(f64::total_cmp);
            median_m[i] = d[d.len() / 2];
        }
    }
    Ok(Some(PairVote { a: a.0, b: b.0, matches: pairs.len(), median_m }))
}

/// Per photo: turned or not, from the votes of its pairs (a photo no pair voted on is
/// left as tagged).
pub fn verdicts(count: usize, votes: &[PairVote]) -> Vec<bool> {
    let mut tally = vec![(0u32, 0u32); count];
    for v in votes {
        let Some((ta, tb)) = v.best() else { continue };
        for (i, t) in [(v.a, ta), (v.b, tb)] {
            if t {
                tally[i].0 += 1;
            } else {
                tally[i].1 += 1;
            }
        }
    }
    tally.iter().map(|&(turned, kept)| turned > kept).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{GimbalAngles, GimbalChain, Mount, Vec3};

    fn nadir(north: f64, yaw_deg: f64) -> CameraPose {
        let angles = GimbalAngles { yaw: yaw_deg.to_radians(), pitch: -90f64.to_radians(), roll: 0.0 };
        CameraPose::from_gimbal(Vec3::new(north, 0.0, -60.0), GimbalChain::YawPitchRoll, angles, Mount::Earth)
    }

    /// A photo decoded at a quarter (just under 4000 px wide: 1000, the first scale at least
    /// the features' 900 px) gives its keypoints where the whole photo's are: the same
    /// ground matched in both lies within a pixel of the full photo. The photo is 3997 px
    /// wide, so its quarter is 1000 px, not 3997 / 4: a scale taken from the sizes, or a
    /// half-pixel slip, puts them 1.5-3 px apart. A decode of another size (a turned photo)
    /// is declined.
    #[test]
    fn features_of_a_reduced_decode_are_in_the_photos_full_pixels() {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dji-sample/DJI_0030.JPG");
        assert_eq!(reduced_read(4000), (opencv::imgcodecs::IMREAD_REDUCED_COLOR_4, 4));
        assert_eq!(reduced_read(1600), (opencv::imgcodecs::IMREAD_COLOR, 1));
        let photo = crate::imaging::read_image(&path, opencv::imgcodecs::IMREAD_COLOR).unwrap();
        let whole = Mat::roi(&photo, core::Rect::new(0, 0, 3997, 2250)).unwrap().try_clone().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let cut = dir.path().join("cut.jpg");
        let quality = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 95]);
        assert!(opencv::imgcodecs::imwrite(cut.to_str().unwrap(), &whole, &quality).unwrap());
        let whole = crate::imaging::read_image(&cut, opencv::imgcodecs::IMREAD_COLOR).unwrap();
        let (flags, factor) = reduced_read(3997);
        let small = crate::imaging::read_image(&cut, flags).unwrap();
        assert_eq!((small.cols(), small.rows(), factor), (1000, 563, 4));
        let a = features(&whole).unwrap();
        let b = features_of_reduced(&small, (3997, 2250), factor).unwrap().expect("the expected size");
        let pairs = matched(&a, &b).unwrap();
        assert!(pairs.len() > 300, "{} matches", pairs.len());
        let mut d: Vec<f64> = pairs
            .iter()
            .map(|&(i, j)| (a.pixels[i].u - b.pixels[j].u).hypot(a.pixels[i].v - b.pixels[j].v))
            .collect();
        d.sort_by(f64::total_cmp);
        let median = d[d.len() / 2];
        println!("{} matches, {median:.2} px apart (median) at full resolution", pairs.len());
        assert!(median < 1.0, "matched keypoints {median:.2} px apart at full resolution");
        // Turned by EXIF, the decode is high where it should be wide.
        assert!(features_of_reduced(&small, (2250, 3997), factor).unwrap().is_none());
    }

    /// Ground points seen from two nadir photos 30 m apart agree as tagged, and a photo
    /// whose yaw is recorded half a turn off is found.
    #[test]
    fn a_photo_tagged_half_a_turn_off_is_found_by_its_overlap() {
        let k = Intrinsics { width: 1000, height: 750, fx: 1000.0, fy: 1000.0, cx: 499.5, cy: 374.5 };
        let (a, b) = (nadir(0.0, 30.0), nadir(30.0, 30.0));
        let ground: Vec<Vec3> = (0..60)
            .map(|i| Vec3::new(15.0 + (i % 10) as f64 * 2.0 - 9.0, (i / 10) as f64 * 4.0 - 10.0, 0.0))
            .collect();
        let project = |pose: &CameraPose, p: &Vec3| pose.project(&k, p).expect("in view");
        let fa = |pose: &CameraPose| ground.iter().map(|p| project(pose, p)).collect::<Vec<_>>();
        let (pa, pb) = (fa(&a), fa(&b));
        // The vote's arithmetic on these exact matches, as tagged and with b's yaw off.
        let score = |pose_b: &CameraPose| -> [f64; 4] {
            let mut m = [0.0; 4];
            for (i, (ta, tb)) in
                [(false, false), (false, true), (true, false), (true, true)].into_iter().enumerate()
            {
                let mut d: Vec<f64> = pa
                    .iter()
                    .zip(&pb)
                    .filter_map(|(&x, &y)| {
                        let x = if ta { turned(&k, x) } else { x };
                        let y = if tb { turned(&k, y) } else { y };
                        let ga = on_ground(&a, &k, x, 0.0)?;
                        let gb = on_ground(pose_b, &k, y, 0.0)?;
                        Some((ga[0] - gb[0]).hypot(ga[1] - gb[1]))
                    })
                    .collect();
                d.sort_by(f64::total_cmp);
                m[i] = d[d.len() / 2];
            }
            m
        };
        let right = PairVote { a: 0, b: 1, matches: 60, median_m: score(&b) };
        assert_eq!(right.best(), Some((false, false)), "{right:?}");
        assert!(right.median_m[0] < 1e-6);
        let wrong = PairVote { a: 0, b: 1, matches: 60, median_m: score(&nadir(30.0, 210.0)) };
        assert_eq!(wrong.best(), Some((false, true)), "{wrong:?}");
        let unsure = PairVote { a: 0, b: 1, matches: 60, median_m: [19.5, 54.6, 71.5, 18.2] };
        assert_eq!(unsure.best(), None, "two combinations alike: no vote");
        assert_eq!(
            verdicts(3, &[wrong, PairVote { a: 1, b: 2, matches: 60, median_m: [9.0, 9.0, 0.1, 9.0] }]),
            [false, true, false]
        );
    }
}
