//! Cast shadows, told apart from water by their edges, so the `water` segmenter does not
//! take a tree's shadow on a road for a lake (issue #21: a forest shadow across a road
//! drew hundreds of landmarks to its edge instead of the shore).
//!
//! Per pixel the two cannot be told apart: a shadow is lit by the sky alone, so it is the
//! sky's blue at a low value, and so is water that reflects the sky (the simulator's lake
//! and the real tree shadows on the DJI sample's road are both H 105-120, S 110-140, V
//! 85-115 in OpenCV's HSV). What differs is the edge. Across a shadow's edge the surface
//! is the same and only the light changes: every channel darker, blue least (the DJI
//! sample's road: blue 0.61, green 0.42, red 0.34 of its sunlit values), and the surface's
//! texture, relative to its brightness, the same on both sides or more (leaf-dappled).
//! Across a shore the material changes: the DJI sample's lake is darker than its beach in
//! every channel alike (ln(blue/red ratio) -0.08 at the median), and open water is
//! smoother than the land it meets (relative texture 0.3 of the beach's; the simulator's
//! water a tenth).
//!
//! So: candidate regions are the bluish dark pixels; each region's outline is probed a
//! few pixels to either side, and a region is a shadow when its outline is mostly a light
//! edge (darker, bluer, as textured) rather than a material edge (darker, but not bluer or
//! much smoother). Measured with `cargo run --release --example segment -- OUT IMAGE
//! --shadow ...` (a sky-lit shadow cast over a polygon): the water rule took 32 %, 19 % and
//! 29 % of shadows cast over DJI_0030's road and beach, DJI_0032's road and grass and
//! DJI_0031's path, and with this check none; the three photos' lakes are unchanged.

use opencv::core::{self, Mat, Point, Scalar, Size, Vector};
use opencv::imgproc;
use opencv::prelude::*;

/// A candidate pixel is bluish, ln(blue / red) above this (grey paving is -0.05 to 0.1
/// in sunlight and 0.4-0.6 in shadow on the DJI sample)...
const CANDIDATE_BLUE: f32 = 0.2;
/// ...and dark: its largest channel under this (sunlit paving is 190 there).
const CANDIDATE_MAX_VALUE: u8 = 150;
/// Candidate regions smaller than this fraction of the image are left alone (a car's
/// shadow is too small to become water after the segmenter's clean-up anyway).
const MIN_FRACTION: f64 = 0.002;
/// How far to either side of an outline the two sides are compared, working-size pixels
/// (past the 5 px colour mean and 7 px texture window, so each sample is one side only).
const PROBE_PX: f32 = 8.0;
/// A light edge: the inside under this fraction of the outside's brightness...
const EDGE_DARKER: f32 = 0.75;
/// ...bluer by more than this in ln(blue ratio / red ratio) (a real tree shadow: 0.58,
/// the skylight of the tests: 0.41, the lake against its beach: -0.08)...
const EDGE_BLUER: f32 = 0.15;
/// ...and its relative texture at least this share of the outside's (open water: 0.1-0.35).
const EDGE_TEXTURE: f32 = 0.6;
/// A region is a shadow with at least this many light-edge probes (every other outline
/// pixel is probed)...
const MIN_LIGHT_EDGES: usize = 20;
/// ...and this many times as many as the material edges that are as much darker.
const LIGHT_OVER_MATERIAL: usize = 2;

