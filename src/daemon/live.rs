//! The two pipelines as the worker runs them live: adapters from a [`LiveFrame`] to the
//! pure pipeline libraries ([`crate::area`], [`crate::indoor`]) and from their results to a
//! [`Report`] and to result files in the state directory.
//!
//! Files, read through `STATE/results/area/` and `STATE/results/indoor/`, which are
//! symbolic links into one folder per run ([`mavloc_data::sets`]):
//!
//! ```text
//! results/area   -> area.runs/<run>/set-<N>   landmarks.csv, .ply, area.geojson, area.kml,
//!                                             border.csv, summary.json
//! results/indoor -> indoor.runs/<run>         trajectory.csv, summary.json
//! ```
//!
//! - area: the whole set is written into a fresh folder every [`AREA_CHECKPOINT_FRAMES`]
//!   frames and when asked (snapshot, stop), and the link switched to it in one rename,
//!   because the files belong together: a crash or a full disk leaves the previous
//!   complete set, never new landmarks beside an old border;
//! - indoor: `trajectory.csv`, appended and flushed every frame (a crash loses at most
//!   the line being written), and `summary.json`, written atomically.
//!
//! A run is one daemon start (or a pipeline reset), named by its UTC start time
//! ([`new_run`]). A new run starts empty, so a restart does not add the world it sees
//! again to what the last run found (it did: 171 landmarks became 342); the last run's
//! results stay in `area.runs/`. A pipeline rebuilt after a panic continues its run from
//! the run's last complete set. A failed write is a [`Warning::WriteFailed`]: a WARNING to
//! the ground and a counter.

use std::io;
use std::path::{Path, PathBuf};

use nalgebra::Vector2;

use super::core::Warning;
use super::flightlog::{Adjusted, FlightLog, Poll};
use super::worker::{LiveFrame, LivePipeline, PipelineEvent, PositionEstimate, Report, VelocityEstimate};
use crate::area::features::prepare;
use crate::area::offline::{write_results, RunSummary};
use crate::area::{AreaPipeline, FrameInput};
use crate::geometry::{Geodetic, Intrinsics, LocalFrame};
use crate::indoor::derotate::Preprocessor;
use crate::indoor::flow::{self, Flow, FlowFrame};
use crate::indoor::landing::{Hold, LandingTrigger, LandingZone};
use crate::indoor::localizer::{Localizer, LocalizerParams};
use crate::indoor::model::Model;
use crate::indoor::offline::model_settings;
use crate::output::LandmarkRecord;
use crate::settings::Settings;
use mavloc_data::results::TrajectoryRow;
use mavloc_data::sets::{self, ResultSets};
use mavloc_data::table::Appender;

/// Area results are rewritten every this many frames.
pub const AREA_CHECKPOINT_FRAMES: u64 = 25;

/// Frames the area pipeline may have waiting: its results are a map, not a control
/// input, so a frame a quarter of a second late is as good as one on time, and a short
/// queue rides out the moments when the pipeline shares the cores with the camera (the
/// simulated camera renders on both). The indoor pipeline keeps only the newest frame.
pub const AREA_QUEUE_FRAMES: usize = 4;

/// The files of an area result set.
const AREA_FILES: [&str; 6] =
    ["landmarks.csv", "landmarks.ply", "area.geojson", "area.kml", "border.csv", "summary.json"];

/// Keeps `failing`, the writes that failed since the last that worked (a full disk), up
/// to date with one more, `ok` or not. The first that works after failures returns
/// `"{again}, after N failed {what}"`: without it the warnings were the last word in the
/// log and on the ground station.
fn count_write(failing: &mut u64, ok: bool, again: &str, what: &str) -> Option<String> {
    if !ok {
        *failing += 1;
        return None;
    }
    match std::mem::take(failing) {
        0 => None,
        n => Some(format!("{again}, after {n} failed {what}")),
    }
}

/// A new run id: the UTC time now (`yyyymmddThhmmssZ`), made unique among the runs of
/// both pipelines under `results` (`-2`, `-3`, ... for starts within one second). The
/// daemon takes one per start and per pipeline reset.
pub fn new_run(results: &Path) -> String {
    sets::new_run_id(std::time::SystemTime::now(), |id| {
        ["area", "indoor"].iter().any(|n| results.join(format!("{n}.runs")).join(id).exists())
    })
}

/// The area pipeline, live.
pub struct AreaLive {
    /// Stopped cleanly: the last write says the results are complete.
    finished: bool,
    pipeline: AreaPipeline,
    k_full: Intrinsics,
    downscale: u32,
    sets: ResultSets,
    /// Landmarks purged from the library (converged ones still tracked are added when
    /// writing; the two are disjoint, see `Library::purge`).
    results: Vec<LandmarkRecord>,
    /// Added to the library's landmark ids, so results resumed from the run's last set
    /// keep theirs.
    id_offset: u64,
    origin: Geodetic,
    frames: u64,
    /// Time spent per stage over the run; segmenting and the grey conversion as `prepare`.
    timing: crate::area::StageTiming,
    prepare: std::time::Duration,
    /// Frame times (ms) since `minute_start`, and the median of each minute before: does
    /// the frame cost stay flat as the library fills (logged and in `summary.json`)?
    minute_ms: Vec<f64>,
    minute_start: std::time::Instant,
    minute_medians: Vec<f64>,
    no_mask_warned: bool,
    /// Checkpoint writes that failed since the last that worked (a full disk): the
    /// first that works again says so, or the warnings would be the last word.
    writes_failing: u64,
    /// A mask of another size than its frame was said (once).
    bad_mask_warned: bool,
    started: std::time::Instant,
    settings: crate::settings::Area,
    /// `gimbal.aim = "border"`: report where the border is, per frame, smoothed over
    /// frames ([`AIM_SMOOTHING`]).
    aim: bool,
    /// The smoothed aim, earth-frame (yaw, pitch), radians; it waits through frames with
    /// no border in view.
    aimed: Option<(f64, f64)>,
    /// The gimbal chain the log's angles are in, and the configured offsets in them.
    chain: crate::geometry::GimbalChain,
    offsets: [f64; 3],
    /// `area.attitude_prior_deg > 0`: the run's sightings and poses, for the bundle
    /// adjustment after each landing ([`super::flightlog`]).
    log: Option<FlightLog>,
    /// The last adjustment's landmarks, by id: they stand for the filters' in every set
    /// written after it (landmarks that converge later are the filters' until the next
    /// landing).
    refined: std::collections::BTreeMap<u64, LandmarkRecord>,
    /// The last adjustment, for `summary.json`.
    adjusted: Option<Adjusted>,
    /// Asked again (a touchdown, a command) while an adjustment ran: another follows it.
    adjust_again: Option<&'static str>,
    /// The static gimbal offset (yaw, pitch, roll, degrees) the last adjustment found,
    /// added to the angles of every frame posed by the gimbal since; the log keeps the
    /// angles as reported, so each adjustment finds the whole offset again.
    bias: Option<[f64; 3]>,
    /// `area.adjust_first_frames`: the logged frames at which the next adjustment in
    /// flight starts.
    next_adjust: usize,
}

/// The SD of a gimbal mount's static offset before any adjustment, degrees: what the
/// offset an adjustment finds is weighed against before the frames after it get it
/// ([`crate::area::refine::weighed_offset`]). Degrees, as the issue's DJI photos (2.4-5.0
/// deg, partly per photo) and PX4 SITL's heading (about 1 deg) were off.
pub const MOUNT_PRIOR_DEG: f64 = 2.0;

