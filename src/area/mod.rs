//! Area localisation (area seed `area-localization-thesis.txt`, ch. 4-5): the 3D border of
//! an area the camera sees, from SIFT landmarks in a band around the segmented area, each
//! estimated by its own UKF from bearing measurements.
//!
//! One frame at a time, no look-ahead, as fig. 5.1: [`features`] (process new image,
//! sec. 5.2) -> [`library`] match and estimate (sec. 5.4) -> purge (sec. 5.5) -> add
//! (sec. 5.3). [`baseline`] is the seed's previous method (sec. 2.1) for comparison,
//! [`border`] fits a 3D border line to the results (the seed's future work, ch. 9),
//! [`eval`] measures results as the seed does (ch. 6), and [`offline`] runs a dataset.
//! For photo surveys: [`imageup`] finds photos tagged half a turn off, [`align`] aligns
//! the photos to each other by tie points before the filters run (ours), [`refine`]
//! adjusts attitudes and a static gimbal offset with the landmarks (sec. 6.10-6.11),
//! [`crosslines`] measures how well two flight lines agree, [`segment`] finds the target
//! in real images, [`shadow`] keeps cast shadows out of the water it finds.
//!
//! The pipeline is a plain synchronous library: it takes a grey frame, its target mask and
//! the camera pose the telemetry gives, and returns what changed. It knows nothing of
//! files, MAVLink or tokio.

pub mod align;
pub mod baseline;
pub mod border;
pub mod crosslines;
pub mod eval;
pub mod features;
pub mod imageup;
pub mod library;
pub mod offline;
pub mod rays;
pub mod refine;
pub mod residuals;
pub mod segment;
pub mod shadow;

use std::time::{Duration, Instant};

use opencv::core::Mat;
use opencv::prelude::*;

use crate::geometry::{CameraPose, Intrinsics, Pixel};
use crate::settings::Area as AreaSettings;
use features::FeatureExtractor;
use library::{Library, LibraryParams, MatchStats, TraceEntry};
use mavloc_data::results::LandmarkRecord;

/// Why a frame could not be processed.
#[derive(Debug, thiserror::Error)]
pub enum AreaError {
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error("{0}")]
    Input(String),
}

/// One frame for the pipeline, at the processing resolution.
pub struct FrameInput<'a> {
    pub index: u64,
    /// 8-bit grey frame.
    pub grey: &'a Mat,
    /// 8-bit target mask (non-zero inside the target area), same size.
    pub mask: &'a Mat,
    /// Camera pose from the (time-aligned) telemetry.
    pub pose: CameraPose,
}

/// What one frame did.
#[derive(Clone, Debug, Default)]
pub struct FrameReport {
    pub features: usize,
    pub stats: MatchStats,
    pub purged: usize,
    pub added: usize,
    /// Landmarks that converged and were purged this frame: results.
    pub converged: Vec<LandmarkRecord>,
    /// Library size after the frame.
    pub landmarks: usize,
    /// Per-update history, when tracing is on: every match's update (gated ones too),
    /// then each landmark created here with its first sighting.
    pub trace: Vec<TraceEntry>,
    /// When tracing is on: where each landmark was seen in this frame, `(landmark,
    /// pixel)`: the landmarks created here and every match, gated ones included (the
    /// residual report checks each ray a landmark was built from, and a frame whose pose
    /// is wrong has all its matches gated).
    pub sightings: Vec<(u64, Pixel)>,
    /// The sightings the landmarks are built from: those created here and the matches the
    /// gate accepted (what a landmark's own triangulation may use; a gated match is a
    /// sighting the filter refused).
    pub accepted_sightings: Vec<(u64, Pixel)>,
    pub timing: StageTiming,
}

/// Time spent per stage.
#[derive(Clone, Copy, Debug, Default)]
pub struct StageTiming {
    pub band: Duration,
    pub sift: Duration,
    pub match_estimate: Duration,
    pub purge_add: Duration,
}

impl std::ops::AddAssign for StageTiming {
    fn add_assign(&mut self, o: StageTiming) {
        self.band += o.band;
        self.sift += o.sift;
        self.match_estimate += o.match_estimate;
        self.purge_add += o.purge_add;
    }
}

/// The area pipeline.
pub struct AreaPipeline {
    k: Intrinsics,
    extractor: FeatureExtractor,
    library: Library,
    trace: bool,
}

