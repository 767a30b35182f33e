//! Frame preparation for the texton histograms: downscale to the working resolution and,
//! beyond the seed (its future work, indoor seed ch. 5), derotate by the camera's attitude.
//!
//! Derotation warps the frame to a virtual camera at the same place that looks straight
//! down with image right = east and image up = north. For a flat floor that is the pure
//! rotation homography `H = K_v R_v^T R_c K^-1` (`R_c` "local <- camera" of the real
//! camera, `R_v` of the virtual one). The histogram is then taken over a disk centred on the
//! nadir, so every frame describes the same footprint whatever the heading, roll and pitch;
//! textons are not rotation invariant, and without this a turned vehicle sees other
//! textons on the same floor. Parts of the disk the camera did not see are masked out.
//!
//! With a reference height (`indoor.height_ref_m`, kept in the model) the virtual camera's
//! focal length is also scaled by `height / height_ref`, so the floor appears at the scale
//! it has from the reference height whatever the height: textons are not scale invariant
//! either. Below the reference the camera sees only the middle of the disk (the rest is
//! masked out), above it the disk is a magnified middle of the frame. This is what lets
//! the vehicle localise while climbing or descending through heights the model was not
//! trained at.

use mavloc_geometry::{Intrinsics, Rot3};
use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Scalar, Size, BORDER_CONSTANT, CV_8UC1};
use opencv::imgproc;
use opencv::prelude::*;

use super::textons::{PatchMask, YuvImage};

// Moved to `crate::imaging` (the sim camera uses it too); this path is kept for callers.
pub use crate::imaging::bgr_from_rgb;

/// A prepared frame: the image to take patches from and where patches may be taken.
pub struct Canvas {
    pub img: YuvImage,
    pub mask: PatchMask,
}

/// Prepares frames of one camera.
#[derive(Clone, Debug)]
pub struct Preprocessor {
    /// The camera's intrinsics at its own resolution.
    pub camera: Intrinsics,
    /// The intrinsics at the working resolution.
    pub work: Intrinsics,
    pub derotate: bool,
    /// Remove brightness and contrast: Y to a fixed mean and SD over the valid pixels, U
    /// and V scaled about neutral by the same factor (an affine change of RGB is undone).
    pub normalise: bool,
    /// Rescale to the floor's scale from this camera height (m); `None`: no rescaling.
    pub height_ref: Option<f64>,
    patch: (usize, usize),
}

/// The rescaling is bounded: below a quarter of the reference height too little of the
/// disk is seen to describe the place, above four times it the magnified middle is blur.
const SCALE_RANGE: (f64, f64) = (0.25, 4.0);

/// Intrinsics of the same camera at `scale` times the resolution (pixel centres kept).
pub fn scaled(k: &Intrinsics, scale: f64) -> Intrinsics {
    Intrinsics {
        width: ((k.width as f64 * scale).round() as u32).max(1),
        height: ((k.height as f64 * scale).round() as u32).max(1),
        fx: k.fx * scale,
        fy: k.fy * scale,
        cx: (k.cx + 0.5) * scale - 0.5,
        cy: (k.cy + 0.5) * scale - 0.5,
    }
}

/// "local <- virtual camera": optical axis down, image x east, image y south.
fn virtual_camera() -> Matrix3<f64> {
    Matrix3::new(
        0.0, -1.0, 0.0, //
        1.0, 0.0, 0.0, //
        0.0, 0.0, 1.0,
    )
}

impl Preprocessor {
    /// `work_width`: frames are downscaled to this width (never upscaled).
    pub fn new(camera: Intrinsics, work_width: u32, derotate: bool, patch: (usize, usize)) -> Preprocessor {
        let scale = (work_width as f64 / camera.width as f64).min(1.0);
        let work = scaled(&camera, scale);
        Preprocessor { camera, work, derotate, normalise: false, height_ref: None, patch }
    }

    /// Side of the derotated canvas: the largest disk the level camera sees whole.
    pub fn side(&self) -> usize {
        self.work.width.min(self.work.height) as usize
    }

    /// The virtual camera's focal length over the real one's for a camera `height` above
    /// the floor: 1 without a reference height (or a usable height).
    pub fn scale(&self, height: Option<f64>) -> f64 {
        match (self.height_ref, height) {
            (Some(r), Some(h)) if r > 0.0 && h.is_finite() && h > 0.0 => {
                (h / r).clamp(SCALE_RANGE.0, SCALE_RANGE.1)
            }
            _ => 1.0,
        }
    }