/// The cast shadows of an 8-bit BGR image (the segmenter's working size): 255 inside.
pub fn cast_shadows(small: &Mat) -> opencv::Result<Mat> {
    let (w, h) = (small.cols(), small.rows());
    // Read as one slice: a copy only when the image is a view into a larger one.
    let copy;
    let img = if small.is_continuous() {
        small
    } else {
        copy = small.try_clone()?;
        &copy
    };
    // ln(blue / red) > CANDIDATE_BLUE without a logarithm per pixel.
    let blue_over_red = CANDIDATE_BLUE.exp();
    let cand: Vec<u8> = img
        .data_typed::<core::Vec3b>()?
        .iter()
        .map(|p| {
            let bluish = p[0] as f32 + 1.0 > blue_over_red * (p[2] as f32 + 1.0);
            let value = p[0].max(p[1]).max(p[2]);
            if bluish && value < CANDIDATE_MAX_VALUE {
                255
            } else {
                0
            }
        })
        .collect();
    let cand = Mat::from_slice(&cand)?.reshape(1, h)?.try_clone()?;
    let cand = super::segment::morph(&cand, imgproc::MORPH_OPEN, 5)?;
    let cand = super::segment::morph(&cand, imgproc::MORPH_CLOSE, 9)?;

    // Each side's mean colour, and its local contrast relative to its brightness.
    let mut f = Mat::default();
    img.convert_to(&mut f, core::CV_32FC3, 1.0, 1.0)?;
    let colour = box_mean(&f, 5)?;
    let mut grey = Mat::default();
    imgproc::cvt_color(img, &mut grey, imgproc::COLOR_BGR2GRAY, 0)?;
    let mut lap = Mat::default();
    imgproc::laplacian(&grey, &mut lap, core::CV_32F, 3, 1.0, 0.0, core::BORDER_REPLICATE)?;
    let mut abs = Mat::default();
    core::absdiff(&lap, &Scalar::all(0.0), &mut abs)?;
    let contrast = box_mean(&abs, 7)?;
    let mut grey_f = Mat::default();
    grey.convert_to(&mut grey_f, core::CV_32F, 1.0, 0.0)?;
    let brightness = box_mean(&grey_f, 7)?;
    let relative_texture = |x: i32, y: i32| -> opencv::Result<f32> {
        // +8 grey levels: the dark side's sensor and JPEG noise is not texture.
        Ok(*contrast.at_2d::<f32>(y, x)? / (*brightness.at_2d::<f32>(y, x)? + 8.0))
    };

    let mut contours: Vector<Vector<Point>> = Vector::new();
    imgproc::find_contours(
        &cand,
        &mut contours,
        imgproc::RETR_EXTERNAL,
        imgproc::CHAIN_APPROX_NONE,
        Point::new(0, 0),
    )?;
    let mut shadows: Vector<Vector<Point>> = Vector::new();
    let min_area = MIN_FRACTION * (w * h) as f64;
    let margin = PROBE_PX as i32 + 1;
    for c in contours.iter() {
        if imgproc::contour_area(&c, false)? < min_area {
            continue;
        }
        let pts = c.to_vec();
        let n = pts.len();
        let (mut light, mut material) = (0usize, 0usize);
        for i in (0..n).step_by(2) {
            let p = pts[i];
            // An outline along the image's border has nothing outside to compare.
            if p.x < margin || p.y < margin || p.x >= w - margin || p.y >= h - margin {
                continue;
            }
            let (a, b) = (pts[(i + 3) % n], pts[(i + n - 3) % n]);
            let (tx, ty) = ((a.x - b.x) as f32, (a.y - b.y) as f32);
            let norm = tx.hypot(ty);
            if norm == 0.0 {
                continue;
            }
            let (nx, ny) = (-ty / norm * PROBE_PX, tx / norm * PROBE_PX);
            let one = Point::new((p.x as f32 + nx).round() as i32, (p.y as f32 + ny).round() as i32);
            let other = Point::new((p.x as f32 - nx).round() as i32, (p.y as f32 - ny).round() as i32);
            let (in_one, in_other) =
                (*cand.at_2d::<u8>(one.y, one.x)? > 0, *cand.at_2d::<u8>(other.y, other.x)? > 0);
            if in_one == in_other {
                continue; // a thin neck or a corner: no clean two sides
            }
            let (inside, outside) = if in_one { (one, other) } else { (other, one) };
            let ci = *colour.at_2d::<core::Vec3f>(inside.y, inside.x)?;
            let co = *colour.at_2d::<core::Vec3f>(outside.y, outside.x)?;
            let ratio = [ci[0] / co[0], ci[1] / co[1], ci[2] / co[2]];
            let darker = (ratio[0] + ratio[1] + ratio[2]) / 3.0 < EDGE_DARKER;
            if !darker {
                continue; // the region's edge against more shade, or against darker ground
            }
            let bluer = (ratio[0] / ratio[2]).ln() > EDGE_BLUER;
            let textured = relative_texture(inside.x, inside.y)?
                >= EDGE_TEXTURE * relative_texture(outside.x, outside.y)?;
            if bluer && textured {
                light += 1;
            } else {
                material += 1;
            }
        }
        if light >= MIN_LIGHT_EDGES && light >= LIGHT_OVER_MATERIAL * material {
            shadows.push(c);
        }
    }
    super::segment::filled(&shadows, h, w)
}

fn box_mean(src: &Mat, size: i32) -> opencv::Result<Mat> {
    let mut out = Mat::default();
    imgproc::blur(src, &mut out, Size::new(size, size), Point::new(-1, -1), core::BORDER_REPLICATE)?;
    Ok(out)
}
