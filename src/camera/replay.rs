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
    /// Local time the next frame is due: the one before's plus their gap in the dataset.
    due: f64,
    /// The dataset time of the frame before.
    prev_t: Option<f64>,
    realtime: bool,
}

/// The longest gap between two frames a real-time replay waits for: a recording spans a
/// flight, and a longer gap (between two flights, or a wrong time: one frame at t = 1e12
/// stalled a replay for good, with no word) is replayed at once.
const MAX_WAIT_S: f64 = 60.0;

/// How long to wait after the frame at `prev` for the one at `t`, and why not as long as
/// their times say, when not.
fn paced_gap(prev: Option<f64>, t: f64) -> (f64, Option<String>) {
    let Some(prev) = prev else { return (0.0, None) };
    let gap = t - prev;
    if gap.is_finite() && (0.0..=MAX_WAIT_S).contains(&gap) {
        return (gap, None);
    }
    let why = if gap < 0.0 {
        format!("comes {:.3} s before the frame before it (the dataset's times run backwards)", -gap)
    } else {
        format!("comes {gap:.1} s after the frame before it (more than {MAX_WAIT_S} s)")
    };
    (0.0, Some(why))
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
        Ok(Replay {
            ds,
            settings: s.clone(),
            due: ctx.now(),
            prev_t: None,
            ctx,
            next: 0,
            realtime: s.camera.realtime,
        })
    }
}

impl FrameSource for Replay {
    fn next(&mut self) -> Result<Option<Captured>, SourceError> {
        loop {
            let Some(r) = self.ds.records.get(self.next) else { return Ok(None) };
            self.next += 1;
            if self.realtime {
                let (gap, why) = paced_gap(self.prev_t, r.t);
                if let Some(why) = why {
                    tracing::warn!("dataset frame {} {why}: replayed without waiting", r.frame);
                }
                self.due += gap;
                if !self.ctx.sleep_until(self.due) {
                    return Ok(None);
                }
            }
            self.prev_t = Some(r.t);
            let (fp, mp) = (self.ds.frame_path(r), self.ds.mask_path(r));
            let k = self.ds.camera.intrinsics();
            // As `mavloc area` does: a bad frame is skipped with a warning saying why, not fatal.
            let image = match crate::imaging::read_image(&fp, imgcodecs::IMREAD_COLOR) {
                Ok(i) if (i.cols(), i.rows()) == (k.width as i32, k.height as i32) => i,
                Ok(i) => {
                    tracing::warn!(
                        "dataset frame {} ({}) is {}x{} px, but the dataset's camera is {}x{}: skipped",
                        r.frame,
                        fp.display(),
                        i.cols(),
                        i.rows(),
                        k.width,
                        k.height
                    );
                    continue;
                }
                Err(e) => {
                    tracing::warn!("dataset frame {} skipped: {e}", r.frame);
                    continue;
                }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A real-time replay waits the dataset's gaps, except a gap it must not wait for:
    /// times that run backwards, or one so long (a frame at t = 1e12) that the replay
    /// would stall for good; those are named and not waited for.
    #[test]
    fn a_replay_waits_the_gaps_but_not_a_backwards_or_endless_one() {
        assert_eq!(paced_gap(None, 5.0), (0.0, None));
        assert_eq!(paced_gap(Some(5.0), 5.25), (0.25, None));
        assert_eq!(paced_gap(Some(5.0), 65.0), (60.0, None));
        let (gap, why) = paced_gap(Some(5.0), 1e12);
        assert_eq!(gap, 0.0);
        assert!(why.unwrap().contains("more than 60 s"));
        let (gap, why) = paced_gap(Some(5.0), 4.0);
        assert_eq!(gap, 0.0);
        assert!(why.unwrap().contains("run backwards"));
        assert_eq!(paced_gap(Some(5.0), f64::NAN).0, 0.0);
    }
}