impl AreaLive {
    /// `k_full`: the camera's intrinsics at capture size; `origin`: the local frame's WGS84
    /// origin until the autopilot tells another; `link`: the results path users read
    /// (`STATE/results/area`); `run`: the daemon's run id ([`new_run`]).
    pub fn new(
        s: &Settings,
        k_full: Intrinsics,
        origin: Geodetic,
        link: &Path,
        run: &str,
    ) -> Result<AreaLive, String> {
        let downscale = s.area.downscale.max(1);
        let refining = s.area.attitude_prior_deg > 0.0;
        let pipeline = AreaPipeline::new(&s.area, k_full.downscaled(downscale))
            .map_err(|e| e.to_string())?
            .with_trace(refining);
        let sets = ResultSets::open(link, run)
            .map_err(|e| format!("cannot open results {}: {e}", link.display()))?;
        // A new run starts empty. This run's own last set exists only when the pipeline is
        // rebuilt (after a panic, a pipeline switch): continue from it, or the next
        // checkpoint would replace it with fewer landmarks.
        let results = match sets.current() {
            Some(set) => resume(&set.join("landmarks.csv"), &sets.run_dir()),
            None => Vec::new(),
        };
        let id_offset = results.iter().map(|l| l.id + 1).max().unwrap_or(0);
        tracing::info!("area: run {run}, results in {} (a link to its newest set)", link.display());
        Ok(AreaLive {
            finished: false,
            pipeline,
            k_full,
            downscale,
            sets,
            results,
            id_offset,
            origin,
            frames: 0,
            timing: crate::area::StageTiming::default(),
            prepare: std::time::Duration::ZERO,
            minute_ms: Vec::new(),
            minute_start: std::time::Instant::now(),
            minute_medians: Vec::new(),
            no_mask_warned: false,
            writes_failing: 0,
            bad_mask_warned: false,
            started: std::time::Instant::now(),
            settings: s.area.clone(),
            aim: s.gimbal.aim == crate::settings::GimbalAim::Border,
            aimed: None,
            chain: s.gimbal.chain,
            offsets: [s.gimbal.yaw_offset_deg, s.gimbal.pitch_offset_deg, s.gimbal.roll_offset_deg],
            log: refining.then(|| FlightLog::new(s.gimbal.chain)),
            refined: Default::default(),
            adjusted: None,
            adjust_again: None,
            bias: None,
            next_adjust: 0,
        })
    }

    /// Everything converged so far: purged results and converged landmarks still tracked,
    /// as the last adjustment left them where it moved them.
    fn all_landmarks(&self) -> Vec<LandmarkRecord> {
        let mut all = self.results.clone();
        all.extend(self.pipeline.converged_now().into_iter().map(|l| self.shifted(l)));
        for l in &mut all {
            if let Some(r) = self.refined.get(&l.id) {
                *l = r.clone();
            }
        }
        all
    }

    fn shifted(&self, mut l: LandmarkRecord) -> LandmarkRecord {
        l.id += self.id_offset;
        l
    }

    /// Writes a set in flight, saying in `report` how long the border is, or why the
    /// write failed and, at the first that works after failures, that the results are
    /// written again.
    fn checkpoint(&mut self, report: &mut Report) {
        let written = self.write();
        report.events.extend(self.count_write(&written));
        match written {
            Ok((_, lines)) => {
                let length: f64 = lines.iter().flat_map(|l| l.windows(2).map(|w| (w[1] - w[0]).norm())).sum();
                report.counters.push(("BRD_LINES", lines.len() as f32));
                report.counters.push(("BRD_LEN", length as f32));
            }
            Err(e) => report.warnings.push(Warning::WriteFailed(format!("area: cannot write results: {e}"))),
        }
    }

    /// Counts a write in flight (a checkpoint, the map at the touchdown, the adjusted
    /// map): after failed ones, the first that works returns the line saying so.
    fn count_write<T>(&mut self, written: &io::Result<T>) -> Option<String> {
        count_write(&mut self.writes_failing, written.is_ok(), "area: results written again", "writes")
    }

    /// Whether a checkpoint or the stop writes a set: not while this run has no landmark
    /// and has written none, so the last run's map stays current (a restart on the ground
    /// made an empty set current within seconds: an outside audit). A snapshot asked for
    /// over MAVLink writes one anyway.
    fn worth_a_set(&self) -> bool {
        // The landmarks first (no copy of them, no look at the disk while there are any).
        !self.results.is_empty() || !self.pipeline.converged_now().is_empty() || self.sets.current().is_some()
    }

    /// Writes a new result set and makes it current; returns its files (by the link's
    /// path, as users read them) and the border lines fitted. On an error the previous set
    /// stays current.
    fn write(&self) -> io::Result<(Vec<PathBuf>, Vec<Vec<crate::geometry::Vec3>>)> {
        let landmarks = self.all_landmarks();
        let elapsed = self.started.elapsed().as_secs_f64();
        let per_frame = |d: std::time::Duration| d.as_secs_f64() * 1000.0 / self.frames.max(1) as f64;
        // Live, frames/s is the camera's rate when the pipeline keeps up; the stage times
        // say how much of each frame's interval the pipeline used.
        let mut summary = RunSummary {
            method: "ukf".into(),
            frames: self.frames,
            elapsed_s: elapsed,
            frames_per_s: if elapsed > 0.0 { self.frames as f64 / elapsed } else { 0.0 },
            prepare_ms: per_frame(self.prepare),
            band_ms: per_frame(self.timing.band),
            sift_ms: per_frame(self.timing.sift),
            match_estimate_ms: per_frame(self.timing.match_estimate),
            purge_add_ms: per_frame(self.timing.purge_add),
            frame_ms_per_minute: self.minute_medians.clone(),
            complete: self.finished,
            ..RunSummary::default()
        };
        if let Some(a) = &self.adjusted {
            let r = &a.refined;
            let scale = self.downscale as f64;
            summary.refined_median_before_px = Some(r.median_before_px * scale);
            summary.refined_median_after_px = Some(r.median_after_px * scale);
            summary.refined_left_out = Some(r.left_out);
            summary.refined_frames = Some(a.frames as u64);
            summary.refined_landmarks = Some(r.landmarks.len());
            summary.refined_elapsed_s = Some((a.elapsed_s * 10.0).round() / 10.0);
            if let Some((o, sd)) = r.offset_deg {
                summary.refined_gimbal_offset_deg = Some(o);
                summary.refined_gimbal_offset_sd_deg = Some(sd);
            }
            summary.attitude_correction_median_deg = r.median_correction_deg();
        }
        summary.gimbal_offset_applied_deg = self.bias;
        let frame = LocalFrame::new(self.origin);
        let mut lines = Vec::new();
        self.sets.write(|dir| {
            lines = write_results(dir, &frame, "mavloc run: area", &landmarks, &mut summary)?;
            Ok(())
        })?;
        let link = self.sets.runs().link();
        Ok((AREA_FILES.iter().map(|f| link.join(f)).collect(), lines))
    }
}

/// The landmarks of this run's last set, for a rebuilt pipeline. A file that does not
/// parse (a disk fault) is moved aside into the run's folder, where it outlives the set,
/// and the run goes on without it: better fewer landmarks than no pipeline.
fn resume(path: &Path, run_dir: &Path) -> Vec<LandmarkRecord> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) => {
            tracing::warn!("area: cannot read {} ({e}); this run goes on without it", path.display());
            return Vec::new();
        }
    };
    match crate::output::parse_landmarks_csv(&text, &path.display().to_string()) {
        Ok(results) => {
            tracing::info!(
                "area: continuing the run with {} landmarks from {}",
                results.len(),
                path.display()
            );
            results
        }
        Err(e) => {
            // Into the run's folder: it outlives the set it came from.
            let said = mavloc_data::state::set_aside(path, Some(run_dir), "landmark file", &e.to_string());
            tracing::warn!("area: {said}; the run goes on without it");
            Vec::new()
        }
    }
}

