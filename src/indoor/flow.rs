//! The vehicle's horizontal velocity from two consecutive frames of its downward camera
//! over a flat floor: visual odometry, beyond the indoor seed (whose particle filter has
//! no motion input but a random walk, sec. 3.3.4).
//!
//! Why: with no GPS the autopilot's velocity is made of mavloc's own position estimates
//! and its IMU, so it cannot serve as the particles' motion model (an error would feed
//! itself), and PX4's EKF2, given positions alone, had to infer the velocity from them:
//! against PX4 v1.16 SIH its velocity came out at 0.6-0.8 of the true one on one axis and
//! its position lagged the truth by about 0.3 s. A measured velocity serves both.
//!
//! How: both frames are warped to a virtual camera at the same place that looks straight
//! down, north up (the homography of [`super::derotate`]), each with its focal length
//! chosen so that one canvas pixel is the same size on the floor in both. Rotation and the
//! change of height are then taken out, and what is left between the two canvases is a
//! translation, the camera's horizontal displacement, which phase correlation measures
//! to a fraction of a pixel (OpenCV's `phaseCorrelate`). The canvas covers the middle of
//! the lower frame's view, so it stays inside both views for tilts up to about 8 degrees.

use mavloc_geometry::{Intrinsics, Rot3};
use nalgebra::{Matrix3, Vector2, Vector3};
use opencv::core::{Mat, Size, BORDER_CONSTANT, CV_32F};
use opencv::imgproc;
use opencv::prelude::*;

use super::derotate::nadir_homography;

/// Canvas side, pixels: a size the DFT takes fast; the canvas covers about 110x110 pixels
/// of a 320x240 frame with a 70 degree view, so little is upsampled.
const SIDE: i32 = 128;
/// The canvas spans this share of the lower frame's narrower half view on each side of
/// the nadir: small enough that, turned to any heading (its corners reach out by the
/// square's diagonal), it stays in view at tilts up to about 8 degrees.
const FILL: f64 = 0.45;
/// A displacement of more than this share of the canvas is not trusted (phase
/// correlation wraps around at half of it).
const MAX_SHIFT_SHARE: f64 = 0.25;
/// Below this peak (`phaseCorrelate`'s response, 0..1) the canvases did not match: a
/// repetitive floor, a blurred frame, a jump. On 100 rendered pairs at 0.3-1.5 m, tilted
/// and turned, matching frames peaked at 0.65-0.9 and unrelated ones at 0.07 (median),
/// 0.22 at most.
pub const MIN_RESPONSE: f64 = 0.3;
/// Below this SD of the grey levels (0-255) a canvas has nothing to match: phase
/// correlation of two blank canvases still peaks, at no motion.
const MIN_CONTRAST: f64 = 3.0;
/// Frames further apart than this are not compared (the vehicle may have turned or
/// moved out of the canvas).
pub const MAX_DT_S: f64 = 0.5;
/// SD of the measured shift in canvas pixels for a good match (phase correlation's
/// sub-pixel peak; measured on rendered pairs, 0.05-0.1 px), kept with a margin.
const SHIFT_SD_PX: f64 = 0.3;
/// SD of the error in the attitude change between two frames as the autopilot reports
/// it, rad. An error of the change turns the view like a move would: `height x` this per
/// frame interval. Against PX4 v1.16 SIH (frames rendered from its true attitude,
/// derotated with its estimate) EKF2's attitude error changed by 0.135 deg RMS in roll and
/// 0.064 in pitch over a 67 ms frame interval (its gyro's noise), and the velocity came out
/// 0.02 m/s RMS off on x and 0.03-0.05 on y at about 1 m, under the 0.059-0.070 m/s this
/// claims. Kept above what was measured on purpose: claiming the measured 0.15 deg (0.042
/// m/s), with `EKF2_EVV_NOISE` 0.03 to let it count, EKF2's velocity came out closer to the
/// truth (0.046 m/s RMS against 0.057) but PX4's precision landings touched down farther
/// from the zone, 0.210 m on average over 13 cold starts (two misses) against 0.134 m over
/// 14 with this (README, "Against PX4 SITL", session 44).
const ATTITUDE_CHANGE_SD_RAD: f64 = 0.25 * std::f64::consts::PI / 180.0;

