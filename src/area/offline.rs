//! `mavloc area`: the area pipeline (or the ground-plane baseline) over a recorded dataset,
//! with results written as the run goes.
//!
//! The results (`landmarks.csv`, `.ply`, `area.geojson`, `area.kml`, `border.csv`,
//! `summary.json`, and the reports and plots beside them) belong together, so they are
//! replaced as a set: written into a hidden folder beside `--out` and put in its place in
//! one step when the run ends ([`mavloc_data::staged::StagedDir`]). A run that fails or is
//! killed leaves the previous results whole, with none of its own files among them (each
//! file written atomically was not enough: a run interrupted half way left a new
//! `landmarks.csv` beside the earlier run's `summary.json`, and files only one run wrote,
//! such as `trace.csv`, stayed beside another run's results). The staging folder gets a
//! checkpoint every `CHECKPOINT_FRAMES` frames (`complete: false`): after a crash the next
//! run into the same `--out` keeps it as `NAME.interrupted-PID`. A run stopped on request
//! ([`run_stoppable`], Ctrl-C in `mavloc area`) ends early and puts what it has in place,
//! `complete: false` in `summary.json`; over complete earlier results it puts it beside
//! them instead, as `NAME.stopped`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use opencv::imgcodecs;
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use super::border::{self, BorderParams};
use super::features::prepare;
use super::{baseline, AreaPipeline, FrameInput, StageTiming};
use crate::geometry::LocalFrame;
use crate::output::{self, LandmarkRecord};
use crate::settings::{AreaMethod, Settings};
use mavloc_data::dataset::Dataset;
use mavloc_data::results::border_csv;
use mavloc_data::table::{fixed, Appender, Row};

const CHECKPOINT_FRAMES: u64 = 100;
/// Datasets this short (photo surveys) get the residual report without `--trace`, as does
/// any run that refines its attitudes.
pub const RESIDUAL_MAX_FRAMES: usize = 100;
/// The baseline keeps one border pixel in this many along each contour.
const BASELINE_STEP_PX: usize = 8;

/// What a run did; also written as `summary.json`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RunSummary {
    pub method: String,
    pub frames: u64,
    pub skipped_frames: u64,
    pub elapsed_s: f64,
    pub frames_per_s: f64,
    pub landmarks: usize,
    pub border_lines: usize,
    /// Per frame: reading the files (offline), segmenting and the grey conversion.
    #[serde(default)]
    pub prepare_ms: f64,
    pub band_ms: f64,
    pub sift_ms: f64,
    pub match_estimate_ms: f64,
    pub purge_add_ms: f64,
    /// Median pipeline time of frames 45-54 and 495-504 (does cost grow with flight time?).
    pub frame_ms_at_50: Option<f64>,
    pub frame_ms_at_500: Option<f64>,
    /// The same for the match-and-estimate stage alone, the part that would grow with the
    /// library if descriptors were not capped (SIFT depends on how much band is in view).
    pub match_ms_at_50: Option<f64>,
    pub match_ms_at_500: Option<f64>,
    /// Live runs: the median frame time (ms, preparation included) of each minute.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frame_ms_per_minute: Vec<f64>,
    /// Reprojection residuals of converged landmarks (pixels at full resolution), when
    /// computed (`residuals.csv`): the median and 90th percentile over frames of each
    /// frame's median, weighted by its matches; and frames whose yaw looks off by 180 deg.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_median_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_p90_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub yaw_off_180_frames: Vec<u64>,
    /// Attitude refinement (`area.attitude_prior_deg`): median reprojection error of the
    /// sightings before and after (full-resolution pixels), and the median correction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_median_before_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_median_after_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attitude_correction_median_deg: Option<f64>,
    /// Sightings the refinement left out as false matches (`area::refine`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_left_out: Option<usize>,
    /// Live, the adjustment after the last landing (`daemon::flightlog`): the frames and
    /// landmarks it adjusted and how long it took (seconds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_frames: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_landmarks: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_elapsed_s: Option<f64>,
    /// The static gimbal offset the refinement found beside the per-frame corrections
    /// (yaw, pitch, roll, degrees, to add to `gimbal.*_offset_deg`) and its SD from the
    /// sightings.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_gimbal_offset_deg: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_gimbal_offset_sd_deg: Option<[f64; 3]>,
    /// Why the refinement's solution was not used (`area::refine::Refined::implausible`):
    /// the landmarks are then the filters'.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refined_rejected: Option<String>,
    /// The static gimbal offsets of the configuration (`gimbal.*_offset_deg`: yaw, pitch,
    /// roll, degrees) the run added to every frame's reported angles, so the tagged poses
    /// its corrections apply to can be rebuilt (`mavloc eval area`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gimbal_offsets_deg: Option<[f64; 3]>,
    /// Live: the static gimbal offset the daemon adds to the frames' reported angles since
    /// an adjustment found it (`area.adjust_first_frames`, `daemon::flightlog`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gimbal_offset_applied_deg: Option<[f64; 3]>,
    /// Flight lines (split where the track turns); the pairs of points a converged
    /// landmark gets from two lines' rays alone (one per landmark and pair of lines); the
    /// median distance between them, with the poses the filters ran on (aligned, when the
    /// photos were), with the poses as tagged (only when aligned) and after refinement
    /// (`area::crosslines`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flight_lines: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_pairs: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_median_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_tagged_median_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_refined_median_m: Option<f64>,
    /// Photo alignment by tie points before the filters (`area.align_prior_deg`,
    /// `area::align`): photos aligned, tie points kept, overlapping pairs matched and
    /// linked, the tie points' median reprojection error (full-resolution pixels) with
    /// the tags and aligned, the median correction, and how far apart the tie points seen
    /// from two lines are, triangulated from each line with the tags and aligned.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aligned_photos: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tie_points: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tie_pairs_matched: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tie_pairs_linked: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tie_pairs_dropped: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub align_median_before_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub align_median_after_px: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub align_correction_median_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_tie_pairs: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_tie_median_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cross_line_tie_aligned_median_m: Option<f64>,
    /// When the alignment reached at least half the photos and `area.aligned_*` are set:
    /// the bearing noise (degrees) and the sightings per landmark the filters ran with.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aligned_bearing_noise_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aligned_min_observations: Option<u32>,
    /// Photos left out of the landmark filters with those settings: the alignment did not
    /// reach them.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub unaligned_frames: Vec<u64>,
    /// Why the first skipped frame was skipped (file and reason).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_skip_reason: Option<String>,
    /// The factor the frames were scaled down by (`area.downscale`): `trace.csv`'s pixels
    /// are at that scale.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub downscale: Option<u32>,
    pub complete: bool,
    /// The dataset's telemetry file's CRC-32 (hex): `mavloc eval` refuses to measure the
    /// result against another dataset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset_crc32: Option<String>,
    /// Where the results were put: `--out`, or beside it (`NAME.stopped`) for a run
    /// stopped part way over complete earlier results.
    #[serde(skip)]
    pub written_to: PathBuf,
}

