//! `mavloc indoor train` and `mavloc indoor run` over datasets (indoor seed sec. 3.3).
//!
//! Training: frames are prepared (downscaled, derotated), a texton dictionary is learned
//! from random patches, every frame gets a full-sampling histogram, and the per-rank
//! measurement covariances `Sigma[j] = E[(T - P_j)(T - P_j)^T]` are fitted by leave-one-out:
//! each training frame is queried, with a random-sampling histogram as in flight, against
//! all the others. The seed fitted `Var(T - P_j)` on a recorded flight; the second moment
//! about zero is used because the mixture is centred on the neighbour, so a bias belongs
//! in the spread.
//!
//! Running: each frame of a flight goes through the [`Localizer`]; `trajectory.csv` and
//! `summary.json` are written into a folder beside `--out` and put in its place whole at
//! the end (`mavloc_data::staged::begin_results`): a run that fails or is killed leaves the
//! earlier results as they were, and its checkpoints (every `CHECKPOINT_FRAMES` frames) are
//! kept by the next run as `NAME.interrupted-PID`. A run stopped on request
//! ([`run_stoppable`], Ctrl-C in `mavloc indoor run`) puts the frames so far in place, or
//! beside complete earlier results as `NAME.stopped`.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use nalgebra::{Matrix2, Vector2};
use opencv::imgcodecs;
use rand::SeedableRng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::derotate::{Canvas, Preprocessor};
use super::knn::Knn;
use super::localizer::{Localizer, LocalizerParams};
use super::model::{from_matrix, FrameParams, Model, TrainingInfo, MODEL_FORMAT, MODEL_VERSION};
use super::textons::{Dictionary, Learning};
use crate::geometry::Intrinsics;
use crate::settings::{DictionaryMethod, Indoor};
use mavloc_data::dataset::{Dataset, TelemetryRecord};
use mavloc_data::results::{trajectory_csv, TrajectoryRow};

/// Frames prepared at once (bounds memory for large training sets).
const BATCH: usize = 128;
/// Images the dictionary learns from, spread over the dataset, and patches from each.
const DICTIONARY_IMAGES: usize = 200;
const PATCHES_PER_IMAGE: usize = 300;
/// k-means iterations when `indoor.dictionary = "k-means"`.
const KMEANS_ITERATIONS: u32 = 15;
/// Process noise per frame when it can be neither configured nor fitted, metres.
const FALLBACK_PROCESS_SD_M: f64 = 0.05;

/// A training frame: dataset index, full-sampling and random-sampling histograms.
type Row = (usize, Vec<f32>, Vec<f32>);
/// The same with its (x, y) label.
type Labelled = (usize, Vec<f32>, Vec<f32>, [f64; 2]);

/// How training frames get their x, y.
#[derive(Clone, Debug)]
pub enum Labelling {
    /// The dataset's true positions (simulator, or a motion-capture log).
    Telemetry,
    /// Homography against an orthomap image (sec. 3.2).
    Homography(super::labelling::OrthoMap),
}

#[derive(Clone, Debug)]
pub struct TrainOptions {
    pub dataset: PathBuf,
    pub out: PathBuf,
    pub labelling: Labelling,
    pub seed: u64,
}

/// What training did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainReport {
    pub images: usize,
    pub rejected: usize,
    pub seconds: f64,
    pub histogram_seconds: f64,
    pub loo_rms_m: Vec<f64>,
    /// Per rank: SD of the right neighbours' error (sqrt of half the trace of Sigma[j]),
    /// and how often the rank is right.
    pub inlier_sd_m: Vec<f64>,
    pub inlier_fraction: Vec<f64>,
    pub process_source: String,
}

fn pose_rotation(r: &TelemetryRecord, ds: &Dataset) -> mavloc_geometry::Rot3 {
    r.measured.camera_pose(ds.camera.chain, ds.camera.gimbal_frame).local_from_camera()
}

/// Reads one frame; `None` (with a warning) when it is unreadable.
fn read(ds: &Dataset, r: &TelemetryRecord) -> Option<opencv::core::Mat> {
    match crate::imaging::read_image(&ds.frame_path(r), imgcodecs::IMREAD_COLOR) {
        Ok(m) => Some(m),
        Err(why) => {
            tracing::warn!(frame = r.frame, "frame skipped: {why}");
            None
        }
    }
}

