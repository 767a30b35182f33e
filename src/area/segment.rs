//! Target masks for real images: the area pipeline needs, per frame, the pixels of the
//! target area (the seed took them from AirSim's segmentation, sec. 4.2.3). Chosen by
//! `area.segmenter`:
//!
//! - `masks`: the dataset's `masks/NNNNNN.png` (rendered, or made by another tool);
//! - `water`: open water: smooth (low local contrast) and neither vegetation-green nor
//!   light and colourless (sand, foam, paving), by per-image thresholds (Otsu) rather than fixed ones, so a dark lake
//!   and a bright sea both work; then morphological clean-up and only large regions kept;
//! - `hsv`: pixels inside the configured HSV box (`area.hsv_low`, `area.hsv_high`, OpenCV
//!   ranges H 0-180, S and V 0-255), for other colour-distinct areas (a burn scar, a
//!   flood's brown water), with the same clean-up.
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

fn morph(src: &Mat, op: i32, size: i32) -> opencv::Result<Mat> {
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
    let mut out = Mat::zeros(m.rows(), m.cols(), core::CV_8UC1)?.to_mat()?;
    imgproc::draw_contours(
        &mut out,
        &keep,
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
    let mut raw = Mat::default();
    core::bitwise_and(&smooth, &land_free, &mut raw, &core::no_array())?;
    clean(&raw)
}

fn hsv_box(small: &Mat, low: &[f64], high: &[f64]) -> opencv::Result<Mat> {
    let mut hsv = Mat::default();
    imgproc::cvt_color(small, &mut hsv, imgproc::COLOR_BGR2HSV, 0)?;
    clean(&hsv_in(&hsv, [low[0], low[1], low[2]], [high[0], high[1], high[2]])?)
}

/// The target mask of a BGR frame (255 inside), at the frame's size. `None` for
/// `segmenter = "masks"`: the caller reads the dataset's mask.
pub fn segment(frame: &Mat, s: &AreaSettings) -> opencv::Result<Option<Mat>> {
    if s.segmenter == Segmenter::Masks {
        return Ok(None);
    }
    let scale = (WORK_WIDTH as f64 / frame.cols() as f64).min(1.0);
    let mut small = Mat::default();
    if scale < 1.0 {
        let size = Size::new(WORK_WIDTH, (frame.rows() as f64 * scale).round() as i32);
        imgproc::resize(frame, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    } else {
        small = frame.try_clone()?;
    }
    let m = match s.segmenter {
        Segmenter::Water => water(&small)?,
        Segmenter::Hsv => hsv_box(&small, &s.hsv_low, &s.hsv_high)?,
        Segmenter::Masks => unreachable!(),
    };
    if scale >= 1.0 {
        return Ok(Some(m));
    }
    let mut full = Mat::default();
    imgproc::resize(&m, &mut full, frame.size()?, 0.0, 0.0, imgproc::INTER_LINEAR)?;
    let mut bin = Mat::default();
    imgproc::threshold(&full, &mut bin, 127.0, 255.0, imgproc::THRESH_BINARY)?;
    Ok(Some(bin))
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
}