impl LivePipeline for AreaLive {
    fn process(&mut self, frame: &LiveFrame) -> Report {
        let mut report = Report::default();
        if let Some(o) = frame.origin {
            self.origin = o;
        }
        let t_prepare = std::time::Instant::now();
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
                let why = if self.settings.segmenter == crate::settings::Segmenter::Learned {
                    "area.segmenter = \"learned\" trains on a dataset's masks (mavloc area) and makes none live"
                } else {
                    "area.segmenter = \"masks\""
                };
                report.events.push(format!(
                    "area: this camera gives no target mask and {why}; frames are skipped (set area.segmenter to \"water\" or \"hsv\")"
                ));
            }
            return report;
        };
        // `prepare` would stretch a mask of another size over the frame: the border
        // somewhere else, with no word.
        use opencv::prelude::MatTraitConst;
        if (mask.cols(), mask.rows()) != (frame.image.cols(), frame.image.rows()) {
            if !self.bad_mask_warned {
                self.bad_mask_warned = true;
                report.events.push(format!(
                    "area: frame {} skipped: its mask is {}x{} px, the frame {}x{} (frames with such masks are skipped)",
                    frame.index,
                    mask.cols(),
                    mask.rows(),
                    frame.image.cols(),
                    frame.image.rows()
                ));
            }
            return report;
        }
        let (grey, small_mask) = match prepare(&frame.image, mask, self.downscale) {
            Ok(v) => v,
            Err(e) => {
                report.events.push(format!("area: frame {} unusable: {e}", frame.index));
                return report;
            }
        };
        let prepared = t_prepare.elapsed();
        let camera = self.biased(&frame.pose);
        let input = FrameInput { index: frame.index, grey: &grey, mask: &small_mask, pose: camera };
        if self.aim {
            // In the angles the gimbal reports: its manager holds those at the setpoint, so
            // a bearing with the offset found added would point the camera that far off.
            if let Some((yaw, pitch)) = border_bearing(
                &small_mask,
                &frame.pose.camera,
                self.pipeline.intrinsics(),
                self.settings.ground_down_m,
            ) {
                // Each frame's nearest shore is a few pixels' choice: smoothed, the
                // setpoints move with the shore, not with the pixels.
                let (y, p) = self.aimed.map_or((yaw, pitch), |(y, p)| {
                    let dy = crate::geometry::wrap_angle(yaw - y);
                    (crate::geometry::wrap_angle(y + AIM_SMOOTHING * dy), p + AIM_SMOOTHING * (pitch - p))
                });
                self.aimed = Some((y, p));
                report.aim = Some((y, p));
            }
        }
        let r = match self.pipeline.process(&input) {
            Ok(r) => r,
            Err(e) => {
                report.events.push(format!("area: frame {}: {e}", frame.index));
                return report;
            }
        };
        if let Some(log) = self.log.as_mut() {
            if log.add(self.frames, &frame.pose, &r.sightings, self.id_offset) {
                report.events.push(format!(
                    "area: {} sightings kept for the map's adjustment, the most it keeps; later frames are not in it",
                    super::flightlog::MAX_SIGHTINGS
                ));
            }
        }
        if let Some(note) = self.adjust_in_flight() {
            report.events.push(note);
        }
        self.frames += 1;
        self.prepare += prepared;
        self.timing += r.timing;
        let t = r.timing;
        self.minute_ms
            .push((prepared + t.band + t.sift + t.match_estimate + t.purge_add).as_secs_f64() * 1e3);
        if self.minute_start.elapsed() >= std::time::Duration::from_secs(60) {
            let ms = &mut self.minute_ms;
            ms.sort_by(f64::total_cmp);
            let at = |q: f64| ms[((ms.len() - 1) as f64 * q).round() as usize];
            let (median, p95, max) = (at(0.5), at(0.95), at(1.0));
            tracing::info!(
                "area: last minute {} frames, frame time median {median:.1} ms, 95th percentile {p95:.1} ms, max {max:.1} ms; {} landmarks tracked, {} converged",
                ms.len(),
                r.landmarks,
                self.results.len() + r.converged.len()
            );
            self.minute_medians.push((median * 10.0).round() / 10.0);
            ms.clear();
            self.minute_start = std::time::Instant::now();
        }
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
        if self.frames.is_multiple_of(AREA_CHECKPOINT_FRAMES) && self.worth_a_set() {
            self.checkpoint(&mut report);
        }
        report
    }

    fn apply(&mut self, s: &Settings) {
        // Turned on in flight: the sightings from now on; turned off: none kept. A new
        // resolution or chain starts the log again (its pixels and angles are the old
        // ones'), as the pipeline's own landmarks go on.
        // New configured gimbal offsets do as well: the logged angles have the old ones in.
        let refining = s.area.attitude_prior_deg > 0.0;
        let offsets = |g: &crate::settings::Gimbal| [g.yaw_offset_deg, g.pitch_offset_deg, g.roll_offset_deg];
        let same = s.area.downscale.max(1) == self.downscale
            && s.gimbal.chain == self.chain
            && offsets(&s.gimbal) == self.offsets;
        if refining != self.log.is_some() || (refining && !same) {
            if self.log.as_ref().is_some_and(|l| l.frames() > 0) {
                tracing::info!(
                    "area: the sightings kept for the map's adjustment start again (new settings)"
                );
            }
            self.log = refining.then(|| FlightLog::new(s.gimbal.chain));
            self.pipeline.set_trace(refining);
            // The offset found is one of the angles as they were reported before.
            self.bias = None;
            self.next_adjust = 0;
            // A landing queued behind the adjustment the old log took with it is not lost:
            // it goes to the new log now (which says why if it has too few frames).
            if let Some(why) = self.adjust_again.take() {
                self.settings = s.area.clone();
                let note = self.start_adjustment(why);
                tracing::info!("{note}");
            }
        }
        if s.area.adjust_first_frames == 0 {
            self.bias = None;
        }
        self.offsets = offsets(&s.gimbal);
        self.chain = s.gimbal.chain;
        self.settings = s.area.clone();
        self.aim = s.gimbal.aim == crate::settings::GimbalAim::Border;
        self.downscale = s.area.downscale.max(1);
        if let Err(e) = self.pipeline.reconfigure(&s.area, self.k_full.downscaled(self.downscale)) {
            tracing::warn!("area: new settings not applied: {e}");
        }
    }

    fn write_results(&self) -> io::Result<Vec<PathBuf>> {
        self.write().map(|(files, _)| files)
    }

    fn finish(&mut self) -> io::Result<Vec<PathBuf>> {
        self.finished = true;
        // An adjustment that has just finished goes into the last set; one still running
        // is left (a stop must not wait a minute).
        for e in self.poll() {
            match e {
                PipelineEvent::WriteFailed(line) => tracing::warn!("{line}"),
                PipelineEvent::Note(line) => tracing::info!("{line}"),
                other => tracing::info!("{other:?}"),
            }
        }
        if self.log.as_ref().is_some_and(FlightLog::running) {
            tracing::warn!(
                "area: stopped while the map was being adjusted; the last set holds the landmarks as they were before"
            );
        }
        if !self.worth_a_set() {
            tracing::info!("area: stopped with no landmark; the results before this run stay current");
            return Ok(Vec::new());
        }
        self.write_results()
    }

    /// The vehicle touched down: the run's map adjusted on a thread of its own
    /// ([`super::flightlog`]); [`LivePipeline::poll`] writes it when it is done.
    fn adjust_map(&mut self, why: &str) -> Vec<PipelineEvent> {
        let Some(log) = self.log.as_ref() else {
            return vec![PipelineEvent::Note(format!(
                "area: {why}; the map is not adjusted: area.attitude_prior_deg (AREA_ADJ_PRIOR) is 0"
            ))];
        };
        if log.running() {
            self.adjust_again = Some(if why == "landed" { "landed" } else { "asked to" });
            return vec![PipelineEvent::Note(format!(
                "area: {why} while the map is being adjusted; it is adjusted again after"
            ))];
        }
        // The map at the touchdown, whole, before the adjustment replaces it.
        let mut events = Vec::new();
        let written = self.write();
        events.extend(self.count_write(&written).map(PipelineEvent::Note));
        if let Err(e) = written {
            events.push(PipelineEvent::WriteFailed(format!("area: cannot write results: {e}")));
        }
        events.push(PipelineEvent::Note(self.start_adjustment(why)));
        events
    }

    fn poll(&mut self) -> Vec<PipelineEvent> {
        let Some(log) = self.log.as_mut() else { return Vec::new() };
        let adjusted = match log.poll() {
            Poll::Idle | Poll::Running => return Vec::new(),
            Poll::Failed(why) => {
                let mut events = vec![PipelineEvent::Note(format!("area: the map is not adjusted: {why}"))];
                if let Some(why) = self.adjust_again.take() {
                    events.push(PipelineEvent::Note(self.start_adjustment(why)));
                }
                return events;
            }
            Poll::Done(a) => *a,
        };
        if let Some(why) = adjusted.refined.implausible(self.settings.attitude_prior_deg) {
            let mut events = vec![PipelineEvent::Note(format!(
                "area: the map's adjustment is not used: {why}; the map stays the filters'"
            ))];
            if let Some(why) = self.adjust_again.take() {
                events.push(PipelineEvent::Note(self.start_adjustment(why)));
            }
            return events;
        }
        let r = &adjusted.refined;
        let scale = self.downscale as f64;
        let mut line = format!(
            "area: map adjusted in {:.0} s: {} landmarks, sightings {:.2} -> {:.2} px, frames turned {:.2} deg (medians)",
            adjusted.elapsed_s,
            r.landmarks.len(),
            r.median_before_px * scale,
            r.median_after_px * scale,
            r.median_correction_deg().unwrap_or(0.0),
        );
        if let (Some((o, _)), Some(cov)) = (r.offset_deg, r.offset_covariance_deg2) {
            line.push_str(&format!("; gimbal offset yaw {:.2} pitch {:.2} roll {:.2} deg", o[0], o[1], o[2]));
            // Only with the adjustments in flight asked for: against PX4 SITL adding it
            // gained nothing (README, "The map adjusted in flight").
            if self.settings.adjust_first_frames > 0 {
                let kept = crate::area::refine::weighed_offset(&o.into(), &cov, MOUNT_PRIOR_DEG);
                self.bias = Some([kept.x, kept.y, kept.z]);
                line.push_str(&format!(
                    "; added to later frames: yaw {:.2} pitch {:.2} roll {:.2} deg",
                    kept.x, kept.y, kept.z
                ));
            }
        }
        // Added to what earlier adjustments moved: a landmark this one left out (its
        // sightings were in a log started again since) keeps its last adjusted place.
        self.refined.extend(r.landmarks.iter().map(|l| (l.id, l.clone())));
        self.adjusted = Some(adjusted);
        let mut events = vec![PipelineEvent::Note(line)];
        let written = self.write();
        events.extend(self.count_write(&written).map(PipelineEvent::Note));
        if let Err(e) = written {
            events.push(PipelineEvent::WriteFailed(format!("area: cannot write the adjusted results: {e}")));
        }
        if let Some(why) = self.adjust_again.take() {
            events.push(PipelineEvent::Note(self.start_adjustment(why)));
        }
        events
    }
}