/// Reads and prepares one frame as a whole canvas (training); `None` (with a warning)
/// when it is unusable.
fn load(ds: &Dataset, pre: &Preprocessor, r: &TelemetryRecord) -> Option<(opencv::core::Mat, Canvas)> {
    let img = read(ds, r)?;
    match pre.prepare(&img, Some(&pose_rotation(r, ds)), Some(frame_height(r))) {
        Ok(c) => Some((img, c)),
        Err(e) => {
            tracing::warn!(frame = r.frame, path = %ds.frame_path(r).display(), "frame skipped: {e}");
            None
        }
    }
}

/// The camera's height above the floor (the local frame's z = 0).
fn frame_height(r: &TelemetryRecord) -> f64 {
    -r.measured.position[2]
}

/// The frame preparation `[indoor]` configures for a camera with intrinsics `k` (for a
/// run, the settings [`model_settings`] gives, so frames are prepared as in training).
pub fn preprocessor(k: Intrinsics, s: &Indoor) -> Preprocessor {
    let mut p = Preprocessor::new(k, s.work_width, s.derotate, (s.patch_w as usize, s.patch_h as usize));
    p.normalise = s.normalise;
    p.height_ref = (s.height_ref_m > 0.0).then_some(s.height_ref_m);
    p
}

/// `indoor.height_ref_m` for training: as configured when positive, off when negative,
/// and when 0 the median camera height of the training frames (views rendered or flown
/// from 0.8-1.2 m otherwise show the floor at scales 20 % apart, and textons are not scale
/// invariant: measured over ten unseen floors, a 1000-view model's error went from
/// 0.43 to 0.11 m RMS on one of them).
fn with_reference_height(s: &Indoor, ds: &Dataset) -> Indoor {
    let mut s = s.clone();
    if s.height_ref_m == 0.0 {
        let mut heights: Vec<f64> =
            ds.records.iter().map(frame_height).filter(|h| h.is_finite() && *h > MIN_REFERENCE_M).collect();
        heights.sort_by(f64::total_cmp);
        s.height_ref_m = heights.get(heights.len() / 2).copied().unwrap_or(-1.0);
    }
    s
}

/// Below this camera height (m) a training frame's height is taken as unknown.
const MIN_REFERENCE_M: f64 = 0.05;

/// Learns the configured dictionary from patches in image order: the seed starts from
/// patches of one image, then learns over the rest in random order (sec. 3.3.1).
pub(crate) fn learn_dictionary(
    mut samples: Vec<Vec<f32>>,
    s: &Indoor,
    seed: u64,
) -> Result<Dictionary, String> {
    let n = s.textons as usize;
    if samples.len() > n {
        use rand::seq::SliceRandom;
        samples[n..].shuffle(&mut rand::rngs::StdRng::seed_from_u64(seed));
    }
    let learning = match s.dictionary {
        DictionaryMethod::Competitive => {
            Learning::Competitive { rate_millis: ((s.learning_rate * 1000.0).round() as u32).max(1) }
        }
        DictionaryMethod::KMeans => Learning::KMeans { iterations: KMEANS_ITERATIONS },
    };
    Dictionary::learn_from_patches(&samples, n, s.patch_w as usize, s.patch_h as usize, learning)
}