    /// The homography from working-resolution pixels to canvas pixels for a camera with
    /// rotation "local <- camera (OpenCV axes)", its virtual focal length `scale` times the
    /// real one ([`Preprocessor::scale`]).
    pub fn homography(&self, local_from_camera: &Rot3, scale: f64) -> Matrix3<f64> {
        let k = &self.work;
        let kw = Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0);
        let c = (self.side() as f64 - 1.0) / 2.0;
        // At scale 1 one canvas pixel is one working pixel at the nadir.
        let f = k.fx * scale;
        let kv = Matrix3::new(f, 0.0, c, 0.0, f, c, 0.0, 0.0, 1.0);
        let kw_inv = kw.try_inverse().expect("intrinsics with non-zero focal lengths are invertible");
        kv * virtual_camera().transpose() * local_from_camera.matrix() * kw_inv
    }

    /// Ground offset (north, east) per metre of height of a canvas pixel from the nadir.
    pub fn canvas_offset(&self, u: f64, v: f64) -> (f64, f64) {
        let c = (self.side() as f64 - 1.0) / 2.0;
        (-(v - c) / self.work.fx, (u - c) / self.work.fx)
    }

    /// Prepares a BGR frame at the camera's resolution. `attitude` is the camera's
    /// rotation "local <- camera (OpenCV axes)"; without it, or with derotation off, the
    /// whole downscaled frame is used as the seed does. `height`: the camera's height
    /// above the floor, for the rescaling to the reference height (if there is one).
    pub fn prepare(&self, bgr: &Mat, attitude: Option<&Rot3>, height: Option<f64>) -> opencv::Result<Canvas> {
        if (bgr.cols(), bgr.rows()) != (self.camera.width as i32, self.camera.height as i32) {
            return Err(opencv::Error::new(
                opencv::core::StsBadSize,
                format!(
                    "frame is {}x{}, the camera is {}x{}",
                    bgr.cols(),
                    bgr.rows(),
                    self.camera.width,
                    self.camera.height
                ),
            ));
        }
        let mut resized = Mat::default();
        let small = if self.work.width != self.camera.width {
            let size = Size::new(self.work.width as i32, self.work.height as i32);
            imgproc::resize(bgr, &mut resized, size, 0.0, 0.0, imgproc::INTER_AREA)?;
            &resized
        } else {
            bgr
        };
        let (pw, ph) = self.patch;
        match attitude.filter(|_| self.derotate) {
            None => {
                let mut img = yuv_from_bgr(small)?;
                let valid = vec![true; img.width * img.height];
                if self.normalise {
                    normalise(&mut img, &valid);
                }
                let mask = PatchMask::from_valid(img.width, img.height, &valid, pw, ph);
                Ok(Canvas { img, mask })
            }
            Some(r) => {
                let h = self.homography(r, self.scale(height));
                let hm = Mat::from_slice_2d(&[
                    [h[(0, 0)], h[(0, 1)], h[(0, 2)]],
                    [h[(1, 0)], h[(1, 1)], h[(1, 2)]],
                    [h[(2, 0)], h[(2, 1)], h[(2, 2)]],
                ])?;
                let side = self.side() as i32;
                let size = Size::new(side, side);
                let mut warped = Mat::default();
                imgproc::warp_perspective(
                    small,
                    &mut warped,
                    &hm,
                    size,
                    imgproc::INTER_LINEAR,
                    BORDER_CONSTANT,
                    Scalar::all(0.0),
                )?;
                let ones =
                    Mat::new_rows_cols_with_default(small.rows(), small.cols(), CV_8UC1, Scalar::all(255.0))?;
                let mut seen = Mat::default();
                imgproc::warp_perspective(
                    &ones,
                    &mut seen,
                    &hm,
                    size,
                    imgproc::INTER_NEAREST,
                    BORDER_CONSTANT,
                    Scalar::all(0.0),
                )?;
                let mut img = yuv_from_bgr(&warped)?;
                let n = side as usize;
                let c = (n as f64 - 1.0) / 2.0;
                let r2 = (n as f64 / 2.0).powi(2);
                let seen = seen.data_bytes()?;
                let valid: Vec<bool> = (0..n * n)
                    .map(|i| {
                        let (x, y) = ((i % n) as f64 - c, (i / n) as f64 - c);
                        seen[i] == 255 && x * x + y * y <= r2
                    })
                    .collect();
                if self.normalise {
                    normalise(&mut img, &valid);
                }
                let mask = PatchMask::from_valid(n, n, &valid, pw, ph);
                Ok(Canvas { img, mask })
            }
        }
    }
}

