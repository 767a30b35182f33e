//! "Process new image" (area seed sec. 5.2, fig. 5.4-5.8): the band around the target
//! area and the SIFT features in it.
//!
//! The band is `dilate(mask) - mask` with an elliptical kernel of the configured width
//! (fig. 5.6-5.7). SIFT runs only on pieces of the band ([`band_regions`]: its bounding
//! box cut into strips, each shrunk to the band pixels it holds) plus a margin for the
//! scale space and descriptor support: inside the band that gives the keypoints SIFT
//! finds on the whole frame (up to the margin's edge effects at coarse scales), at a
//! fraction of the cost when the border covers part of the view.

use opencv::core::{self, KeyPoint, Mat, Point, Rect, Scalar, Size, Vector};
use opencv::features2d::SIFT;
use opencv::imgproc;
use opencv::prelude::*;

use crate::geometry::Pixel;

/// SIFT keypoints of one frame with their descriptors (one 128-float row each).
pub struct Features {
    pub pixels: Vec<Pixel>,
    pub responses: Vec<f32>,
    /// Distance of each keypoint to the target area, pixels.
    pub border_px: Vec<f32>,
    pub descriptors: Mat,
}

/// The band around the target area and every pixel's distance to the area.
pub struct Band {
    /// 8-bit, 255 in the band.
    pub mask: Mat,
    /// Euclidean distance to the nearest target pixel (0 inside it), `CV_32F`.
    pub distance: Mat,
}

impl Features {
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }
}

/// How the band is cut for SIFT.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pieces {
    /// The band's bounding box, whole.
    OneBox,
    /// Strips of it shrunk to their band pixels ([`band_regions`]).
    Strips,
}

/// Builds bands and extracts features.
pub struct FeatureExtractor {
    first: core::Ptr<SIFT>,
    later: core::Ptr<SIFT>,
    kernel: Mat,
    band_px: i32,
    counts: (i32, i32),
}

/// Pixels around the band kept for SIFT's scale space and descriptor windows.
const ROI_MARGIN: i32 = 24;
/// SIFT runs on pieces of the band this long (or shorter): a border crossing the view
/// diagonally, or wrapping the target, leaves most of its bounding box empty. Measured on
/// the 960x540 coastline and cliff flights (`mavloc area`, 300-400 frames): SIFT 35.4 ->
/// 18.7 ms and 39.7 -> 22.2 ms per frame against one box, landmarks within 1 cm of mean
/// error; shorter pieces pay more for their margins.
const STRIP_PX: i32 = 5 * ROI_MARGIN;

impl FeatureExtractor {
    /// `first_count` features on the first frame (`L_max`), `later_count` afterwards
    /// (`10 L_max`, seed sec. 5.2); `band_px` is the band width at the processing resolution.
    pub fn new(first_count: i32, later_count: i32, band_px: i32) -> opencv::Result<FeatureExtractor> {
        let band_px = band_px.max(1);
        let kernel = imgproc::get_structuring_element(
            imgproc::MORPH_ELLIPSE,
            Size::new(2 * band_px + 1, 2 * band_px + 1),
            Point::new(-1, -1),
        )?;
        Ok(FeatureExtractor {
            first: SIFT::create(first_count, 3, 0.04, 10.0, 1.6)?,
            later: SIFT::create(later_count, 3, 0.04, 10.0, 1.6)?,
            kernel,
            band_px,
            counts: (first_count, later_count),
        })
    }

    /// The band around the target area: `dilate(mask) - mask` (8-bit, 255 in the band).
    ///
    /// Computed as the pixels outside the target whose Euclidean distance to it is at most
    /// the band width (an exact distance transform): the same set as dilating with a disk,
    /// in time independent of the band width (a 51 px disk dilation costs ten times more).
    pub fn band(&self, mask: &Mat) -> opencv::Result<Band> {
        let mut outside = Mat::default();
        imgproc::threshold(mask, &mut outside, 127.0, 255.0, imgproc::THRESH_BINARY_INV)?;
        let mut distance = Mat::default();
        imgproc::distance_transform(
            &outside,
            &mut distance,
            imgproc::DIST_L2,
            imgproc::DIST_MASK_PRECISE,
            core::CV_32F,
        )?;
        let mut band = Mat::default();
        core::in_range(&distance, &Scalar::all(0.5), &Scalar::all(self.band_px as f64 + 1e-3), &mut band)?;
        Ok(Band { mask: band, distance })
    }