/// Trains a model from a labelled dataset and writes it to `opts.out`.
pub fn train(
    opts: &TrainOptions,
    s: &Indoor,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<TrainReport, String> {
    let start = Instant::now();
    let ds = Dataset::open(&opts.dataset)?;
    if ds.records.is_empty() {
        return Err(format!("{} has no frames", opts.dataset.display()));
    }
    let s = &with_reference_height(s, &ds);
    let pre = preprocessor(ds.camera.intrinsics(), s);
    let patch = (s.patch_w as usize, s.patch_h as usize);

    // 1. Dictionary, from random patches of images spread over the dataset.
    let step = ds.records.len().div_ceil(DICTIONARY_IMAGES).max(1);
    let picked: Vec<&TelemetryRecord> = ds.records.iter().step_by(step).collect();
    let patches: Vec<Vec<Vec<f32>>> = picked
        .par_iter()
        .enumerate()
        .map(|(i, r)| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(opts.seed.wrapping_add(i as u64));
            load(&ds, &pre, r)
                .map(|(_, c)| Dictionary::sample_patches(&c.img, &c.mask, patch, PATCHES_PER_IMAGE, &mut rng))
                .unwrap_or_default()
        })
        .collect();
    let dictionary = learn_dictionary(patches.into_iter().flatten().collect(), s, opts.seed)?;

    // 2. Histograms: full sampling for the model, random sampling for the leave-one-out fit.
    let hist_start = Instant::now();
    let classifier = dictionary.classifier();
    let total = ds.records.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let mut rows: Vec<Row> = Vec::with_capacity(total);
    for (b, batch) in ds.records.chunks(BATCH).enumerate() {
        let part: Vec<Option<Row>> = batch
            .par_iter()
            .enumerate()
            .map(|(i, r)| {
                let index = b * BATCH + i;
                let out = load(&ds, &pre, r).map(|(img, c)| {
                    let mut rng = rand::rngs::StdRng::seed_from_u64(opts.seed ^ (index as u64 + 1));
                    let full = dictionary.histogram_full_serial(&c.img, Some(&c.mask));
                    // As in flight: patches gathered from the frame ([`Preprocessor::sample`]).
                    let mut patches = Vec::new();
                    let random = match pre.sample(
                        &img,
                        Some(&pose_rotation(r, &ds)),
                        Some(frame_height(r)),
                        s.samples as usize,
                        &mut rng,
                        &mut patches,
                    ) {
                        Ok(_) => classifier.histogram_of_patches(&patches),
                        Err(_) => vec![0.0; dictionary.len()],
                    };
                    (index, full, random)
                });
                progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, total);
                out
            })
            .collect();
        rows.extend(part.into_iter().flatten());
    }
    let histogram_seconds = hist_start.elapsed().as_secs_f64();

    // 3. Labels.
    let mut rejected = 0;
    let (labelling_name, labelled): (&str, Vec<Labelled>) = match &opts.labelling {
        Labelling::Telemetry => (
            "telemetry",
            rows.into_iter()
                .map(|(i, f, r)| {
                    let p = ds.records[i].truth.position;
                    (i, f, r, [p[0], p[1]])
                })
                .collect(),
        ),
        Labelling::Homography(map) => {
            let labels: Vec<Option<[f64; 2]>> = rows
                .par_iter()
                .map(|(i, _, _)| {
                    map.label(&ds, &ds.records[*i]).unwrap_or_else(|e| {
                        tracing::warn!("frame not labelled, rejected: {e}");
                        None
                    })
                })
                .collect();
            let mut out = Vec::new();
            for ((i, f, r), l) in rows.into_iter().zip(labels) {
                match l {
                    Some(p) => out.push((i, f, r, p)),
                    None => rejected += 1,
                }
            }
            ("homography", out)
        }
    };
    if labelled.len() < 2 {
        return Err(format!("only {} usable labelled frames; at least 2 are needed", labelled.len()));
    }
    let histograms: Vec<Vec<f32>> = labelled.iter().map(|(_, f, _, _)| f.clone()).collect();
    let positions: Vec<[f64; 2]> = labelled.iter().map(|(_, _, _, p)| *p).collect();

    // 4. Sigma[j] by leave-one-out.
    let knn = Knn::new(&histograms)?;
    let k = (s.k as usize).min(histograms.len() - 1).max(1);
    let diffs: Vec<Vec<Vector2<f64>>> = labelled
        .par_iter()
        .enumerate()
        .map_init(
            || (Vec::new(), Vec::new()),
            |(scratch, found), (i, (_, _, random, p))| {
                knn.nearest(random, k, Some(i), scratch, found);
                found.iter().map(|nb| Vector2::from(*p) - Vector2::from(positions[nb.index])).collect()
            },
        )
        .collect();
    let mut min = [f64::INFINITY; 2];
    let mut max = [f64::NEG_INFINITY; 2];
    for p in &positions {
        for c in 0..2 {
            min[c] = min[c].min(p[c]);
            max[c] = max[c].max(p[c]);
        }
    }
    let area = ((max[0] - min[0]) * (max[1] - min[1])).max(1.0);
    let mut measurement_cov = Vec::new();
    let mut inlier_fraction = Vec::new();
    let mut loo_rms_m = Vec::new();
    for j in 0..k {
        let errors: Vec<Vector2<f64>> = diffs.iter().filter_map(|d| d.get(j).copied()).collect();
        loo_rms_m
            .push((errors.iter().map(|d| d.norm_squared()).sum::<f64>() / errors.len().max(1) as f64).sqrt());
        let (cov, pi) = super::model::fit_robust(&errors, area);
        measurement_cov.push(from_matrix(&cov));
        inlier_fraction.push(pi);
    }

    // 5. Process noise: configured, or fitted from the labels when they are a flight.
    let (process, process_source) =
        process_noise(&ds, &labelled.iter().map(|l| l.0).collect::<Vec<_>>(), &positions, s);

    let model = Model {
        format: MODEL_FORMAT.into(),
        version: MODEL_VERSION,
        frame: FrameParams {
            work_width: pre.work.width,
            work_fx: pre.work.fx,
            derotate: s.derotate,
            normalise: s.normalise,
            height_ref_m: pre.height_ref,
        },
        dictionary,
        histograms,
        positions,
        measurement_cov,
        inlier_fraction,
        process_cov: from_matrix(&process),
        bounds: [min, max],
        training: TrainingInfo {
            dataset: opts.dataset.display().to_string(),
            labelling: labelling_name.into(),
            images: labelled.len(),
            rejected,
            process_source: process_source.clone(),
            loo_rms_m: loo_rms_m.clone(),
        },
    };
    model.validate()?;
    model.save(&opts.out)?;
    Ok(TrainReport {
        images: model.positions.len(),
        rejected,
        seconds: start.elapsed().as_secs_f64(),
        histogram_seconds,
        loo_rms_m,
        inlier_sd_m: model.measurement_cov.iter().map(|c| ((c[0][0] + c[1][1]) / 2.0).sqrt()).collect(),
        inlier_fraction: model.inlier_fraction.clone(),
        process_source,
    })
}

