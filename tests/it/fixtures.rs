//! Fixtures several test modules share: datasets the simulator renders and the small
//! indoor model, built once and cached in cargo's test scratch folder (`target/tmp`).
//! A rendered dataset is stamped with the renderer's inputs (the sources of the simulator
//! and of the crates it uses, its scenarios and textures, and `Cargo.lock`), so a change
//! elsewhere in mavloc does not render again (about a minute each time); a model is
//! stamped with the trainer's inputs (mavloc's library sources and the crates it uses, and
//! the views it was trained on), so a change to the tests alone does not train again
//! (38 s of CPU for the two models). Rendering and training are deterministic, so a
//! cached fixture is the one the test would make.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use mavloc::indoor::offline::{train, Labelling, TrainOptions, TrainReport};
use mavloc_sim::{render_dataset, RenderOptions, Scenario};

pub const BIN: &str = env!("CARGO_BIN_EXE_mavloc");

/// `c` with SIGINT at its default action in the child, as Ctrl-C at a terminal finds it. A
/// test that interrupts a command must not depend on how the suite was started: a
/// background job of a script starts with SIGINT ignored, which the child inherits, and
/// mavloc then keeps ignoring it as a background job should (CI started that way failed
/// both Ctrl-C tests, session 33).
pub fn ctrl_c_reaches(c: &mut std::process::Command) -> &mut std::process::Command {
    use std::os::unix::process::CommandExt;
    // SAFETY: signal(2) only, between fork and exec.
    unsafe {
        c.pre_exec(|| {
            libc::signal(libc::SIGINT, libc::SIG_DFL);
            Ok(())
        })
    }
}

/// A hash of the files under `dirs` and of `files` (relative to the project root): what a
/// fixture built from them depends on. A file missed here would leave a stale fixture, so
/// it is whole folders, not a list of files. A file that cannot be read (a dangling link,
/// an editor's lock) counts by its name and the error.
///
/// The files are read when a test first asks, not when this binary was built: if one of
/// them changed since the build (an edit while the tests run), the binary's identity goes
/// into the stamp too, so what this binary makes is never taken for what the edited
/// sources would make.
fn sources_stamp(dirs: &[&str], files: &[&str]) -> String {
    use std::hash::{Hash, Hasher};
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, out);
            } else {
                out.push(p);
            }
        }
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut paths: Vec<PathBuf> = files.iter().map(|f| root.join(f)).collect();
    for dir in dirs {
        walk(&root.join(dir), &mut paths);
    }
    let exe = std::fs::metadata(std::env::current_exe().unwrap()).unwrap();
    let built = exe.modified().unwrap();
    let mut h = std::collections::hash_map::DefaultHasher::new();
    let mut edited_since = false;
    for f in paths {
        f.strip_prefix(root).unwrap().hash(&mut h);
        match std::fs::read(&f) {
            Ok(bytes) => bytes.hash(&mut h),
            Err(e) => e.kind().hash(&mut h),
        }
        edited_since |= std::fs::metadata(&f).and_then(|m| m.modified()).is_ok_and(|t| t > built);
    }
    if edited_since {
        format!("{:016x} built {} {built:?}", h.finish(), exe.len())
    } else {
        format!("{:016x}", h.finish())
    }
}

/// What a rendered dataset depends on: the simulator crate, the geometry and data crates
/// it uses, the locked dependency versions.
fn renderer_stamp() -> &'static str {
    static STAMP: OnceLock<String> = OnceLock::new();
    STAMP.get_or_init(|| {
        let dirs = ["sim/src", "sim/scenarios", "sim/assets", "src/geometry", "data"];
        format!("renderer {}", sources_stamp(&dirs, &["Cargo.lock", "sim/Cargo.toml"]))
    })
}

/// What a trained model depends on besides its views and settings: the trainer is
/// mavloc's library (its whole source tree, which holds the geometry crate) and the crates
/// of this workspace it uses, built with the locked dependency versions and the manifests.
fn trainer_stamp() -> &'static str {
    static STAMP: OnceLock<String> = OnceLock::new();
    STAMP.get_or_init(|| {
        let files = ["Cargo.lock", "Cargo.toml", "sim/Cargo.toml"];
        // The Debian OpenCV it links decodes and filters the frames.
        let opencv = opencv::core::get_version_string().unwrap();
        format!("trainer {} opencv {opencv}", sources_stamp(&["src", "data", "sim/src"], &files))
    })
}

