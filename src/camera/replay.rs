//! `dataset`: replays a recorded dataset (the simulation-world format) with its own
//! measured poses, at the recorded times (`camera.realtime`) or as fast as the pipeline
//! takes frames. The poses are the ones `mavloc area` uses offline, static gimbal
//! corrections included, so a live replay reproduces the offline run.

use nalgebra::UnitQuaternion;
use opencv::imgcodecs;
use opencv::prelude::*;

use super::{Captured, FrameSource, SourceContext, SourceError};
use crate::align::{AlignedPose, VehicleSample};
use crate::settings::Settings;
use mavloc_data::dataset::GimbalFrame;
use mavloc_data::Dataset;

pub struct Replay {
    ds: Dataset,
    settings: Settings,
    ctx: SourceContext,
    next: usize,
    /// Local time of the first frame; frame i is due at start + (t_i - t_0).
    start: f64,
    realtime: bool,
}

impl Replay {
    pub fn open(s: &Settings, ctx: SourceContext) -> Result<Replay, SourceError> {
        if s.camera.path.is_empty() {
            return Err(SourceError::Fatal("camera.source = \"dataset\" needs camera.path".into()));
        }
        let ds = Dataset::open(std::path::Path::new(&s.camera.path)).map_err(SourceError::Fatal)?;
        if ds.records.is_empty() {
            return Err(SourceError::Fatal(format!("dataset {} has no frames", s.camera.path)));
        }
        Ok(Replay { ds, settings: s.clone(), start: ctx.now(), ctx, next: 0, realtime: s.camera.realtime })
    }
}

impl FrameSource for Replay {
    fn next(&mut self) -> Result<Option<Captured>, SourceError> {
        loop {
            let Some(r) = self.ds.records.get(self.next) else { return Ok(None) };
            self.next += 1;
            let t0 = self.ds.records[0].t;
            if self.realtime && !self.ctx.sleep_until(self.start + (r.t - t0)) {
                return Ok(None);
            }
            let (fp, mp) = (self.ds.frame_path(r), self.ds.mask_path(r));
            let image = crate::imaging::read_image(&fp, imgcodecs::IMREAD_COLOR).ok();
            let k = self.ds.camera.intrinsics();
            let Some(image) = image.filter(|i| (i.cols(), i.rows()) == (k.width as i32, k.height as i32))
            else {
                // As `mavloc area` does: a bad frame is skipped with a warning, not fatal.
                tracing::warn!(frame = r.frame, path = %fp.display(), "unreadable or wrongly sized frame, skipped");
                continue;
            };
            let mask = if mp.exists() {
                crate::imaging::read_image(&mp, imgcodecs::IMREAD_GRAYSCALE).ok()
            } else {
                None
            };
            let m = &r.measured;
            let a = m.attitude_deg.map(f64::to_radians);
            let pose = AlignedPose {
                autopilot_time: r.t,
                vehicle: VehicleSample {
                    position: m.position(),
                    velocity: m.velocity.into(),
                    attitude: UnitQuaternion::from_euler_angles(a[0], a[1], a[2]),
                },
                camera: self.ds.camera_pose(m, self.settings.gimbal.offsets_deg()),
                from_gimbal: self.ds.camera.gimbal_frame == GimbalFrame::Earth,
            };
            return Ok(Some(Captured {
                index: r.frame,
                capture_s: self.ctx.now(),
                image,
                mask,
                pose: Some(pose),
                truth: Some(r.truth.position),
            }));
        }
    }

    fn describe(&self) -> String {
        format!(
            "dataset {} ({} frames, {})",
            self.ds.dir.display(),
            self.ds.records.len(),
            if self.realtime { "at the recorded rate" } else { "as fast as the pipeline goes" }
        )
    }
}