/// Options of a run.
#[derive(Clone, Debug)]
pub struct RunOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    pub method: AreaMethod,
    pub trace: bool,
    /// Stop after this many frames.
    pub max_frames: Option<usize>,
    /// Write contact sheets of every frame beside its target mask: `masks.png`, or
    /// `masks-01.png`, ... 12 frames to a page.
    pub debug_masks: bool,
}

/// Writes the result files of a run (each atomically), `summary.json` last; returns the
/// border lines it fitted. `out` is the run's staging folder ([`run`]) or the daemon's.
pub fn write_results(
    out: &Path,
    frame: &LocalFrame,
    name: &str,
    landmarks: &[LandmarkRecord],
    summary: &mut RunSummary,
) -> std::io::Result<Vec<Vec<crate::geometry::Vec3>>> {
    let points: Vec<_> = landmarks.iter().map(|l| l.position).collect();
    let borders = border::fit(&points, &BorderParams::default());
    summary.landmarks = landmarks.len();
    summary.border_lines = borders.len();
    output::write_atomic(&out.join("landmarks.csv"), output::landmarks_csv(landmarks).as_bytes())?;
    output::write_atomic(&out.join("landmarks.ply"), output::landmarks_ply(frame, landmarks).as_bytes())?;
    output::write_atomic(
        &out.join("area.geojson"),
        output::area_geojson(frame, landmarks, &borders).as_bytes(),
    )?;
    output::write_atomic(
        &out.join("area.kml"),
        output::area_kml(frame, name, landmarks, &borders).as_bytes(),
    )?;
    output::write_atomic(&out.join("border.csv"), border_csv(&borders).as_bytes())?;
    let json = serde_json::to_string_pretty(summary).expect("summary serialises");
    output::write_atomic(&out.join("summary.json"), json.as_bytes())?;
    Ok(borders)
}

/// One row of `trace.csv`: a landmark update (seed fig. 6.2): the sighting, measured and
/// predicted bearing, gate distance and verdict, and the estimate after the update; or a
/// landmark's first sighting, with no prediction or gate distance and its initial estimate
/// (so every ray a landmark was built from is in the file).
#[derive(Serialize, Deserialize)]
struct TraceRow {
    frame: u64,
    landmark: u64,
    #[serde(serialize_with = "fixed::dp3")]
    u: f64,
    #[serde(serialize_with = "fixed::dp3")]
    v: f64,
    #[serde(serialize_with = "fixed::dp6")]
    meas_yaw: f64,
    #[serde(serialize_with = "fixed::dp6")]
    meas_pitch: f64,
    /// Empty on the row of a landmark's first sighting, which created it.
    #[serde(serialize_with = "fixed::opt_dp6")]
    pred_yaw: Option<f64>,
    #[serde(serialize_with = "fixed::opt_dp6")]
    pred_pitch: Option<f64>,
    #[serde(serialize_with = "fixed::opt_dp4")]
    mahalanobis: Option<f64>,
    #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01")]
    accepted: bool,
    #[serde(serialize_with = "fixed::dp4")]
    north: f64,
    #[serde(serialize_with = "fixed::dp4")]
    east: f64,
    #[serde(serialize_with = "fixed::dp4")]
    down: f64,
    /// Upper triangle of the covariance: nn, ne, nd, ee, ed, dd.
    #[serde(serialize_with = "fixed::dp5")]
    p_nn: f64,
    #[serde(serialize_with = "fixed::dp5")]
    p_ne: f64,
    #[serde(serialize_with = "fixed::dp5")]
    p_nd: f64,
    #[serde(serialize_with = "fixed::dp5")]
    p_ee: f64,
    #[serde(serialize_with = "fixed::dp5")]
    p_ed: f64,
    #[serde(serialize_with = "fixed::dp5")]
    p_dd: f64,
}

