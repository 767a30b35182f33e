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
    /// Frames skipped because their image (or, where the masks are the target, their
    /// mask) could not be used.
    unreadable: u64,
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
            unreadable: 0,
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
            // The area pipeline takes the dataset's masks as its target with `masks` (and
            // `learned`, which segments nothing live); with `water` or `hsv`, and indoors,
            // they are not used, so not read (a bad one warned of at every frame).
            let mask_needed = self.settings.daemon.pipeline == crate::settings::PipelineKind::Area
                && matches!(
                    self.settings.area.segmenter,
                    crate::settings::Segmenter::Masks | crate::settings::Segmenter::Learned
                );
            let (image, mask) = match read_frame(&fp, &mp, (k.width, k.height), mask_needed) {
                Ok(v) => v,
                // As `mavloc area` does: a bad frame is skipped with a warning saying why,
                // not fatal, and counted.
                Err(why) => {
                    self.unreadable += 1;
                    tracing::warn!(
                        "dataset frame {} skipped: {why} ({} skipped in all)",
                        r.frame,
                        self.unreadable
                    );
                    continue;
                }
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
        let skipped = match self.unreadable {
            0 => String::new(),
            n => format!(", {n} unreadable skipped"),
        };
        format!(
            "dataset {} ({} frames, {}{skipped})",
            self.ds.dir.display(),
            self.ds.records.len(),
            if self.realtime { "at the recorded rate" } else { "as fast as the pipeline goes" }
        )
    }

    fn unreadable(&self) -> u64 {
        self.unreadable
    }
}

/// A dataset frame of `size` px and, where the masks are the target (`needed`: the area
/// pipeline with `area.segmenter = "masks"` or `"learned"`), its mask, or why the frame
/// cannot be replayed: the mask must then be there, readable and of the frame's size, as
/// `mavloc area` wants it (a stretched mask would put the border elsewhere). Where they
/// are not the target, the mask is not read.
fn read_frame(
    frame: &std::path::Path,
    mask: &std::path::Path,
    size: (u32, u32),
    needed: bool,
) -> Result<(opencv::core::Mat, Option<opencv::core::Mat>), String> {
    let image = crate::imaging::read_image(frame, imgcodecs::IMREAD_COLOR)?;
    let want = (size.0 as i32, size.1 as i32);
    if (image.cols(), image.rows()) != want {
        return Err(format!(
            "{} is {}x{} px, but the dataset's camera is {}x{}",
            frame.display(),
            image.cols(),
            image.rows(),
            size.0,
            size.1
        ));
    }
    if !needed {
        return Ok((image, None));
    }
    if !mask.exists() {
        // A dataset with no masks at all is the live pipeline's to say once (it names the
        // segmenter to set); one missing among others is this frame's fault.
        return match mask.parent().is_some_and(|d| d.is_dir()) {
            true => Err(format!("{} is missing (area.segmenter = \"masks\")", mask.display())),
            false => Ok((image, None)),
        };
    }
    let m = crate::imaging::read_image(mask, imgcodecs::IMREAD_GRAYSCALE)?;
    if (m.cols(), m.rows()) != want {
        return Err(format!(
            "{}: the mask is {}x{} px, the frame {}x{}",
            mask.display(),
            m.cols(),
            m.rows(),
            want.0,
            want.1
        ));
    }
    Ok((image, Some(m)))
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

    /// A replayed frame is skipped, with the file and the reason, as `mavloc area` skips
    /// it: a frame of another size than the dataset's camera, and, where the masks are
    /// the target, a mask that is unreadable, of another size or missing among others.
    /// Where they are not, the mask is not read and the frame plays.
    #[test]
    fn a_replayed_frame_with_a_bad_image_or_mask_is_skipped_as_offline() {
        use opencv::core;
        let dir = tempfile::tempdir().unwrap();
        let (frames, masks) = (dir.path().join("frames"), dir.path().join("masks"));
        std::fs::create_dir_all(&frames).unwrap();
        let write = |p: &std::path::Path, w: i32, h: i32| {
            let m = Mat::new_rows_cols_with_default(h, w, core::CV_8UC1, core::Scalar::all(255.0)).unwrap();
            imgcodecs::imwrite(p, &m, &core::Vector::new()).unwrap();
        };
        write(&frames.join("1.png"), 32, 24);
        write(&frames.join("2.png"), 16, 24);
        let (f1, m1) = (frames.join("1.png"), masks.join("1.png"));
        // No masks at all: the live pipeline says so once; the frame plays.
        let (_, mask) = read_frame(&f1, &m1, (32, 24), true).unwrap();
        assert!(mask.is_none());
        let e = read_frame(&frames.join("2.png"), &m1, (32, 24), false).unwrap_err();
        assert!(e.contains("2.png is 16x24 px") && e.contains("camera is 32x24"), "{e}");
        std::fs::create_dir_all(&masks).unwrap();
        let e = read_frame(&f1, &m1, (32, 24), true).unwrap_err();
        assert!(e.contains("1.png is missing"), "{e}");
        write(&m1, 16, 12);
        let e = read_frame(&f1, &m1, (32, 24), true).unwrap_err();
        assert!(e.contains("the mask is 16x12 px, the frame 32x24"), "{e}");
        let (_, mask) = read_frame(&f1, &m1, (32, 24), false).unwrap();
        assert!(mask.is_none(), "a mask that is not the target is not read");
        std::fs::write(&m1, b"").unwrap();
        let e = read_frame(&f1, &m1, (32, 24), true).unwrap_err();
        assert!(e.contains("empty file"), "{e}");
        write(&m1, 32, 24);
        let (image, mask) = read_frame(&f1, &m1, (32, 24), true).unwrap();
        assert_eq!((image.cols(), mask.unwrap().rows()), (32, 24));
    }
}
