//! How well do a dataset's poses agree with its images? SIFT matches between frames
//! (whole frames, Lowe ratio 0.7), each match's two viewing rays from the recorded poses,
//! and how far apart the rays pass: with right poses they nearly meet, and the miss
//! distance over the range is the angular error per ray pair. Used to measure the bearing
//! noise of `config/photo-survey.toml` on the DJI sample.
//!
//! `cargo run --release --example ray_miss -- DATASET [YAW_OFFSET_DEG]`: the optional
//! offset turns every recorded gimbal yaw, to see how a wrong yaw shows.

use mavloc::geometry::{Pixel, Vec3};
use mavloc::settings::Settings;
use mavloc_data::Dataset;
use opencv::core::{self, DMatch, KeyPoint, Mat, Size, Vector};
use opencv::features2d::{BFMatcher, SIFT};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else { anyhow::bail!("usage: ray_miss DATASET [YAW_OFFSET_DEG]") };
    let yaw_offset: f64 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(0.0);
    let ds = Dataset::open(std::path::Path::new(path)).map_err(|e| anyhow::anyhow!(e))?;
    let mut s = Settings::default();
    s.gimbal.yaw_offset_deg = yaw_offset;
    // Half resolution, as the photo-survey pipeline runs.
    let k = ds.camera.intrinsics().downscaled(2);
    let mut sift = SIFT::create(4000, 3, 0.04, 10.0, 1.6)?;
    let (mut keypoints, mut descriptors) = (Vec::new(), Vec::new());
    for r in &ds.records {
        let img = imgcodecs::imread(ds.frame_path(r), imgcodecs::IMREAD_GRAYSCALE)?;
        let mut small = Mat::default();
        let size = Size::new(k.width as i32, k.height as i32);
        imgproc::resize(&img, &mut small, size, 0.0, 0.0, imgproc::INTER_AREA)?;
        let (mut kp, mut d) = (Vector::<KeyPoint>::new(), Mat::default());
        sift.detect_and_compute(&small, &core::no_array(), &mut kp, &mut d, false)?;
        keypoints.push(kp);
        descriptors.push(d);
    }
    let poses: Vec<_> =
        ds.records.iter().map(|r| ds.camera_pose(&r.measured, s.gimbal.offsets_deg())).collect();
    let matcher = BFMatcher::create(core::NORM_L2, false)?;
    println!("pair  matches  miss median (m)  range median (m)  angle (deg)  height median (m)");
    for a in 0..ds.records.len() {
        for b in a + 1..ds.records.len().min(a + 3) {
            let mut knn = Vector::<Vector<DMatch>>::new();
            matcher.knn_train_match(
                &descriptors[a],
                &descriptors[b],
                &mut knn,
                2,
                &core::no_array(),
                false,
            )?;
            let (mut miss, mut range, mut height) = (Vec::new(), Vec::new(), Vec::new());
            for pair in knn.iter().filter(|p| p.len() == 2) {
                let (m1, m2) = (pair.get(0)?, pair.get(1)?);
                if m1.distance >= 0.7 * m2.distance {
                    continue;
                }
                let (pa, pb) = (
                    keypoints[a].get(m1.query_idx as usize)?.pt(),
                    keypoints[b].get(m1.train_idx as usize)?.pt(),
                );
                let da = poses[a].direction(&k, Pixel::new(pa.x as f64, pa.y as f64));
                let db = poses[b].direction(&k, Pixel::new(pb.x as f64, pb.y as f64));
                let (oa, ob) = (poses[a].position, poses[b].position);
                // Closest points of the two rays (unit directions).
                let w = oa - ob;
                let (c, d, e) = (da.dot(&db), da.dot(&w), db.dot(&w));
                let den = 1.0 - c * c;
                if den < 1e-9 {
                    continue;
                }
                let (sa, sb) = ((c * e - d) / den, (e - c * d) / den);
                let (p1, p2): (Vec3, Vec3) = (oa + da * sa, ob + db * sb);
                miss.push((p1 - p2).norm());
                range.push(sa.abs());
                height.push(-(p1 + p2).z / 2.0);
            }
            let n = miss.len();
            let (m, r) = (median(&mut miss), median(&mut range));
            println!(
                "{a}-{b}  {n:7}  {m:15.2}  {r:16.1}  {:11.2}  {:17.1}",
                (m / r).to_degrees(),
                median(&mut height)
            );
        }
    }
    Ok(())
}
