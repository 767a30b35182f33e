//! Target masks for real images: the area pipeline needs, per frame, the pixels of the
//! target area (the seed took them from AirSim's segmentation, sec. 4.2.3). Chosen by
//! `area.segmenter`:
//!
//! - `masks`: the dataset's `masks/NNNNNN.png` (rendered, or made by another tool);
//! - `water`: open water: smooth (low local contrast) and neither vegetation-green nor
//!   light and colourless (sand, foam, paving), by per-image thresholds (Otsu) rather than fixed ones, so a dark lake
//!   and a bright sea both work; not a cast shadow ([`super::shadow`]: told apart by its
//!   edges); then morphological clean-up and only large regions kept;
//! - `hsv`: pixels inside the configured HSV box (`area.hsv_low`, `area.hsv_high`, OpenCV
//!   ranges H 0-180, S and V 0-255), for other colour-distinct areas (a burn scar, a
//!   flood's brown water), with the same clean-up;
//! - `learned` (offline): a classifier of colour and local contrast trained on the masks
//!   the user made for a few frames of the dataset ([`Learned`]), for a target the rules
//!   get wrong (a shadow the water rule takes for water), with the same clean-up.
//!
//! Segmentation runs at most 800 px wide (masks are smooth; the clean-up kernels are in
//! those pixels) and the mask is scaled back to the frame.