/// One frame as the flow needs it.
pub struct FlowFrame {
    /// Autopilot time of capture, s.
    pub t: f64,
    /// Grey, 8-bit, at the camera's resolution (only the canvas is made float).
    pub gray: Mat,
    /// "local <- camera (OpenCV axes)".
    pub local_from_camera: Rot3,
    /// The camera's height above the floor, m.
    pub height: f64,
}

impl FlowFrame {
    pub fn new(t: f64, bgr: &Mat, local_from_camera: Rot3, height: f64) -> opencv::Result<FlowFrame> {
        let mut gray = Mat::default();
        imgproc::cvt_color_def(bgr, &mut gray, imgproc::COLOR_BGR2GRAY)?;
        Ok(FlowFrame { t, gray, local_from_camera, height })
    }
}

/// The motion between two frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Motion {
    pub dt: f64,
    /// Horizontal displacement of the camera (north, east), m.
    pub displacement: Vector2<f64>,
    /// `displacement / dt`, m/s.
    pub velocity: Vector2<f64>,
    /// From the change of height (down positive), m/s.
    pub vertical_velocity: f64,
    /// SD of each horizontal velocity component, m/s: the image's part and the part of
    /// the attitude the autopilot reports.
    pub sd_m_s: f64,
    /// Phase correlation's peak, 0..1.
    pub response: f64,
    /// Canvas pixel on the floor, m.
    pub pixel_m: f64,
}

/// Why two frames gave no motion.
#[derive(Clone, Debug, PartialEq)]
pub enum NoMotion {
    /// Not after the previous frame, or too long after it.
    Time(f64),
    /// No usable height.
    Height(f64),
    /// The canvas is not inside both views (tilted too far): where a corner of it falls
    /// in the image, pixels.
    OutOfView((f64, f64)),
    /// Nothing to match on the floor (grey-level SD).
    Blank(f64),
    /// The canvases did not match well enough.
    Weak(f64),
    /// Matched, but further than the canvas allows.
    TooFar(f64),
    Cv(String),
}

impl std::fmt::Display for NoMotion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NoMotion::Time(dt) => write!(f, "frames {dt:.3} s apart"),
            NoMotion::Height(h) => write!(f, "no usable height ({h:.2} m)"),
            NoMotion::OutOfView((x, y)) => {
                write!(f, "the floor patch is not in both views (a corner at pixel {x:.0}, {y:.0})")
            }
            NoMotion::Blank(sd) => write!(f, "a blank floor (grey-level SD {sd:.1})"),
            NoMotion::Weak(r) => write!(f, "frames do not match (peak {r:.2})"),
            NoMotion::TooFar(px) => write!(f, "shift of {px:.1} px is beyond the canvas"),
            NoMotion::Cv(e) => write!(f, "OpenCV: {e}"),
        }
    }
}

impl From<opencv::Error> for NoMotion {
    fn from(e: opencv::Error) -> Self {
        NoMotion::Cv(e.to_string())
    }
}

/// Measures the motion between frames; keeps what every pair uses (the correlation's
/// window), so a frame costs only its two warps and the correlation.
pub struct Flow {
    window: Mat,
}

impl Flow {
    pub fn new() -> opencv::Result<Flow> {
        let mut window = Mat::default();
        imgproc::create_hanning_window(&mut window, Size::new(SIDE, SIDE), CV_32F)?;
        Ok(Flow { window })
    }

    /// The camera's motion from `prev` to `cur`; `k`: the intrinsics of their images.
    pub fn motion(&self, prev: &FlowFrame, cur: &FlowFrame, k: &Intrinsics) -> Result<Motion, NoMotion> {
        motion(prev, cur, k, &self.window)
    }
}

