//! The two pipelines as the worker runs them live: adapters from a [`LiveFrame`] to the
//! pure pipeline libraries ([`crate::area`], [`crate::indoor`]) and from their results to a
//! [`Report`] and to result files in the state directory.
//!
//! Files (under `STATE/results/area/` or `STATE/results/indoor/`):
//! - area: `landmarks.csv`, `.ply`, `area.geojson`, `area.kml`, `border.csv`,
//!   `summary.json`, each rewritten atomically every [`AREA_CHECKPOINT_FRAMES`] frames and
//!   when asked (snapshot, stop), so a crash leaves the last complete set;
//! - indoor: `trajectory.csv`, appended and flushed every frame (a crash loses at most
//!   the line being written), and `summary.json`.

use std::path::{Path, PathBuf};

use nalgebra::Vector2;

use super::worker::{LiveFrame, LivePipeline, PositionEstimate, Report};
use crate::area::features::prepare;
use crate::area::offline::{write_results, RunSummary};
use crate::area::{AreaPipeline, FrameInput};
use crate::geometry::{Geodetic, Intrinsics, LocalFrame};
use crate::indoor::derotate::Preprocessor;
use crate::indoor::landing::{Hold, LandingTrigger, LandingZone};
use crate::indoor::localizer::{Localizer, LocalizerParams};
use crate::indoor::model::Model;
use crate::indoor::offline::model_settings;
use crate::output::LandmarkRecord;
use crate::settings::Settings;
use mavloc_data::results::TrajectoryRow;
use mavloc_data::table::Appender;

/// Area results are rewritten every this many frames.
pub const AREA_CHECKPOINT_FRAMES: u64 = 25;

/// The area pipeline, live.
pub struct AreaLive {
    pipeline: AreaPipeline,
    k_full: Intrinsics,
    downscale: u32,
    dir: PathBuf,
    results: Vec<LandmarkRecord>,
    /// Added to the library's landmark ids, so results resumed from disk keep theirs.
    id_offset: u64,
    origin: Geodetic,
    frames: u64,
    no_mask_warned: bool,
    started: std::time::Instant,
    settings: crate::settings::Area,
    /// `gimbal.aim = "border"`: report where the border is, per frame.
    aim: bool,
}

