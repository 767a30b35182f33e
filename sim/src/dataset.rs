//! Rendering scenarios into datasets. The format itself (records, files, reading) is
//! `mavloc_data::dataset`; this module renders the frames and masks and writes them, the
//! telemetry and the ground truth through it.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use mavloc_data::dataset::{self, Appearance, CameraFile, GimbalFrame, PoseRecord, TelemetryRecord};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

use crate::mission::Mission;
use crate::render::Renderer;
use crate::scenario::{NoiseSpec, Scenario};
use crate::state::State;
use crate::world::World;

/// A true state as the dataset records it.
pub fn pose_record(s: &State) -> PoseRecord {
    PoseRecord {
        position: s.position.into(),
        attitude_deg: s.attitude.map(f64::to_degrees),
        gimbal_deg: [s.gimbal.yaw.to_degrees(), s.gimbal.pitch.to_degrees(), s.gimbal.roll.to_degrees()],
        velocity: s.velocity.into(),
    }
}

/// Rendering choices that may differ from the scenario file.
#[derive(Clone, Debug, Default)]
pub struct RenderOptions {
    /// At most this many frames (default: one lap).
    pub frames: Option<usize>,
    /// Resolution override, keeping the field of view.
    pub size: Option<(u32, u32)>,
    pub seed: Option<u64>,
    pub noise: Option<NoiseSpec>,
    /// Overwrite a non-empty output folder.
    pub force: bool,
    /// Render this many random labelled views (indoor seed sec. 3.4.2) instead of the
    /// mission's flight. Indoor scenarios only.
    pub views: Option<usize>,
    /// Photometric change for every frame of a flight (brightness, contrast, blur).
    pub appearance: Option<Appearance>,
    /// Take the frames and masks from this dataset instead of rendering them: only the
    /// telemetry is drawn anew, with this render's noise. The dataset must have been
    /// rendered from the same scenario (noise aside), seed and size, and hold every shot
    /// ([`FramesFrom`]). A noise study renders its flight once.
    pub frames_from: Option<PathBuf>,
}

/// Frames and masks taken from an earlier render ([`RenderOptions::frames_from`]), each
/// checked to be the same shot: the same frame number, true pose and appearance.
struct FramesFrom {
    ds: mavloc_data::Dataset,
}

impl FramesFrom {
    /// Opens `dir` and checks that it was rendered from `scenario` (its noise aside).
    fn open(dir: &Path, scenario: &Scenario) -> Result<FramesFrom, String> {
        let ds = mavloc_data::Dataset::open(dir).map_err(|e| format!("--frames-from: {e}"))?;
        let path = dir.join("scenario.toml");
        let text =
            std::fs::read_to_string(&path).map_err(|e| format!("--frames-from: {}: {e}", path.display()))?;
        let mut theirs: Scenario =
            toml::from_str(&text).map_err(|e| format!("--frames-from: {}: {e}", path.display()))?;
        let mut ours = scenario.clone();
        theirs.noise = ours.noise.clone();
        (theirs.base_dir, ours.base_dir) = (None, None);
        if theirs != ours {
            // The scenario first: another scenario has another seed too, and naming the
            // seed would hide what differs.
            let what = if theirs.name != ours.name {
                format!("scenario {:?} (this render: {:?})", theirs.name, ours.name)
            } else if theirs.seed != ours.seed {
                format!("seed {} (this render: {})", theirs.seed, ours.seed)
            } else if (theirs.camera.width, theirs.camera.height) != (ours.camera.width, ours.camera.height) {
                format!(
                    "size {}x{} (this render: {}x{})",
                    theirs.camera.width, theirs.camera.height, ours.camera.width, ours.camera.height
                )
            } else {
                format!("another setting of scenario {:?} than its noise", theirs.name)
            };
            return Err(format!(
                "--frames-from {}: rendered with {what}; render the frames anew",
                dir.display()
            ));
        }
        Ok(FramesFrom { ds })
    }

    /// Copies shot `i`'s frame and mask into `out` (copies, not links: a mask edited by
    /// hand in one dataset must not change in the other).
    fn copy(
        &self,
        i: usize,
        truth: &PoseRecord,
        appearance: Option<Appearance>,
        out: &Path,
    ) -> Result<(), String> {
        let dir = self.ds.dir.display();
        let r = self.ds.records.iter().find(|r| r.frame == i as u64).ok_or_else(|| {
            // Past its last frame it is shorter (rendered with fewer --frames); inside it,
            // the frame was dropped as it was rendered (--drop-rate).
            let last = self.ds.records.last().map_or(0, |r| r.frame);
            if i as u64 > last {
                format!(
                    "--frames-from {dir}: it ends at frame {last} (rendered with fewer frames, or its last ones dropped), and this render needs frame {i}: render no more frames than it holds (--frames {}), or render the frames anew",
                    last + 1
                )
            } else {
                format!("--frames-from {dir}: it has no frame {i} (dropped when it was rendered); render the frames anew")
            }
        })?;
        // A tolerance, though serde_json's float_roundtrip gives the numbers back exactly:
        // the check must not hang on a feature flag.
        let close =
            |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-9 * x.abs().max(1.0));
        let same_pose = close(&r.truth.position, &truth.position)
            && close(&r.truth.attitude_deg, &truth.attitude_deg)
            && close(&r.truth.gimbal_deg, &truth.gimbal_deg);
        if !same_pose || r.appearance != appearance {
            return Err(format!(
                "--frames-from {dir}: its frame {i} is another shot; render the frames anew"
            ));
        }
        let name = format!("{i:06}.png");
        for (from, sub) in [(self.ds.frame_path(r), "frames"), (self.ds.mask_path(r), "masks")] {
            let to = out.join(sub).join(&name);
            std::fs::copy(&from, &to).map_err(|e| {
                format!("--frames-from: cannot copy {} to {}: {e}", from.display(), to.display())
            })?;
        }
        Ok(())
    }
}