impl Row for TraceRow {
    const COLUMNS: &'static str =
        "frame,landmark,u,v,meas_yaw,meas_pitch,pred_yaw,pred_pitch,mahalanobis,accepted,\
                                   north,east,down,p_nn,p_ne,p_nd,p_ee,p_ed,p_dd";
}

/// The sightings a run's `trace.csv` holds: frame, landmark, pixel (at the run's scale,
/// `RunSummary::downscale`), and whether the update was accepted.
pub fn read_trace_sightings(path: &Path) -> Result<Vec<(u64, u64, crate::geometry::Pixel, bool)>, String> {
    let rows = mavloc_data::table::read::<TraceRow>(path).map_err(|e| e.to_string())?;
    Ok(rows
        .iter()
        .map(|r| (r.frame, r.landmark, crate::geometry::Pixel::new(r.u, r.v), r.accepted))
        .collect())
}

impl From<&super::library::TraceEntry> for TraceRow {
    fn from(t: &super::library::TraceEntry) -> TraceRow {
        let c = t.covariance;
        TraceRow {
            frame: t.frame,
            landmark: t.landmark,
            u: t.pixel.u,
            v: t.pixel.v,
            meas_yaw: t.measurement[0],
            meas_pitch: t.measurement[1],
            pred_yaw: t.prediction.map(|p| p[0]),
            pred_pitch: t.prediction.map(|p| p[1]),
            mahalanobis: t.mahalanobis,
            accepted: t.accepted,
            north: t.mean[0],
            east: t.mean[1],
            down: t.mean[2],
            p_nn: c[0],
            p_ne: c[1],
            p_nd: c[2],
            p_ee: c[3],
            p_ed: c[4],
            p_dd: c[5],
        }
    }
}

/// Photo surveys are aligned up to this many photos (every overlapping pair is matched).
pub const ALIGN_MAX_FRAMES: usize = 500;
/// SD of the attitude of a photo aligned by its tie points, as the refinement after the
/// landmark filters takes it (degrees): the alignment leaves its tie points 0.3 px off
/// (median, Seneca's photos matched at 1600 px), hundreds to thousands per photo, so its
/// attitude is known to a few hundredths of a degree; 0.05 deg is a pixel at 1250 px
/// focal length.
const ALIGNED_PRIOR_DEG: f64 = 0.05;

/// A row of `alignment.csv`: a photo's correction ([`super::align::Correction`]), its
/// rotation vector in degrees about local north, east and down.
#[derive(Serialize, Deserialize)]
pub struct AlignmentRow {
    pub frame: u64,
    pub tie_sightings: usize,
    #[serde(serialize_with = "fixed::dp4")]
    pub correction_deg: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub about_north_deg: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub about_east_deg: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub about_down_deg: f64,
    #[serde(serialize_with = "fixed::dp3")]
    pub shift_north_m: f64,
    #[serde(serialize_with = "fixed::dp3")]
    pub shift_east_m: f64,
    #[serde(serialize_with = "fixed::dp3")]
    pub shift_down_m: f64,
}

impl Row for AlignmentRow {
    const COLUMNS: &'static str = "frame,tie_sightings,correction_deg,about_north_deg,about_east_deg,about_down_deg,shift_north_m,shift_east_m,shift_down_m";
}

