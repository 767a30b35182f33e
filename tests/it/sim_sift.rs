//! The simulated world is good enough for SIFT: along the coastline flight, features in the
//! band around the water (area seed sec. 5.2: dilate the mask, subtract it) are found and
//! matched between consecutive frames with the seed's ratio test (r < 0.5, eq. 5.10).

use mavloc_sim::{Mission, Renderer, Scenario, World};
use opencv::core::{self, KeyPoint, Mat, Vector};
use opencv::features2d::{BFMatcher, SIFT};
use opencv::imgproc;
use opencv::prelude::*;

fn to_mat(data: &[u8], w: u32, h: u32, channels: i32) -> Mat {
    let flat = Mat::from_slice(data).unwrap();
    flat.reshape(channels, h as i32).unwrap().try_clone().unwrap_or_else(|_| panic!("{w}x{h}"))
}

/// Band of `width` px around the target area: dilate(mask) - mask.
fn band(mask: &Mat, width: i32) -> Mat {
    let kernel = imgproc::get_structuring_element(
        imgproc::MORPH_ELLIPSE,
        core::Size::new(2 * width + 1, 2 * width + 1),
        core::Point::new(-1, -1),
    )
    .unwrap();
    let mut dilated = Mat::default();
    imgproc::dilate(
        mask,
        &mut dilated,
        &kernel,
        core::Point::new(-1, -1),
        1,
        core::BORDER_CONSTANT,
        imgproc::morphology_default_border_value().unwrap(),
    )
    .unwrap();
    let mut out = Mat::default();
    core::subtract(&dilated, mask, &mut out, &core::no_array(), -1).unwrap();
    out
}

#[test]
fn sift_matches_consecutive_coastline_frames_in_the_border_band() {
    let scenario = Scenario::load("coastline").unwrap();
    let world = World::build(&scenario).unwrap();
    let mission = Mission::plan(&world).unwrap();
    let renderer = Renderer::new(&world);
    // The area pipeline's working resolution: full HD downscaled by 2, band 50 px -> 25 px.
    let k = scenario.intrinsics().downscaled(2);
    let mut sift = SIFT::create(2000, 3, 0.04, 10.0, 1.6).unwrap();
    let matcher = BFMatcher::create(core::NORM_L2, false).unwrap();
    let mut previous: Option<Mat> = None;
    let mut counts = Vec::new();
    for i in 0..8 {
        let state = mission.state(30.0 + i as f64 / mission.frame_rate);
        let frame = renderer.render(&mission.camera_pose(&state), &k);
        let rgb = to_mat(&frame.rgb, frame.width, frame.height, 3);
        let mut grey = Mat::default();
        imgproc::cvt_color(&rgb, &mut grey, imgproc::COLOR_RGB2GRAY, 0).unwrap();
        let mask = to_mat(&frame.mask, frame.width, frame.height, 1);
        assert!(core::count_non_zero(&mask).unwrap() > 0, "frame {i} sees water");
        let band = band(&mask, 25);
        let mut kps = Vector::<KeyPoint>::new();
        let mut desc = Mat::default();
        sift.detect_and_compute(&grey, &band, &mut kps, &mut desc, false).unwrap();
        if let Some(prev) = &previous {
            let mut knn = Vector::<Vector<core::DMatch>>::new();
            matcher.knn_train_match(prev, &desc, &mut knn, 2, &core::no_array(), false).unwrap();
            let good = knn
                .iter()
                .filter(|p| p.len() == 2 && p.get(0).unwrap().distance < 0.5 * p.get(1).unwrap().distance)
                .count();
            counts.push(good);
        }
        previous = Some(desc);
    }
    counts.sort_unstable();
    let median = counts[counts.len() / 2];
    println!("ratio-test matches between consecutive frames in the band: {counts:?}, median {median}");
    assert!(median >= 40, "median {median} ratio-test matches: {counts:?}");
}