fn motion(prev: &FlowFrame, cur: &FlowFrame, k: &Intrinsics, window: &Mat) -> Result<Motion, NoMotion> {
    let dt = cur.t - prev.t;
    if !(dt > 0.0 && dt <= MAX_DT_S) {
        return Err(NoMotion::Time(dt));
    }
    let low = prev.height.min(cur.height);
    if !(low.is_finite() && low > 0.02) {
        return Err(NoMotion::Height(low));
    }
    // The canvas: FILL of the lower frame's narrower half view, each side of the nadir.
    let half_view = (k.cx / k.fx).min(k.cy / k.fy);
    let pixel_m = 2.0 * FILL * half_view * low / SIDE as f64;
    let a = canvas(prev, k, pixel_m)?;
    let b = canvas(cur, k, pixel_m)?;
    for c in [&a, &b] {
        let (mut mean, mut sd) = (Mat::default(), Mat::default());
        opencv::core::mean_std_dev(c, &mut mean, &mut sd, &opencv::core::no_array())?;
        let sd = *sd.at::<f64>(0)?;
        if sd.is_nan() || sd < MIN_CONTRAST {
            return Err(NoMotion::Blank(sd));
        }
    }
    let mut response = 0.0;
    // The floor's content moves by `shift` canvas pixels from a to b.
    let shift = imgproc::phase_correlate(&a, &b, window, Some(&mut response))?;
    if response.is_nan() || response < MIN_RESPONSE {
        return Err(NoMotion::Weak(response));
    }
    let px = shift.x.hypot(shift.y);
    if px > MAX_SHIFT_SHARE * SIDE as f64 {
        return Err(NoMotion::TooFar(px));
    }
    // Canvas up is north, right is east: the floor sliding down (+v) in view means the
    // camera went north; sliding right (+u), it went west.
    let displacement = Vector2::new(shift.y * pixel_m, -shift.x * pixel_m);
    Ok(Motion {
        dt,
        displacement,
        velocity: displacement / dt,
        vertical_velocity: (prev.height - cur.height) / dt,
        sd_m_s: (SHIFT_SD_PX * pixel_m).hypot(ATTITUDE_CHANGE_SD_RAD * low) / dt,
        response,
        pixel_m,
    })
}

/// `f`'s view warped to the north-up nadir canvas with canvas pixels `pixel_m` on the floor.
fn canvas(f: &FlowFrame, k: &Intrinsics, pixel_m: f64) -> Result<Mat, NoMotion> {
    let focal = f.height / pixel_m;
    let centre = (SIDE as f64 - 1.0) / 2.0;
    let h = nadir_homography(k, &f.local_from_camera, focal, centre);
    let inv = h.try_inverse().ok_or(NoMotion::OutOfView((f64::NAN, f64::NAN)))?;
    let last = SIDE as f64 - 1.0;
    for (u, v) in [(0.0, 0.0), (last, 0.0), (0.0, last), (last, last)] {
        let p = inv * Vector3::new(u, v, 1.0);
        let (x, y) = (p.x / p.z, p.y / p.z);
        if !(p.z > 0.0 && x >= 0.0 && y >= 0.0 && x <= (k.width - 1) as f64 && y <= (k.height - 1) as f64) {
            return Err(NoMotion::OutOfView((x, y)));
        }
    }
    let m = to_mat(&h)?;
    let mut out = Mat::default();
    imgproc::warp_perspective(
        &f.gray,
        &mut out,
        &m,
        Size::new(SIDE, SIDE),
        imgproc::INTER_LINEAR,
        BORDER_CONSTANT,
        Default::default(),
    )?;
    // Float for the correlation: the canvas only, not the whole frame.
    let mut float = Mat::default();
    out.convert_to(&mut float, CV_32F, 1.0, 0.0)?;
    Ok(float)
}