/// Aligns the dataset's photos by their tie points (`area::align`), fills the summary's
/// alignment fields and writes `alignment.csv`; returns the rotation correction of each
/// frame the tie points reached. Empty when no two photos share a tie point.
fn align_photos(
    ds: &Dataset,
    s: &Settings,
    records: &[mavloc_data::dataset::TelemetryRecord],
    out: &Path,
    summary: &mut RunSummary,
) -> anyhow::Result<std::collections::BTreeMap<u64, super::align::Correction>> {
    use super::align;
    use std::collections::BTreeMap;
    let k = ds.camera.intrinsics();
    let t0 = Instant::now();
    // Photos in parallel (decoding and SIFT are single-threaded; Seneca's 27 photos took
    // 9.1 s one after another on this 2-core machine).
    use rayon::prelude::*;
    let read: Vec<Option<align::Photo>> = records
        .par_iter()
        .map(|r| -> opencv::Result<Option<align::Photo>> {
            // A frame that cannot be read is reported by the run itself.
            let Ok(img) = crate::imaging::read_image(&ds.frame_path(r), imgcodecs::IMREAD_COLOR) else {
                return Ok(None);
            };
            if (img.cols(), img.rows()) != (k.width as i32, k.height as i32) {
                return Ok(None);
            }
            let features = super::imageup::features_sized(&img, align::FEATURES, align::WORK_WIDTH)?;
            let pose = ds.camera_pose(&r.measured, s.gimbal.offsets_deg());
            Ok(Some(align::Photo { frame: r.frame, features, pose }))
        })
        .collect::<opencv::Result<_>>()?;
    let photos: Vec<align::Photo> = read.into_iter().flatten().collect();
    let t_features = t0.elapsed().as_secs_f64();
    let (pairs, tried) = align::match_pairs(&photos, &k, s.area.ground_down_m, s.area.align_prior_deg)?;
    let t_matching = t0.elapsed().as_secs_f64() - t_features;
    summary.tie_pairs_matched = Some(tried);
    let tagged: BTreeMap<u64, crate::geometry::CameraPose> =
        photos.iter().map(|p| (p.frame, p.pose)).collect();
    let Some(a) =
        align::align(&photos, pairs, &k, s.area.ground_down_m, s.area.align_prior_deg, s.area.align_shift_m)
    else {
        tracing::warn!("photo alignment: no two photos share a tie point; the tags are used as they are");
        summary.tie_points = Some(0);
        return Ok(BTreeMap::new());
    };
    let mut per_frame: BTreeMap<u64, usize> = BTreeMap::new();
    for s in &a.ties.sightings {
        *per_frame.entry(s.0).or_default() += 1;
    }
    summary.aligned_photos = Some(per_frame.len());
    summary.tie_pairs_linked = Some(a.ties.pairs_linked);
    summary.tie_pairs_dropped = Some(a.dropped_pairs);
    summary.tie_points = Some(a.ties.points.len());
    summary.align_median_before_px = Some(a.median_before_px);
    summary.align_median_after_px = Some(a.median_after_px);
    let mut angles: Vec<f64> = a
        .corrections
        .iter()
        .filter(|(f, _)| per_frame.contains_key(f))
        .map(|(_, c)| c.rotation.norm().to_degrees())
        .collect();
    if !angles.is_empty() {
        summary.align_correction_median_deg = Some(super::residuals::quantile(&mut angles, 0.5));
    }
    // Do the lines agree on the tie points, as tagged and aligned?
    let lines = super::crosslines::flight_lines(&tagged.iter().map(|(f, p)| (*f, p.position)).collect());
    if lines.values().max().is_some_and(|&m| m >= 1) {
        let at: BTreeMap<u64, crate::geometry::Vec3> =
            a.ties.points.iter().map(|l| (l.id, l.position)).collect();
        let aligned: BTreeMap<u64, crate::geometry::CameraPose> =
            tagged.iter().map(|(f, p)| (*f, a.corrections[f].apply(p))).collect();
        let sd = s.area.bearing_noise_deg.to_radians();
        let median = |poses: &BTreeMap<u64, crate::geometry::CameraPose>| {
            let mut d = super::crosslines::disagreement(&a.ties.sightings, poses, &k, &lines, &at, sd);
            (d.len(), (!d.is_empty()).then(|| super::residuals::quantile(&mut d, 0.5)))
        };
        let (n, before) = median(&tagged);
        summary.cross_line_tie_pairs = Some(n);
        summary.cross_line_tie_median_m = before;
        summary.cross_line_tie_aligned_median_m = median(&aligned).1;
    }
    let rows: Vec<AlignmentRow> = a
        .corrections
        .iter()
        .map(|(f, c)| {
            let g = c.rotation.map(f64::to_degrees);
            AlignmentRow {
                frame: *f,
                tie_sightings: per_frame.get(f).copied().unwrap_or(0),
                correction_deg: g.norm(),
                about_north_deg: g.x,
                about_east_deg: g.y,
                about_down_deg: g.z,
                shift_north_m: c.shift.x,
                shift_east_m: c.shift.y,
                shift_down_m: c.shift.z,
            }
        })
        .collect();
    output::write_atomic(&out.join("alignment.csv"), mavloc_data::table::to_string(&rows).as_bytes())?;
    tracing::info!(
        photos = per_frame.len(),
        tie_points = a.ties.points.len(),
        // Rounded: the full digits of a median or a timing say nothing a reader uses.
        before_px = %format_args!("{:.1}", a.median_before_px),
        after_px = %format_args!("{:.2}", a.median_after_px),
        dropped = a.dropped,
        dropped_pairs = a.dropped_pairs,
        features_s = %format_args!("{t_features:.1}"),
        matching_s = %format_args!("{t_matching:.1}"),
        adjusting_s = %format_args!("{:.1}", t0.elapsed().as_secs_f64() - t_features - t_matching),
        "photos aligned by their tie points"
    );
    // Only the photos the tie points reached: the others keep their tags (and the
    // refinement's prior for tags).
    Ok(a.corrections.into_iter().filter(|(f, _)| per_frame.contains_key(f)).collect())
}

/// Runs the configured method over a dataset. `progress(done, total)` after each frame.
pub fn run(opts: &RunOptions, s: &Settings, progress: impl FnMut(u64, u64)) -> anyhow::Result<RunSummary> {
    Ok(run_observed(opts, s, progress, false, None)?.0)
}

/// [`run`], ending after the frame in hand once `stop` is set: the results of the frames
/// before are put in place as a set, `complete: false` in their summary.
pub fn run_stoppable(
    opts: &RunOptions,
    s: &Settings,
    progress: impl FnMut(u64, u64),
    stop: &AtomicBool,
) -> anyhow::Result<RunSummary> {
    Ok(run_observed(opts, s, progress, false, Some(stop))?.0)
}

/// What a run saw, for estimating things that hold for the whole flight (the gimbal's
/// static offset, `mavloc calibrate gimbal`): every sighting of a converged landmark at
/// the pipeline's resolution, the landmarks, and that resolution.
#[derive(Clone, Debug, Default)]
pub struct Observations {
    pub sightings: Vec<(u64, u64, crate::geometry::Pixel)>,
    pub landmarks: Vec<LandmarkRecord>,
    pub k: Option<crate::geometry::Intrinsics>,
    pub downscale: u32,
}

