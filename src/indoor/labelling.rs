//! Labelling training frames by homography against an orthomap (indoor seed sec. 3.2):
//! SIFT keypoints of the frame and of the map, Lowe's ratio test over brute-force matches,
//! a RANSAC homography, and the frame's nadir (its centre when the attitude is unknown)
//! projected onto the map and turned into metres with the map's scale. Frames with too
//! few RANSAC inliers are rejected and counted.
//!
//! The map image is north-up (image x = east, image y = south) and centred on the local
//! origin unless `origin` says where its top-left pixel centre is.

use std::path::Path;

use opencv::calib3d;
use opencv::core::{DMatch, KeyPoint, Mat, Point2f, Ptr, Vector};
use opencv::features2d::{BFMatcher, SIFT};
use opencv::imgcodecs;
use opencv::imgproc;
use opencv::prelude::*;

use mavloc_data::dataset::{Dataset, TelemetryRecord};

/// Lowe's ratio (his paper's 0.8 is loose for a map with repeated texture).
const RATIO: f32 = 0.75;
/// RANSAC reprojection threshold, map pixels.
const RANSAC_PX: f64 = 4.0;
/// Frames are downscaled to about this width before SIFT (speed; the map should have a
/// similar ground resolution).
const SIFT_WIDTH: i32 = 640;

/// An orthomap with its SIFT features.
pub struct OrthoMap {
    keypoints: Vector<KeyPoint>,
    descriptors: Mat,
    pub metres_per_px: f64,
    /// (north, east) of the top-left pixel centre, metres.
    pub origin: [f64; 2],
    pub min_inliers: usize,
    pub width: i32,
    pub height: i32,
}

impl std::fmt::Debug for OrthoMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OrthoMap")
            .field("keypoints", &self.keypoints.len())
            .field("metres_per_px", &self.metres_per_px)
            .field("origin", &self.origin)
            .finish()
    }
}

impl Clone for OrthoMap {
    fn clone(&self) -> Self {
        OrthoMap {
            keypoints: self.keypoints.clone(),
            descriptors: self.descriptors.try_clone().expect("cloning a descriptor matrix"),
            ..*self
        }
    }
}

// SAFETY: OpenCV matrices and keypoint vectors are plain owned buffers; `OrthoMap` is only
// read after construction, never mutated, so sharing it between threads is sound.
unsafe impl Sync for OrthoMap {}
unsafe impl Send for OrthoMap {}

fn sift() -> opencv::Result<Ptr<SIFT>> {
    SIFT::create(0, 3, 0.04, 10.0, 1.6)
}

fn features(grey: &Mat) -> opencv::Result<(Vector<KeyPoint>, Mat)> {
    let mut kp = Vector::new();
    let mut desc = Mat::default();
    sift()?.detect_and_compute(grey, &Mat::default(), &mut kp, &mut desc, false)?;
    Ok((kp, desc))
}

impl OrthoMap {
    /// Loads the map image. `origin` defaults to centring the map on the local origin.
    pub fn load(
        path: &Path,
        metres_per_px: f64,
        origin: Option<[f64; 2]>,
        min_inliers: usize,
    ) -> Result<OrthoMap, String> {
        if !(metres_per_px.is_finite() && metres_per_px > 0.0) {
            return Err(format!("map scale must be positive metres per pixel, got {metres_per_px}"));
        }
        let grey = imgcodecs::imread(path, imgcodecs::IMREAD_GRAYSCALE)
            .map_err(|e| format!("cannot read map {}: {e}", path.display()))?;
        if grey.empty() {
            return Err(format!("cannot read map {} as an image", path.display()));
        }
        let (kp, desc) = features(&grey).map_err(|e| format!("SIFT on {}: {e}", path.display()))?;
        if kp.len() < 4 {
            return Err(format!("map {} has only {} SIFT keypoints", path.display(), kp.len()));
        }
        let (w, h) = (grey.cols(), grey.rows());
        let origin = origin
            .unwrap_or([(h as f64 - 1.0) / 2.0 * metres_per_px, -(w as f64 - 1.0) / 2.0 * metres_per_px]);
        Ok(OrthoMap {
            keypoints: kp,
            descriptors: desc,
            metres_per_px,
            origin,
            min_inliers,
            width: w,
            height: h,
        })
    }