impl AreaLive {
    /// `k_full`: the camera's intrinsics at capture size; `origin`: the local frame's WGS84
    /// origin until the autopilot tells another.
    pub fn new(s: &Settings, k_full: Intrinsics, origin: Geodetic, dir: PathBuf) -> Result<AreaLive, String> {
        let downscale = s.area.downscale.max(1);
        let pipeline = AreaPipeline::new(&s.area, k_full.downscaled(downscale)).map_err(|e| e.to_string())?;
        std::fs::create_dir_all(&dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        // Results of an earlier run (a restart after a crash, a pipeline rebuilt after a
        // panic) are kept: the next checkpoint must not overwrite them with fewer.
        let path = dir.join("landmarks.csv");
        let results = match std::fs::read_to_string(&path) {
            Ok(text) => crate::output::parse_landmarks_csv(&text, &path.display().to_string())?,
            Err(_) => Vec::new(),
        };
        if !results.is_empty() {
            tracing::info!("area: resuming with {} landmarks from {}", results.len(), path.display());
        }
        let id_offset = results.iter().map(|l| l.id + 1).max().unwrap_or(0);
        Ok(AreaLive {
            pipeline,
            k_full,
            downscale,
            dir,
            results,
            id_offset,
            origin,
            frames: 0,
            no_mask_warned: false,
            started: std::time::Instant::now(),
            settings: s.area.clone(),
            aim: s.gimbal.aim == crate::settings::GimbalAim::Border,
        })
    }

    /// Everything converged so far: purged results and converged landmarks still tracked.
    fn all_landmarks(&self) -> Vec<LandmarkRecord> {
        let mut all = self.results.clone();
        all.extend(self.pipeline.converged_now().into_iter().map(|l| self.shifted(l)));
        all
    }

    fn shifted(&self, mut l: LandmarkRecord) -> LandmarkRecord {
        l.id += self.id_offset;
        l
    }

    /// Writes the result files; returns them and the border lines fitted.
    fn write(&self) -> std::io::Result<(Vec<PathBuf>, Vec<Vec<crate::geometry::Vec3>>)> {
        let dir = &self.dir;
        let landmarks = self.all_landmarks();
        let elapsed = self.started.elapsed().as_secs_f64();
        let mut summary = RunSummary {
            method: "ukf".into(),
            frames: self.frames,
            elapsed_s: elapsed,
            frames_per_s: if elapsed > 0.0 { self.frames as f64 / elapsed } else { 0.0 },
            ..RunSummary::default()
        };
        let frame = LocalFrame::new(self.origin);
        let lines = write_results(dir, &frame, "mavloc run: area", &landmarks, &mut summary)?;
        let files =
            ["landmarks.csv", "landmarks.ply", "area.geojson", "area.kml", "border.csv", "summary.json"]
                .iter()
                .map(|f| dir.join(f))
                .collect();
        Ok((files, lines))
    }
}

impl LivePipeline for AreaLive {
    fn process(&mut self, frame: &LiveFrame) -> Report {
        let mut report = Report::default();
        if let Some(o) = frame.origin {
            self.origin = o;
        }
        // The configured segmenter (water, HSV) decides the target, as in `mavloc area`;
        // with `masks` the camera's own mask does (the sim camera's, a dataset's).
        let segmented = match crate::area::segment::segment(&frame.image, &self.settings) {
            Ok(m) => m,
            Err(e) => {
                report.events.push(format!("area: frame {} not segmented: {e}", frame.index));
                return report;
            }
        };
        let Some(mask) = segmented.as_ref().or(frame.mask.as_ref()) else {
            if !self.no_mask_warned {
                self.no_mask_warned = true;
                report.events.push(
                    "area: this camera gives no target mask and area.segmenter = \"masks\"; frames are skipped (set area.segmenter to \"water\" or \"hsv\")".into(),
                );
            }
            return report;
        };
        let (grey, small_mask) = match prepare(&frame.image, mask, self.downscale) {
            Ok(v) => v,
            Err(e) => {
                report.events.push(format!("area: frame {} unusable: {e}", frame.index));
                return report;
            }
        };
        let input =
            FrameInput { index: frame.index, grey: &grey, mask: &small_mask, pose: frame.pose.camera };
        if self.aim {
            report.aim = border_bearing(&small_mask, &frame.pose.camera, self.pipeline.intrinsics());
        }
        let r = match self.pipeline.process(&input) {
            Ok(r) => r,
            Err(e) => {
                report.events.push(format!("area: frame {}: {e}", frame.index));
                return report;
            }
        };
        self.frames += 1;
        report.processed = true;
        let before = self.results.len();
        report.new_landmarks = r.converged.iter().map(|l| l.position.into()).collect();
        let converged: Vec<_> = r.converged.into_iter().map(|l| self.shifted(l)).collect();
        self.results.extend(converged);
        if before == 0 && !self.results.is_empty() {
            report.events.push(format!("area: first {} landmarks converged", self.results.len()));
        } else if before / 100 != self.results.len() / 100 {
            report.events.push(format!("area: {} landmarks converged", self.results.len()));
        }
        report.counters = vec![
            ("LMK_TRACK", r.landmarks as f32),
            ("LMK_CONV", self.results.len() as f32),
            ("LMK_FEAT", r.features as f32),
        ];
        if self.frames.is_multiple_of(AREA_CHECKPOINT_FRAMES) {
            match self.write() {
                Ok((_, lines)) => {
                    let length: f64 =
                        lines.iter().flat_map(|l| l.windows(2).map(|w| (w[1] - w[0]).norm())).sum();
                    report.counters.push(("BRD_LINES", lines.len() as f32));
                    report.counters.push(("BRD_LEN", length as f32));
                }
                Err(e) => report.events.push(format!("area: cannot write results: {e}")),
            }
        }
        report
    }

    fn apply(&mut self, s: &Settings) {
        self.settings = s.area.clone();
        self.aim = s.gimbal.aim == crate::settings::GimbalAim::Border;
        self.downscale = s.area.downscale.max(1);
        if let Err(e) = self.pipeline.reconfigure(&s.area, self.k_full.downscaled(self.downscale)) {
            tracing::warn!("area: new settings not applied: {e}");
        }
    }

    fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
        self.write().map(|(files, _)| files)
    }
}

/// Earth-frame bearing (yaw, pitch) of the centroid of the mask's border pixels: where
/// the camera should look to keep the border in the middle of the picture. `None` when
/// too little border is in view to say.
fn border_bearing(
    mask: &opencv::core::Mat,
    pose: &crate::geometry::CameraPose,
    k: &Intrinsics,
) -> Option<(f64, f64)> {
    use opencv::{core, imgproc, prelude::*};
    let kernel = imgproc::get_structuring_element(
        imgproc::MORPH_RECT,
        core::Size::new(3, 3),
        core::Point::new(-1, -1),
    )
    .ok()?;
    let mut edge = opencv::core::Mat::default();
    imgproc::morphology_ex(
        mask,
        &mut edge,
        imgproc::MORPH_GRADIENT,
        &kernel,
        core::Point::new(-1, -1),
        1,
        core::BORDER_REPLICATE,
        imgproc::morphology_default_border_value().ok()?,
    )
    .ok()?;
    let m = imgproc::moments(&edge, true).ok()?;
    // At least a few dozen border pixels, or the centroid is noise.
    if m.m00 < 30.0 || edge.rows() == 0 {
        return None;
    }
    let px = crate::geometry::Pixel::new(m.m10 / m.m00, m.m01 / m.m00);
    let b = pose.pixel_bearing(k, px);
    Some((b.yaw, b.pitch))
}

