//! Which way does each photo really face? An independent check of the photo alignment
//! on real photos: each photo of an imported dataset is registered to an orthomosaic of
//! the same ground (SIFT, Lowe's ratio 0.8, a homography by MAGSAC++), and the direction
//! its image-up takes in the mosaic is its heading, up to one rotation common to every
//! photo (the mosaic's grid against true north: a UTM mosaic's convergence is 0.66 deg at
//! the Duluth shore of `../shared/data/dji-sample`). Printed beside the heading the tags
//! give (the earth-frame gimbal yaw) and the aligned one (the tag plus `about_down_deg` of
//! `R/alignment.csv`), each minus the mosaic's: what is left after the common rotation is
//! each photo's own heading error. A nadir camera's tilt is not checked: the ground's own
//! slope enters the homography as much as the tilt does.
//!
//! `cargo run --release --example ortho_yaw -- DATASET RESULT MOSAIC [SCALE]`, e.g. with
//! the DJI sample imported to D, `mavloc area --dataset D --out R`, and the survey's
//! mosaic preview `../shared/data/textures/brighton_beach.jpg`; SCALE (default 0.18)
//! brings a photo near the mosaic's ground resolution.

use std::collections::BTreeMap;
use std::path::Path;

use mavloc_data::Dataset;
use opencv::core::{self, DMatch, KeyPoint, Mat, Point2f, Vector};
use opencv::features2d::{BFMatcher, SIFT};
use opencv::prelude::*;
use opencv::{calib3d, imgcodecs, imgproc};

fn sift(img: &Mat, count: i32) -> opencv::Result<(Vector<KeyPoint>, Mat)> {
    let mut s = SIFT::create(count, 3, 0.04, 10.0, 1.6)?;
    let (mut kp, mut d) = (Vector::new(), Mat::default());
    s.detect_and_compute(img, &core::no_array(), &mut kp, &mut d, false)?;
    Ok((kp, d))
}

/// Wraps an angle to -180..180 degrees.
fn wrap(a: f64) -> f64 {
    (a + 540.0).rem_euclid(360.0) - 180.0
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let usage = "usage: ortho_yaw DATASET RESULT MOSAIC [SCALE]";
    let (Some(dataset), Some(result), Some(mosaic)) = (args.get(1), args.get(2), args.get(3)) else {
        anyhow::bail!(usage)
    };
    let scale: f64 = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(0.18);
    let ds = Dataset::open(Path::new(dataset)).map_err(|e| anyhow::anyhow!(e))?;
    // Each photo's correction about the vertical (degrees), from the alignment.
    let mut about_down: BTreeMap<u64, f64> = BTreeMap::new();
    let csv = std::fs::read_to_string(Path::new(result).join("alignment.csv"))?;
    let header: Vec<&str> = csv.lines().next().unwrap_or_default().split(',').collect();
    let col = header
        .iter()
        .position(|h| *h == "about_down_deg")
        .ok_or_else(|| anyhow::anyhow!("no about_down_deg in alignment.csv"))?;
    for line in csv.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        about_down.insert(f[0].parse()?, f[col].parse()?);
    }
    let ortho = imgcodecs::imread(mosaic, imgcodecs::IMREAD_GRAYSCALE)?;
    anyhow::ensure!(!ortho.empty(), "cannot read {mosaic}");
    let (ko, dort) = sift(&ortho, 30000)?;
    let matcher = BFMatcher::create(core::NORM_L2, false)?;
    let mut rows = Vec::new();
    for r in &ds.records {
        let img = mavloc::imaging::read_image(&ds.frame_path(r), imgcodecs::IMREAD_GRAYSCALE)
            .map_err(anyhow::Error::msg)?;
        let mut small = Mat::default();
        imgproc::resize(&img, &mut small, core::Size::new(0, 0), scale, scale, imgproc::INTER_AREA)?;
        let (kp, d) = sift(&small, 0)?;
        let mut knn = Vector::<Vector<DMatch>>::new();
        matcher.knn_train_match(&d, &dort, &mut knn, 2, &core::no_array(), false)?;
        let (mut src, mut dst) = (Vector::<Point2f>::new(), Vector::<Point2f>::new());
        for m in knn.iter().filter(|m| m.len() == 2) {
            let (a, b) = (m.get(0)?, m.get(1)?);
            if a.distance < 0.8 * b.distance {
                src.push(kp.get(a.query_idx as usize)?.pt());
                dst.push(ko.get(a.train_idx as usize)?.pt());
            }
        }
        let mut mask = Mat::default();
        let h = calib3d::find_homography(&src, &dst, &mut mask, calib3d::USAC_MAGSAC, 2.0)?;
        if h.empty() {
            println!("frame {}: not registered to the mosaic ({} matches)", r.frame, src.len());
            continue;
        }
        let inliers = core::count_non_zero(&mask)?;
        // Image-up through the photo's centre, in the mosaic: its heading from mosaic-up.
        let (cx, cy) = (small.cols() as f32 / 2.0, small.rows() as f32 / 2.0);
        let pts: Vector<Point2f> = Vector::from_iter([Point2f::new(cx, cy), Point2f::new(cx, cy - 100.0)]);
        let mut out = Vector::<Point2f>::new();
        core::perspective_transform(&pts, &mut out, &h)?;
        let (p0, p1) = (out.get(0)?, out.get(1)?);
        let heading = ((p1.x - p0.x) as f64).atan2(-(p1.y - p0.y) as f64).to_degrees();
        let tag = r.measured.gimbal_deg[0];
        let aligned = about_down.get(&r.frame).map(|c| tag + c);
        rows.push((r.frame, src.len(), inliers, heading, tag, aligned));
    }
    println!("frame  matches  inliers  mosaic heading  tag - mosaic  aligned - mosaic (deg)");
    for &(f, m, i, h, t, a) in &rows {
        let a = a.map_or("-".to_string(), |a| format!("{:+.2}", wrap(a - h)));
        println!("{f:>5} {m:>8} {i:>8} {h:>15.2} {:>+13.2} {a:>17}", wrap(t - h));
    }
    // What is left after the rotation common to all photos: each one's own error.
    let spread = |v: Vec<f64>| {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        (mean, v.iter().map(|x| (x - mean).abs()).fold(0.0, f64::max))
    };
    let (tm, ts) = spread(rows.iter().map(|r| wrap(r.4 - r.3)).collect());
    println!("tags: common {tm:+.2} deg, each photo within {ts:.2} deg of it");
    if rows.iter().all(|r| r.5.is_some()) && !rows.is_empty() {
        let (am, asp) = spread(rows.iter().map(|r| wrap(r.5.unwrap() - r.3)).collect());
        println!("aligned: common {am:+.2} deg, each photo within {asp:.2} deg of it");
    }
    Ok(())
}