/// Builds `key` with `make` (which writes into the folder it is given) unless it was built
/// with the same `stamp`. Serialised, within this process and with any other test process
/// (`make test` runs two at once, the Makefile's `test`): fixtures are CPU-bound and used
/// read-only.
fn cached(key: &str, stamp: &str, make: impl FnOnce(&Path)) -> PathBuf {
    use std::os::fd::AsRawFd;
    static LOCK: Mutex<()> = Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fixtures");
    std::fs::create_dir_all(&root).unwrap();
    // Held until this function returns (closing the file releases it).
    let lock = std::fs::File::create(root.join(".lock")).unwrap();
    // SAFETY: flock(2) on a descriptor this function owns.
    assert_eq!(unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX) }, 0, "flock the fixtures");
    let dir = root.join(key);
    let stamp_file = stamp_of(&dir);
    if dir.is_dir() && std::fs::read_to_string(&stamp_file).ok().as_deref() == Some(stamp) {
        return dir;
    }
    // Built beside, then renamed: an interrupted run never leaves a half fixture.
    let partial = root.join(format!("{key}.partial"));
    let _ = std::fs::remove_dir_all(&partial);
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_file(&stamp_file);
    make(&partial);
    std::fs::rename(&partial, &dir).unwrap();
    std::fs::write(&stamp_file, stamp).unwrap();
    dir
}

/// Where the stamp of the fixture in `dir` is kept: beside it.
fn stamp_of(dir: &Path) -> PathBuf {
    dir.with_file_name(format!("{}.stamp", dir.file_name().unwrap().to_string_lossy()))
}

/// A dataset of `scenario` rendered with `opts`; `key` names the options.
pub fn rendered(key: &str, scenario: &str, opts: &RenderOptions) -> PathBuf {
    render_cached(key, &Scenario::load(scenario).unwrap(), opts)
}

/// `scenario` rendered with `opts` under `key`, stamped with the renderer's inputs and
/// with the scenario and options themselves (a test that changes them renders again).
fn render_cached(key: &str, scenario: &Scenario, opts: &RenderOptions) -> PathBuf {
    let stamp = format!("{}\n{scenario:?}\n{opts:?}", renderer_stamp());
    cached(key, &stamp, |out| {
        render_dataset(scenario, opts, out, |_, _| {}).unwrap();
    })
}

/// `scenario` with `opts` under `key`, its frames and masks copied from the fixture
/// `frames` (rendered from the same scenario, seed and size: `RenderOptions::frames_from`),
/// only the telemetry drawn: another noise over the same flight costs no rendering.
pub fn renoised(key: &str, frames: &Path, scenario: &str, opts: &RenderOptions) -> PathBuf {
    let scenario = Scenario::load(scenario).unwrap();
    let opts = RenderOptions { frames_from: Some(frames.to_path_buf()), ..opts.clone() };
    let of_frames = std::fs::read_to_string(stamp_of(frames)).unwrap();
    let stamp = format!("{}\n{scenario:?}\n{opts:?}\nframes: {of_frames}", renderer_stamp());
    cached(key, &stamp, |out| {
        render_dataset(&scenario, &opts, out, |_, _| {}).unwrap();
    })
}

/// `frames` frames of `scenario`'s flight with the seed's noise at 480x270.
pub fn small_flight(scenario: &str, frames: usize) -> PathBuf {
    let opts = RenderOptions { frames: Some(frames), size: Some((480, 270)), ..RenderOptions::default() };
    rendered(&format!("{scenario}-{frames}-480x270"), scenario, &opts)
}

/// The coastline's first 100 frames at 960x540 as photos: every frame's gimbal yaw and
/// pitch 3 deg off on its own, GNSS-grade positions (0.3/0.3/0.5 m).
pub fn coastline_photo_noise_flight() -> PathBuf {
    let noise = mavloc_sim::scenario::NoiseSpec {
        gimbal_yaw_sd_deg: 3.0,
        gimbal_pitch_sd_deg: 3.0,
        position_sd_m: [0.3, 0.3, 0.5],
        ..Default::default()
    };
    let opts =
        RenderOptions { frames: Some(100), size: Some((960, 540)), noise: Some(noise), ..Default::default() };
    rendered("coastline-100-960x540-photo-noise", "coastline", &opts)
}

/// A coastline flight with exact telemetry but a static gimbal offset (yaw 1.5, pitch -2,
/// roll 0.5 deg), rendered once per build of the tests.
pub fn offset_flight() -> std::path::PathBuf {
    let noise = mavloc_sim::scenario::NoiseSpec {
        gimbal_yaw_sd_deg: 0.0,
        gimbal_pitch_sd_deg: 0.0,
        position_sd_m: [0.0; 3],
        gimbal_offset_deg: [1.5, -2.0, 0.5],
        ..Default::default()
    };
    let opts = mavloc_sim::RenderOptions {
        frames: Some(100),
        size: Some((960, 540)),
        noise: Some(noise),
        ..Default::default()
    };
    // The photo-noise flight's frames (`coastline_photo_noise_flight`), under this noise's telemetry.
    let frames = crate::fixtures::coastline_photo_noise_flight();
    crate::fixtures::renoised("coastline-100-960x540-gimbal-offset", &frames, "coastline", &opts)
}