/// The indoor pipeline, live.
pub struct IndoorLive {
    model: Model,
    settings: Settings,
    pre: Preprocessor,
    localizer: Localizer,
    trigger: LandingTrigger,
    trajectory: Appender<TrajectoryRow>,
    dir: PathBuf,
    frames: u64,
    last_hold: Option<Hold>,
}

fn zone(s: &Settings) -> LandingZone {
    let i = &s.indoor;
    LandingZone {
        centre: Vector2::new(i.landing_x_m, i.landing_y_m),
        radius_m: i.landing_radius_m,
        sigma_gate_m: i.landing_sigma_gate_m,
        frames: i.landing_frames,
    }
}

impl IndoorLive {
    pub fn new(s: &Settings, k: Intrinsics, dir: PathBuf) -> Result<IndoorLive, String> {
        let model = Model::load(Path::new(&s.indoor.model))?;
        let mut settings = s.clone();
        settings.indoor = model_settings(&model, &s.indoor);
        let i = &settings.indoor;
        let mut pre =
            Preprocessor::new(k, i.work_width, i.derotate, (i.patch_w as usize, i.patch_h as usize));
        pre.normalise = i.normalise;
        let rel = (pre.work.fx - model.frame.work_fx).abs() / model.frame.work_fx;
        if rel > 0.1 {
            tracing::warn!(
                "indoor: the camera's focal length at the working width differs from the model's by {:.0} %; textons will be seen at another scale",
                rel * 100.0
            );
        }
        let localizer = Localizer::new(&model, LocalizerParams::from_settings(i, 1))?;
        std::fs::create_dir_all(&dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
        let path = dir.join("trajectory.csv");
        let trajectory =
            Appender::append(&path).map_err(|e| format!("cannot open {}: {e}", path.display()))?;
        Ok(IndoorLive {
            trigger: LandingTrigger::new(zone(&settings)),
            model,
            settings,
            pre,
            localizer,
            trajectory,
            dir,
            frames: 0,
            last_hold: None,
        })
    }
}

impl LivePipeline for IndoorLive {
    fn process(&mut self, frame: &LiveFrame) -> Report {
        let mut report = Report::default();
        let attitude = frame.pose.camera.local_from_camera();
        let canvas = match self.pre.prepare(&frame.image, Some(&attitude)) {
            Ok(c) => c,
            Err(e) => {
                report.events.push(format!("indoor: frame {} unusable: {e}", frame.index));
                return report;
            }
        };
        let v = frame.pose.vehicle.velocity;
        let t = frame.pose.autopilot_time;
        let e = self.localizer.step(t, &canvas, Some(Vector2::new(v.x, v.y)));
        self.frames += 1;
        report.processed = true;
        let truth = frame.truth.unwrap_or([f64::NAN; 3]);
        // Append-only and flushed per frame: a crash loses at most the line being written.
        let row = TrajectoryRow {
            frame: frame.index,
            t,
            x: e.position.x,
            y: e.position.y,
            sigma_x: e.spread.0,
            sigma_y: e.spread.1,
            true_x: truth[0],
            true_y: truth[1],
        };
        if let Err(err) = self.trajectory.push(&row) {
            report.events.push(format!("indoor: cannot append to trajectory.csv: {err}"));
        }
        report.position = Some(PositionEstimate {
            autopilot_time: t,
            north: e.position.x,
            east: e.position.y,
            down: frame.pose.vehicle.position.z,
            cov: [[e.spread.0 * e.spread.0, 0.0], [0.0, e.spread.1 * e.spread.1]],
        });
        report.counters = vec![("IND_SDX", e.spread.0 as f32), ("IND_SDY", e.spread.1 as f32)];
        match self.trigger.update(e.position, e.spread) {
            Ok(()) => {
                report.landing_requested = true;
                report.events.push(format!(
                    "indoor: landing zone reached at x {:.2} y {:.2} m (sd {:.2}, {:.2} m)",
                    e.position.x, e.position.y, e.spread.0, e.spread.1
                ));
            }
            Err(h) => self.last_hold = Some(h),
        }
        report
    }

    fn apply(&mut self, s: &Settings) {
        let indoor = model_settings(&self.model, &s.indoor);
        let params = LocalizerParams::from_settings(&indoor, 1);
        if !self.localizer.set_params(&params) {
            match Localizer::new(&self.model, params) {
                Ok(l) => {
                    self.localizer = l;
                    tracing::info!("indoor: k or particle count changed: localiser restarted");
                }
                Err(e) => tracing::warn!("indoor: new settings not applied: {e}"),
            }
        }
        // A new zone arms the trigger again; the same zone must not fire twice.
        if zone(s) != zone(&self.settings) {
            self.trigger = LandingTrigger::new(zone(s));
        }
        self.settings = s.clone();
        self.settings.indoor = indoor;
    }

    fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
        let summary = serde_json::json!({
            "frames": self.frames,
            "landing_fired": self.trigger.fired(),
            "last_hold": self.last_hold.map(|h| format!("{h:?}")),
        });
        let path = self.dir.join("summary.json");
        crate::output::write_atomic(&path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
        Ok(vec![self.dir.join("trajectory.csv"), path])
    }
}