/// The seed's process noise: the second moment of the per-frame displacement of a
/// training flight (sec. 3.3.4). Random views are not a flight; then the configured value
/// or a fallback is used, and the model says which.
fn process_noise(
    ds: &Dataset,
    indices: &[usize],
    positions: &[[f64; 2]],
    s: &Indoor,
) -> (Matrix2<f64>, String) {
    if s.process_sigma_m > 0.0 {
        let v = s.process_sigma_m * s.process_sigma_m;
        return (Matrix2::identity() * v, format!("configured: {} m per frame", s.process_sigma_m));
    }
    let steps: Vec<Vector2<f64>> = indices
        .windows(2)
        .zip(positions.windows(2))
        .filter(|(i, _)| i[1] == i[0] + 1 && ds.records[i[1]].t > ds.records[i[0]].t)
        .map(|(_, p)| Vector2::from(p[1]) - Vector2::from(p[0]))
        .collect();
    let mut lengths: Vec<f64> = steps.iter().map(|d| d.norm()).collect();
    lengths.sort_by(f64::total_cmp);
    let is_flight = steps.len() >= 10 && lengths[lengths.len() / 2] < 0.25;
    if is_flight {
        let m = steps.iter().fold(Matrix2::zeros(), |acc, d| acc + d * d.transpose()) / steps.len() as f64;
        let m = m + Matrix2::identity() * 1e-6;
        return (m, format!("fitted on {} frame-to-frame steps of the training flight", steps.len()));
    }
    let v = FALLBACK_PROCESS_SD_M * FALLBACK_PROCESS_SD_M;
    (
        Matrix2::identity() * v,
        format!("default {FALLBACK_PROCESS_SD_M} m per frame (the training frames are not a flight)"),
    )
}

#[derive(Clone, Debug)]
pub struct RunOptions {
    pub dataset: PathBuf,
    pub model: PathBuf,
    pub out: PathBuf,
    pub max_frames: Option<usize>,
    /// Ignore the telemetry's velocity (the velocity model then fits it from estimates).
    pub no_velocity: bool,
    /// Move the particles with the camera's own velocity ([`super::flow`]), as the daemon
    /// does without GPS, instead of the telemetry's.
    pub camera_velocity: bool,
    pub seed: u64,
}

/// Frames between checkpoints of a run's results.
const CHECKPOINT_FRAMES: usize = 100;

