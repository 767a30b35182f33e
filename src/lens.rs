//! Whether a lens model can be undone over a whole image. OpenCV's distortion model maps
//! an ideal (pinhole) point at normalised radius `r` to the observed radius
//! `g(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)` (plus the
//! small tangential terms). Undistorting a frame (`cv::undistort`, or the maps the live
//! camera builds) keeps the camera matrix and fetches each output pixel from `g` of its
//! radius, so it needs `g` to grow out to the output's corner. Coefficients fitted on a
//! narrow part of the field, or given for another image size, turn over before that: the
//! output beyond the turn shows the image folded back on itself, bearings there are wrong,
//! and OpenCV says nothing. mavloc refuses such a model by name instead.

use crate::geometry::Intrinsics;

/// Where the radial model turns over, as a fraction of the way from the principal point to
/// the image's farthest corner, when that is inside the image (`< 1`); `None` when `g`
/// grows all the way to the corner. `distortion` is OpenCV's
/// `[k1, k2, p1, p2(, k3(, k4, k5, k6))]`; the tangential `p1, p2` do not enter (they move
/// points by a few pixels, far less than a fold).
pub fn fold(k: &Intrinsics, distortion: &[f64]) -> Option<f64> {
    let c = |i: usize| distortion.get(i).copied().unwrap_or(0.0);
    let (k1, k2, k3, k4, k5, k6) = (c(0), c(1), c(4), c(5), c(6), c(7));
    let g = |r: f64| {
        let r2 = r * r;
        let den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
        (den > 0.0).then(|| r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / den)
    };
    // The farthest corner, normalised (pixel edges, not centres).
    let (w, h) = (k.width as f64, k.height as f64);
    let reach = [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)]
        .iter()
        .map(|&(u, v)| ((u - k.cx) / k.fx).hypot((v - k.cy) / k.fy))
        .fold(0.0, f64::max);
    if !(reach > 0.0 && reach.is_finite()) {
        return None;
    }
    // Steps of a 4000th of the way find a turn to well under a pixel.
    const STEPS: usize = 4000;
    let mut last = 0.0;
    for i in 1..=STEPS {
        let r = reach * i as f64 / STEPS as f64;
        match g(r) {
            Some(now) if now > last => last = now,
            _ => return Some((i - 1) as f64 / STEPS as f64),
        }
    }
    None
}