/// A flight over the indoor floor at 0.5 m instead of 1 m (0.4-0.6 m with its swing), the
/// heights a vehicle climbs and descends through, 320x240.
pub fn low_indoor_flight(frames: usize) -> PathBuf {
    let mut scenario = Scenario::load("indoor-floor").unwrap();
    scenario.mission.altitude_m = 0.5;
    let opts = RenderOptions { frames: Some(frames), size: Some((320, 240)), ..Default::default() };
    render_cached(&format!("indoor-floor-flight-{frames}-320x240-at-0.5m"), &scenario, &opts)
}

/// 400 random views of the indoor floor at 320x240: the training set of the small model.
pub fn indoor_views() -> PathBuf {
    let opts = RenderOptions { views: Some(400), size: Some((320, 240)), ..Default::default() };
    rendered("indoor-floor-views-400-320x240", "indoor-floor", &opts)
}

/// The indoor floor's orthophoto, 4 m each way from its centre at 5 mm a pixel (1600x1600),
/// as `floor.png`: rendered once per build of the tests.
pub fn indoor_orthophoto() -> PathBuf {
    let scenario = Scenario::load("indoor-floor").unwrap();
    let stamp = format!("{}\n{scenario:?}\northophoto 4.0 m 0.005 m", renderer_stamp());
    let dir = cached("indoor-floor-orthophoto-4m-5mm", &stamp, |out| {
        std::fs::create_dir_all(out).unwrap();
        let world = mavloc_sim::World::build(&scenario).unwrap();
        let (w, h, rgb) = world.orthophoto(4.0, 0.005);
        let png = out.join("floor.png");
        mavloc_data::pngfile::write(&png, w as u32, h as u32, &rgb, mavloc_data::pngfile::Channels::Rgb)
            .unwrap();
    });
    dir.join("floor.png")
}

/// The small indoor model the live indoor flights use, trained on [`indoor_views`] with
/// the default settings.
pub fn small_indoor_model() -> &'static Path {
    &small_indoor_training().0
}

/// [`small_indoor_model`] and what its training reported, for every test that trains with
/// the default settings on these views: trained again only when the trainer or the views
/// change.
pub fn small_indoor_training() -> &'static (PathBuf, TrainReport) {
    static MODEL: OnceLock<(PathBuf, TrainReport)> = OnceLock::new();
    MODEL.get_or_init(|| {
        let dir = trained_on_views("indoor-floor-model-400", &mavloc::settings::Indoor::default());
        let report =
            serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
        (dir.join("floor.model"), report)
    })
}

/// A model trained on [`indoor_views`] without rescaling to a reference height
/// (`height_ref_m` < 0): what the rescaled default is compared against. Cached like
/// [`small_indoor_model`]: training is half of that comparison's time.
pub fn plain_indoor_model() -> PathBuf {
    let settings = mavloc::settings::Indoor { height_ref_m: -1.0, ..Default::default() };
    trained_on_views("indoor-floor-model-400-plain", &settings).join("floor.model")
}

/// A folder with `floor.model`, trained on [`indoor_views`] with `settings`, and its
/// training's `report.json`, under `key`: trained again only when the trainer or the
/// views change.
fn trained_on_views(key: &str, settings: &mavloc::settings::Indoor) -> PathBuf {
    let views = indoor_views();
    let of_views = std::fs::read_to_string(stamp_of(&views)).unwrap();
    let (labelling, seed) = (Labelling::Telemetry, 1);
    let stamp = format!("{}\n{settings:?}\n{labelling:?} seed {seed}\nviews: {of_views}", trainer_stamp());
    cached(key, &stamp, |out| {
        std::fs::create_dir_all(out).unwrap();
        let opts = TrainOptions { dataset: views, out: out.join("floor.model"), labelling, seed };
        let report = train(&opts, settings, |_, _| {}).unwrap();
        std::fs::write(out.join("report.json"), serde_json::to_string(&report).unwrap()).unwrap();
    })
}

/// Reads a child's output to its end on a thread of its own, so the child never blocks on
/// a full pipe (64 KB) while the test waits for it to exit: a relay that printed more
/// than that hung until the test's time limit.
pub fn read_in_background(mut from: impl std::io::Read + Send + 'static) -> std::thread::JoinHandle<String> {
    std::thread::spawn(move || {
        let mut out = String::new();
        from.read_to_string(&mut out).expect("the child's output is UTF-8");
        out
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
    render_cached(&format!("coastline-photos-{frames}-960x540-3deg"), &scenario, &opts)
}