    /// The band by morphological dilation, as the seed builds it (fig. 5.6-5.7); kept to
    /// check and benchmark [`FeatureExtractor::band`] against.
    pub fn band_by_dilation(&self, mask: &Mat) -> opencv::Result<Mat> {
        let mut binary = Mat::default();
        imgproc::threshold(mask, &mut binary, 127.0, 255.0, imgproc::THRESH_BINARY)?;
        let mut dilated = Mat::default();
        imgproc::dilate(
            &binary,
            &mut dilated,
            &self.kernel,
            Point::new(-1, -1),
            1,
            core::BORDER_CONSTANT,
            imgproc::morphology_default_border_value()?,
        )?;
        let mut band = Mat::default();
        core::subtract(&dilated, &binary, &mut band, &core::no_array(), -1)?;
        Ok(band)
    }

    /// Band width at the processing resolution, pixels.
    pub fn band_px(&self) -> i32 {
        self.band_px
    }

    /// SIFT keypoints and descriptors inside `band` of the grey frame.
    pub fn extract(&mut self, grey: &Mat, band: &Band, first: bool) -> opencv::Result<Features> {
        self.extract_in(grey, band, first, Pieces::Strips)
    }

    /// [`FeatureExtractor::extract`] over the band cut as `pieces` (one box: to check and
    /// benchmark the pieces against).
    pub fn extract_in(
        &mut self,
        grey: &Mat,
        band: &Band,
        first: bool,
        pieces: Pieces,
    ) -> opencv::Result<Features> {
        let distance = &band.distance;
        let band = &band.mask;
        let mut points = Mat::default();
        core::find_non_zero(band, &mut points)?;
        let empty = Features {
            pixels: Vec::new(),
            responses: Vec::new(),
            border_px: Vec::new(),
            descriptors: Mat::default(),
        };
        if points.empty() {
            return Ok(empty);
        }
        let bbox = imgproc::bounding_rect(&points)?;
        let full = Rect::new(0, 0, grey.cols(), grey.rows());
        let regions = match pieces {
            Pieces::OneBox => vec![bbox],
            Pieces::Strips => {
                band_regions(band, bbox, (bbox.width.max(bbox.height) + STRIP_PX - 1) / STRIP_PX)?
            }
        };
        let sift = if first { &mut self.first } else { &mut self.later };
        // (keypoint in frame pixels, its region, its descriptor row there)
        let mut found: Vec<(KeyPoint, usize, i32)> = Vec::new();
        let mut region_descriptors = Vec::with_capacity(regions.len());
        for (i, core_rect) in regions.iter().enumerate() {
            let roi = Rect::new(
                core_rect.x - ROI_MARGIN,
                core_rect.y - ROI_MARGIN,
                core_rect.width + 2 * ROI_MARGIN,
                core_rect.height + 2 * ROI_MARGIN,
            ) & full;
            let grey_roi = Mat::roi(grey, roi)?;
            // Only this region's own band pixels: no keypoint is found twice.
            let mut band_roi = Mat::zeros(roi.height, roi.width, core::CV_8UC1)?.to_mat()?;
            let inner =
                Rect::new(core_rect.x - roi.x, core_rect.y - roi.y, core_rect.width, core_rect.height);
            Mat::roi(band, *core_rect)?.copy_to(&mut Mat::roi_mut(&mut band_roi, inner)?)?;
            let mut kps = Vector::<KeyPoint>::new();
            let mut descriptors = Mat::default();
            sift.detect_and_compute(&grey_roi, &band_roi, &mut kps, &mut descriptors, false)?;
            for (row, mut kp) in kps.iter().enumerate() {
                kp.set_pt(core::Point2f::new(kp.pt().x + roi.x as f32, kp.pt().y + roi.y as f32));
                found.push((kp, i, row as i32));
            }
            region_descriptors.push(descriptors);
        }
        // Each region kept its best `limit`, so the best `limit` of all of them are the
        // frame's best `limit`: what one SIFT call over the whole band would keep.
        found.sort_by(|a, b| b.0.response().total_cmp(&a.0.response()));
        let limit = if first { self.counts.0 } else { self.counts.1 };
        if limit > 0 {
            found.truncate(limit as usize);
        }
        let mut pixels = Vec::with_capacity(found.len());
        let mut responses = Vec::with_capacity(found.len());
        let mut border_px = Vec::with_capacity(found.len());
        let mut descriptors = Mat::zeros(found.len() as i32, 128, core::CV_32F)?.to_mat()?;
        for (i, (kp, region, row)) in found.iter().enumerate() {
            let (x, y) = (kp.pt().x, kp.pt().y);
            pixels.push(Pixel::new(x as f64, y as f64));
            responses.push(kp.response());
            let (xi, yi) =
                ((x.round() as i32).clamp(0, grey.cols() - 1), (y.round() as i32).clamp(0, grey.rows() - 1));
            border_px.push(*distance.at_2d::<f32>(yi, xi)?);
            region_descriptors[*region].row(*row)?.copy_to(&mut descriptors.row_mut(i as i32)?)?;
        }
        Ok(Features { pixels, responses, border_px, descriptors })
    }
}