/// Target mean and SD of Y after normalisation, grey levels.
const NORMAL_MEAN: f32 = 128.0;
const NORMAL_SD: f32 = 40.0;

/// Brightness `b` and contrast `c` (`RGB' = c RGB + b`) give `Y' = c Y + b` and
/// `U' - 128 = c (U - 128)`: standardising Y over the valid pixels and scaling U and V by
/// the same factor undoes them.
pub fn normalise(img: &mut YuvImage, valid: &[bool]) {
    let (mut sum, mut sum2, mut n) = (0.0f64, 0.0f64, 0usize);
    for (p, _) in img.data.iter().zip(valid).filter(|(_, v)| **v) {
        sum += p[0] as f64;
        sum2 += (p[0] as f64).powi(2);
        n += 1;
    }
    if n < 2 {
        return;
    }
    let mean = sum / n as f64;
    let sd = ((sum2 / n as f64 - mean * mean).max(0.0)).sqrt();
    if sd < 1e-3 {
        return;
    }
    let gain = NORMAL_SD / sd as f32;
    let mean = mean as f32;
    for p in &mut img.data {
        p[0] = (p[0] - mean) * gain + NORMAL_MEAN;
        p[1] = (p[1] - 128.0) * gain + 128.0;
        p[2] = (p[2] - 128.0) * gain + 128.0;
    }
}

/// A continuous 8-bit BGR image to Y, U, V.
pub fn yuv_from_bgr(bgr: &Mat) -> opencv::Result<YuvImage> {
    let (w, h) = (bgr.cols() as usize, bgr.rows() as usize);
    if bgr.is_continuous() {
        return Ok(YuvImage::from_bgr(w, h, bgr.data_bytes()?));
    }
    // A view into a larger image: copy it to one block first.
    Ok(YuvImage::from_bgr(w, h, bgr.try_clone()?.data_bytes()?))
}