fn to_mat(h: &Matrix3<f64>) -> opencv::Result<Mat> {
    let rows: Vec<Vec<f64>> = (0..3).map(|r| (0..3).map(|c| h[(r, c)]).collect()).collect();
    Mat::from_slice_2d(&rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavloc_geometry::{body_rotation, CameraPose, GimbalAngles, GimbalChain, Mount, Vec3};
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use std::f64::consts::PI;

    /// A floor texture: blurred noise, `res` m per pixel, its top-left corner at
    /// (north, east) = (N0, -N0).
    const TEX: i32 = 1200;
    const RES: f64 = 0.0025;
    const N0: f64 = TEX as f64 * RES / 2.0;

    fn floor(seed: u64, blur: f64) -> Mat {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let data: Vec<u8> = (0..TEX * TEX).map(|_| rng.random()).collect();
        let m = Mat::from_slice(&data).unwrap().reshape(1, TEX).unwrap().try_clone().unwrap();
        let mut out = Mat::default();
        imgproc::gaussian_blur_def(&m, &mut out, Size::new(0, 0), blur).unwrap();
        let mut bgr = Mat::default();
        imgproc::cvt_color_def(&out, &mut bgr, imgproc::COLOR_GRAY2BGR).unwrap();
        bgr
    }

    fn camera(roll: f64, pitch: f64, yaw: f64) -> Rot3 {
        CameraPose::from_gimbal(
            Vec3::zeros(),
            GimbalChain::YawPitchRoll,
            GimbalAngles { yaw: 0.0, pitch: -PI / 2.0, roll: 0.0 },
            Mount::Body { attitude: body_rotation(roll, pitch, yaw) },
        )
        .local_from_camera()
    }

    /// Renders the floor as a camera at (north, east), `height` above it, sees it: each
    /// pixel's ray meets the floor (z = 0) where the texture is read. Written apart from
    /// the module's own warping, through the floor plane.
    fn render(tex: &Mat, k: &Intrinsics, r: &Rot3, north: f64, east: f64, height: f64) -> Mat {
        let kinv = Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0).try_inverse().unwrap();
        // Ray (n, e, d) -> floor point (north + h n/d, east + h e/d), homogeneous.
        let on_floor = Matrix3::new(height, 0.0, north, 0.0, height, east, 0.0, 0.0, 1.0);
        // Floor (n, e) -> texture pixel (col, row).
        let to_tex = Matrix3::new(0.0, 1.0 / RES, N0 / RES, -1.0 / RES, 0.0, N0 / RES, 0.0, 0.0, 1.0);
        let m = to_tex * on_floor * r.matrix() * kinv;
        let mut out = Mat::default();
        imgproc::warp_perspective(
            tex,
            &mut out,
            &to_mat(&m).unwrap(),
            Size::new(k.width as i32, k.height as i32),
            imgproc::INTER_LINEAR | imgproc::WARP_INVERSE_MAP,
            BORDER_CONSTANT,
            Default::default(),
        )
        .unwrap();
        out
    }

    fn motion(a: &FlowFrame, b: &FlowFrame, k: &Intrinsics) -> Result<Motion, NoMotion> {
        Flow::new().unwrap().motion(a, b, k)
    }

    fn k() -> Intrinsics {
        Intrinsics::from_hfov(320, 240, 70f64.to_radians())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Whatever the attitude, heading and change of height between the frames, the
        /// displacement comes out to a fraction of a canvas pixel (1-5 mm).
        #[test]
        fn the_displacement_is_the_cameras_whatever_the_attitude_and_height(
            r0 in -0.15f64..0.15, p0 in -0.15f64..0.15, yaw0 in -PI..PI,
            dr in -0.03f64..0.03, dp in -0.03f64..0.03, dyaw in -0.05f64..0.05,
            h0 in 0.3f64..1.5, dh in -0.05f64..0.05,
            fn_ in -0.05f64..0.05, fe in -0.05f64..0.05,
        ) {
            let tex = floor(1, 1.5);
            let k = k();
            // Up to 5 % of the height per frame: 0.75 m/s at 1 m and 15 frames/s.
            let (dn, de) = (fn_ * h0, fe * h0);
            let (n0, e0) = (0.1, -0.2);
            let a_rot = camera(r0, p0, yaw0);
            let b_rot = camera(r0 + dr, p0 + dp, yaw0 + dyaw);
            let a = FlowFrame::new(0.0, &render(&tex, &k, &a_rot, n0, e0, h0), a_rot, h0).unwrap();
            let b = FlowFrame::new(1.0 / 15.0, &render(&tex, &k, &b_rot, n0 + dn, e0 + de, h0 + dh), b_rot, h0 + dh).unwrap();
            let m = match motion(&a, &b, &k) {
                // The canvas leaves a frame's view only when it is tilted beyond the range
                // the generator starts from (10 deg at 0.3 m: roll 0.12 with pitch -0.16
                // once came out), and then saying so is the right answer.
                Err(NoMotion::OutOfView(_)) => {
                    let tilt = r0.hypot(p0).max((r0 + dr).hypot(p0 + dp));
                    prop_assert!(tilt > 0.15, "out of view at a tilt of {tilt:.3} rad, height {h0:.2} m");
                    return Ok(());
                }
                other => other.unwrap(),
            };
            let err = ((m.displacement.x - dn).powi(2) + (m.displacement.y - de).powi(2)).sqrt();
            // A pixel of the canvas is 2-10 mm here; the claimed SD is 0.3 px.
            prop_assert!(err <= 0.5 * m.pixel_m + 0.001,
                "moved ({dn:.4}, {de:.4}), measured ({:.4}, {:.4}), pixel {:.4} m, peak {:.2}",
                m.displacement.x, m.displacement.y, m.pixel_m, m.response);
            prop_assert!((m.velocity - m.displacement * 15.0).norm() < 1e-9);
            prop_assert!((m.vertical_velocity + dh * 15.0).abs() < 1e-9);
        }
    }

    #[test]
    fn a_featureless_floor_gives_no_motion() {
        let k = k();
        let flat = Mat::new_rows_cols_with_default(TEX, TEX, opencv::core::CV_8UC3, 128.into()).unwrap();
        let r = camera(0.0, 0.0, 0.0);
        let a = FlowFrame::new(0.0, &render(&flat, &k, &r, 0.0, 0.0, 1.0), r, 1.0).unwrap();
        let b = FlowFrame::new(0.066, &render(&flat, &k, &r, 0.02, 0.0, 1.0), r, 1.0).unwrap();
        assert!(matches!(motion(&a, &b, &k), Err(NoMotion::Blank(_))), "{:?}", motion(&a, &b, &k));
    }

    #[test]
    fn unrelated_frames_steep_tilts_and_stale_frames_give_no_motion() {
        let k = k();
        let tex = floor(2, 1.5);
        let r = camera(0.0, 0.0, 0.0);
        let a = FlowFrame::new(0.0, &render(&tex, &k, &r, 0.0, 0.0, 1.0), r, 1.0).unwrap();
        // Another part of the floor altogether.
        let far = FlowFrame::new(0.066, &render(&tex, &k, &r, 1.0, 0.8, 1.0), r, 1.0).unwrap();
        let m = motion(&a, &far, &k);
        assert!(matches!(m, Err(NoMotion::Weak(_) | NoMotion::TooFar(_))), "{m:?}");
        // Tilted 35 degrees: the canvas leaves the view.
        let tilted = camera(0.6, 0.0, 0.0);
        let t = FlowFrame::new(0.066, &render(&tex, &k, &tilted, 0.0, 0.0, 1.0), tilted, 1.0).unwrap();
        assert!(matches!(motion(&a, &t, &k), Err(NoMotion::OutOfView(_))));
        let late = FlowFrame::new(2.0, &render(&tex, &k, &r, 0.0, 0.0, 1.0), r, 1.0).unwrap();
        assert_eq!(motion(&a, &late, &k), Err(NoMotion::Time(2.0)));
        let low = FlowFrame::new(0.066, &render(&tex, &k, &r, 0.0, 0.0, 1.0), r, 0.0).unwrap();
        assert!(matches!(motion(&a, &low, &k), Err(NoMotion::Height(_))));
    }

    #[test]
    fn the_claimed_sd_covers_the_error_of_a_flight_of_pairs() {
        // 60 pairs at 1 m, 0.5 m/s in random directions with a little attitude motion:
        // the velocity error's RMS is below the SD each pair claims.
        let tex = floor(3, 1.5);
        let k = k();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let (mut sq, mut claimed) = (0.0, 0.0);
        for _ in 0..60 {
            let yaw: f64 = rng.random_range(-PI..PI);
            let dir: f64 = rng.random_range(-PI..PI);
            let v = Vector2::new(dir.cos(), dir.sin()) * 0.5;
            let dt = 1.0 / 15.0;
            let a_rot = camera(rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1), yaw);
            let b_rot = camera(rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1), yaw + 0.02);
            let a = FlowFrame::new(0.0, &render(&tex, &k, &a_rot, 0.0, 0.0, 1.0), a_rot, 1.0).unwrap();
            let b =
                FlowFrame::new(dt, &render(&tex, &k, &b_rot, v.x * dt, v.y * dt, 1.0), b_rot, 1.0).unwrap();
            let m = motion(&a, &b, &k).unwrap();
            sq += (m.velocity - v).norm_squared() / 2.0;
            claimed += m.sd_m_s.powi(2);
        }
        let (rms, sd) = ((sq / 60.0).sqrt(), (claimed / 60.0).sqrt());
        assert!(rms < sd, "velocity error RMS {rms:.4} m/s per axis, claimed SD {sd:.4}");
        // The image's part alone is much smaller: this is exact attitude.
        assert!(rms < 0.03, "velocity error RMS {rms:.4} m/s per axis");
        assert!(sd < 0.1, "a useful velocity: SD {sd:.4} m/s");
    }
}