/// What a run did; also `summary.json`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RunSummary {
    pub frames: usize,
    pub skipped_frames: usize,
    pub motion_model: String,
    pub derotate: bool,
    /// Frames per second of whole frames: reading and decoding the file, preparing the
    /// frame and localising it (the stages below add up to it).
    pub frames_per_s: f64,
    /// Mean time to read and decode a frame's file, ms.
    #[serde(default)]
    pub read_ms: f64,
    /// Mean time to downscale, derotate and normalise a frame, ms.
    pub prepare_ms: f64,
    /// Mean localiser time per frame (histogram, k-NN, particle filter), ms.
    pub localize_ms: f64,
    /// Frames per second of the localiser alone.
    #[serde(default)]
    pub localize_frames_per_s: f64,
    /// `--camera-velocity`: frames with a velocity from the camera, and its RMS error per
    /// axis against the dataset's true velocity, m/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_velocity_frames: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_velocity_rms_m_s: Option<f64>,
    pub complete: bool,
    /// Where the results were put: `--out`, or beside it (`NAME.stopped`) for a run
    /// stopped part way over complete earlier results.
    #[serde(skip)]
    pub written_to: PathBuf,
    /// The dataset's telemetry file's CRC-32 (hex): `mavloc eval` refuses to measure the
    /// result against another dataset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset_crc32: Option<String>,
}

fn write_trajectory(out: &Path, rows: &[TrajectoryRow], summary: &RunSummary) -> Result<(), String> {
    let csv = trajectory_csv(rows);
    let write = |path: PathBuf, bytes: &[u8]| {
        mavloc_data::write_atomic(&path, bytes).map_err(|e| format!("cannot write {}: {e}", path.display()))
    };
    write(out.join("trajectory.csv"), csv.as_bytes())?;
    let json = serde_json::to_string_pretty(summary).map_err(|e| e.to_string())?;
    write(out.join("summary.json"), json.as_bytes())
}

/// The settings a model fixes (how its frames were prepared) over the configured ones.
pub fn model_settings(model: &Model, s: &Indoor) -> Indoor {
    let mut settings = s.clone();
    settings.work_width = model.frame.work_width;
    settings.derotate = model.frame.derotate;
    settings.normalise = model.frame.normalise;
    settings.height_ref_m = model.frame.height_ref_m.unwrap_or(-1.0);
    settings.patch_w = model.dictionary.w as u32;
    settings.patch_h = model.dictionary.h as u32;
    settings
}

/// Runs a model over a flight.
pub fn run(opts: &RunOptions, s: &Indoor, progress: impl Fn(usize, usize)) -> Result<RunSummary, String> {
    run_stoppable(opts, s, progress, &AtomicBool::new(false))
}

