//! OpenCV image helpers shared by the pipelines, the frame sources and the commands. They
//! live below all of them so that a camera source need not import a pipeline to use one.

use opencv::core::Mat;
use opencv::imgproc;
use opencv::prelude::*;

/// An 8-bit RGB buffer (the simulator's frames) as an OpenCV BGR image.
pub fn bgr_from_rgb(rgb: &[u8], height: u32) -> opencv::Result<Mat> {
    let m = Mat::from_slice(rgb)?;
    let m = m.reshape(3, height as i32)?;
    let mut bgr = Mat::default();
    imgproc::cvt_color(&m, &mut bgr, imgproc::COLOR_RGB2BGR, 0)?;
    Ok(bgr)
}