impl AreaPipeline {
    /// A pipeline for frames with intrinsics `k` (at the processing resolution, i.e. after
    /// the configured downscale).
    pub fn new(s: &AreaSettings, k: Intrinsics) -> Result<AreaPipeline, AreaError> {
        k.validate().map_err(AreaError::Input)?;
        let band = (s.band_px as f64 / s.downscale.max(1) as f64).round().max(1.0) as i32;
        let l_max = s.l_max as i32;
        let extractor = FeatureExtractor::new(l_max, l_max * s.feature_factor as i32, band)?;
        let library = Library::new(LibraryParams::from_settings(s))?;
        Ok(AreaPipeline { k, extractor, library, trace: false })
    }

    /// Applies new settings to a running pipeline, keeping its landmarks: the library's
    /// gates and noise at once, the band and feature counts from the next frame.
    /// `k` is the intrinsics at the new processing resolution (the downscale may change).
    pub fn reconfigure(&mut self, s: &AreaSettings, k: Intrinsics) -> Result<(), AreaError> {
        k.validate().map_err(AreaError::Input)?;
        let band = (s.band_px as f64 / s.downscale.max(1) as f64).round().max(1.0) as i32;
        let l_max = s.l_max as i32;
        self.extractor = FeatureExtractor::new(l_max, l_max * s.feature_factor as i32, band)?;
        self.library.params = LibraryParams::from_settings(s);
        self.k = k;
        Ok(())
    }

    /// Records every update for outlier analysis (seed fig. 6.2).
    pub fn with_trace(mut self, on: bool) -> Self {
        self.trace = on;
        self
    }

    /// [`AreaPipeline::with_trace`] on a running pipeline.
    pub fn set_trace(&mut self, on: bool) {
        self.trace = on;
    }

    pub fn intrinsics(&self) -> &Intrinsics {
        &self.k
    }

    /// Landmarks currently tracked.
    pub fn tracked(&self) -> usize {
        self.library.landmarks.len()
    }

    /// Processes one frame (seed fig. 5.1).
    pub fn process(&mut self, input: &FrameInput) -> Result<FrameReport, AreaError> {
        let (w, h) = (input.grey.cols(), input.grey.rows());
        if (w, h) != (self.k.width as i32, self.k.height as i32) {
            return Err(AreaError::Input(format!(
                "frame {} is {w}x{h} but the pipeline expects {}x{}",
                input.index, self.k.width, self.k.height
            )));
        }
        if (input.mask.cols(), input.mask.rows()) != (w, h) {
            return Err(AreaError::Input(format!(
                "mask of frame {} has another size than the frame",
                input.index
            )));
        }
        let mut report = FrameReport::default();
        let t0 = Instant::now();
        let band = self.extractor.band(input.mask)?;
        let t1 = Instant::now();
        let first = self.library.landmarks.is_empty();
        let features = self.extractor.extract(input.grey, &band, first)?;
        let t2 = Instant::now();
        report.features = features.len();
        let trace = if self.trace { Some(&mut report.trace) } else { None };
        let (stats, used) =
            self.library.match_and_estimate(input.index, &features, &input.pose, &self.k, trace)?;
        report.stats = stats;
        let t3 = Instant::now();
        let (purged, converged) = self.library.purge(input.index);
        report.purged = purged;
        report.converged = converged;
        let created = if self.trace { Some(&mut report.trace) } else { None };
        report.added = self.library.add(input.index, &features, &used, &input.pose, &self.k, created);
        report.accepted_sightings =
            report.trace.iter().filter(|t| t.accepted).map(|t| (t.landmark, t.pixel)).collect();
        report.sightings = report.trace.iter().map(|t| (t.landmark, t.pixel)).collect();
        report.landmarks = self.library.landmarks.len();
        report.timing =
            StageTiming { band: t1 - t0, sift: t2 - t1, match_estimate: t3 - t2, purge_add: t3.elapsed() };
        Ok(report)
    }

    /// Landmarks still in the library that have converged: results at the end of a run
    /// or on demand (the library is not changed).
    pub fn converged_now(&self) -> Vec<LandmarkRecord> {
        self.library.landmarks.iter().filter(|l| self.library.converged(l)).map(|l| l.record()).collect()
    }
}