/// The band's bounding box cut into `strips` along its longer side; each strip split
/// across at band-free gaps wider than two margins (a strip crossing a band that wraps the
/// target meets it twice), and each piece shrunk to the band pixels it holds.
fn band_regions(band: &Mat, bbox: Rect, strips: i32) -> opencv::Result<Vec<Rect>> {
    let strips = strips.max(1);
    let mut out = Vec::new();
    let horizontal = bbox.width >= bbox.height;
    let len = if horizontal { bbox.width } else { bbox.height };
    for i in 0..strips {
        let (a, b) = (len * i / strips, len * (i + 1) / strips);
        if b <= a {
            continue;
        }
        let r = if horizontal {
            Rect::new(bbox.x + a, bbox.y, b - a, bbox.height)
        } else {
            Rect::new(bbox.x, bbox.y + a, bbox.width, b - a)
        };
        // Band pixels per line across the strip (rows of a vertical strip, columns of a
        // horizontal one).
        let mut counts = Mat::default();
        let dim = if horizontal { 1 } else { 0 };
        core::reduce(&Mat::roi(band, r)?, &mut counts, dim, core::REDUCE_MAX, -1)?;
        let counts = counts.data_bytes()?.to_vec();
        let mut start: Option<usize> = None;
        let mut last = 0usize;
        let push = |s: usize, e: usize, out: &mut Vec<Rect>| -> opencv::Result<()> {
            let piece = if horizontal {
                Rect::new(r.x, r.y + s as i32, r.width, (e - s + 1) as i32)
            } else {
                Rect::new(r.x + s as i32, r.y, (e - s + 1) as i32, r.height)
            };
            let mut pts = Mat::default();
            core::find_non_zero(&Mat::roi(band, piece)?, &mut pts)?;
            if !pts.empty() {
                let t = imgproc::bounding_rect(&pts)?;
                out.push(Rect::new(piece.x + t.x, piece.y + t.y, t.width, t.height));
            }
            Ok(())
        };
        for (j, &c) in counts.iter().enumerate() {
            if c == 0 {
                continue;
            }
            match start {
                Some(s) if j - last > 2 * ROI_MARGIN as usize => {
                    push(s, last, &mut out)?;
                    start = Some(j);
                }
                None => start = Some(j),
                _ => {}
            }
            last = j;
        }
        if let Some(s) = start {
            push(s, last, &mut out)?;
        }
    }
    Ok(out)
}