/// [`run`], ending after the frame in hand once `stop` is set (Ctrl-C), as `mavloc area`
/// does: the frames so far are the results (`complete: false`), put beside complete
/// earlier results as `NAME.stopped` instead of over them.
pub fn run_stoppable(
    opts: &RunOptions,
    s: &Indoor,
    progress: impl Fn(usize, usize),
    stop: &AtomicBool,
) -> Result<RunSummary, String> {
    let ds = Dataset::open(&opts.dataset)?;
    let model = Model::load(&opts.model)?;
    let settings = model_settings(&model, s);
    let pre = preprocessor(ds.camera.intrinsics(), &settings);
    let rel = (pre.work.fx - model.frame.work_fx).abs() / model.frame.work_fx;
    if rel > 0.1 {
        tracing::warn!(
            model_fx = model.frame.work_fx,
            camera_fx = pre.work.fx,
            "the camera's focal length at the working width differs from the model's by {:.0} %; textons will be seen at another scale",
            rel * 100.0
        );
    }
    let mut loc = Localizer::new(&model, LocalizerParams::from_settings(&settings, opts.seed))?;
    // Whether --out holds a complete earlier set, which a stopped run must not replace.
    let earlier_complete = std::fs::read_to_string(opts.out.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .is_some_and(|v| v["complete"] == true);
    // Written beside --out and put in place whole at the end, as `mavloc area` does.
    let staged = mavloc_data::staged::begin_results(&opts.out)?;
    let out = staged.path().to_path_buf();
    let total = opts.max_frames.unwrap_or(usize::MAX).min(ds.records.len());
    let mut summary = RunSummary {
        motion_model: format!("{:?}", settings.motion_model).to_lowercase(),
        derotate: settings.derotate,
        dataset_crc32: mavloc_data::dataset::telemetry_crc32(&ds.dir),
        ..RunSummary::default()
    };
    let (mut read_s, mut prepare_s, mut localize_s) = (0.0, 0.0, 0.0);
    let mut rows = Vec::with_capacity(total);
    let k = ds.camera.intrinsics();
    let mut last_flow: Option<super::flow::FlowFrame> = None;
    let flow = super::flow::Flow::new().map_err(|e| e.to_string())?;
    let (mut flow_n, mut flow_sq) = (0usize, 0.0);
    let mut stopped = false;
    for (i, r) in ds.records.iter().take(total).enumerate() {
        if stop.load(Ordering::SeqCst) {
            stopped = true;
            break;
        }
        let t0 = Instant::now();
        let Some(img) = read(&ds, r) else {
            summary.skipped_frames += 1;
            progress(i + 1, total);
            continue;
        };
        let t1 = Instant::now();
        if let Err(e) = loc.sample_frame(&pre, &img, Some(&pose_rotation(r, &ds)), Some(frame_height(r))) {
            tracing::warn!(frame = r.frame, path = %ds.frame_path(r).display(), "frame skipped: {e}");
            summary.skipped_frames += 1;
            progress(i + 1, total);
            continue;
        }
        let t2 = Instant::now();
        let v = if opts.camera_velocity {
            let cur = super::flow::FlowFrame::new(r.t, &img, pose_rotation(r, &ds), frame_height(r))
                .map_err(|e| format!("frame {}: {e}", r.frame))?;
            let m = last_flow.as_ref().and_then(|prev| flow.motion(prev, &cur, &k).ok());
            last_flow = Some(cur);
            m.map(|m| {
                flow_n += 1;
                flow_sq += ((m.velocity.x - r.truth.velocity[0]).powi(2)
                    + (m.velocity.y - r.truth.velocity[1]).powi(2))
                    / 2.0;
                m.velocity
            })
        } else {
            (!opts.no_velocity).then(|| Vector2::new(r.measured.velocity[0], r.measured.velocity[1]))
        };
        let e = loc.step_sampled(r.t, v);
        read_s += (t1 - t0).as_secs_f64();
        prepare_s += (t2 - t1).as_secs_f64();
        localize_s += t2.elapsed().as_secs_f64();
        rows.push(TrajectoryRow {
            frame: r.frame,
            t: r.t,
            x: e.position.x,
            y: e.position.y,
            sigma_x: e.spread.0,
            sigma_y: e.spread.1,
            true_x: r.truth.position[0],
            true_y: r.truth.position[1],
            fix: e.fix,
        });
        summary.frames = rows.len();
        // Checkpoints in the staging folder: kept by the next run after a crash.
        if rows.len() % CHECKPOINT_FRAMES == 0 {
            write_trajectory(&out, &rows, &summary)?;
        }
        progress(i + 1, total);
    }
    let n = rows.len().max(1) as f64;
    summary.read_ms = read_s / n * 1000.0;
    summary.prepare_ms = prepare_s / n * 1000.0;
    summary.localize_ms = localize_s / n * 1000.0;
    let whole = read_s + prepare_s + localize_s;
    summary.frames_per_s = if whole > 0.0 { rows.len() as f64 / whole } else { 0.0 };
    summary.localize_frames_per_s = if localize_s > 0.0 { rows.len() as f64 / localize_s } else { 0.0 };
    if opts.camera_velocity {
        summary.camera_velocity_frames = Some(flow_n);
        summary.camera_velocity_rms_m_s = (flow_n > 0).then(|| (flow_sq / flow_n as f64).sqrt());
    }
    summary.complete = !stopped;
    write_trajectory(&out, &rows, &summary)?;
    // A run that could use no frame has nothing to stand for: the earlier results stay.
    // A run stopped part way does not replace complete earlier results either.
    summary.written_to = opts.out.clone();
    if !rows.is_empty() {
        if stopped && earlier_complete {
            summary.written_to = staged.commit_beside("stopped")?;
        } else {
            staged.commit()?;
        }
    }
    Ok(summary)
}