/// What a render produced.
#[derive(Clone, Debug)]
pub struct RenderSummary {
    pub frames: usize,
    pub dropped: usize,
    pub dir: PathBuf,
}

/// A frame or mask, written plainly: it is inside the staged folder, which is flushed to
/// disk once when committed (an fsync per file, two per frame, made rendering wait on
/// the disk: 300 small frames took 6 s, nearly all of it waiting).
fn write_png(path: &Path, width: u32, height: u32, data: &[u8], colour: bool) -> Result<(), String> {
    let channels =
        if colour { mavloc_data::pngfile::Channels::Rgb } else { mavloc_data::pngfile::Channels::Grey };
    mavloc_data::pngfile::encode(width, height, data, channels)
        .and_then(|bytes| std::fs::write(path, bytes))
        .map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// Renders a scenario into a dataset folder. `progress(done, total)` is called after each
/// frame.
pub fn render_dataset(
    scenario: &Scenario,
    opts: &RenderOptions,
    out: &Path,
    progress: impl FnMut(usize, usize),
) -> Result<RenderSummary, String> {
    render_dataset_until(scenario, opts, out, progress, &AtomicBool::new(false))
}

/// The error of a render stopped by its flag ([`render_dataset_until`]).
pub const STOPPED: &str = "stopped by Ctrl-C";

/// [`render_dataset`] that stops after the frame in hand once `stop` is set (Ctrl-C): it
/// then fails with [`STOPPED`], its staging folder removed and `out` as it was.
pub fn render_dataset_until(
    scenario: &Scenario,
    opts: &RenderOptions,
    out: &Path,
    mut progress: impl FnMut(usize, usize),
    stop: &AtomicBool,
) -> Result<RenderSummary, String> {
    let mut scenario = scenario.clone();
    if let Some(seed) = opts.seed {
        scenario.seed = seed;
    }
    if let Some((w, h)) = opts.size {
        scenario.camera.width = w;
        scenario.camera.height = h;
    }
    if let Some(noise) = &opts.noise {
        scenario.noise = noise.clone();
    }
    scenario.validate()?;
    // Written beside `out` and put in place whole at the end: a failed render leaves no
    // half-written folder, and --force replaces the old dataset instead of writing over it.
    let staged = mavloc_data::staged::begin_dataset(out, opts.force)?;
    let final_dir = out;
    let out = staged.path();
    dataset::prepare(out)?;

    let frames_from = opts.frames_from.as_deref().map(|dir| FramesFrom::open(dir, &scenario)).transpose()?;
    let world = World::build(&scenario)?;
    let mission = Mission::plan(&world)?;
    let renderer = Renderer::new(&world);
    let k = scenario.intrinsics();

    // Static files first; telemetry last marks completeness.
    let camera = CameraFile::new(k, scenario.camera.chain, mission.gimbal_frame, scenario.origin);
    dataset::write_camera(out, &camera)?;
    dataset::write_file(
        out,
        "scenario.toml",
        toml::to_string(&scenario).map_err(|e| e.to_string())?.as_bytes(),
    )?;
    // The truth travels with the data: evaluation reads it, it never rebuilds the world.
    dataset::write_ground_truth(out, &world.frame, &world.ground_truth)?;
    let plan = serde_json::to_string_pretty(&mission.qgc_plan(&world.frame)).map_err(|e| e.to_string())?;
    dataset::write_file(out, "mission.plan", plan.as_bytes())?;

    let noise = &scenario.noise;
    let mut rng = rand::rngs::StdRng::seed_from_u64(scenario.seed ^ 0x5eed);
    let unit = Normal::new(0.0, 1.0).map_err(|e| e.to_string())?;
    // What to render: the mission's flight, or random views.
    let shots: Vec<(State, Option<Appearance>)> = match opts.views {
        Some(count) => {
            if mission.gimbal_frame != GimbalFrame::Body {
                return Err(format!("--views is for indoor scenarios; {} flies a mission", scenario.name));
            }
            let spec = scenario.views.clone().unwrap_or_default();
            crate::views::random_views(&spec, count, scenario.seed)
                .into_iter()
                .map(|(s, a)| (s, Some(a)))
                .collect()
        }
        None => {
            let times = mission.frame_times();
            let total = opts.frames.unwrap_or(usize::MAX).min(times.len());
            times[..total].iter().map(|&t| (mission.state(t), opts.appearance)).collect()
        }
    };
    let total = shots.len();
    let mut records = Vec::new();
    let mut dropped = 0;
    let mut written = 0;
    let mut drift = Drift::default();
    for (i, (truth, appearance)) in shots.iter().enumerate() {
        if stop.load(Ordering::SeqCst) {
            return Err(STOPPED.into());
        }
        // Drawn for every shot, dropped or not, so the drift's time course does not
        // depend on the drops.
        let wander = drift.step(noise, truth.t, opts.views.is_none(), &mut rng, &unit);
        if noise.drop_rate > 0.0 && rand::Rng::random::<f64>(&mut rng) < noise.drop_rate {
            dropped += 1;
            progress(i + 1, total);
            continue;
        }
        let appearance = appearance.filter(|a| !a.is_identity());
        if let Some(from) = &frames_from {
            from.copy(i, &pose_record(truth), appearance, out)?;
        } else {
            let mut frame = renderer.render(&mission.camera_pose(truth), &k);
            if let Some(a) = appearance {
                crate::views::apply(&a, frame.width as usize, frame.height as usize, &mut frame.rgb);
            }
            let name = format!("{i:06}.png");
            write_png(&out.join("frames").join(&name), frame.width, frame.height, &frame.rgb, true)?;
            write_png(&out.join("masks").join(&name), frame.width, frame.height, &frame.mask, false)?;
        }
        let mut measured = measure(&mission, truth, noise, opts.views.is_none(), &mut rng, &unit);
        for (g, w) in measured.gimbal_deg.iter_mut().zip(wander) {
            *g += w;
        }
        let record = TelemetryRecord {
            frame: i as u64,
            t: truth.t,
            truth: pose_record(truth),
            measured,
            appearance,
            autopilot_time: None,
        };
        records.push(record);
        written += 1;
        progress(i + 1, total);
    }
    // A stop up to here leaves `out` as it was.
    if stop.load(Ordering::SeqCst) {
        return Err(STOPPED.into());
    }
    dataset::write_telemetry(out, &records)?;
    staged.commit()?;
    Ok(RenderSummary { frames: written, dropped, dir: final_dir.to_path_buf() })
}

/// The slowly varying gimbal error ([`NoiseSpec::gimbal_drift_sd_deg`]): a first-order
/// Gauss-Markov process per angle, stationary from the first shot.
#[derive(Default)]
struct Drift {
    state: Option<(f64, [f64; 3])>,
}

impl Drift {
    /// The error at time `t` (seconds; zero for random views, which have no flight).
    fn step(
        &mut self,
        n: &NoiseSpec,
        t: f64,
        on_flight: bool,
        rng: &mut impl rand::Rng,
        unit: &Normal<f64>,
    ) -> [f64; 3] {
        if !on_flight || n.gimbal_drift_sd_deg.iter().all(|sd| *sd <= 0.0) {
            return [0.0; 3];
        }
        let sd = n.gimbal_drift_sd_deg;
        let next = match self.state {
            None => [0, 1, 2].map(|i| sd[i] * unit.sample(rng)),
            Some((t0, x)) => {
                let a = (-(t - t0).max(0.0) / n.gimbal_drift_tau_s.max(1e-6)).exp();
                let s = (1.0 - a * a).sqrt();
                [0, 1, 2].map(|i| a * x[i] + s * sd[i] * unit.sample(rng))
            }
        };
        self.state = Some((t, next));
        next
    }
}

/// What the vehicle reports for a true state: position noise, the gimbal attitude of
/// `gimbal_lag_s` earlier with static offsets and noise. Random views have no flight to
/// lag along (`on_flight` false).
fn measure(
    mission: &Mission,
    truth: &State,
    noise: &NoiseSpec,
    on_flight: bool,
    rng: &mut impl rand::Rng,
    unit: &Normal<f64>,
) -> PoseRecord {
    let mut sample = |sd: f64| if sd > 0.0 { sd * unit.sample(rng) } else { 0.0 };
    let lagged = if noise.gimbal_lag_s > 0.0 && on_flight {
        mission.state(truth.t - noise.gimbal_lag_s)
    } else {
        *truth
    };
    let mut r = pose_record(truth);
    for (c, sd) in r.position.iter_mut().zip(noise.position_sd_m) {
        *c += sample(sd);
    }
    let g = pose_record(&lagged).gimbal_deg;
    r.gimbal_deg = [
        g[0] + noise.gimbal_offset_deg[0] + sample(noise.gimbal_yaw_sd_deg),
        g[1] + noise.gimbal_offset_deg[1] + sample(noise.gimbal_pitch_sd_deg),
        g[2] + noise.gimbal_offset_deg[2],
    ];
    r
}
