//! The seed's previous method (area seed sec. 2.1, eq. 2.7-2.10; evaluated in sec. 6.11):
//! project the target area's border pixels onto a horizontal ground plane of assumed
//! height. Kept as a baseline so both methods run on the same data.

use opencv::core::{Mat, Point, Vector};
use opencv::imgproc;
use opencv::prelude::*;

use crate::geometry::{CameraPose, Intrinsics, Pixel, Vec3};

/// Ground-plane points of the border of `mask` (non-zero = target), one every `step`
/// pixels along each contour. Contour pixels on the image edge are skipped: there the
/// mask is cut by the frame, not bounded by the area.
pub fn border_points(
    mask: &Mat,
    pose: &CameraPose,
    k: &Intrinsics,
    ground_down: f64,
    step: usize,
) -> opencv::Result<Vec<Vec3>> {
    let mut binary = Mat::default();
    imgproc::threshold(mask, &mut binary, 127.0, 255.0, imgproc::THRESH_BINARY)?;
    let mut contours = Vector::<Vector<Point>>::new();
    imgproc::find_contours(
        &binary,
        &mut contours,
        imgproc::RETR_LIST,
        imgproc::CHAIN_APPROX_NONE,
        Point::new(0, 0),
    )?;
    let (w, h) = (mask.cols(), mask.rows());
    let mut out = Vec::new();
    for contour in contours.iter() {
        for (i, p) in contour.iter().enumerate() {
            if i % step.max(1) != 0 || p.x <= 0 || p.y <= 0 || p.x >= w - 1 || p.y >= h - 1 {
                continue;
            }
            if let Some(g) = pose.ground_intersection(k, Pixel::new(p.x as f64, p.y as f64), ground_down) {
                out.push(g);
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::area::features::blank;
    use crate::geometry::{GimbalAngles, GimbalChain, Mount};
    use opencv::core::{Rect, Scalar};

    #[test]
    fn nadir_square_projects_to_a_square_on_the_ground() {
        let k = Intrinsics::from_hfov(101, 101, 90f64.to_radians());
        let pose = CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -50.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, -90.0, 0.0),
            Mount::Earth,
        );
        let mut mask = blank(101, 101, 0.0).unwrap();
        imgproc::rectangle(&mut mask, Rect::new(30, 30, 41, 41), Scalar::all(255.0), -1, imgproc::LINE_8, 0)
            .unwrap();
        let pts = border_points(&mask, &pose, &k, 0.0, 1).unwrap();
        assert!(pts.len() > 100);
        // Pixel 30 is 20 px from the centre (50): 20 / fx of the 50 m height.
        let expected = 20.0 / k.fx * 50.0;
        for p in pts {
            assert!(p.z.abs() < 1e-9);
            let r = p.x.abs().max(p.y.abs());
            assert!((r - expected).abs() < 1e-9, "{p:?}");
        }
    }
}