    /// Map pixel to (north, east).
    pub fn to_metres(&self, u: f64, v: f64) -> [f64; 2] {
        [self.origin[0] - v * self.metres_per_px, self.origin[1] + u * self.metres_per_px]
    }

    /// The label of one dataset frame, `None` when it has too few inliers.
    pub fn label(&self, ds: &Dataset, r: &TelemetryRecord) -> Result<Option<[f64; 2]>, String> {
        let path = ds.frame_path(r);
        let grey = imgcodecs::imread(&path, imgcodecs::IMREAD_GRAYSCALE)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        if grey.empty() {
            return Err(format!("cannot read {}", path.display()));
        }
        let k = ds.camera.intrinsics();
        let rot = r.measured.camera_pose(ds.camera.chain, ds.camera.gimbal_frame).local_from_camera();
        let nadir = super::derotate::nadir_pixel(&k, &rot).unwrap_or((k.cx, k.cy));
        self.locate(&grey, nadir).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Where pixel `point` of a grey frame lies on the map, if the frame matches it.
    pub fn locate(&self, grey: &Mat, point: (f64, f64)) -> opencv::Result<Option<[f64; 2]>> {
        let scale = (SIFT_WIDTH as f64 / grey.cols() as f64).min(1.0);
        let small = if scale < 1.0 {
            let mut out = Mat::default();
            imgproc::resize(
                grey,
                &mut out,
                opencv::core::Size::default(),
                scale,
                scale,
                imgproc::INTER_AREA,
            )?;
            out
        } else {
            grey.clone()
        };
        let (kp, desc) = features(&small)?;
        if kp.len() < 4 {
            return Ok(None);
        }
        let matcher = BFMatcher::create(opencv::core::NORM_L2, false)?;
        let mut knn: Vector<Vector<DMatch>> = Vector::new();
        matcher.knn_train_match(&desc, &self.descriptors, &mut knn, 2, &Mat::default(), false)?;
        let mut src = Vector::<Point2f>::new();
        let mut dst = Vector::<Point2f>::new();
        for m in knn.iter() {
            if m.len() == 2 {
                let (a, b) = (m.get(0)?, m.get(1)?);
                if a.distance < RATIO * b.distance {
                    src.push(kp.get(a.query_idx as usize)?.pt());
                    dst.push(self.keypoints.get(a.train_idx as usize)?.pt());
                }
            }
        }
        if src.len() < self.min_inliers.max(4) {
            return Ok(None);
        }
        let mut inliers = Mat::default();
        let h = calib3d::find_homography(&src, &dst, &mut inliers, calib3d::RANSAC, RANSAC_PX)?;
        if h.empty() {
            return Ok(None);
        }
        let count = opencv::core::count_non_zero(&inliers)? as usize;
        if count < self.min_inliers {
            return Ok(None);
        }
        let (x, y) = ((point.0 + 0.5) * scale - 0.5, (point.1 + 0.5) * scale - 0.5);
        let m = |r: i32, c: i32| h.at_2d::<f64>(r, c).copied();
        let w = m(2, 0)? * x + m(2, 1)? * y + m(2, 2)?;
        if w.abs() < 1e-12 {
            return Ok(None);
        }
        let u = (m(0, 0)? * x + m(0, 1)? * y + m(0, 2)?) / w;
        let v = (m(1, 0)? * x + m(1, 1)? * y + m(1, 2)?) / w;
        Ok(Some(self.to_metres(u, v)))
    }
}