/// Converts an 8-bit BGR or grey frame to grey and shrinks it (and its mask) by an
/// integer factor: area averaging for the frame, nearest for the mask so it stays binary.
pub fn prepare(frame: &Mat, mask: &Mat, downscale: u32) -> opencv::Result<(Mat, Mat)> {
    let mut grey = Mat::default();
    if frame.channels() == 3 {
        imgproc::cvt_color(frame, &mut grey, imgproc::COLOR_BGR2GRAY, 0)?;
    } else {
        grey = frame.try_clone()?;
    }
    if downscale <= 1 {
        return Ok((grey, mask.try_clone()?));
    }
    let size = Size::new(grey.cols() / downscale as i32, grey.rows() / downscale as i32);
    let mut small = Mat::default();
    imgproc::resize(&grey, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    let mut small_mask = Mat::default();
    // INTER_AREA then threshold: a destination pixel is target if most of its block is.
    imgproc::resize(mask, &mut small_mask, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    let mut binary = Mat::default();
    imgproc::threshold(&small_mask, &mut binary, 127.0, 255.0, imgproc::THRESH_BINARY)?;
    Ok((small, binary))
}

/// A blank 8-bit image, for tests.
#[cfg(test)]
pub(crate) fn blank(width: i32, height: i32, value: f64) -> opencv::Result<Mat> {
    Mat::new_rows_cols_with_default(height, width, core::CV_8UC1, Scalar::all(value))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn band_surrounds_the_target_outside_it() {
        let ex = FeatureExtractor::new(10, 100, 5).unwrap();
        let mut mask = blank(60, 40, 0.0).unwrap();
        imgproc::rectangle(&mut mask, Rect::new(20, 10, 20, 20), Scalar::all(255.0), -1, imgproc::LINE_8, 0)
            .unwrap();
        let band = ex.band(&mask).unwrap().mask;
        let at = |m: &Mat, x: i32, y: i32| *m.at_2d::<u8>(y, x).unwrap();
        assert_eq!(at(&band, 30, 20), 0, "inside the target is not band");
        assert_eq!(at(&band, 17, 20), 255, "3 px left of the target is band");
        assert_eq!(at(&band, 12, 20), 0, "8 px away is outside the band");
    }

    #[test]
    fn distance_band_matches_the_dilation_band() {
        let ex = FeatureExtractor::new(10, 100, 12).unwrap();
        let mut mask = blank(200, 150, 0.0).unwrap();
        imgproc::circle(&mut mask, Point::new(90, 70), 40, Scalar::all(255.0), -1, imgproc::LINE_8, 0)
            .unwrap();
        imgproc::rectangle(&mut mask, Rect::new(120, 20, 50, 30), Scalar::all(255.0), -1, imgproc::LINE_8, 0)
            .unwrap();
        let (a, b) = (ex.band(&mask).unwrap().mask, ex.band_by_dilation(&mask).unwrap());
        let mut diff = Mat::default();
        core::bitwise_xor(&a, &b, &mut diff, &core::no_array()).unwrap();
        let differing = core::count_non_zero(&diff).unwrap();
        let total = core::count_non_zero(&b).unwrap();
        // Only the rim where the disk kernel's pixel raster and the exact distance disagree.
        assert!(differing * 20 < total, "{differing} of {total} band pixels differ");
    }

    #[test]
    fn empty_band_gives_no_features() {
        let mut ex = FeatureExtractor::new(10, 100, 5).unwrap();
        let grey = blank(64, 48, 90.0).unwrap();
        let none = ex.band(&blank(64, 48, 0.0).unwrap()).unwrap();
        let f = ex.extract(&grey, &none, true).unwrap();
        assert!(f.is_empty());
    }

    /// A diagonal border and a ring: every band pixel lies in exactly one piece, and the
    /// pieces cover far less than the band's bounding box.
    #[test]
    fn band_pieces_cover_each_band_pixel_once_in_less_area() {
        let ex = FeatureExtractor::new(10, 100, 12).unwrap();
        for shape in 0..2 {
            let mut mask = blank(960, 540, 0.0).unwrap();
            if shape == 0 {
                let pts = Vector::<Point>::from_iter([
                    Point::new(0, 0),
                    Point::new(960, 0),
                    Point::new(960, 40),
                    Point::new(0, 500),
                ]);
                imgproc::fill_convex_poly(&mut mask, &pts, Scalar::all(255.0), imgproc::LINE_8, 0).unwrap();
            } else {
                imgproc::circle(
                    &mut mask,
                    Point::new(480, 270),
                    200,
                    Scalar::all(255.0),
                    -1,
                    imgproc::LINE_8,
                    0,
                )
                .unwrap();
            }
            let band = ex.band(&mask).unwrap().mask;
            let mut points = Mat::default();
            core::find_non_zero(&band, &mut points).unwrap();
            let bbox = imgproc::bounding_rect(&points).unwrap();
            let pieces =
                band_regions(&band, bbox, (bbox.width.max(bbox.height) + STRIP_PX - 1) / STRIP_PX).unwrap();
            let mut seen = blank(960, 540, 0.0).unwrap();
            for r in &pieces {
                let mut roi = Mat::roi_mut(&mut seen, *r).unwrap();
                let mut plus = Mat::default();
                core::add(&roi, &Scalar::all(1.0), &mut plus, &core::no_array(), -1).unwrap();
                plus.copy_to(&mut roi).unwrap();
            }
            let area: i32 = pieces.iter().map(|r| r.area()).sum();
            for y in 0..540 {
                for x in 0..960 {
                    if *band.at_2d::<u8>(y, x).unwrap() != 0 {
                        assert_eq!(*seen.at_2d::<u8>(y, x).unwrap(), 1, "band pixel ({x}, {y})");
                    }
                }
            }
            // The diagonal's box is mostly empty; the ring's pieces still hold its middle.
            let most = [0.3, 0.6][shape];
            assert!(
                (area as f64) < most * bbox.area() as f64,
                "shape {shape}: pieces {area} px against the box's {}",
                bbox.area()
            );
        }
    }

    /// SIFT on the pieces finds what SIFT on the band's whole bounding box finds.
    #[test]
    fn band_pieces_find_the_keypoints_of_one_box() {
        let mut ex = FeatureExtractor::new(4000, 4000, 25).unwrap();
        // Blobs of many sizes and contrasts: keypoints at every scale.
        let mut blobs = blank(960, 540, 128.0).unwrap();
        let mut rng = core::RNG::new(7).unwrap();
        for _ in 0..3000 {
            let (x, y) = (rng.uniform(0, 960).unwrap(), rng.uniform(0, 540).unwrap());
            let r = rng.uniform(2, 14).unwrap();
            let v = rng.uniform(0, 256).unwrap() as f64;
            imgproc::circle(&mut blobs, Point::new(x, y), r, Scalar::all(v), -1, imgproc::LINE_AA, 0)
                .unwrap();
        }
        let mut grey = Mat::default();
        imgproc::gaussian_blur(&blobs, &mut grey, Size::new(0, 0), 1.0, 1.0, core::BORDER_DEFAULT).unwrap();
        let mut mask = blank(960, 540, 0.0).unwrap();
        let pts = Vector::<Point>::from_iter([Point::new(0, 0), Point::new(960, 0), Point::new(0, 540)]);
        imgproc::fill_convex_poly(&mut mask, &pts, Scalar::all(255.0), imgproc::LINE_8, 0).unwrap();
        let band = ex.band(&mask).unwrap();
        let pieces = ex.extract(&grey, &band, false).unwrap();
        let one = ex.extract_in(&grey, &band, false, Pieces::OneBox).unwrap();
        let kps = &one.pixels;
        assert!(kps.len() > 100, "{} keypoints: the test needs texture", kps.len());
        let found =
            kps.iter().filter(|k| pieces.pixels.iter().any(|p| (p.u - k.u).hypot(p.v - k.v) < 0.5)).count();
        assert!(
            found * 100 >= kps.len() * 95,
            "pieces found {found} of one box's {} keypoints ({} in all)",
            kps.len(),
            pieces.len()
        );
        assert!(pieces.len() * 100 <= kps.len() * 105, "{} against {}", pieces.len(), kps.len());
        assert_eq!(pieces.descriptors.rows() as usize, pieces.len());
    }
}
