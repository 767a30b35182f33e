//! `render_dataset` writes every file of the format for each scenario, and they parse back.

use mavloc_data::Dataset;
use mavloc_sim::scenario::NoiseSpec;
use mavloc_sim::{render_dataset, RenderOptions, Scenario};

fn render(name: &str, frames: usize, noise: Option<NoiseSpec>) -> (tempfile::TempDir, Dataset) {
    render_at(name, frames, noise, (160, 120))
}

fn render_at(
    name: &str,
    frames: usize,
    noise: Option<NoiseSpec>,
    size: (u32, u32),
) -> (tempfile::TempDir, Dataset) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join(name);
    let opts = RenderOptions { frames: Some(frames), size: Some(size), noise, ..RenderOptions::default() };
    let mut calls = 0;
    let scenario = if name == "indoor-floor" { coarse_indoor() } else { Scenario::load(name).unwrap() };
    let summary = render_dataset(&scenario, &opts, &out, |_, _| calls += 1).unwrap();
    assert_eq!(calls, frames, "progress after every frame");
    assert_eq!(summary.frames + summary.dropped, frames);
    let ds = Dataset::open(&out).unwrap();
    (dir, ds)
}

/// A PNG's size, colour type and pixels.
fn read_png(path: &std::path::Path) -> (u32, u32, png::ColorType, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    (info.width, info.height, info.color_type, buf)
}

/// The indoor scenario with a coarse floor (2 cm texels instead of 5 mm): 1/16 of the
/// texels to generate (a second or two each time), for tests that do not look at them.
fn coarse_indoor() -> Scenario {
    let mut s = Scenario::load("indoor-floor").unwrap();
    s.ground.metres_per_texel = 0.02;
    s
}

#[test]
fn every_scenario_renders_and_parses_back() {
    for name in ["coastline", "cliff", "indoor-floor"] {
        let (_dir, ds) = render(name, 4, None);
        assert_eq!(ds.records.len(), 4, "{name}");
        assert_eq!((ds.camera.width, ds.camera.height), (160, 120));
        for r in &ds.records {
            let (w, h, colour, _) = read_png(&ds.frame_path(r));
            assert_eq!((w, h, colour), (160, 120, png::ColorType::Rgb));
            let (w, h, colour, _) = read_png(&ds.mask_path(r));
            assert_eq!((w, h, colour), (160, 120, png::ColorType::Grayscale));
        }
        for f in ["scenario.toml", "ground_truth.geojson", "mission.plan"] {
            assert!(ds.dir.join(f).exists(), "{name}: {f}");
        }
        let scenario = Scenario::load(ds.dir.join("scenario.toml").to_str().unwrap()).unwrap();
        assert_eq!(scenario.camera.width, 160, "scenario.toml records the overrides");
        if name != "indoor-floor" {
            assert!(!ds.ground_truth.is_empty() && ds.ground_truth[0].len() > 100, "{name}");
            let geo: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(ds.dir.join("ground_truth.geojson")).unwrap())
                    .unwrap();
            assert_eq!(geo["type"], "FeatureCollection");
            // The masks see the target somewhere along the flight.
            let seen = ds.records.iter().any(|r| read_png(&ds.mask_path(r)).3.contains(&255));
            assert!(seen, "{name}: no target in any mask");
        }
    }
}

#[test]
fn noise_is_applied_to_measured_only() {
    let noise = NoiseSpec { gimbal_offset_deg: [0.0, 2.0, 0.0], ..NoiseSpec::default() };
    let (_dir, ds) = render("coastline", 6, Some(noise));
    let mut pitch_diff = 0.0;
    for r in &ds.records {
        pitch_diff += r.measured.gimbal_deg[1] - r.truth.gimbal_deg[1];
        let dz = (r.measured.position[2] - r.truth.position[2]).abs();
        assert!(dz < 10.0);
    }
    let mean = pitch_diff / ds.records.len() as f64;
    assert!((mean - 2.0).abs() < 1.0, "static pitch offset shows: {mean}");
    let (_dir, clean) = render("coastline", 3, Some(NoiseSpec::none()));
    for r in &clean.records {
        assert_eq!(r.truth, r.measured);
    }
}

