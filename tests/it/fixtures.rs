//! Fixtures several test modules share: datasets the simulator renders and the small
//! indoor model, built once per build of this test binary. They are cached in cargo's
//! test scratch folder (`target/tmp`) under a stamp of this binary, which has the
//! renderer and the trainer compiled in: a changed build renders and trains again, a
//! rerun of the same build reads what is there. Rendering is deterministic for a
//! scenario and options, so a cached dataset is the one the test would render.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use mavloc::indoor::offline::{train, Labelling, TrainOptions, TrainReport};
use mavloc_sim::{render_dataset, RenderOptions, Scenario};

pub const BIN: &str = env!("CARGO_BIN_EXE_mavloc");

/// This test binary's identity: its size and modification time.
fn build_stamp() -> String {
    let exe = std::env::current_exe().unwrap();
    let m = std::fs::metadata(&exe).unwrap();
    format!("{} {:?}", m.len(), m.modified().unwrap())
}

/// Builds `key` with `make` (which writes into the folder it is given) unless this
/// build already did. Serialised: fixtures are CPU-bound and used read-only.
fn cached(key: &str, make: impl FnOnce(&Path)) -> PathBuf {
    static LOCK: Mutex<()> = Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fixtures");
    let dir = root.join(key);
    let stamp_file = root.join(format!("{key}.stamp"));
    let stamp = build_stamp();
    if dir.is_dir() && std::fs::read_to_string(&stamp_file).ok().as_deref() == Some(stamp.as_str()) {
        return dir;
    }
    // Built beside, then renamed: an interrupted run never leaves a half fixture.
    let partial = root.join(format!("{key}.partial"));
    let _ = std::fs::remove_dir_all(&partial);
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_file(&stamp_file);
    std::fs::create_dir_all(&root).unwrap();
    make(&partial);
    std::fs::rename(&partial, &dir).unwrap();
    std::fs::write(&stamp_file, stamp).unwrap();
    dir
}

/// A dataset of `scenario` rendered with `opts`; `key` names the options.
pub fn rendered(key: &str, scenario: &str, opts: &RenderOptions) -> PathBuf {
    cached(key, |out| {
        render_dataset(&Scenario::load(scenario).unwrap(), opts, out, |_, _| {}).unwrap();
    })
}

/// A flight over the indoor floor at 0.5 m instead of 1 m (0.4-0.6 m with its swing), the
/// heights a vehicle climbs and descends through, 320x240.
pub fn low_indoor_flight(frames: usize) -> PathBuf {
    cached(&format!("indoor-floor-flight-{frames}-320x240-at-0.5m"), |out| {
        let mut scenario = Scenario::load("indoor-floor").unwrap();
        scenario.mission.altitude_m = 0.5;
        let opts = RenderOptions { frames: Some(frames), size: Some((320, 240)), ..Default::default() };
        render_dataset(&scenario, &opts, out, |_, _| {}).unwrap();
    })
}

/// 400 random views of the indoor floor at 320x240: the training set of the small model.
pub fn indoor_views() -> PathBuf {
    let opts = RenderOptions { views: Some(400), size: Some((320, 240)), ..Default::default() };
    rendered("indoor-floor-views-400-320x240", "indoor-floor", &opts)
}

/// The small indoor model the live indoor flights use, trained on [`indoor_views`] with
/// the default settings.
pub fn small_indoor_model() -> &'static Path {
    &small_indoor_training().0
}

/// [`small_indoor_model`] and what its training reported: trained once per build, for
/// every test that trains with the default settings on these views.
pub fn small_indoor_training() -> &'static (PathBuf, TrainReport) {
    static MODEL: OnceLock<(PathBuf, TrainReport)> = OnceLock::new();
    MODEL.get_or_init(|| {
        let views = indoor_views();
        let dir = cached("indoor-floor-model-400", |out| {
            std::fs::create_dir_all(out).unwrap();
            let opts = TrainOptions {
                dataset: views,
                out: out.join("floor.model"),
                labelling: Labelling::Telemetry,
                seed: 1,
            };
            let report = train(&opts, &mavloc::settings::Indoor::default(), |_, _| {}).unwrap();
            std::fs::write(out.join("report.json"), serde_json::to_string(&report).unwrap()).unwrap();
        });
        let report =
            serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
        (dir.join("floor.model"), report)
    })
}

/// The Python with pymavlink: `$MAVLOC_PYTHON` (the Makefile points it at the venv `make
/// deps` creates), else that venv if it exists, else `python3` on PATH.
pub fn python() -> std::path::PathBuf {
    if let Some(p) = std::env::var_os("MAVLOC_PYTHON").filter(|p| std::path::Path::new(p).exists()) {
        return p.into();
    }
    let venv = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python");
    if venv.exists() {
        venv
    } else {
        "python3".into()
    }
}

/// The coastline flown as a photo survey: a photo every 3.3 s (10 m apart) instead of
/// video at 6 Hz, `frames` photos at 960x540, each photo's gimbal yaw and pitch 3 deg off
/// on its own and GNSS-grade positions (0.3/0.3/0.5 m).
pub fn coastline_photo_survey(frames: usize) -> PathBuf {
    cached(&format!("coastline-photos-{frames}-960x540-3deg"), |out| {
        let mut scenario = Scenario::load("coastline").unwrap();
        scenario.mission.frame_rate_hz = 0.3;
        let noise = mavloc_sim::scenario::NoiseSpec {
            gimbal_yaw_sd_deg: 3.0,
            gimbal_pitch_sd_deg: 3.0,
            position_sd_m: [0.3, 0.3, 0.5],
            ..Default::default()
        };
        let opts = RenderOptions {
            frames: Some(frames),
            size: Some((960, 540)),
            noise: Some(noise),
            ..Default::default()
        };
        render_dataset(&scenario, &opts, out, |_, _| {}).unwrap();
    })
}
