//! The OpenCV build the pipelines rely on is usable: SIFT (features2d) detects and
//! describes keypoints, and the brute-force matcher with Lowe's ratio test (area seed
//! eq. 5.10) matches them between two shifted views. Catches a missing or mismatched
//! libopencv-dev on a fresh machine before any pipeline does.

use opencv::core::{self, KeyPoint, Mat, Scalar, Vector, CV_8UC1};
use opencv::features2d::{BFMatcher, SIFT};
use opencv::imgproc;
use opencv::prelude::*;

/// A deterministic textured image: random bright blobs on a dark background.
fn blobs(width: i32, height: i32, shift: i32) -> Mat {
    let mut img = Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(20.0)).unwrap();
    let mut state = 12345u64;
    let mut next = |m: i32| {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 33) % m as u64) as i32
    };
    for _ in 0..150 {
        let (x, y, r, v) = (next(width), next(height), 3 + next(9), 80 + next(170));
        imgproc::circle(
            &mut img,
            core::Point::new(x + shift, y),
            r,
            Scalar::all(v as f64),
            -1,
            imgproc::LINE_8,
            0,
        )
        .unwrap();
    }
    img
}

fn sift(img: &Mat) -> (Vector<KeyPoint>, Mat) {
    let mut sift = SIFT::create(500, 3, 0.04, 10.0, 1.6).unwrap();
    let mut kps = Vector::<KeyPoint>::new();
    let mut desc = Mat::default();
    sift.detect_and_compute(img, &core::no_array(), &mut kps, &mut desc, false).unwrap();
    (kps, desc)
}

#[test]
fn sift_detects_and_ratio_test_matches_a_shifted_view() {
    let (a_kp, a_desc) = sift(&blobs(480, 270, 0));
    let (b_kp, b_desc) = sift(&blobs(480, 270, 7));
    assert!(a_kp.len() > 50, "only {} keypoints", a_kp.len());
    assert_eq!(a_desc.cols(), 128, "SIFT descriptors have 128 entries");

    let matcher = BFMatcher::create(core::NORM_L2, false).unwrap();
    let mut knn = Vector::<Vector<core::DMatch>>::new();
    matcher.knn_train_match(&a_desc, &b_desc, &mut knn, 2, &core::no_array(), false).unwrap();
    let mut good = 0;
    let mut consistent = 0;
    for pair in knn.iter() {
        if pair.len() == 2 && pair.get(0).unwrap().distance < 0.5 * pair.get(1).unwrap().distance {
            good += 1;
            let m = pair.get(0).unwrap();
            let pa = a_kp.get(m.query_idx as usize).unwrap().pt();
            let pb = b_kp.get(m.train_idx as usize).unwrap().pt();
            if ((pb.x - pa.x) - 7.0).abs() < 1.0 && (pb.y - pa.y).abs() < 1.0 {
                consistent += 1;
            }
        }
    }
    assert!(good > 20, "only {good} ratio-test matches");
    assert!(consistent * 10 >= good * 9, "{consistent} of {good} matches agree with the 7 px shift");
}