use opencv::core::{self, Mat, Point, Scalar, Size, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

use crate::settings::{Area as AreaSettings, Segmenter};

const WORK_WIDTH: i32 = 800;
/// Regions smaller than this fraction of the image are dropped (glints, puddles, roofs).
const MIN_REGION_FRACTION: f64 = 0.01;

fn kernel(size: i32) -> opencv::Result<Mat> {
    imgproc::get_structuring_element(imgproc::MORPH_ELLIPSE, Size::new(size, size), Point::new(-1, -1))
}

pub(super) fn morph(src: &Mat, op: i32, size: i32) -> opencv::Result<Mat> {
    let mut out = Mat::default();
    imgproc::morphology_ex(
        src,
        &mut out,
        op,
        &kernel(size)?,
        Point::new(-1, -1),
        1,
        core::BORDER_REPLICATE,
        imgproc::morphology_default_border_value()?,
    )?;
    Ok(out)
}

/// Outer outlines of a mask's regions (holes not traced).
fn outlines(mask: &Mat) -> opencv::Result<Vector<Vector<Point>>> {
    let mut contours = Vector::new();
    imgproc::find_contours(
        mask,
        &mut contours,
        imgproc::RETR_EXTERNAL,
        imgproc::CHAIN_APPROX_SIMPLE,
        Point::new(0, 0),
    )?;
    Ok(contours)
}

/// Opening and closing, then only regions of at least MIN_REGION_FRACTION of the image,
/// with their holes filled.
fn clean(raw: &Mat) -> opencv::Result<Mat> {
    let m = morph(raw, imgproc::MORPH_OPEN, 7)?;
    let m = morph(&m, imgproc::MORPH_CLOSE, 15)?;
    let contours = outlines(&m)?;
    let min_area = MIN_REGION_FRACTION * (m.rows() * m.cols()) as f64;
    let mut keep: Vector<Vector<Point>> = Vector::new();
    for c in contours.iter() {
        if imgproc::contour_area(&c, false)? >= min_area {
            keep.push(c);
        }
    }
    filled(&keep, m.rows(), m.cols())
}

/// A `rows` x `cols` mask, 255 inside the outlines (holes filled).
pub(super) fn filled(outlines: &Vector<Vector<Point>>, rows: i32, cols: i32) -> opencv::Result<Mat> {
    let mut out = Mat::zeros(rows, cols, core::CV_8UC1)?.to_mat()?;
    imgproc::draw_contours(
        &mut out,
        outlines,
        -1,
        Scalar::all(255.0),
        imgproc::FILLED,
        imgproc::LINE_8,
        &core::no_array(),
        i32::MAX,
        Point::new(0, 0),
    )?;
    Ok(out)
}

/// Otsu threshold of an 8-bit image.
fn otsu(img: &Mat) -> opencv::Result<f64> {
    let mut dummy = Mat::default();
    imgproc::threshold(img, &mut dummy, 0.0, 255.0, imgproc::THRESH_BINARY | imgproc::THRESH_OTSU)
}

/// Local contrast: mean absolute Laplacian over a 15 px window, 8-bit.
fn texture(grey: &Mat) -> opencv::Result<Mat> {
    let mut lap = Mat::default();
    imgproc::laplacian(grey, &mut lap, core::CV_16S, 3, 1.0, 0.0, core::BORDER_REPLICATE)?;
    let mut abs = Mat::default();
    core::convert_scale_abs(&lap, &mut abs, 1.0, 0.0)?;
    let mut t = Mat::default();
    imgproc::blur(&abs, &mut t, Size::new(15, 15), Point::new(-1, -1), core::BORDER_REPLICATE)?;
    Ok(t)
}

/// Pixels of an HSV image inside the box `low` ..= `high`.
fn hsv_in(hsv: &Mat, low: [f64; 3], high: [f64; 3]) -> opencv::Result<Mat> {
    let mut out = Mat::default();
    let (l, h) = (Scalar::new(low[0], low[1], low[2], 0.0), Scalar::new(high[0], high[1], high[2], 0.0));
    core::in_range(hsv, &l, &h, &mut out)?;
    Ok(out)
}

fn water(small: &Mat) -> opencv::Result<Mat> {
    let candidate = smooth_dark_not_land(small)?;
    // A shadow on paving is as smooth, dark and blue as water; it is told apart by its
    // edges (a change of light, not of material). Grown a little so the shadow's soft
    // rim (penumbra) goes with it.
    let shade = morph(&super::shadow::cast_shadows(small)?, imgproc::MORPH_DILATE, 9)?;
    let mut raw = Mat::default();
    core::subtract(&candidate, &shade, &mut raw, &core::no_array(), -1)?;
    clean(&raw)
}

/// The water rule's pixels before shadows are taken out.
fn smooth_dark_not_land(small: &Mat) -> opencv::Result<Mat> {
    let mut grey = Mat::default();
    imgproc::cvt_color(small, &mut grey, imgproc::COLOR_BGR2GRAY, 0)?;
    let tex = texture(&grey)?;
    // Smooth: below the image's own Otsu split of local contrast (at most a fixed
    // ceiling, so an all-water frame does not split its ripples in two).
    let t = otsu(&tex)?.min(40.0);
    let mut smooth = Mat::default();
    imgproc::threshold(&tex, &mut smooth, t, 255.0, imgproc::THRESH_BINARY_INV)?;
    // Not vegetation (green hue with some saturation).
    let mut hsv = Mat::default();
    imgproc::cvt_color(small, &mut hsv, imgproc::COLOR_BGR2HSV, 0)?;
    let veg = hsv_in(&hsv, [30.0, 60.0, 20.0], [85.0, 255.0, 255.0])?;
    // Light and colourless: sand, foam, and paving (roads, paths and roofs are as smooth
    // as water from the air, but brighter and greyer than open water).
    let bright = hsv_in(&hsv, [0.0, 0.0, 140.0], [180.0, 45.0, 255.0])?;
    let mut not_land = Mat::default();
    core::bitwise_or(&veg, &bright, &mut not_land, &core::no_array())?;
    let mut land_free = Mat::default();
    core::bitwise_not(&not_land, &mut land_free, &core::no_array())?;
    let mut candidate = Mat::default();
    core::bitwise_and(&smooth, &land_free, &mut candidate, &core::no_array())?;
    Ok(candidate)
}

fn hsv_box(small: &Mat, low: &[f64], high: &[f64]) -> opencv::Result<Mat> {
    let mut hsv = Mat::default();
    imgproc::cvt_color(small, &mut hsv, imgproc::COLOR_BGR2HSV, 0)?;
    clean(&hsv_in(&hsv, [low[0], low[1], low[2]], [high[0], high[1], high[2]])?)
}

/// The target mask of a BGR frame (255 inside), at the frame's size. `None` for
/// `segmenter = "masks"` (the caller reads the dataset's mask) and `"learned"` (the
/// caller's trained [`Learned`]).
pub fn segment(frame: &Mat, s: &AreaSettings) -> opencv::Result<Option<Mat>> {
    let m = match s.segmenter {
        // The dataset's masks, or a model trained on some of them: `Learned::segment`.
        Segmenter::Masks | Segmenter::Learned => return Ok(None),
        Segmenter::Water => water(&shrunk(frame)?)?,
        Segmenter::Hsv => hsv_box(&shrunk(frame)?, &s.hsv_low, &s.hsv_high)?,
    };
    Ok(Some(to_frame_size(&m, frame)?))
}

/// `frame` at most `WORK_WIDTH` wide: the size the segmenters (and the shadow check)
/// work at.
pub fn shrunk(frame: &Mat) -> opencv::Result<Mat> {
    let scale = (WORK_WIDTH as f64 / frame.cols() as f64).min(1.0);
    if scale >= 1.0 {
        return frame.try_clone();
    }
    let mut small = Mat::default();
    let size = Size::new(WORK_WIDTH, (frame.rows() as f64 * scale).round() as i32);
    imgproc::resize(frame, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    Ok(small)
}

/// A mask made at the working size, back at the frame's size (binary).
fn to_frame_size(m: &Mat, frame: &Mat) -> opencv::Result<Mat> {
    if m.size()? == frame.size()? {
        return m.try_clone();
    }
    let mut full = Mat::default();
    imgproc::resize(m, &mut full, frame.size()?, 0.0, 0.0, imgproc::INTER_LINEAR)?;
    let mut bin = Mat::default();
    imgproc::threshold(&full, &mut bin, 127.0, 255.0, imgproc::THRESH_BINARY)?;
    Ok(bin)
}

/// Bins of the learned segmenter's feature: hue, saturation, value and local contrast.
const BINS_H: usize = 30;
const BINS_S: usize = 16;
const BINS_V: usize = 16;
/// Local contrast ([`texture`], 8-bit) split at these values: water's is under 8-16 in
/// the DJI photos (the water rule's Otsu split came out at 40 there, capped).
const TEXTURE_SPLITS: [u8; 3] = [8, 16, 32];
const BINS: usize = BINS_H * BINS_S * BINS_V * (TEXTURE_SPLITS.len() + 1);

/// Each pixel's bin, at the working size.
fn feature_bins(small: &Mat) -> opencv::Result<Vec<u32>> {
    let mut hsv = Mat::default();
    imgproc::cvt_color(small, &mut hsv, imgproc::COLOR_BGR2HSV, 0)?;
    let mut grey = Mat::default();
    imgproc::cvt_color(small, &mut grey, imgproc::COLOR_BGR2GRAY, 0)?;
    let tex = texture(&grey)?;
    let (hsv, tex) = (hsv.try_clone()?, tex.try_clone()?);
    let px = hsv.data_typed::<core::Vec3b>()?;
    let t = tex.data_typed::<u8>()?;
    Ok(px
        .iter()
        .zip(t)
        .map(|(p, &t)| {
            let h = (p[0] as usize * BINS_H / 181).min(BINS_H - 1);
            let s = p[1] as usize * BINS_S / 256;
            let v = p[2] as usize * BINS_V / 256;
            let tb = TEXTURE_SPLITS.iter().filter(|&&x| t >= x).count();
            (((h * BINS_S + s) * BINS_V + v) * (TEXTURE_SPLITS.len() + 1) + tb) as u32
        })
        .collect())
}

/// `area.segmenter = "learned"`: the probability of the target in each bin of colour
/// (hue, saturation, value) and local contrast, counted over the pixels of frames the user
/// made masks for (histogram back-projection; a bin no training pixel fell in is not
/// target). Trained per survey, it learns what this lake and
/// this survey's shadows look like: trained on DJI_0031 with the water rule's mask (whose
/// road has tree shadows), it takes none of a sky-lit shadow cast on DJI_0030, where the
/// water rule takes 32 % (test `a_segmenter_learned_from_one_photo_...`; `cargo run
/// --release --example segment -- OUT DJI_0030.JPG --shadow ... --train DJI_0031.JPG`).
pub struct Learned {
    /// P(target | bin).
    p: Vec<f32>,
}

/// The counts a [`Learned`] segmenter is made from, added one frame at a time (a survey's
/// masked frames need not all be in memory).
pub struct LearnedCounts {
    inside: Vec<u32>,
    outside: Vec<u32>,
}

impl Default for LearnedCounts {
    fn default() -> Self {
        LearnedCounts { inside: vec![0; BINS], outside: vec![0; BINS] }
    }
}

impl LearnedCounts {
    /// A frame and its mask (8-bit, non-zero inside; any size).
    pub fn add(&mut self, frame: &Mat, mask: &Mat) -> opencv::Result<()> {
        let small = shrunk(frame)?;
        let mut m = Mat::default();
        imgproc::resize(mask, &mut m, small.size()?, 0.0, 0.0, imgproc::INTER_NEAREST)?;
        let m = m.try_clone()?;
        for (b, &k) in feature_bins(&small)?.iter().zip(m.data_typed::<u8>()?) {
            if k > 127 {
                self.inside[*b as usize] += 1;
            } else {
                self.outside[*b as usize] += 1;
            }
        }
        Ok(())
    }

    /// The segmenter; `None` when no training pixel is inside or none outside the target.
    pub fn model(&self) -> Option<Learned> {
        let sum = |v: &[u32]| v.iter().map(|&c| c as f64).sum::<f64>();
        let (ni, no) = (sum(&self.inside), sum(&self.outside));
        if ni == 0.0 || no == 0.0 {
            return None;
        }
        // One pseudo-count at the training share of target, which a bin seen a few times
        // hardly moves from; a bin never seen is not target, whatever that share (a
        // training set mostly of water must not make every new colour water).
        let prior = ni / (ni + no);
        let p = self
            .inside
            .iter()
            .zip(&self.outside)
            .map(
                |(&i, &o)| {
                    if i + o == 0 {
                        0.0
                    } else {
                        ((i as f64 + prior) / (i as f64 + o as f64 + 1.0)) as f32
                    }
                },
            )
            .collect();
        Some(Learned { p })
    }
}

impl Learned {
    /// From frames and their masks (8-bit, non-zero inside; any size each). `None` when no
    /// training pixel is inside or none outside the target.
    pub fn train(examples: &[(Mat, Mat)]) -> opencv::Result<Option<Learned>> {
        let mut counts = LearnedCounts::default();
        for (frame, mask) in examples {
            counts.add(frame, mask)?;
        }
        Ok(counts.model())
    }

    /// The target mask of a BGR frame (255 inside), at the frame's size.
    pub fn segment(&self, frame: &Mat) -> opencv::Result<Mat> {
        let small = shrunk(frame)?;
        let bins = feature_bins(&small)?;
        let raw: Vec<u8> = bins.iter().map(|&b| if self.p[b as usize] > 0.5 { 255 } else { 0 }).collect();
        let raw = Mat::from_slice(&raw)?.reshape(1, small.rows())?.try_clone()?;
        to_frame_size(&clean(&raw)?, frame)
    }
}

/// A PNG contact sheet: each frame (scaled to 480 px wide) beside itself with the mask
/// tinted red and its outline drawn, one row per frame, with the frame's index; on the
/// frame, `marks` (full-resolution sightings of converged landmarks and their
/// reprojections, from [`super::residuals::marks`]).
/// Width of a contact sheet tile.
pub const SHEET_TILE_W: i32 = 480;
/// Frames per contact sheet page.
pub const SHEET_PAGE: usize = 12;

/// A frame and its mask shrunk to a contact-sheet tile, kept for the sheet at the end of
/// a run (a full-size copy of every frame would not fit in memory on a long survey).
pub struct SheetRow {
    pub index: u64,
    pub frame: Mat,
    pub mask: Mat,
    /// The frame's full width, for the landmarks' pixel coordinates.
    pub full_width: i32,
}

impl SheetRow {
    pub fn new(index: u64, frame: &Mat, mask: &Mat) -> opencv::Result<SheetRow> {
        let w = SHEET_TILE_W;
        let h = (frame.rows() as f64 * w as f64 / frame.cols() as f64).round() as i32;
        let mut a = Mat::default();
        imgproc::resize(frame, &mut a, Size::new(w, h), 0.0, 0.0, imgproc::INTER_AREA)?;
        let mut m = Mat::default();
        imgproc::resize(mask, &mut m, Size::new(w, h), 0.0, 0.0, imgproc::INTER_NEAREST)?;
        Ok(SheetRow { index, frame: a, mask: m, full_width: frame.cols() })
    }
}

/// Contact sheets of every frame, `SHEET_PAGE` to a page: `masks.png` when one page holds
/// them all, else `masks-01.png`, `masks-02.png`, ... Returns the files written.
pub fn contact_sheets(
    dir: &std::path::Path,
    rows: &[SheetRow],
    marks: &std::collections::BTreeMap<u64, Vec<(crate::geometry::Pixel, Option<crate::geometry::Pixel>)>>,
) -> opencv::Result<Vec<std::path::PathBuf>> {
    let pages: Vec<&[SheetRow]> = rows.chunks(SHEET_PAGE).collect();
    let mut written = Vec::new();
    for (i, page) in pages.iter().enumerate() {
        let name = if pages.len() == 1 { "masks.png".to_string() } else { format!("masks-{:02}.png", i + 1) };
        let path = dir.join(name);
        contact_sheet(&path, page, marks)?;
        written.push(path);
    }
    Ok(written)
}

pub fn contact_sheet(
    path: &std::path::Path,
    rows: &[SheetRow],
    marks: &std::collections::BTreeMap<u64, Vec<(crate::geometry::Pixel, Option<crate::geometry::Pixel>)>>,
) -> opencv::Result<()> {
    let w = SHEET_TILE_W;
    let mut tiles: Vec<Mat> = Vec::new();
    for SheetRow { index, frame, mask, full_width } in rows {
        let mut a = frame.try_clone()?;
        // Converged landmarks: a green ring where SIFT saw it, a red line to where the
        // estimate reprojects (drawn 3x longer so a 20 px residual shows on a 480 px tile).
        let s = w as f64 / *full_width as f64;
        let at = |p: &crate::geometry::Pixel| Point::new((p.u * s).round() as i32, (p.v * s).round() as i32);
        for (seen, reprojected) in marks.get(index).map(Vec::as_slice).unwrap_or(&[]) {
            if let Some(r) = reprojected {
                let end =
                    crate::geometry::Pixel::new(seen.u + 3.0 * (r.u - seen.u), seen.v + 3.0 * (r.v - seen.v));
                let red = Scalar::new(0.0, 0.0, 255.0, 0.0);
                imgproc::line(&mut a, at(seen), at(&end), red, 1, imgproc::LINE_AA, 0)?;
            }
            let green = Scalar::new(0.0, 255.0, 0.0, 0.0);
            imgproc::circle(&mut a, at(seen), 4, green, 1, imgproc::LINE_AA, 0)?;
        }
        let m = mask;
        let mut red = a.try_clone()?;
        red.set_to(&Scalar::new(0.0, 0.0, 255.0, 0.0), m)?;
        let mut b = Mat::default();
        core::add_weighted(&a, 0.55, &red, 0.45, 0.0, &mut b, -1)?;
        imgproc::draw_contours(
            &mut b,
            &outlines(m)?,
            -1,
            Scalar::new(0.0, 255.0, 255.0, 0.0),
            2,
            imgproc::LINE_8,
            &core::no_array(),
            i32::MAX,
            Point::new(0, 0),
        )?;
        for (img, text) in [(&mut a, format!("frame {index}")), (&mut b, "mask".to_string())] {
            imgproc::put_text(
                img,
                &text,
                Point::new(8, 24),
                imgproc::FONT_HERSHEY_SIMPLEX,
                0.7,
                Scalar::new(255.0, 255.0, 255.0, 0.0),
                2,
                imgproc::LINE_AA,
                false,
            )?;
        }
        let mut row = Mat::default();
        let pair: Vector<Mat> = Vector::from_iter([a, b]);
        core::hconcat(&pair, &mut row)?;
        tiles.push(row);
    }
    if tiles.is_empty() {
        return Ok(());
    }
    let mut sheet = Mat::default();
    core::vconcat(&Vector::<Mat>::from_iter(tiles), &mut sheet)?;
    // OpenCV picks the format from the extension, which the atomic writer's temporary keeps.
    mavloc_data::atomic::write_atomic_path(path, |tmp| match imgcodecs::imwrite_def(tmp, &sheet) {
        Ok(true) => Ok(()),
        Ok(false) => Err(std::io::Error::other(format!("cannot write {}", tmp.display()))),
        Err(e) => Err(std::io::Error::other(e.to_string())),
    })
    .map_err(|e| opencv::Error::new(core::StsError, format!("{}: {e}", path.display())))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth dark-blue lake on the left, textured green-brown land on the right.
    fn shore() -> Mat {
        let (w, h) = (400, 300);
        let mut m = Mat::new_rows_cols_with_default(h, w, core::CV_8UC3, Scalar::all(0.0)).unwrap();
        let mut state = 12345u32;
        for y in 0..h {
            for x in 0..w {
                state = state.wrapping_mul(1664525).wrapping_add(1013904223);
                let n = (state >> 24) as i32 - 128;
                let px = if x < 200 + (y / 10) {
                    core::Vec3b::from([(110 + n / 32) as u8, (70 + n / 32) as u8, (40 + n / 32) as u8])
                } else {
                    core::Vec3b::from([
                        (60 + n / 2).clamp(0, 255) as u8,
                        (120 + n / 2) as u8,
                        (90 + n / 3) as u8,
                    ])
                };
                *m.at_2d_mut::<core::Vec3b>(y, x).unwrap() = px;
            }
        }
        m
    }

    #[test]
    fn water_is_the_smooth_side_of_a_shore() {
        let s = AreaSettings { segmenter: Segmenter::Water, ..AreaSettings::default() };
        let mask = segment(&shore(), &s).unwrap().unwrap();
        let at = |x, y| *mask.at_2d::<u8>(y, x).unwrap();
        assert_eq!(at(50, 150), 255, "lake");
        assert_eq!(at(350, 150), 0, "land");
        // The shoreline lies where it is drawn, within the clean-up's reach.
        let row = 150;
        let edge = (0..400).find(|&x| at(x, row) == 0).unwrap();
        assert!((edge - (200 + row / 10)).abs() <= 8, "edge at {edge}");
    }

    #[test]
    fn an_hsv_box_selects_its_colour() {
        let s = AreaSettings {
            segmenter: Segmenter::Hsv,
            hsv_low: vec![100.0, 100.0, 50.0],
            hsv_high: vec![130.0, 255.0, 255.0],
            ..AreaSettings::default()
        };
        let mask = segment(&shore(), &s).unwrap().unwrap();
        assert_eq!(*mask.at_2d::<u8>(150, 50).unwrap(), 255);
        assert_eq!(*mask.at_2d::<u8>(150, 350).unwrap(), 0);
    }

    fn photo(name: &str) -> Mat {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dji-sample").join(name);
        imgcodecs::imread(path.to_str().unwrap(), imgcodecs::IMREAD_COLOR).unwrap()
    }

    /// A shadow lit by the sky alone (blue 0.45, green 0.38, red 0.30 of the sunlit
    /// values: the hue, saturation and value of the real tree shadow on DJI_0030's beach)
    /// over the polygon with corners at these fractions of the size.
    fn shadowed(img: &Mat, corners: &[(f64, f64)]) -> (Mat, Mat) {
        let (w, h) = (img.cols() as f64, img.rows() as f64);
        let poly: Vector<Point> =
            corners.iter().map(|&(u, v)| Point::new((u * w) as i32, (v * h) as i32)).collect();
        let mut area = Mat::zeros(img.rows(), img.cols(), core::CV_8UC1).unwrap().to_mat().unwrap();
        let polys: Vector<Vector<Point>> = std::iter::once(poly).collect();
        imgproc::fill_poly(&mut area, &polys, Scalar::all(255.0), imgproc::LINE_8, 0, Point::new(0, 0))
            .unwrap();
        let mut dark = Mat::default();
        core::multiply(img, &Scalar::new(0.45, 0.38, 0.30, 0.0), &mut dark, 1.0, -1).unwrap();
        let mut out = img.try_clone().unwrap();
        dark.copy_to_masked(&mut out, &area).unwrap();
        (out, area)
    }

    fn fraction(mask: &Mat, of: &Mat) -> f64 {
        let mut both = Mat::default();
        core::bitwise_and(mask, of, &mut both, &core::no_array()).unwrap();
        core::count_non_zero(&both).unwrap() as f64 / core::count_non_zero(of).unwrap().max(1) as f64
    }

    /// The shadow: a sky-lit shadow cast across DJI_0030's road and beach is
    /// smooth, not green and not bright, so the water rule before its shadow check takes a
    /// third of it for water. The learned segmenter, trained on the next photo (DJI_0031,
    /// with the water rule's mask: its tree shadows on the road are land there), takes
    /// none of it and still finds the lake the rule finds on the unshadowed photo.
    #[test]
    fn a_segmenter_learned_from_one_photo_takes_no_shadow_for_water_where_the_rule_does() {
        let rule = AreaSettings { segmenter: Segmenter::Water, ..AreaSettings::default() };
        let corners = [(0.3125, 0.267), (0.65, 0.356), (0.65, 0.8), (0.3125, 0.733)];
        let original = photo("DJI_0030.JPG");
        let (shadowed, area) = shadowed(&original, &corners);
        let rule_took = fraction(&unchecked(&shadowed), &area);

        let teacher = photo("DJI_0031.JPG");
        let teacher_mask = segment(&teacher, &rule).unwrap().unwrap();
        let learned = Learned::train(&[(teacher, teacher_mask)]).unwrap().unwrap();
        let by_learned = learned.segment(&shadowed).unwrap();
        let learned_took = fraction(&by_learned, &area);
        // The lake: against the rule's mask of the photo without the shadow.
        let lake = segment(&original, &rule).unwrap().unwrap();
        let (mut inter, mut union) = (Mat::default(), Mat::default());
        core::bitwise_and(&by_learned, &lake, &mut inter, &core::no_array()).unwrap();
        core::bitwise_or(&by_learned, &lake, &mut union, &core::no_array()).unwrap();
        let iou = core::count_non_zero(&inter).unwrap() as f64 / core::count_non_zero(&union).unwrap() as f64;
        println!("shadow taken for water: rule {rule_took:.3}, learned {learned_took:.3}; lake IoU {iou:.3}");
        assert!(rule_took > 0.2, "the failure this guards against: {rule_took}");
        assert!(learned_took < 0.03, "{learned_took}");
        assert!(iou > 0.75, "{iou}");
    }

    /// The water rule without its shadow check, at the frame's size.
    fn unchecked(frame: &Mat) -> Mat {
        let raw = smooth_dark_not_land(&shrunk(frame).unwrap()).unwrap();
        to_frame_size(&clean(&raw).unwrap(), frame).unwrap()
    }

    fn iou(a: &Mat, b: &Mat, within: &Mat) -> f64 {
        let (mut i, mut u) = (Mat::default(), Mat::default());
        core::bitwise_and(a, b, &mut i, within).unwrap();
        core::bitwise_or(a, b, &mut u, within).unwrap();
        core::count_non_zero(&i).unwrap() as f64 / core::count_non_zero(&u).unwrap().max(1) as f64
    }

    /// Sky-lit shadows cast over paving, beach and grass of the three DJI photos: smooth,
    /// dark and bluish, so the rule's colour and smoothness take 19-32 % of each for water.
    /// The shadow check (`area::shadow`: the shadow's edge is a change of light, not of
    /// material) leaves none of them, and each photo's lake, outside the shadow, is the
    /// lake of the photo without it.
    #[test]
    fn the_water_rule_takes_no_cast_shadow_for_water_and_keeps_the_lake() {
        let rule = AreaSettings { segmenter: Segmenter::Water, ..AreaSettings::default() };
        let cases: [(&str, &[(f64, f64)]); 3] = [
            ("DJI_0030.JPG", &[(0.3125, 0.267), (0.65, 0.356), (0.65, 0.8), (0.3125, 0.733)]),
            ("DJI_0031.JPG", &[(0.3, 0.0), (0.5, 0.0), (0.5, 1.0), (0.3, 1.0)]),
            ("DJI_0032.JPG", &[(0.0, 0.5), (0.3, 0.5), (0.3, 1.0), (0.0, 1.0)]),
        ];
        for (name, corners) in cases {
            let original = photo(name);
            let (shadowed, area) = shadowed(&original, corners);
            let before = fraction(&unchecked(&shadowed), &area);
            let checked = segment(&shadowed, &rule).unwrap().unwrap();
            let after = fraction(&checked, &area);
            let mut outside = Mat::default();
            core::bitwise_not(&area, &mut outside, &core::no_array()).unwrap();
            let lake = segment(&original, &rule).unwrap().unwrap();
            let kept = iou(&checked, &lake, &outside);
            println!("{name}: shadow taken for water {before:.3} without the check, {after:.3} with it; lake IoU {kept:.3}");
            assert!(before > 0.15, "{name}: the failure this guards against: {before}");
            assert!(after < 0.02, "{name}: {after} of the shadow taken for water");
            assert!(kept > 0.95, "{name}: lake IoU {kept}");
        }
    }

    /// A lake darker and bluer than its beach, as the simulator's is (RGB 38, 62, 84 against
    /// light sand), has the colour change of a shadow's edge, but the material changes:
    /// the water is smooth, the sand is not. It stays water.
    #[test]
    fn a_blue_lake_darker_than_its_beach_is_water_not_a_shadow() {
        let (w, h) = (400, 300);
        let mut m = Mat::new_rows_cols_with_default(h, w, core::CV_8UC3, Scalar::all(0.0)).unwrap();
        let mut state = 99u32;
        for y in 0..h {
            for x in 0..w {
                state = state.wrapping_mul(1664525).wrapping_add(1013904223);
                let n = (state >> 24) as i32 - 128;
                let px = if (x - 200).pow(2) + (y - 150).pow(2) < 100 * 100 {
                    [84 + n / 64, 62 + n / 64, 38 + n / 64]
                } else {
                    [150 + n / 3, 170 + n / 3, 185 + n / 3]
                };
                *m.at_2d_mut::<core::Vec3b>(y, x).unwrap() =
                    core::Vec3b::from(px.map(|c| c.clamp(0, 255) as u8));
            }
        }
        let small = shrunk(&m).unwrap();
        let shade = super::super::shadow::cast_shadows(&small).unwrap();
        assert_eq!(core::count_non_zero(&shade).unwrap(), 0, "the lake taken for a shadow");
        let s = AreaSettings { segmenter: Segmenter::Water, ..AreaSettings::default() };
        let mask = segment(&m, &s).unwrap().unwrap();
        assert_eq!(*mask.at_2d::<u8>(150, 200).unwrap(), 255, "lake");
        assert_eq!(*mask.at_2d::<u8>(20, 20).unwrap(), 0, "sand");
    }

    /// Training needs both classes; a frame's mask of one class alone gives no model.
    #[test]
    fn a_learned_segmenter_needs_both_classes() {
        let img = shore();
        let all = Mat::new_rows_cols_with_default(img.rows(), img.cols(), core::CV_8UC1, Scalar::all(255.0))
            .unwrap();
        assert!(Learned::train(&[(img.clone(), all)]).unwrap().is_none());
        assert!(Learned::train(&[]).unwrap().is_none());
    }
}