/// [`run`], also returning the observations when `observe` (the sightings are then kept
/// for any number of frames).
pub fn run_observed(
    opts: &RunOptions,
    s: &Settings,
    mut progress: impl FnMut(u64, u64),
    observe: bool,
    stop: Option<&AtomicBool>,
) -> anyhow::Result<(RunSummary, Observations)> {
    let ds = Dataset::open(&opts.dataset).map_err(|e| anyhow::anyhow!(e))?;
    if let Some(line) = ds.torn_line {
        tracing::warn!(
            "{}: line {line} is torn (a recording cut off as it wrote it): the {} frames before it are the dataset",
            opts.dataset.join(mavloc_data::dataset::TELEMETRY_FILE).display(),
            ds.records.len()
        );
    }
    // Whether --out holds a complete earlier set, which a stopped run must not replace.
    let earlier_complete = std::fs::read_to_string(opts.out.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .is_some_and(|v| v["complete"] == true);
    let staged = mavloc_data::staged::begin_results(&opts.out).map_err(|e| anyhow::anyhow!(e))?;
    let out = staged.path().to_path_buf();
    let k_full = ds.camera.intrinsics();
    let downscale = s.area.downscale.max(1);
    let k = k_full.downscaled(downscale);
    let frame = LocalFrame::new(ds.camera.origin);
    let name = format!("mavloc area: {}", opts.dataset.display());
    let method = match opts.method {
        AreaMethod::Ukf => "ukf",
        AreaMethod::GroundPlane => "ground-plane",
    };
    // The refinement needs every sighting too: without them `area.attitude_prior_deg` on a
    // video longer than RESIDUAL_MAX_FRAMES was ignored unless `--trace` was given.
    let refine = s.area.attitude_prior_deg > 0.0;
    let residuals = observe || opts.trace || refine || ds.records.len() <= RESIDUAL_MAX_FRAMES;
    let mut seen: Vec<(u64, u64, crate::geometry::Pixel)> = Vec::new();
    // The subset the landmark filters accepted (the cross-line measure triangulates each
    // landmark from what it was built of, not from matches its gate refused).
    let mut accepted: Vec<(u64, u64, crate::geometry::Pixel)> = Vec::new();
    let mut poses = std::collections::BTreeMap::new();
    let mut measured = std::collections::BTreeMap::new();
    let mut pipeline = match opts.method {
        AreaMethod::Ukf => Some(AreaPipeline::new(&s.area, k)?.with_trace(residuals)),
        AreaMethod::GroundPlane => None,
    };
    // Appended and flushed every frame: after a crash the staging folder (removed by the
    // next run into the same --out) holds the trace up to the last frame.
    let mut trace_file =
        if opts.trace { Some(Appender::<TraceRow>::create(&out.join("trace.csv"))?) } else { None };

    let total = opts.max_frames.unwrap_or(usize::MAX).min(ds.records.len()) as u64;
    let mut results: Vec<LandmarkRecord> = Vec::new();
    let mut stopped = false;
    let mut summary = RunSummary {
        method: method.into(),
        dataset_crc32: mavloc_data::dataset::telemetry_crc32(&ds.dir),
        downscale: Some(s.area.downscale.max(1)),
        gimbal_offsets_deg: Some(s.gimbal.offsets_deg()),
        ..RunSummary::default()
    };
    let mut timing = StageTiming::default();
    let mut frame_ms = Vec::new();
    let mut match_ms = Vec::new();
    // Every frame on the contact sheets, as tiles.
    let mut sheet = Vec::new();
    let start = Instant::now();
    let aligning = s.area.align_prior_deg > 0.0 && pipeline.is_some();
    let alignment = if aligning && (total as usize) <= ALIGN_MAX_FRAMES {
        align_photos(&ds, s, &ds.records[..total as usize], &out, &mut summary)?
    } else {
        if aligning {
            tracing::warn!("photo alignment is for surveys of up to {ALIGN_MAX_FRAMES} photos; not aligned");
        }
        std::collections::BTreeMap::new()
    };
    let aligned = |f: u64, pose: crate::geometry::CameraPose| match alignment.get(&f) {
        Some(c) => c.apply(&pose),
        None => pose,
    };
    // Poses that fit thousands of tie points are not the tags: once the photos are
    // aligned, the filters may take each sighting for what SIFT measures and a landmark
    // from two photos (the alignment has checked those photos' poses against each other;
    // a single tag cannot be). A photo the alignment did not reach keeps its tag's error:
    // when at least half the photos are reached, the others are left out of the filters
    // (one photo over open water with no tie point should not cost the whole survey its
    // landmarks); when fewer are, the filters keep the tags' settings for the whole run.
    let tuning = s.area.aligned_bearing_noise_deg > 0.0 || s.area.aligned_min_observations > 0;
    let reached = summary.aligned_photos.unwrap_or(0) as u64;
    let mut left_out = std::collections::BTreeSet::new();
    let tuned;
    let s = if tuning && reached >= 2 && 2 * reached >= total {
        left_out.extend(
            ds.records.iter().take(total as usize).map(|r| r.frame).filter(|f| !alignment.contains_key(f)),
        );
        let mut t = s.clone();
        if s.area.aligned_bearing_noise_deg > 0.0 {
            t.area.bearing_noise_deg = s.area.aligned_bearing_noise_deg;
        }
        if s.area.aligned_min_observations > 0 {
            t.area.min_observations = s.area.aligned_min_observations;
        }
        summary.aligned_bearing_noise_deg = Some(t.area.bearing_noise_deg);
        summary.aligned_min_observations = Some(t.area.min_observations);
        if let Some(p) = pipeline.as_mut() {
            p.reconfigure(&t.area, k)?;
        }
        tuned = t;
        &tuned
    } else {
        if tuning && summary.aligned_photos.is_some() {
            tracing::warn!(
                "photo alignment reached {reached} of {total} photos, fewer than half: the landmark filters keep the tags' bearing noise and sightings"
            );
        }
        s
    };
    // `segmenter = "learned"`: trained on the masks the user made for some frames (those
    // frames keep their own masks).
    let learned = match s.area.segmenter {
        crate::settings::Segmenter::Learned => {
            // One frame at a time; a masked frame that cannot be read is left out (the run
            // names it when it reaches it).
            let (mut counts, mut examples) = (super::segment::LearnedCounts::default(), 0);
            for r in ds.records.iter().take(total as usize) {
                let (fp, mp) = (ds.frame_path(r), ds.mask_path(r));
                if !mp.exists() {
                    continue;
                }
                let read = crate::imaging::read_image(&fp, imgcodecs::IMREAD_COLOR)
                    .and_then(|f| Ok((f, crate::imaging::read_image(&mp, imgcodecs::IMREAD_GRAYSCALE)?)));
                match read {
                    Ok((frame, mask)) => {
                        counts.add(&frame, &mask)?;
                        examples += 1;
                    }
                    Err(e) => tracing::warn!("not learned from: {e}"),
                }
            }
            let trained = counts.model().ok_or_else(|| {
                anyhow::anyhow!(
                    "area.segmenter = \"learned\" learns from masks you make for a few frames: put them in {} \
                     (8-bit PNG named as the frame, white on the target, black elsewhere, with some of each); \
                     {} found",
                    ds.dir.join("masks").display(),
                    if examples == 0 { "none".to_string() } else { format!("{examples} with only one class") }
                )
            })?;
            tracing::info!(frames = examples, "segmenter learned from the dataset's masks");
            Some(trained)
        }
        _ => None,
    };
    let mut preparing = std::time::Duration::ZERO;
    for (i, record) in ds.records.iter().take(total as usize).enumerate() {
        // Before the frame, so a stretch of skipped frames does not hide the request.
        if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
            stopped = true;
            break;
        }
        let t_read = Instant::now();
        let frame_path = ds.frame_path(record);
        let mask_path = ds.mask_path(record);
        // The frame and its mask, or why this frame cannot be used (naming the file).
        let loaded = crate::imaging::read_image(&frame_path, imgcodecs::IMREAD_COLOR).and_then(|img| {
            if (img.cols(), img.rows()) != (k_full.width as i32, k_full.height as i32) {
                return Err(format!(
                    "{}: {}x{} px, but the dataset's camera is {}x{}",
                    frame_path.display(),
                    img.cols(),
                    img.rows(),
                    k_full.width,
                    k_full.height
                ));
            }
            let mask = match (super::segment::segment(&img, &s.area).map_err(|e| e.to_string())?, &learned) {
                (Some(m), _) => m,
                (None, Some(l)) if !mask_path.exists() => l.segment(&img).map_err(|e| e.to_string())?,
                (None, _) => crate::imaging::read_image(&mask_path, imgcodecs::IMREAD_GRAYSCALE)
                    .map_err(|e| format!("its mask {e}"))?,
            };
            if (mask.cols(), mask.rows()) != (img.cols(), img.rows()) {
                return Err(format!("{}: the mask's size differs from the frame's", mask_path.display()));
            }
            Ok((img, mask))
        });
        let (img, mask) = match loaded {
            Ok(v) => v,
            Err(why) => {
                tracing::warn!(frame = record.frame, "frame skipped: {why}");
                summary.skipped_frames += 1;
                summary.first_skip_reason.get_or_insert(why);
                progress(i as u64 + 1, total);
                continue;
            }
        };
        if opts.debug_masks {
            sheet.push(super::segment::SheetRow::new(record.frame, &img, &mask)?);
        }
        let (grey, small_mask) = prepare(&img, &mask, downscale)?;
        preparing += t_read.elapsed();
        let pose = aligned(record.frame, ds.camera_pose(&record.measured, s.gimbal.offsets_deg()));
        if pipeline.is_some() && left_out.contains(&record.frame) {
            tracing::warn!(
                frame = record.frame,
                "left out of the landmark filters: no tie point links it to the other photos, so its pose is the tag's ({})",
                frame_path.display()
            );
            summary.unaligned_frames.push(record.frame);
            progress(i as u64 + 1, total);
            continue;
        }
        match pipeline.as_mut() {
            Some(p) => {
                let t = Instant::now();
                let report =
                    p.process(&FrameInput { index: record.frame, grey: &grey, mask: &small_mask, pose })?;
                frame_ms.push(t.elapsed().as_secs_f64() * 1000.0);
                match_ms.push(report.timing.match_estimate.as_secs_f64() * 1000.0);
                timing += report.timing;
                tracing::debug!(
                    frame = record.frame,
                    features = report.features,
                    matched = report.stats.matched,
                    gated = report.stats.gated,
                    conflicts = report.stats.conflicts,
                    added = report.added,
                    purged = report.purged,
                    converged = report.converged.len(),
                    tracked = report.landmarks,
                    "frame processed"
                );
                results.extend(report.converged);
                if residuals {
                    poses.insert(record.frame, pose);
                    measured.insert(record.frame, record.measured);
                    seen.extend(report.sightings.iter().map(|&(id, px)| (record.frame, id, px)));
                    accepted.extend(report.accepted_sightings.iter().map(|&(id, px)| (record.frame, id, px)));
                }
                if let Some(f) = trace_file.as_mut() {
                    f.extend(&report.trace.iter().map(TraceRow::from).collect::<Vec<_>>())?;
                }
            }
            None => {
                let pts =
                    baseline::border_points(&small_mask, &pose, &k, s.area.ground_down_m, BASELINE_STEP_PX)?;
                for p in pts {
                    let id = results.len() as u64;
                    results.push(LandmarkRecord {
                        id,
                        position: p,
                        sigma_max_m: f64::NAN,
                        observations: 1,
                        first_frame: record.frame,
                        last_frame: record.frame,
                    });
                }
            }
        }
        summary.frames += 1;
        // Checkpoints in the staging folder: a long run killed near its end leaves them,
        // and the next run into --out keeps them as `NAME.interrupted-PID`.
        if summary.frames.is_multiple_of(CHECKPOINT_FRAMES) {
            summary.elapsed_s = start.elapsed().as_secs_f64();
            summary.frames_per_s = summary.frames as f64 / summary.elapsed_s;
            write_results(&out, &frame, &name, &results, &mut summary)?;
        }
        progress(i as u64 + 1, total);
    }
    if let Some(p) = pipeline.as_ref() {
        results.extend(p.converged_now());
    }
    summary.elapsed_s = start.elapsed().as_secs_f64();
    summary.frames_per_s =
        if summary.elapsed_s > 0.0 { summary.frames as f64 / summary.elapsed_s } else { 0.0 };
    let per_frame = |d: std::time::Duration| d.as_secs_f64() * 1000.0 / summary.frames.max(1) as f64;
    summary.prepare_ms = per_frame(preparing);
    summary.band_ms = per_frame(timing.band);
    summary.sift_ms = per_frame(timing.sift);
    summary.match_estimate_ms = per_frame(timing.match_estimate);
    summary.purge_add_ms = per_frame(timing.purge_add);
    let window = |v: &[f64], from: usize| -> Option<f64> {
        let mut w: Vec<f64> = v.get(from..from + 10)?.to_vec();
        w.sort_by(f64::total_cmp);
        Some(w[w.len() / 2])
    };
    summary.frame_ms_at_50 = window(&frame_ms, 45);
    summary.frame_ms_at_500 = window(&frame_ms, 495);
    summary.match_ms_at_50 = window(&match_ms, 45);
    summary.match_ms_at_500 = window(&match_ms, 495);
    let mut marks = std::collections::BTreeMap::new();
    if residuals && pipeline.is_some() {
        let rows = super::residuals::per_frame(&seen, &results, &poses, &k, downscale as f64);
        marks = super::residuals::marks(&seen, &results, &poses, &k, downscale as f64);
        let mut all: Vec<f64> = Vec::new();
        for r in &rows {
            all.extend(std::iter::repeat_n(r.median_px, r.landmarks.max(1)));
        }
        if !all.is_empty() {
            summary.residual_median_px = Some(super::residuals::quantile(&mut all, 0.5));
            summary.residual_p90_px = Some(super::residuals::quantile(&mut all, 0.9));
        }
        summary.yaw_off_180_frames = rows.iter().filter(|r| r.yaw_off_180).map(|r| r.frame).collect();
        output::write_atomic(&out.join("residuals.csv"), super::residuals::csv(&rows).as_bytes())?;
        // Cross-line agreement with the recorded poses (and below, refined).
        // Lines from the recorded positions: the aligned ones move by metres, enough to
        // split a line where the recorded track runs straight.
        let recorded = |f: &u64| ds.camera_pose(&measured[f], s.gimbal.offsets_deg()).position;
        let lines = super::crosslines::flight_lines(&poses.keys().map(|f| (*f, recorded(f))).collect());
        let line_count = lines.values().max().map_or(0, |m| m + 1);
        let surveyed_in_lines = line_count >= 2;
        let sd_rad = s.area.bearing_noise_deg.to_radians();
        let cross = |poses: &std::collections::BTreeMap<u64, crate::geometry::CameraPose>,
                     landmarks: &[mavloc_data::results::LandmarkRecord]| {
            let at = landmarks.iter().map(|l| (l.id, l.position)).collect();
            let mut d = super::crosslines::disagreement(&accepted, poses, &k, &lines, &at, sd_rad);
            (d.len(), (!d.is_empty()).then(|| super::residuals::quantile(&mut d, 0.5)))
        };
        if surveyed_in_lines {
            let (n, median) = cross(&poses, &results);
            summary.flight_lines = Some(line_count);
            summary.cross_line_pairs = Some(n);
            summary.cross_line_median_m = median;
            if !alignment.is_empty() {
                // The same sightings with the poses as tagged: what the alignment fixed.
                let tagged = poses
                    .keys()
                    .map(|f| (*f, ds.camera_pose(&measured[f], s.gimbal.offsets_deg())))
                    .collect();
                summary.cross_line_tagged_median_m = cross(&tagged, &results).1;
            }
        }
        if refine && !results.is_empty() {
            // Attitude refinement (area::refine): landmarks, per-frame attitude
            // corrections and the gimbal's static offset together, from every sighting of
            // the converged landmarks.
            let base = s.gimbal.offsets_deg();
            let pose = |f: u64, o: &crate::geometry::Vec3| {
                aligned(f, ds.camera_pose(&measured[&f], [base[0] + o.x, base[1] + o.y, base[2] + o.z]))
            };
            let frames: Vec<u64> = poses.keys().copied().collect();
            let params = super::refine::RefineParams {
                // A sighting is as good as the bearing noise the filters assume.
                pixel_sd: (s.area.bearing_noise_deg.to_radians() * k.fx).max(0.5),
                ..super::refine::RefineParams::new(s.area.attitude_prior_deg)
            };
            // Photos aligned by their tie points have each had their own rotation found
            // already, a shared offset with it: no static offset is left to tell apart
            // (and for a nadir camera its yaw and roll are one rotation). Their rotations
            // rest on thousands of tie points: the landmarks' few sightings may refine
            // them by hundredths of a degree, not turn them (with the tags' 2 deg prior,
            // Seneca's aligned photos turned by 0.66 deg, their sightings reprojected
            // worse, 1.8 -> 2.4 px, and two lines' landmarks went from 0.19 to 0.33 m
            // apart: a few false sightings pulling them).
            let r = if alignment.is_empty() {
                super::refine::refine_with_offset(&seen, &results, &frames, &pose, &k, &params)
            } else {
                let priors = alignment.keys().map(|f| (*f, ALIGNED_PRIOR_DEG.to_radians())).collect();
                super::refine::refine_with_priors(&seen, &results, &poses, &k, &params, &priors)
            };
            let scale = downscale as f64;
            // Only the unaligned photos' and frames' corrections are held to the prior this
            // way; aligned photos' rest on their tie points.
            let rejected = if alignment.is_empty() { r.implausible(s.area.attitude_prior_deg) } else { None };
            if let Some(why) = rejected {
                tracing::warn!("attitude refinement not used: {why}; the filters' landmarks are the results");
                summary.refined_rejected = Some(why);
            } else {
                summary.refined_median_before_px = Some(r.median_before_px * scale);
                summary.refined_median_after_px = Some(r.median_after_px * scale);
                summary.refined_left_out = Some(r.left_out);
                if let Some((o, sd)) = r.offset_deg {
                    summary.refined_gimbal_offset_deg = Some(o);
                    summary.refined_gimbal_offset_sd_deg = Some(sd);
                }
                summary.attitude_correction_median_deg = r.median_correction_deg();
                let mut csv =
                    String::from("frame,correction_deg,about_north_deg,about_east_deg,about_down_deg\n");
                for (f, d) in &r.corrections {
                    let g = d.map(f64::to_degrees);
                    csv.push_str(&format!("{f},{:.4},{:.4},{:.4},{:.4}\n", g.norm(), g.x, g.y, g.z));
                }
                output::write_atomic(&out.join("attitude.csv"), csv.as_bytes())?;
                results = r.landmarks;
                let refined: std::collections::BTreeMap<u64, crate::geometry::CameraPose> = frames
                    .iter()
                    .map(|&f| {
                        let o = r.offset_deg.map_or(crate::geometry::Vec3::zeros(), |(o, _)| o.into());
                        (f, super::refine::corrected(&pose(f, &o), &r.corrections[&f]))
                    })
                    .collect();
                if surveyed_in_lines {
                    summary.cross_line_refined_median_m = cross(&refined, &results).1;
                }
                marks = super::residuals::marks(&seen, &results, &refined, &k, scale);
            }
        }
    }
    summary.complete = !stopped;
    let borders = write_results(&out, &frame, &name, &results, &mut summary)?;
    if !results.is_empty() {
        // Top and side view of what was found (`mavloc eval area` redraws it over the
        // ground truth when there is one). A figure is a convenience: failing to draw one
        // is reported, not fatal, since the results are already written.
        let points: Vec<_> = results.iter().map(|l| l.position).collect();
        let title = format!("{} landmarks, local NED around the dataset origin", points.len());
        if let Err(e) = output::plot::landmark_views(&out.join("views.png"), &points, &[], &borders, &title) {
            tracing::warn!("views.png not drawn: {e}");
        }
    }
    if opts.debug_masks {
        super::segment::contact_sheets(&out, &sheet, &marks)?;
    }
    // A run that could use no frame has nothing to stand for: the earlier results stay.
    // A run stopped part way does not replace complete earlier results either: what it
    // made goes beside them.
    summary.written_to = opts.out.clone();
    if summary.frames > 0 {
        if stopped && earlier_complete {
            summary.written_to = staged.commit_beside("stopped").map_err(|e| anyhow::anyhow!(e))?;
        } else {
            staged.commit().map_err(|e| anyhow::anyhow!(e))?;
        }
    }
    let observations = if observe {
        Observations { sightings: seen, landmarks: results, k: Some(k), downscale }
    } else {
        Observations::default()
    };
    Ok((summary, observations))
}