impl AreaLive {
    /// The static gimbal offset added to the frames now, if any (degrees).
    pub fn offset_added(&self) -> Option<[f64; 3]> {
        self.bias
    }

    /// The camera pose the pipeline takes for a frame: as reported, with the static
    /// gimbal offset the last adjustment found added to the gimbal's angles (frames posed
    /// by the fixed mount have no gimbal angles to correct).
    fn biased(&self, pose: &crate::align::AlignedPose) -> crate::geometry::CameraPose {
        match self.bias {
            Some([yaw, pitch, roll]) if pose.from_gimbal => {
                let reported = super::record::pose_record(pose, self.chain, [0.0; 3], |p| p);
                super::flightlog::pose_at(
                    &reported,
                    self.chain,
                    &crate::geometry::Vec3::new(yaw, pitch, roll),
                )
            }
            _ => pose.camera,
        }
    }

    /// `area.adjust_first_frames`: starts an adjustment in flight once the log holds that
    /// many frames, then each time they have doubled (the whole log each time, so the
    /// adjustments' cost stays within about twice the last one's); what the ground is
    /// told.
    fn adjust_in_flight(&mut self) -> Option<String> {
        let first = self.settings.adjust_first_frames as usize;
        let log = self.log.as_ref()?;
        let frames = log.frames();
        if first == 0 || log.running() || frames < first.max(self.next_adjust) {
            return None;
        }
        self.next_adjust = 2 * frames;
        Some(self.start_adjustment(&format!("{frames} frames logged")))
    }

    /// Starts the adjustment of the run's map; what the ground is told.
    fn start_adjustment(&mut self, why: &str) -> String {
        let landmarks = self.all_landmarks();
        let k = *self.pipeline.intrinsics();
        let (prior, noise) = (self.settings.attitude_prior_deg, self.settings.bearing_noise_deg);
        let Some(log) = self.log.as_mut() else { return "area: the map is not adjusted (off)".into() };
        match log.start(&landmarks, &k, prior, noise) {
            Ok(frames) => {
                format!("area: {why}; adjusting the map: {} landmarks over {frames} frames", landmarks.len())
            }
            Err(not) => format!("area: {why}; the map is not adjusted: {not}"),
        }
    }
}

/// Weight of a frame's aim in the smoothed one (about 1 s at 6 frames/s).
const AIM_SMOOTHING: f64 = 0.2;

/// Earth-frame bearing (yaw, pitch) of the nearest stretch of the border in view: where
/// the camera should look to keep the closest shore in the middle of the picture, as a
/// mission's ROI on the nearest shore point does. (The centroid of all border pixels, used
/// before, was pulled up by the far shore: against PX4 SITL the gimbal settled 30 degrees
/// down where the ROI's geometry is 54, doubling the range to the landmarks.) The border
/// pixels are put on the ground plane `ground_down` (local NED down); the nearest 10 %
/// (horizontally) are averaged. `None` when too little border is in view to say.
fn border_bearing(
    mask: &opencv::core::Mat,
    pose: &crate::geometry::CameraPose,
    k: &Intrinsics,
    ground_down: f64,
) -> Option<(f64, f64)> {
    use opencv::{core, imgproc};
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
    let mut points = core::Vector::<core::Point>::new();
    core::find_non_zero(&edge, &mut points).ok()?;
    // At least a few dozen border pixels, or the border is noise.
    if points.len() < 30 {
        return None;
    }
    let step = points.len().div_ceil(2000);
    let mut ground: Vec<(f64, crate::geometry::Vec3)> = points
        .iter()
        .step_by(step)
        .filter_map(|p| {
            let g = pose.ground_intersection(
                k,
                crate::geometry::Pixel::new(p.x as f64, p.y as f64),
                ground_down,
            )?;
            let d = (g - pose.position).xy().norm();
            d.is_finite().then_some((d, g))
        })
        .collect();
    if ground.len() < 10 {
        return None;
    }
    let n = (ground.len() / 10).max(10);
    ground.select_nth_unstable_by(n - 1, |a, b| a.0.total_cmp(&b.0));
    let target = ground[..n].iter().map(|(_, g)| g).sum::<crate::geometry::Vec3>() / n as f64;
    let b = crate::geometry::Bearing::from_direction(&(target - pose.position))?;
    Some((b.yaw, b.pitch))
}

/// The indoor pipeline, live.
pub struct IndoorLive {
    /// Stopped cleanly (see [`AreaLive`]).
    finished: bool,
    model: Model,
    settings: Settings,
    pre: Preprocessor,
    localizer: Localizer,
    trigger: LandingTrigger,
    trajectory: Appender<TrajectoryRow>,
    /// Trajectory lines that could not be appended since the last that could (see
    /// [`AreaLive`]'s `writes_failing`).
    writes_failing: u64,
    /// This run's folder (`results/indoor` points at it).
    dir: PathBuf,
    frames: u64,
    last_hold: Option<Hold>,
    /// The last frame, for the velocity from the next ([`flow`]).
    last_flow: Option<FlowFrame>,
    flow: Flow,
    /// Frames with a velocity, and why the others had none (summary.json).
    flow_ok: u64,
    flow_failed: std::collections::BTreeMap<&'static str, u64>,
    /// The autopilot's horizontal position at the localiser's last frame, to carry the
    /// particles across a gap in the frames ([`IndoorLive::carry_across_gap`]).
    last_vehicle: Option<(f64, Vector2<f64>)>,
    /// Without GPS, where the particles start is decided at the first frame
    /// ([`IndoorLive::start`]): the pad, or near the autopilot's position in the air.
    start_pending: bool,
}

