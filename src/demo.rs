//! The end-to-end demonstration behind `make demo`, from what exists so far: the simulator
//! renders short coastline and cliff flights with the area seed's noise (gimbal 0.5 deg,
//! position 0.5/0.5/2 m), the area pipeline localises each border, the seed's previous
//! method (ground-plane projection) runs on the same frames, and both are evaluated against
//! the ground truth as the seed does (ch. 6). Everything lands in an output folder, plots
//! included. (The live MAVLink daemon and the indoor pipeline are not built yet.)

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::area::eval::{evaluate, AreaEvaluation};
use crate::area::offline::{parse_border_csv, run as run_area, RunOptions, RunSummary};
use crate::output::{parse_landmarks_csv, plot};
use crate::settings::{AreaMethod, Settings};

/// What to run.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    pub out: PathBuf,
    /// Frames per flight (6 per second of flight).
    pub frames: usize,
    /// Render size; the area settings are scaled so the band stays 50 px at full HD.
    pub width: u32,
    pub height: u32,
    pub seed: u64,
}

/// One scenario's outcome.
#[derive(Clone, Debug)]
pub struct ScenarioResult {
    pub name: String,
    pub frames: u64,
    pub summary: RunSummary,
    pub ukf: AreaEvaluation,
    pub ground_plane: AreaEvaluation,
}

/// The demo's report.
#[derive(Clone, Debug)]
pub struct DemoReport {
    pub scenarios: Vec<ScenarioResult>,
    pub out: PathBuf,
    pub elapsed_s: f64,
}

impl DemoReport {
    /// The demo's own acceptance: landmarks converged in every scenario, none farther than
    /// 20 m from the border, mean distance within 3 m.
    pub fn passed(&self) -> bool {
        self.scenarios.iter().all(|s| s.ukf.landmarks > 0 && s.ukf.gt20 == 0 && s.ukf.mean_m <= 3.0)
    }
}

impl fmt::Display for DemoReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "mavloc demo: area localisation on simulated flights (seed noise: gimbal 0.5 deg, position 0.5/0.5/2 m)")?;
        writeln!(
            f,
            "  {:<10} {:>6} {:>8} {:>9} {:>6} {:>10} {:>12} {:>14}",
            "scenario", "frames", "frames/s", "landmarks", ">20 m", "mean d", "border line", "ground plane"
        )?;
        for s in &self.scenarios {
            writeln!(
                f,
                "  {:<10} {:>6} {:>8.1} {:>9} {:>6} {:>8.2} m {:>10.2} m {:>12.2} m",
                s.name,
                s.frames,
                s.summary.frames_per_s,
                s.ukf.landmarks,
                s.ukf.gt20,
                s.ukf.mean_m,
                s.ukf.border_mean_m,
                s.ground_plane.mean_m
            )?;
        }
        writeln!(f, "  mean d: landmarks' mean distance to the ground-truth border (seed table 6.5);")?;
        writeln!(f, "  ground plane: the seed's previous method on the same frames, mean distance.")?;
        writeln!(f, "  results, plots and datasets: {}", self.out.display())?;
        writeln!(
            f,
            "  not built yet: the MAVLink daemon, the live loop, the indoor pipeline (issues #5-#7)"
        )?;
        writeln!(f, "  time {:.1} s; result {}", self.elapsed_s, if self.passed() { "PASS" } else { "FAIL" })
    }
}

fn load_eval(dataset: &Path, result: &Path, fps: f64) -> anyhow::Result<AreaEvaluation> {
    let ds = mavloc_sim::Dataset::open(dataset).map_err(|e| anyhow::anyhow!(e))?;
    let lpath = result.join("landmarks.csv");
    let landmarks = parse_landmarks_csv(&std::fs::read_to_string(&lpath)?, &lpath.display().to_string())
        .map_err(|e| anyhow::anyhow!(e))?;
    let border = parse_border_csv(&std::fs::read_to_string(result.join("border.csv"))?);
    let e = evaluate(&landmarks, &ds.ground_truth, &border, fps);
    let points: Vec<_> = landmarks.iter().map(|l| l.position).collect();
    let title = result.display().to_string();
    plot::distance_histogram(&result.join("histogram.png"), &e.distances, &title)
        .map_err(|e| anyhow::anyhow!(e))?;
    plot::landmark_views(&result.join("views.png"), &points, &ds.ground_truth, &border, &title)
        .map_err(|e| anyhow::anyhow!(e))?;
    Ok(e)
}

/// Runs the demo. `progress(stage)` is told what is happening.
pub fn run(
    settings: &Settings,
    opts: &DemoOptions,
    mut progress: impl FnMut(&str),
) -> anyhow::Result<DemoReport> {
    let start = Instant::now();
    let mut s = settings.clone();
    // Frames are rendered at `width`; keep the band at 50 px of a full-HD frame.
    let full_hd_factor = 1920.0 / opts.width as f64;
    s.area.downscale = 1;
    s.area.band_px = ((settings.area.band_px as f64 / full_hd_factor).round() as u32).max(1);
    let mut scenarios = Vec::new();
    for name in ["coastline", "cliff"] {
        let dir = opts.out.join(name);
        let dataset = dir.join("dataset");
        progress(&format!("rendering {name}"));
        let scenario = mavloc_sim::Scenario::load(name).map_err(|e| anyhow::anyhow!(e))?;
        let render = mavloc_sim::RenderOptions {
            frames: Some(opts.frames),
            size: Some((opts.width, opts.height)),
            seed: Some(opts.seed),
            force: true,
            ..mavloc_sim::RenderOptions::default()
        };
        mavloc_sim::render_dataset(&scenario, &render, &dataset, |_, _| {})
            .map_err(|e| anyhow::anyhow!(e))?;
        progress(&format!("localising the {name} border"));
        let ukf_dir = dir.join("ukf");
        let summary = run_area(
            &RunOptions {
                dataset: dataset.clone(),
                out: ukf_dir.clone(),
                method: AreaMethod::Ukf,
                trace: false,
                max_frames: None,
            },
            &s,
            |_, _| {},
        )?;
        let plane_dir = dir.join("ground-plane");
        let plane = run_area(
            &RunOptions {
                dataset: dataset.clone(),
                out: plane_dir.clone(),
                method: AreaMethod::GroundPlane,
                trace: false,
                max_frames: None,
            },
            &s,
            |_, _| {},
        )?;
        let ukf = load_eval(&dataset, &ukf_dir, summary.frames_per_s)?;
        let ground_plane = load_eval(&dataset, &plane_dir, plane.frames_per_s)?;
        scenarios.push(ScenarioResult {
            name: name.to_string(),
            frames: summary.frames,
            summary,
            ukf,
            ground_plane,
        });
    }
    Ok(DemoReport { scenarios, out: opts.out.clone(), elapsed_s: start.elapsed().as_secs_f64() })
}