/// The pixel (working resolution) where the camera's nadir appears, if in front of it.
pub fn nadir_pixel(k: &Intrinsics, local_from_camera: &Rot3) -> Option<(f64, f64)> {
    let d = local_from_camera.inverse() * Vector3::new(0.0, 0.0, 1.0);
    (d.z > 1e-9).then(|| (k.fx * d.x / d.z + k.cx, k.fy * d.y / d.z + k.cy))
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavloc_geometry::{body_rotation, CameraPose, GimbalAngles, GimbalChain, Mount, Vec3};
    use proptest::prelude::*;
    use std::f64::consts::PI;

    fn down_camera(roll: f64, pitch: f64, yaw: f64) -> Rot3 {
        let pose = CameraPose::from_gimbal(
            Vec3::zeros(),
            GimbalChain::YawPitchRoll,
            GimbalAngles { yaw: 0.0, pitch: -PI / 2.0, roll: 0.0 },
            Mount::Body { attitude: body_rotation(roll, pitch, yaw) },
        );
        pose.local_from_camera()
    }

    proptest! {
        /// A floor point lands where the virtual north-up nadir camera would see it.
        #[test]
        fn homography_maps_floor_points_to_the_virtual_view(
            roll in -0.2f64..0.2, pitch in -0.2f64..0.2, yaw in -PI..PI,
            north in -0.3f64..0.3, east in -0.3f64..0.3, height in 0.5f64..2.0,
        ) {
            let k = Intrinsics::from_hfov(320, 240, 70f64.to_radians());
            let pre = Preprocessor::new(k, 320, true, (6, 6));
            let r = down_camera(roll, pitch, yaw);
            let pose = CameraPose { position: Vec3::new(0.0, 0.0, -height), attitude: r * mavloc_geometry::gimbal_from_camera().inverse() };
            let point = Vec3::new(north, east, 0.0);
            let px = pose.project(&k, &point).unwrap();
            let h = pre.homography(&r, 1.0);
            let q = h * Vector3::new(px.u, px.v, 1.0);
            let (u, v) = (q.x / q.z, q.y / q.z);
            let (dn, de) = pre.canvas_offset(u, v);
            prop_assert!((dn * height - north).abs() < 1e-9 && (de * height - east).abs() < 1e-9);
        }

        /// With a reference height, a floor point lands where the level camera at the
        /// reference height would see it, from any height and tilt: the floor keeps one
        /// scale on the canvas.
        #[test]
        fn with_a_reference_height_the_floor_keeps_its_scale(
            roll in -0.2f64..0.2, pitch in -0.2f64..0.2, yaw in -PI..PI,
            north in -0.15f64..0.15, east in -0.15f64..0.15, height in 0.4f64..2.0,
        ) {
            let k = Intrinsics::from_hfov(320, 240, 70f64.to_radians());
            let mut pre = Preprocessor::new(k, 320, true, (6, 6));
            pre.height_ref = Some(1.0);
            let r = down_camera(roll, pitch, yaw);
            let pose = CameraPose { position: Vec3::new(0.0, 0.0, -height), attitude: r * mavloc_geometry::gimbal_from_camera().inverse() };
            let px = pose.project(&k, &Vec3::new(north, east, 0.0)).unwrap();
            let q = pre.homography(&r, pre.scale(Some(height))) * Vector3::new(px.u, px.v, 1.0);
            let (dn, de) = pre.canvas_offset(q.x / q.z, q.y / q.z);
            // canvas_offset is per metre of height at scale 1: times the reference height.
            prop_assert!((dn - north).abs() < 1e-9 && (de - east).abs() < 1e-9, "{dn} {de} vs {north} {east}");
        }
    }

    #[test]
    fn the_scale_is_bounded_and_off_without_a_reference() {
        let k = Intrinsics::from_hfov(320, 240, 1.2);
        let mut pre = Preprocessor::new(k, 320, true, (6, 6));
        assert_eq!(pre.scale(Some(0.5)), 1.0, "no reference: no rescaling");
        pre.height_ref = Some(1.0);
        assert_eq!(pre.scale(Some(0.5)), 0.5);
        assert_eq!(pre.scale(Some(0.01)), SCALE_RANGE.0);
        assert_eq!(pre.scale(Some(f64::NAN)), 1.0);
        assert_eq!(pre.scale(None), 1.0);
    }

    #[test]
    fn nadir_of_a_level_camera_is_the_principal_point() {
        let k = Intrinsics::from_hfov(320, 240, 1.2);
        let (u, v) = nadir_pixel(&k, &down_camera(0.0, 0.0, 0.7)).unwrap();
        assert!((u - k.cx).abs() < 1e-9 && (v - k.cy).abs() < 1e-9);
        let (u, _) = nadir_pixel(&k, &down_camera(0.1, 0.0, 0.0)).unwrap();
        assert!(u != k.cx);
    }

    #[test]
    fn normalisation_undoes_brightness_and_contrast() {
        let rgb: Vec<u8> = (0..300).map(|i| ((i * 37) % 200 + 20) as u8).collect();
        let changed: Vec<u8> = rgb.iter().map(|&v| (v as f32 * 1.15 - 12.0).round() as u8).collect();
        let mut a = YuvImage::from_rgb(10, 10, &rgb).unwrap();
        let mut b = YuvImage::from_rgb(10, 10, &changed).unwrap();
        let valid = vec![true; 100];
        normalise(&mut a, &valid);
        normalise(&mut b, &valid);
        for (p, q) in a.data.iter().zip(&b.data) {
            for c in 0..3 {
                // Within the rounding of the 8-bit change.
                assert!((p[c] - q[c]).abs() < 1.5, "{p:?} vs {q:?}");
            }
        }
    }

    #[test]
    fn scaled_intrinsics_keep_the_field_of_view() {
        let k = Intrinsics::from_hfov(640, 480, 1.2);
        let s = scaled(&k, 0.5);
        assert_eq!((s.width, s.height), (320, 240));
        assert!((s.hfov() - k.hfov()).abs() < 1e-9);
        assert!((s.cx - (s.width as f64 - 1.0) / 2.0).abs() < 1e-9);
    }
}