/// The slowly varying gimbal error wanders as set but hardly changes from one frame to the
/// next (an autopilot's attitude estimate, not jitter): over 300 frames (50 s) at 6 Hz
/// with a 20 s correlation time, frame-to-frame steps are a few hundredths of its SD.
#[test]
fn gimbal_drift_wanders_slowly() {
    let noise = NoiseSpec { gimbal_drift_sd_deg: [3.0, 1.0, 0.0], ..NoiseSpec::none() };
    // Telemetry only: frames as small as a camera may be (300 at 160x120 took 9 s).
    let (_dir, ds) = render_at("coastline", 300, Some(noise), (32, 18));
    let err: Vec<[f64; 3]> = ds
        .records
        .iter()
        .map(|r| std::array::from_fn(|i| r.measured.gimbal_deg[i] - r.truth.gimbal_deg[i]))
        .collect();
    let rms = |f: &dyn Fn(&[f64; 3]) -> f64, v: &[[f64; 3]]| {
        (v.iter().map(|e| f(e).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
    };
    let steps: Vec<[f64; 3]> = err.windows(2).map(|w| std::array::from_fn(|i| w[1][i] - w[0][i])).collect();
    let (yaw, pitch, roll) = (rms(&|e| e[0], &err), rms(&|e| e[1], &err), rms(&|e| e[2], &err));
    // 50 s is a few correlation times: the RMS is of the SD's order, not exact.
    assert!(yaw > 0.8 && yaw < 6.0, "yaw drift RMS {yaw}");
    assert!(pitch > 0.25 && pitch < 2.0, "pitch drift RMS {pitch}");
    assert_eq!(roll, 0.0, "no roll drift was asked for");
    // At 1/6 s of a 20 s correlation time a step is sqrt(2 / 120) = 0.13 SD.
    let step = rms(&|e| e[0], &steps);
    assert!(step < 0.2 * 3.0, "yaw steps {step} deg RMS");
    // Positions are untouched.
    assert!(ds.records.iter().all(|r| r.measured.position == r.truth.position));
}

#[test]
fn refuses_to_overwrite_and_reports_broken_telemetry() {
    let (dir, ds) = render("cliff", 2, None);
    let opts = RenderOptions { frames: Some(1), size: Some((64, 48)), ..RenderOptions::default() };
    let err = render_dataset(&Scenario::load("cliff").unwrap(), &opts, &ds.dir, |_, _| {}).unwrap_err();
    assert!(err.contains("not empty") && err.contains("--force"), "{err}");
    std::fs::write(ds.dir.join("telemetry.jsonl"), "{\"frame\": 0, \"t\": oops}\n").unwrap();
    let err = Dataset::open(&ds.dir).unwrap_err();
    assert!(err.contains("telemetry.jsonl line 1"), "{err}");
    drop(dir);
}

#[test]
fn indoor_views_are_labelled_and_varied() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("views");
    let opts = RenderOptions { views: Some(5), size: Some((96, 72)), ..RenderOptions::default() };
    render_dataset(&coarse_indoor(), &opts, &out, |_, _| {}).unwrap();
    let ds = Dataset::open(&out).unwrap();
    assert_eq!(ds.records.len(), 5);
    for r in &ds.records {
        assert!(r.truth.position[0].abs() <= 4.0 && r.truth.position[1].abs() <= 4.0);
        assert!(r.appearance.is_some(), "each view records its photometric change");
    }
    let err = render_dataset(&Scenario::load("coastline").unwrap(), &opts, &dir.path().join("x"), |_, _| {})
        .unwrap_err();
    assert!(err.contains("indoor"), "{err}");
}

/// `frames_from`: the frames and masks of an earlier render, byte for byte what rendering
/// them again gives, under telemetry drawn with the new noise; a render of another seed,
/// size or scenario, or one that dropped a shot, is refused with the reason.
#[test]
fn frames_from_an_earlier_render_are_the_frames_a_new_render_gives() {
    let dir = tempfile::tempdir().unwrap();
    let scenario = Scenario::load("coastline").unwrap();
    let render = |name: &str, noise: NoiseSpec, size: (u32, u32), seed: Option<u64>, from: Option<&str>| {
        let opts = RenderOptions {
            frames: Some(4),
            size: Some(size),
            seed,
            noise: Some(noise),
            frames_from: from.map(|f| dir.path().join(f)),
            ..RenderOptions::default()
        };
        render_dataset(&scenario, &opts, &dir.path().join(name), |_, _| {})
            .map(|_| Dataset::open(&dir.path().join(name)).unwrap())
    };
    let quiet = NoiseSpec::default();
    let offset =
        NoiseSpec { gimbal_offset_deg: [1.5, -2.0, 0.5], gimbal_yaw_sd_deg: 1.0, ..NoiseSpec::default() };
    render("base", quiet.clone(), (96, 54), None, None).unwrap();
    let reused = render("reused", offset.clone(), (96, 54), None, Some("base")).unwrap();
    let fresh = render("fresh", offset.clone(), (96, 54), None, None).unwrap();
    assert_eq!(reused.records, fresh.records, "the telemetry of the new noise");
    assert_eq!(reused.records.len(), 4);
    for r in &fresh.records {
        for (a, b) in [(fresh.frame_path(r), reused.frame_path(r)), (fresh.mask_path(r), reused.mask_path(r))]
        {
            assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap(), "{}", b.display());
        }
    }
    let err = |r: Result<Dataset, String>| r.map(|_| ()).unwrap_err();
    let e = err(render("bigger", offset.clone(), (128, 72), None, Some("base")));
    assert!(e.contains("size 96x54 (this render: 128x72)") && e.contains("render the frames anew"), "{e}");
    let e = err(render("reseeded", offset.clone(), (96, 54), Some(7), Some("base")));
    assert!(e.contains("seed 1 (this render: 7)"), "{e}");
    assert!(!dir.path().join("reseeded").exists(), "a refused render leaves nothing");
    // Another scenario is named as such (its seed differs too).
    let opts = RenderOptions {
        frames: Some(4),
        size: Some((96, 54)),
        frames_from: Some(dir.path().join("base")),
        ..RenderOptions::default()
    };
    let e = render_dataset(&Scenario::load("cliff").unwrap(), &opts, &dir.path().join("cliff"), |_, _| {})
        .map(|_| ())
        .unwrap_err();
    assert!(e.contains("scenario \"coastline\" (this render: \"cliff\")"), "{e}");
    let dropping = NoiseSpec { drop_rate: 0.5, ..NoiseSpec::default() };
    let sparse = render("sparse", dropping, (96, 54), None, None).unwrap();
    assert!(sparse.records.len() < 4, "the seed's draws drop a frame of four");
    let e = err(render("from-sparse", offset, (96, 54), None, Some("sparse")));
    assert!(e.contains("has no frame") && e.contains("dropped"), "{e}");
}
