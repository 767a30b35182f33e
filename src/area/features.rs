//! "Process new image" (area seed sec. 5.2, fig. 5.4-5.8): the band around the target
//! area and the SIFT features in it.
//!
//! The band is `dilate(mask) - mask` with an elliptical kernel of the configured width
//! (fig. 5.6-5.7). SIFT runs only on the band's bounding box plus a margin for the
//! descriptor support, which gives the same keypoints inside the band as running on the
//! whole frame but costs a fraction of it when the border covers part of the view.

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

/// Builds bands and extracts features.
pub struct FeatureExtractor {
    first: core::Ptr<SIFT>,
    later: core::Ptr<SIFT>,
    kernel: Mat,
    band_px: i32,
}

/// Pixels around the band kept for SIFT's scale space and descriptor windows.
const ROI_MARGIN: i32 = 24;

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
        let roi = Rect::new(
            bbox.x - ROI_MARGIN,
            bbox.y - ROI_MARGIN,
            bbox.width + 2 * ROI_MARGIN,
            bbox.height + 2 * ROI_MARGIN,
        ) & full;
        let grey_roi = Mat::roi(grey, roi)?;
        let band_roi = Mat::roi(band, roi)?;
        let mut kps = Vector::<KeyPoint>::new();
        let mut descriptors = Mat::default();
        let sift = if first { &mut self.first } else { &mut self.later };
        sift.detect_and_compute(&grey_roi, &band_roi, &mut kps, &mut descriptors, false)?;
        let mut pixels = Vec::with_capacity(kps.len());
        let mut responses = Vec::with_capacity(kps.len());
        let mut border_px = Vec::with_capacity(kps.len());
        for kp in kps.iter() {
            let pt = kp.pt();
            let (x, y) = (pt.x + roi.x as f32, pt.y + roi.y as f32);
            pixels.push(Pixel::new(x as f64, y as f64));
            responses.push(kp.response());
            let (xi, yi) =
                ((x.round() as i32).clamp(0, grey.cols() - 1), (y.round() as i32).clamp(0, grey.rows() - 1));
            border_px.push(*distance.at_2d::<f32>(yi, xi)?);
        }
        Ok(Features { pixels, responses, border_px, descriptors })
    }
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
}