/// The SD (m) of the autopilot's own displacement over a gap of `gap_s` seconds in the
/// frames, when it flies on mavloc's estimates: EKF2 dead-reckons on its IMU meanwhile.
/// Measured against PX4 SITL (SIH, one 2.1 s gap in flight at 0.5 m/s, `tools/sitl.py
/// --camera-gap 2`): EKF2's displacement was 0.02, 0.09, 0.18 and 0.22 m off the true one
/// after 0.56, 1.06, 1.56 and 2.13 s; this is about 1.4 times that, growing with the
/// square of the gap as an accelerometer bias makes it. With GPS the autopilot knows its
/// displacement better, and this is merely cautious. At most `MAX_CARRY_SD_M`: spread
/// wider, the particles would reach look-alike places, and a gap that long is mostly
/// time on the ground between flights, where the vehicle stands still.
fn dead_reckoning_sd_m(gap_s: f64) -> f64 {
    (0.1 * gap_s + 0.02 * gap_s * gap_s).min(MAX_CARRY_SD_M)
}

/// The widest spread a carry gives the particles (m): the reach of the renewed particles
/// of a track from a given pad (`TRACKING_RECOVERY_SD_M`).
const MAX_CARRY_SD_M: f64 = crate::indoor::localizer::TRACKING_RECOVERY_SD_M;

/// Faster than this across a gap (m/s) the autopilot's displacement is taken for a reset
/// of its position, not a flight, and the particles are not carried by it.
const MAX_CARRY_SPEED_M_S: f64 = 5.0;

/// Variance of the camera's vertical velocity, (m/s)^2: the change of a height that is
/// itself the autopilot's, a rough figure next to the horizontal one.
const VERTICAL_VAR: f64 = 0.3 * 0.3;

/// Where the particles start around the pad in a GPS-denied take-off (m).
const PAD_START_SD_M: f64 = 0.3;

/// A GPS-denied pipeline started in the air (mavloc restarted after a crash, the pipeline
/// rebuilt or reset): the SD (m) of the autopilot's position it searches from. That
/// position was dead-reckoned on the autopilot's IMU since mavloc's last estimate: against
/// PX4 SITL (SIH), 0.3-1.7 m off after 4 s without them (`tools/sitl.py --camera-gap 4`).
const AIR_START_SD_M: f64 = 1.0;

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
    /// `link`: the results path users read (`STATE/results/indoor`); `run`: the daemon's
    /// run id ([`new_run`]). A rebuilt pipeline appends to its run's trajectory.
    pub fn new(s: &Settings, k: Intrinsics, link: &Path, run: &str) -> Result<IndoorLive, String> {
        let model = Model::load(Path::new(&s.indoor.model))?;
        let mut settings = s.clone();
        settings.indoor = model_settings(&model, &s.indoor);
        let i = &settings.indoor;
        let pre = crate::indoor::offline::preprocessor(k, i);
        let rel = (pre.work.fx - model.frame.work_fx).abs() / model.frame.work_fx;
        if rel > 0.1 {
            tracing::warn!(
                "indoor: the camera's focal length at the working width differs from the model's by {:.0} %; textons will be seen at another scale",
                rel * 100.0
            );
        }
        let localizer = Localizer::new(&model, LocalizerParams::from_settings(i, 1))?;
        let start_pending = i.gps_denied;
        let dir = sets::open_run_dir(link, run)
            .map_err(|e| format!("cannot open results {}: {e}", link.display()))?;
        tracing::info!("indoor: run {run}, results in {} (a link to {})", link.display(), dir.display());
        let path = dir.join("trajectory.csv");
        let trajectory =
            Appender::append(&path).map_err(|e| format!("cannot open {}: {e}", path.display()))?;
        Ok(IndoorLive {
            finished: false,
            trigger: LandingTrigger::new(zone(&settings)),
            model,
            settings,
            pre,
            localizer,
            trajectory,
            writes_failing: 0,
            dir,
            frames: 0,
            last_hold: None,
            last_flow: None,
            flow: Flow::new().map_err(|e| format!("indoor: cannot set up the camera's velocity: {e}"))?,
            flow_ok: 0,
            flow_failed: Default::default(),
            last_vehicle: None,
            start_pending,
        })
    }
}

impl IndoorLive {
    /// Without GPS, where the particles start, at the pipeline's first frame. A frame that
    /// only measures the motion (the camera too low to localise) over the pad is a
    /// take-off: from the pad mavloc reported while the vehicle stood there, tracked as
    /// given. Any other first frame is a pipeline started in the air: mavloc restarted
    /// after a crash (systemd's `Restart=on-failure`), the pipeline rebuilt after a panic,
    /// or reset or started by a command. The pad is then wrong by however far the vehicle
    /// flew, and a track given there is never searched out of (against PX4 SITL the
    /// autopilot was sent the pad's neighbourhood, metres off, as fixes, and flew off on
    /// them); so the particles search near where the autopilot itself puts the vehicle,
    /// and no fix goes out until they have found it. Too low to localise (climbing or
    /// descending away from the pad, or too high), they can only be carried on the camera's velocity:
    /// tracked from there as from a pad that may be off.
    fn start(&mut self, frame: &LiveFrame, vehicle: Vector2<f64>) -> Option<String> {
        if !std::mem::take(&mut self.start_pending) {
            return None;
        }
        let i = &self.settings.indoor;
        let pad = Vector2::new(i.pad_x_m, i.pad_y_m);
        let known = vehicle.iter().all(|c| c.is_finite());
        if frame.motion_only && (!known || (vehicle - pad).norm() <= AIR_START_SD_M) {
            self.localizer.start_at(pad, PAD_START_SD_M);
            return None;
        }
        if !known {
            return Some(
                "indoor: started in the air with no position from the autopilot: searching the whole floor"
                    .into(),
            );
        }
        if frame.motion_only {
            self.localizer.start_at(vehicle, AIR_START_SD_M);
            return Some(format!(
                "indoor: started in the air where the camera cannot localise, {:.1} m from the pad: tracking from the autopilot's position x {:.2} y {:.2} m (SD {AIR_START_SD_M} m)",
                (vehicle - pad).norm(),
                vehicle.x,
                vehicle.y
            ));
        }
        self.localizer.search_near(vehicle, AIR_START_SD_M);
        Some(format!(
            "indoor: started in the air: searching near the autopilot's position x {:.2} y {:.2} m (SD {AIR_START_SD_M} m), not from the pad",
            vehicle.x, vehicle.y
        ))
    }

    /// Across a gap in the frames the camera's own velocity is not measured (its flow
    /// needs frames under `flow::MAX_DT_S` apart), and the particles would stay where the
    /// camera left them: they are carried by the autopilot's displacement over the gap
    /// instead. No estimate of mavloc's went into that displacement (none was sent while
    /// the camera was away), so this is not the feedback the GPS-denied motion model
    /// avoids (see `process`).
    fn carry_across_gap(&mut self, t: f64, vehicle: Vector2<f64>) -> Option<String> {
        let last = self.localizer.last_time()?;
        let gap = t - last;
        if gap <= crate::indoor::localizer::MAX_GAP_S {
            return None;
        }
        let (t0, p0) = self.last_vehicle.filter(|(t0, _)| *t0 == last)?;
        let d = vehicle - p0;
        if !d.iter().all(|c| c.is_finite()) {
            return None;
        }
        if d.norm() > MAX_CARRY_SPEED_M_S * (t - t0) {
            return Some(format!(
                "indoor: frames resume after {gap:.1} s; the autopilot moved {:.1} m meanwhile, taken for a reset of its position: the particles are not carried",
                d.norm()
            ));
        }
        let sd = dead_reckoning_sd_m(gap);
        self.localizer.carry(t, d, sd);
        Some(format!(
            "indoor: frames resume after {gap:.1} s; particles carried {:.2} m by the autopilot's position (SD {sd:.2} m)",
            d.norm()
        ))
    }