/// [`fold`] as a sentence for an error message, `None` when the model holds.
pub fn fold_problem(k: &Intrinsics, distortion: &[f64]) -> Option<String> {
    fold(k, distortion).map(|at| {
        format!(
            "the lens model turns back on itself {:.0} % of the way from the principal point to the \
             image's farthest corner, so undistorted frames would show the image folded back beyond \
             that; were the coefficients fitted for another image size (fx, fy are in pixels of this \
             one) or only near the centre?",
            100.0 * at
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Square pixels of focal length `f`, principal point at the centre.
    fn k(width: u32, height: u32, f: f64) -> Intrinsics {
        Intrinsics { fx: f, fy: f, ..Intrinsics::from_hfov(width, height, 1.0) }
    }

    /// Whether OpenCV's own undistortion maps fetch the pixels along the diagonal from the
    /// principal point to the farthest corner from ever farther out: what "no fold" means
    /// for an undistorted frame, computed by OpenCV.
    fn opencv_maps_grow_to_the_corner(k: &Intrinsics, d: &[f64]) -> bool {
        use opencv::core::{Mat, Size};
        use opencv::prelude::*;
        let m = Mat::from_slice_2d(&[[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]).unwrap();
        let dist = Mat::from_slice(d).unwrap().try_clone().unwrap();
        let (mut mx, mut my) = (Mat::default(), Mat::default());
        let size = Size::new(k.width as i32, k.height as i32);
        opencv::calib3d::init_undistort_rectify_map(
            &m,
            &dist,
            &opencv::core::no_array(),
            &m,
            size,
            opencv::core::CV_32FC1,
            &mut mx,
            &mut my,
        )
        .unwrap();
        let n = 400;
        let mut last = -1.0;
        for i in 0..=n {
            let t = i as f64 / n as f64;
            let (u, v) =
                (k.cx + t * (k.width as f64 - 1.0 - k.cx), k.cy + t * (k.height as f64 - 1.0 - k.cy));
            let (x, y) = (u.round() as i32, v.round() as i32);
            let (sx, sy) = (*mx.at_2d::<f32>(y, x).unwrap() as f64, *my.at_2d::<f32>(y, x).unwrap() as f64);
            let r = (sx - k.cx).hypot(sy - k.cy);
            if r < last - 1e-3 {
                return false;
            }
            last = r;
        }
        true
    }

    #[test]
    fn real_lenses_hold() {
        // A wide webcam at 1920x1080 (69 deg across) and a mild survey camera at 4000x3000.
        assert_eq!(fold(&k(1920, 1080, 1400.0), &[-0.3, 0.02, 0.0, 0.0, 0.0]), None);
        assert_eq!(fold(&k(4000, 3000, 2900.0), &[-0.11, 0.08, 0.001, -0.0005, -0.02]), None);
        assert_eq!(fold(&k(640, 480, 500.0), &[]), None, "no distortion");
        assert_eq!(fold(&k(640, 480, 500.0), &[0.0; 5]), None);
    }

    #[test]
    fn a_model_that_turns_over_inside_the_image_is_found_where_it_does() {
        // k1 = -0.5 at f = 500 px, 1920x1080: g' = 1 - 1.5 r^2 is 0 at r = 0.816, and the
        // corner is at r = hypot(960, 540) / 500 = 2.203: the turn is 37 % of the way out.
        let wide = k(1920, 1080, 500.0);
        let at = fold(&wide, &[-0.5, 0.0, 0.0, 0.0, 0.0]).unwrap();
        let expected = (1.0f64 / 1.5).sqrt() / (960.0f64.hypot(540.0) / 500.0);
        assert!((at - expected).abs() < 1e-3, "{at} vs {expected}");
        assert!(!opencv_maps_grow_to_the_corner(&wide, &[-0.5, 0.0, 0.0, 0.0, 0.0]));
        assert!(fold_problem(&wide, &[-0.5, 0.0, 0.0, 0.0, 0.0]).unwrap().contains("37 %"));
        // The webcam's coefficients given with focal lengths of a third of its size (a
        // calibration made at 640x360): turned over inside the image.
        let d = [-0.3, 0.02, 0.0, 0.0, 0.0];
        assert!(opencv_maps_grow_to_the_corner(&k(1920, 1080, 1400.0), &d));
        let wrong = fold(&k(1920, 1080, 1400.0 / 3.0), &d);
        assert!(wrong.is_some_and(|at| at < 1.0), "{wrong:?}");
        assert!(!opencv_maps_grow_to_the_corner(&k(1920, 1080, 1400.0 / 3.0), &d));
        // The rational model's denominator crossing zero inside the image.
        assert!(fold(&wide, &[0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0, 0.0]).is_some());
    }

    proptest! {
        /// Barrel and pincushion models of every strength: the check agrees with OpenCV's
        /// undistortion maps about whether the frame folds.
        #[test]
        fn the_fold_check_agrees_with_opencvs_undistortion_maps(
            k1 in -0.8f64..0.3,
            k2 in -0.2f64..0.2,
            k3 in -0.05f64..0.05,
            f in 120.0f64..700.0,
        ) {
            let k = k(640, 360, f);
            let d = [k1, k2, 0.0, 0.0, k3];
            let folds = fold(&k, &d);
            // Within 3 % of the corner the 400 samples of the oracle may miss the turn.
            prop_assume!(folds.is_none_or(|at| at < 0.97));
            prop_assert_eq!(folds.is_none(), opencv_maps_grow_to_the_corner(&k, &d), "fold {:?}", folds);
        }
    }
}