    /// The camera's motion since the last frame, if it can be measured.
    fn flow(
        &mut self,
        frame: &LiveFrame,
        t: f64,
        attitude: crate::geometry::Rot3,
        height: f64,
    ) -> Option<flow::Motion> {
        let cur = match FlowFrame::new(t, &frame.image, attitude, height) {
            Ok(f) => f,
            Err(e) => {
                tracing::debug!("indoor: no velocity from frame {}: {e}", frame.index);
                *self.flow_failed.entry("opencv").or_default() += 1;
                return None;
            }
        };
        let m = self.last_flow.as_ref().map(|prev| self.flow.motion(prev, &cur, &self.pre.camera));
        self.last_flow = Some(cur);
        match m? {
            Ok(m) => {
                self.flow_ok += 1;
                tracing::debug!(
                    target: "mavloc::flow",
                    "t {t:.4} v {:.4} {:.4} peak {:.2} height {height:.3}",
                    m.velocity.x,
                    m.velocity.y,
                    m.response
                );
                Some(m)
            }
            Err(e) => {
                if self.flow_failed.values().sum::<u64>() < 5 {
                    tracing::info!(
                        "indoor: no velocity from frame {} (height {height:.2} m): {e}",
                        frame.index
                    );
                }
                let kind = match e {
                    flow::NoMotion::Time(_) => "frame gap",
                    flow::NoMotion::Height(_) => "no height",
                    flow::NoMotion::OutOfView(_) => "tilted",
                    flow::NoMotion::Blank(_) => "blank floor",
                    flow::NoMotion::Weak(_) => "no match",
                    flow::NoMotion::TooFar(_) => "too fast",
                    flow::NoMotion::Cv(_) => "opencv",
                };
                *self.flow_failed.entry(kind).or_default() += 1;
                None
            }
        }
    }

    /// One frame, after any carry across a gap (`process`).
    fn process_frame(&mut self, frame: &LiveFrame) -> Report {
        let mut report = Report::default();
        let attitude = frame.pose.camera.local_from_camera();
        // The floor is the local frame's z = 0 (indoor: PX4's height is the floor distance).
        let height = -frame.pose.camera.position.z;
        let v = frame.pose.vehicle.velocity;
        let t = frame.pose.autopilot_time;
        let seen = self.flow(frame, t, attitude, height);
        // With no GPS the autopilot's velocity is made of these very estimates (and its
        // IMU): fed back as the motion model it turns an error into a drift that feeds
        // itself (measured against PX4 SITL). The camera's own velocity serves then, and
        // without one the localiser fits its own.
        let velocity = if self.settings.indoor.gps_denied {
            seen.map(|m| m.velocity)
        } else {
            Some(Vector2::new(v.x, v.y))
        };
        report.velocity = match seen {
            Some(m) => {
                // Into body axes with the same attitude that turned it north-up: the
                // heading cancels (see VelocityEstimate).
                let local = crate::geometry::Vec3::new(m.velocity.x, m.velocity.y, m.vertical_velocity);
                let body = frame.pose.vehicle.attitude.inverse() * local;
                let h = m.sd_m_s * m.sd_m_s;
                Some(VelocityEstimate { body: [body.x, body.y, body.z], var: [h, h, VERTICAL_VAR] })
            }
            // Once the camera has measured the velocity, a frame without keeps the stream going.
            None if self.flow_ok > 0 => Some(VelocityEstimate::UNMEASURED),
            None => None,
        };
        if frame.motion_only {
            if let Some(v) = velocity {
                self.localizer.coast(t, v);
                if self.localizer.tracking() {
                    let (p, spread) = self.localizer.coasted();
                    report.coasted = Some(PositionEstimate {
                        autopilot_time: t,
                        north: p.x,
                        east: p.y,
                        down: frame.pose.vehicle.position.z,
                        cov: fix_covariance(spread, self.localizer.found_track_age(t)),
                    });
                }
            }
            return report;
        }
        let e = match self.localizer.step_frame(
            t,
            &self.pre,
            &frame.image,
            Some(&attitude),
            Some(height),
            velocity,
        ) {
            Ok(e) => e,
            Err(e) => {
                report.events.push(format!("indoor: frame {} unusable: {e}", frame.index));
                return report;
            }
        };
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
            fix: e.fix,
        };
        let appended = self.trajectory.push(&row);
        let again = "indoor: trajectory.csv written again";
        report.events.extend(count_write(&mut self.writes_failing, appended.is_ok(), again, "appends"));
        if let Err(err) = appended {
            let line = format!("indoor: cannot append to trajectory.csv: {err}");
            report.warnings.push(Warning::WriteFailed(line));
        }
        // No fix, no estimate for the autopilot: the heaviest spot of particles still spread
        // over the floor is metres off as often as not, and EKF2 would fly on it.
        report.position = e.fix.then(|| PositionEstimate {
            autopilot_time: t,
            north: e.position.x,
            east: e.position.y,
            down: frame.pose.vehicle.position.z,
            cov: fix_covariance(e.spread, self.localizer.found_track_age(t)),
        });
        report.counters = vec![("IND_SDX", e.spread.0 as f32), ("IND_SDY", e.spread.1 as f32)];
        match self.trigger.observe(&e) {
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
}

impl LivePipeline for IndoorLive {
    fn process(&mut self, frame: &LiveFrame) -> Report {
        let t = frame.pose.autopilot_time;
        let p = frame.pose.vehicle.position;
        let vehicle = Vector2::new(p.x, p.y);
        let started = self.start(frame, vehicle);
        let carried = self.carry_across_gap(t, vehicle);
        let mut report = self.process_frame(frame);
        report.events.extend(started);
        report.events.extend(carried);
        if self.localizer.last_time() == Some(t) {
            self.last_vehicle = Some((t, vehicle));
        }
        report
    }

    fn apply(&mut self, s: &Settings) {
        let indoor = model_settings(&self.model, &s.indoor);
        let params = LocalizerParams::from_settings(&indoor, 1);
        if !self.localizer.set_params(&params) {
            match Localizer::new(&self.model, params) {
                Ok(l) => {
                    // From where the old one put the vehicle, if it ran: a search of the
                    // whole floor would send nothing for seconds and may settle on a
                    // look-alike (an unrun one leaves the start to the first frame).
                    let prior = self.localizer.last_time().map(|_| self.localizer.coasted());
                    self.localizer = l;
                    if let Some((p, (sx, sy))) = prior {
                        self.localizer.search_near(p, sx.max(sy).max(PAD_START_SD_M));
                        self.start_pending = false;
                    }
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

    fn write_results(&self) -> io::Result<Vec<PathBuf>> {
        let summary = serde_json::json!({
            "complete": self.finished,
            "frames": self.frames,
            "landing_fired": self.trigger.fired(),
            "last_hold": self.last_hold.map(|h| format!("{h:?}")),
            "velocity_frames": self.flow_ok,
            "velocity_failed": self.flow_failed,
        });
        let path = self.dir.join("summary.json");
        crate::output::write_atomic(&path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
        Ok(vec![self.dir.join("trajectory.csv"), path])
    }

    fn finish(&mut self) -> io::Result<Vec<PathBuf>> {
        self.finished = true;
        self.write_results()
    }
}

/// The error a fix is sent with beyond its particles' spread, m (SD): the spread says how
/// well the particles agree, not how far the training views they agree on are from the
/// truth. Over nine unseen floors the fixes were 0.042-0.064 m RMS off; on the spread alone
/// an outside trial saw 4 % of the fixes sent beyond 3 SD (0.215 m off, said 0.028 m).
const FIX_SD_FLOOR_M: f64 = 0.06;

/// A track the filter found itself is off by more in its first seconds than its spread
/// says (the particles agreed for a second where the training views agree, which may be
/// off together): over ten unseen floors its fixes were 0.10-0.12 m RMS off in the first
/// 2 s against 0.058 m after, and in six live flights on floor 1234 0.24-0.27 m in the
/// first second (0.46 m at worst, said 0.07 m) and 0.17 m in the next, against 0.053 m
/// after, all with particle SDs of 0.03-0.06 m (session 47). So a young track's fixes
/// carry this much more error (SD, m) for its first [`YOUNG_TRACK_FULL_S`], tapering to
/// none at [`YOUNG_TRACK_S`]. A track from a given pad is not young.
const YOUNG_TRACK_SD_M: f64 = 0.25;
const YOUNG_TRACK_FULL_S: f64 = 1.0;
const YOUNG_TRACK_S: f64 = 2.0;

/// What a fix is sent with: the particles' variance plus [`FIX_SD_FLOOR_M`]'s, and a young
/// found track's (`found_track_age`, s; see [`YOUNG_TRACK_SD_M`]).
fn fix_covariance(spread: (f64, f64), found_track_age: Option<f64>) -> [[f64; 2]; 2] {
    let young = found_track_age.map_or(0.0, |age| {
        let left = ((YOUNG_TRACK_S - age) / (YOUNG_TRACK_S - YOUNG_TRACK_FULL_S)).clamp(0.0, 1.0);
        YOUNG_TRACK_SD_M * left
    });
    let floor = FIX_SD_FLOOR_M * FIX_SD_FLOOR_M + young * young;
    [[spread.0 * spread.0 + floor, 0.0], [0.0, spread.1 * spread.1 + floor]]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A carry's spread covers how far EKF2's dead-reckoned displacement was measured off
    /// (against PX4 SITL: 0.02-0.22 m over 0.56-2.13 s), not many times more, and grows
    /// with the gap up to the reach of a track from a pad.
    #[test]
    fn a_carry_spreads_with_the_gap_up_to_the_reach_of_a_track() {
        for (gap, measured) in [(0.56, 0.02), (1.06, 0.09), (1.56, 0.18), (2.13, 0.22)] {
            let sd = dead_reckoning_sd_m(gap);
            assert!(sd > measured && sd < 2.5 * f64::max(measured, 0.05), "{gap} s: SD {sd}");
        }
        assert!(dead_reckoning_sd_m(4.0) > dead_reckoning_sd_m(3.0));
        assert_eq!(dead_reckoning_sd_m(60.0), MAX_CARRY_SD_M);
    }

    /// A fix goes out with the floor's error beyond the particles' spread: tight particles
    /// are not a 3 cm fix (an outside trial saw fixes 7-9 SD off on the spread alone).
    #[test]
    fn a_fix_is_sent_with_the_training_views_error_beside_its_particles_spread() {
        let c = fix_covariance((0.028, 0.3), None);
        assert!((c[0][0].sqrt() - (0.028f64.powi(2) + FIX_SD_FLOOR_M.powi(2)).sqrt()).abs() < 1e-12);
        assert!(c[0][0].sqrt() > 0.06 && (c[1][1].sqrt() - 0.3).abs() < 0.01, "{c:?}");
        assert_eq!(c[0][1], 0.0);
    }

    /// A track the filter has just found goes out with a quarter metre more error for its
    /// first second (live, its first fixes were up to 0.46 m off, said 0.07 m), tapering to
    /// none at 2 s; a track found long ago, or given, with the floor alone.
    #[test]
    fn a_young_found_tracks_fixes_are_sent_with_more_error() {
        let sd = |age| fix_covariance((0.03, 0.03), age)[0][0].sqrt();
        let settled = sd(None);
        assert!(sd(Some(0.0)) > 0.25 && sd(Some(0.9)) > 0.25, "{} {}", sd(Some(0.0)), sd(Some(0.9)));
        assert!(sd(Some(1.5)) > settled && sd(Some(1.5)) < sd(Some(1.0)), "{}", sd(Some(1.5)));
        assert_eq!(sd(Some(2.0)), settled);
        assert_eq!(sd(Some(30.0)), settled);
    }
    use crate::geometry::Vec3;

    fn area(link: &Path, run: &str) -> AreaLive {
        let s = Settings::default();
        let k = crate::camera::intrinsics(&s).unwrap();
        AreaLive::new(&s, k, Geodetic::new(0.0, 0.0, 0.0), link, run).unwrap()
    }

    /// A straight shore along north, 22 m east of a camera 30 m up that looks east-north-
    /// east and shallow: the aim is the nearest shore point (yaw 90, pitch -53.7 degrees),
    /// not the middle of the shore in view, which the shallow view puts far off (the
    /// centroid of the border pixels is at yaw 46, pitch -45 here).
    #[test]
    fn the_gimbal_is_aimed_at_the_nearest_shore_in_view() {
        use crate::geometry::{GimbalAngles, GimbalChain, Mount};
        use opencv::prelude::*;
        let k = Intrinsics { width: 480, height: 270, fx: 240.0, fy: 240.0, cx: 239.5, cy: 134.5 };
        let a = GimbalAngles { yaw: 60f64.to_radians(), pitch: -35f64.to_radians(), roll: 0.0 };
        let pose = crate::geometry::CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -30.0),
            GimbalChain::YawPitchRoll,
            a,
            Mount::Earth,
        );
        let mut mask = opencv::core::Mat::new_rows_cols_with_default(
            270,
            480,
            opencv::core::CV_8UC1,
            opencv::core::Scalar::all(0.0),
        )
        .unwrap();
        for v in 0..270 {
            for u in 0..480 {
                let px = crate::geometry::Pixel::new(u as f64, v as f64);
                if pose.ground_intersection(&k, px, 0.0).is_some_and(|g| g.y > 22.0) {
                    *mask.at_2d_mut::<u8>(v, u).unwrap() = 255;
                }
            }
        }
        let (yaw, pitch) = border_bearing(&mask, &pose, &k, 0.0).expect("a shore in view");
        let (yaw, pitch) = (yaw.to_degrees(), pitch.to_degrees());
        // The nearest 10 % of the shore in view spans a few metres along it.
        assert!((yaw - 90.0).abs() < 6.0, "yaw {yaw:.1}");
        assert!((pitch + 53.7).abs() < 2.0, "pitch {pitch:.1}");
    }

    /// `area.adjust_first_frames`: adjustments start at that many logged frames, then at
    /// twice the frames of the last start, never while one runs (the next then waits for
    /// it to be collected); the offset an adjustment
    /// found turns the pose of each later frame posed by the gimbal by that many degrees of
    /// the chain's angles, and leaves frames posed by the fixed mount as they came.
    #[test]
    fn adjustments_in_flight_start_at_doubling_frames_and_their_offset_turns_gimbal_frames_only() {
        use crate::align::{AlignedPose, VehicleSample};
        use crate::geometry::{GimbalAngles, Mount};
        let dir = tempfile::tempdir().unwrap();
        let mut s = Settings::default();
        s.area.attitude_prior_deg = 1.0;
        s.area.adjust_first_frames = 40;
        let k = crate::camera::intrinsics(&s).unwrap();
        let mut live =
            AreaLive::new(&s, k, Geodetic::new(0.0, 0.0, 0.0), &dir.path().join("area"), "r").unwrap();
        let chain = s.gimbal.chain;
        let pose = |yaw: f64, from_gimbal: bool| {
            let camera = crate::geometry::CameraPose::from_gimbal(
                Vec3::new(1.0, 2.0, -40.0),
                chain,
                GimbalAngles::from_degrees(yaw, -50.0, 0.0),
                Mount::Earth,
            );
            AlignedPose {
                autopilot_time: 0.0,
                vehicle: VehicleSample {
                    position: camera.position,
                    velocity: Vec3::zeros(),
                    attitude: nalgebra::UnitQuaternion::identity(),
                },
                camera,
                from_gimbal,
            }
        };
        let mut started = Vec::new();
        let wait = |live: &mut AreaLive| {
            // Nothing converged: it ends at once, saying so.
            let t0 = std::time::Instant::now();
            loop {
                let said = live.poll();
                if !said.is_empty() {
                    assert!(format!("{said:?}").contains("no converged landmark"), "{said:?}");
                    return;
                }
                assert!(t0.elapsed().as_secs() < 10);
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        };
        for frame in 0..260u64 {
            assert!(!live.log.as_mut().unwrap().add(frame, &pose(frame as f64, true), &[], 0));
            if let Some(note) = live.adjust_in_flight() {
                started.push((frame + 1, note));
            }
            // The first is left running past the frames of the next (80): none starts
            // beside it; once it is collected the next starts at once.
            if frame == 100 || (frame > 100 && live.log.as_ref().unwrap().running()) {
                wait(&mut live);
            }
        }
        let at: Vec<u64> = started.iter().map(|(f, _)| *f).collect();
        assert_eq!(at, [40, 102, 204], "{started:?}");
        assert!(started[0].1.contains("40 frames logged; adjusting the map"), "{started:?}");

        let reported = pose(30.0, true);
        assert_eq!(live.biased(&reported).attitude, reported.camera.attitude, "no offset found yet");
        live.bias = Some([1.5, -2.0, 0.5]);
        let turned = chain.angles(&live.biased(&reported).attitude);
        let was = chain.angles(&reported.camera.attitude);
        for (d, want) in
            [(turned.yaw - was.yaw, 1.5), (turned.pitch - was.pitch, -2.0), (turned.roll - was.roll, 0.5)]
        {
            assert!((d.to_degrees() - want).abs() < 1e-9, "{turned:?} vs {was:?}");
        }
        assert_eq!(live.biased(&reported).position, reported.camera.position);
        let fixed = pose(30.0, false);
        assert_eq!(
            live.biased(&fixed).attitude,
            fixed.camera.attitude,
            "the fixed mount's frames as they came"
        );

        // A landing queued behind a running adjustment, then new gimbal offsets: the log
        // starts again without the offset found, and the landing is not left queued.
        live.start_adjustment("asked to");
        assert!(live.log.as_ref().unwrap().running());
        let said = format!("{:?}", live.adjust_map("landed"));
        assert!(said.contains("adjusted again after"), "{said}");
        let mut moved = s.clone();
        moved.gimbal.pitch_offset_deg = 1.0;
        live.apply(&moved);
        assert_eq!((live.log.as_ref().unwrap().frames(), live.bias, live.adjust_again), (0, None, None));
    }

    fn landmark(id: u64) -> LandmarkRecord {
        LandmarkRecord {
            id,
            position: Vec3::new(id as f64, 2.0, 0.0),
            sigma_max_m: 0.5,
            observations: 9,
            first_frame: 1,
            last_frame: 20,
        }
    }

    fn rows(path: &Path) -> usize {
        let text = std::fs::read_to_string(path).unwrap();
        crate::output::parse_landmarks_csv(&text, "landmarks.csv").unwrap().len()
    }

    /// A user's test: after a restart the world seen again was added to the last run's
    /// landmarks (171 became 342). A restart is a new run now, starting empty.
    #[test]
    fn a_restart_is_a_new_run_and_does_not_add_to_the_last_ones_landmarks() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let mut first = area(&link, "r1");
        first.results = (0..171).map(landmark).collect();
        first.write_results().unwrap();
        assert_eq!(rows(&link.join("landmarks.csv")), 171);

        // The daemon restarts and stops before any landmark (on the ground): the last run's
        // map stays current; an empty set made current was what the ground then fetched.
        let mut idle = area(&link, "r2");
        assert!(idle.finish().unwrap().is_empty(), "nothing written");
        assert_eq!(rows(&link.join("landmarks.csv")), 171, "the last run's map stays current");

        // The daemon restarts: a new run. A snapshot asked for writes even an empty set.
        let second = area(&link, "r2");
        assert!(second.all_landmarks().is_empty(), "a new run starts empty");
        second.write_results().unwrap();
        assert_eq!(rows(&link.join("landmarks.csv")), 0, "not 171 again, and never 342");
        let kept = ResultSets::open(&link, "r1").unwrap().current().unwrap();
        assert_eq!(rows(&kept.join("landmarks.csv")), 171, "the last run's results are kept");

        // The pipeline rebuilt after a panic continues its own run, with fresh ids.
        let mut rebuilt = area(&link, "r2");
        rebuilt.results.push(landmark(0));
        rebuilt.write_results().unwrap();
        let again = area(&link, "r2");
        assert_eq!(again.all_landmarks().len(), 1);
        assert_eq!(again.id_offset, 1, "new landmarks do not reuse the resumed ids");
    }

    /// After failed checkpoint writes (a full disk), the first that works says so: the
    /// warnings were the last word in the log and on the ground station before.
    #[test]
    fn a_checkpoint_that_works_after_failed_ones_says_the_results_are_written_again() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let mut live = area(&link, "r1");
        live.results = (0..3).map(landmark).collect();
        let mut report = Report::default();
        live.checkpoint(&mut report);
        assert!(report.warnings.is_empty() && report.events.is_empty(), "{report:?}");
        // The next set's folder cannot be made (a file in its way fails it as a full disk would).
        let blocker = live.sets.run_dir().join("set-2.partial");
        std::fs::write(&blocker, "in the way").unwrap();
        for _ in 0..2 {
            live.checkpoint(&mut report);
        }
        assert_eq!(report.warnings.len(), 2, "{report:?}");
        assert!(report.events.is_empty());
        std::fs::remove_file(&blocker).unwrap();
        let mut report = Report::default();
        live.checkpoint(&mut report);
        assert_eq!(report.events, ["area: results written again, after 2 failed writes"]);
        assert_eq!(rows(&link.join("landmarks.csv")), 3);
        let mut report = Report::default();
        live.checkpoint(&mut report);
        assert!(report.events.is_empty(), "said once: {report:?}");
    }

    /// The bookkeeping both pipelines share (the area's checkpoints above, the indoor
    /// trajectory's appends): said once, with the count, at the first write that works.
    #[test]
    fn the_first_write_after_failed_ones_is_said_once_with_their_count() {
        let mut failing = 0;
        let again = "indoor: trajectory.csv written again";
        assert_eq!(count_write(&mut failing, true, again, "appends"), None);
        for _ in 0..3 {
            assert_eq!(count_write(&mut failing, false, again, "appends"), None);
        }
        assert_eq!(
            count_write(&mut failing, true, again, "appends").as_deref(),
            Some("indoor: trajectory.csv written again, after 3 failed appends")
        );
        assert_eq!(count_write(&mut failing, true, again, "appends"), None, "once");
    }

    #[test]
    fn a_run_set_that_does_not_parse_is_moved_aside_and_the_pipeline_starts() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        sets.write(|d| std::fs::write(d.join("landmarks.csv"), "id,north\n1,x,y\n")).unwrap();
        let live = area(&link, "r1");
        assert!(live.all_landmarks().is_empty());
        let aside: Vec<String> = std::fs::read_dir(sets.run_dir())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("landmarks.csv.corrupt-"))
            .collect();
        assert_eq!(aside.len(), 1, "kept for a person to look at, outside the set");
        live.write_results().unwrap();
        assert_eq!(rows(&link.join("landmarks.csv")), 0);
    }

    #[test]
    fn new_runs_of_one_second_get_distinct_ids() {
        let dir = tempfile::tempdir().unwrap();
        let a = new_run(dir.path());
        std::fs::create_dir_all(dir.path().join("indoor.runs").join(&a)).unwrap();
        let b = new_run(dir.path());
        assert_ne!(a, b);
        assert!(a.ends_with('Z') && a.len() == 16, "{a}");
    }
}
