//! The area pipeline end to end on short rendered flights with the seed's noise (gimbal
//! 0.5 deg, position 0.5/0.5/2 m): accuracy bounds that catch a regression, and the
//! ground-plane baseline on the same data for comparison. Small frames (480x270, band
//! 13 px) keep it quick; the full-size figures are in the README.

use mavloc::area::eval::{evaluate, AreaEvaluation};
use mavloc::area::offline::{run, RunOptions};
use mavloc::output::parse_landmarks_csv;
use mavloc::settings::{AreaMethod, Settings};
use mavloc_data::results::parse_border_csv;
use mavloc_data::Dataset;
use mavloc_sim::RenderOptions;

/// The flight, rendered once per build of the tests (see `fixtures`).
fn render(name: &str, frames: usize) -> std::path::PathBuf {
    crate::fixtures::small_flight(name, frames)
}

fn settings() -> Settings {
    let mut s = Settings::default();
    s.area.downscale = 1;
    s.area.band_px = 13;
    s
}

fn run_and_eval(dataset: &std::path::Path, out: &std::path::Path, method: AreaMethod) -> AreaEvaluation {
    run_and_eval_with(dataset, out, method, &settings()).0
}

/// [`run_and_eval`] with `s`, and the run's summary.
fn run_and_eval_with(
    dataset: &std::path::Path,
    out: &std::path::Path,
    method: AreaMethod,
    s: &Settings,
) -> (AreaEvaluation, mavloc::area::offline::RunSummary) {
    let opts = RunOptions {
        dataset: dataset.into(),
        out: out.into(),
        method,
        trace: false,
        max_frames: None,
        debug_masks: false,
    };
    let summary = run(&opts, s, |_, _| {}).unwrap();
    assert!(summary.complete);
    let landmarks =
        parse_landmarks_csv(&std::fs::read_to_string(out.join("landmarks.csv")).unwrap(), "landmarks.csv")
            .unwrap();
    let border = parse_border_csv(&std::fs::read_to_string(out.join("border.csv")).unwrap());
    let ds = Dataset::open(dataset).unwrap();
    for f in ["landmarks.ply", "area.geojson", "area.kml", "summary.json"] {
        assert!(out.join(f).exists(), "{f}");
    }
    (evaluate(&landmarks, &ds.ground_truth, &border, summary.frames_per_s), summary)
}

/// On the flat coastline the ground-plane assumption holds exactly at the shore, so the
/// baseline is good there too: it is not run here (the cliff's test compares them).
///
/// The same run asks for the attitude refinement: on the seed's video noise (2 m of height
/// noise per frame, the positions held) the solution that fits it best turns the whole
/// flight by a 24 deg pitch offset and puts the map 20-30 m off (issue found by a user's
/// run of the README's command). It is refused by name and the results are the filters'
/// landmarks, which is what the accuracy bounds measure. (One run for both: the filters
/// are most of its time.)
#[test]
fn coastline_short_flight_is_accurate_and_a_refinement_that_turns_the_whole_flight_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ds = render("coastline", 240);
    let mut s = settings();
    s.area.attitude_prior_deg = 2.0;
    let (ukf, summary) = run_and_eval_with(&ds, &dir.path().join("ukf"), AreaMethod::Ukf, &s);
    let why = summary.refined_rejected.clone().expect("refused");
    println!("coastline ukf:\n{ukf}\nrefinement: {why}");
    assert!(why.contains("static gimbal offset") || why.contains("would turn"), "{why}");
    assert_eq!(summary.refined_gimbal_offset_deg, None, "no offset offered to copy into the configuration");
    // 131 landmarks at 1.28 m mean (the filters'); the refused solution had them 20 m off.
    assert!(ukf.landmarks >= 100, "{ukf}");
    assert_eq!(ukf.gt20, 0, "{ukf}");
    assert!(ukf.mean_m <= 2.0, "{ukf}");
    assert!(ukf.border_mean_m <= 2.0, "{ukf}");
}

#[test]
fn cliff_short_flight_is_accurate_where_the_ground_plane_fails() {
    let dir = tempfile::tempdir().unwrap();
    let ds = render("cliff", 360);
    let ukf = run_and_eval(&ds, &dir.path().join("ukf"), AreaMethod::Ukf);
    let plane = run_and_eval(&ds, &dir.path().join("plane"), AreaMethod::GroundPlane);
    println!("cliff ukf:\n{ukf}\ncliff ground plane:\n{plane}");
    // 32 landmarks before the ray check (src/area/rays.rs), 26 with it, as accurate
    // (1.32 -> 1.42 m mean, the same 2.76 m max): the count is a floor, accuracy the point.
    assert!(ukf.landmarks >= 20, "{ukf}");
    assert_eq!(ukf.gt20, 0, "{ukf}");
    assert!(ukf.mean_m <= 3.0, "{ukf}");
    assert!(plane.mean_m > 2.0 * ukf.mean_m, "ukf {:.2} m vs ground plane {:.2} m", ukf.mean_m, plane.mean_m);
}

/// `--trace` writes every landmark update; with it, `mavloc eval area` on a rendered
/// dataset sets the landmarks against the point their sightings fix from the true poses,
/// at the pixels' scale (here half size: taken at full size, the same rays missed by 27 m
/// on average against 0.54 m). The 240-frame flight the short-flight test renders (30
/// frames converge no landmark).
#[test]
fn trace_records_every_update() {
    let dir = tempfile::tempdir().unwrap();
    let ds = render("coastline", 240);
    let out = dir.path().join("traced");
    let opts = traced(&ds, &out);
    let mut s = settings();
    s.area.downscale = 2;
    run(&opts, &s, |_, _| {}).unwrap();
    let trace = std::fs::read_to_string(out.join("trace.csv")).unwrap();
    let rows: Vec<&str> = trace.lines().skip(1).collect();
    assert!(rows.len() > 100, "{} updates traced", rows.len());
    assert!(rows.iter().all(|r| r.split(',').count() == 19));
    // Each landmark's first sighting is a row too, with no prediction or gate distance:
    // one per landmark, before its updates, at the frame landmarks.csv says it began.
    let mut first: std::collections::HashMap<&str, (usize, u64)> = Default::default();
    for (i, r) in rows.iter().enumerate() {
        let f: Vec<&str> = r.split(',').collect();
        if f[6].is_empty() {
            assert!(f[7].is_empty() && f[8].is_empty() && f[9] == "1", "{r}");
            assert!(
                first.insert(f[1], (i, f[0].parse().unwrap())).is_none(),
                "landmark {} created twice",
                f[1]
            );
        }
    }
    for (i, r) in rows.iter().enumerate() {
        let id = r.split(',').nth(1).unwrap();
        let created = first.get(id).unwrap_or_else(|| panic!("landmark {id} updated, never created: {r}"));
        assert!(created.0 <= i, "landmark {id} updated before it was created");
    }
    let landmarks =
        parse_landmarks_csv(&std::fs::read_to_string(out.join("landmarks.csv")).unwrap(), "landmarks.csv")
            .unwrap();
    assert!(!landmarks.is_empty());
    for l in &landmarks {
        assert_eq!(
            first.get(l.id.to_string().as_str()).map(|c| c.1),
            Some(l.first_frame),
            "landmark {}",
            l.id
        );
    }
    // `mavloc eval area` sets the traced landmarks against the true poses' fix of them
    // (the rendered dataset's `true` poses), at the trace's scale (summary.json's downscale).
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["downscale"], serde_json::json!(2));
    let eval = std::process::Command::new(crate::fixtures::BIN)
        .args(["eval", "area", "--json", "--dataset"])
        .arg(&ds)
        .arg("--result")
        .arg(&out)
        .env_remove("MAVLOC_CONFIG")
        .output()
        .unwrap();
    assert!(eval.status.success(), "{}", String::from_utf8_lossy(&eval.stderr));
    let e: serde_json::Value = serde_json::from_slice(&eval.stdout).unwrap();
    let (n, all) = (e["true_fix_landmarks"].as_u64().unwrap(), e["landmarks"].as_u64().unwrap());
    assert!(n > 0 && 2 * n >= all, "{n} of {all} landmarks set against the true poses");
    // The seed's noise (0.5 deg, 0.5/0.5/2 m), filters alone: about half a metre.
    let mean = e["true_fix_mean_m"].as_f64().unwrap();
    assert!(mean > 0.0 && mean < 2.0, "{mean}");
}

/// The UKF pipeline over `ds` into `out` with `s`: its landmarks against the ground
/// truth (no border, no speed), and the run's summary.
fn ukf_against_truth(
    ds: &std::path::Path,
    out: &std::path::Path,
    s: &Settings,
) -> (AreaEvaluation, mavloc::area::offline::RunSummary) {
    let o = RunOptions {
        dataset: ds.into(),
        out: out.into(),
        method: AreaMethod::Ukf,
        trace: false,
        max_frames: None,
        debug_masks: false,
    };
    let summary = run(&o, s, |_, _| {}).unwrap();
    let landmarks =
        parse_landmarks_csv(&std::fs::read_to_string(out.join("landmarks.csv")).unwrap(), "").unwrap();
    let truth = Dataset::open(ds).unwrap().ground_truth;
    (evaluate(&landmarks, &truth, &[], 1.0), summary)
}

/// Photo-like poses: every frame's attitude 3 deg off on its own, GNSS-grade positions
/// (0.3/0.3/0.5 m). The landmark filters alone leave metres of error; refining each
/// frame's attitude with the landmarks (`area.attitude_prior_deg`) brings the mean under
/// half and the worst under 6 m. (On the seed's video noise, 2 m of height noise
/// per frame, refinement does not help; it is off by default and on for photo surveys.)
#[test]
fn attitude_refinement_recovers_photo_like_attitude_errors() {
    let dir = tempfile::tempdir().unwrap();
    let ds = crate::fixtures::coastline_photo_noise_flight();
    let eval = |prior: f64, name: &str| {
        let out = dir.path().join(name);
        let mut s = Settings::default();
        s.area.attitude_prior_deg = prior;
        // The flight's own position noise (the ray check counts it).
        s.area.position_noise_m = vec![0.3, 0.3, 0.5];
        // The seed's threshold: told 0.5 deg bearings under 3 deg attitude errors, the
        // filters pass a looser one with landmarks whose error 100 frames of refinement
        // cannot take out (0.75 m: 57 landmarks, 3.02 -> 2.11 m; 0.5 m: 31, 2.64 -> 1.17 m).
        s.area.convergence_m = 0.5;
        ukf_against_truth(&ds, &out, &s)
    };
    let (plain, _) = eval(0.0, "plain");
    let (refined, summary) = eval(2.0, "refined");
    println!("filters alone:\n{plain}\nrefined:\n{refined}");
    assert_eq!(refined.landmarks, plain.landmarks, "the same landmarks, moved");
    assert!(refined.mean_m < 0.5 * plain.mean_m, "mean {:.2} -> {:.2} m", plain.mean_m, refined.mean_m);
    // The filters' 21 m tail on this flight is set aside by the ray check before
    // refinement (28 -> 18 landmarks); refinement still shrinks the worst.
    assert!(
        refined.max_m < 6.0 && refined.max_m < plain.max_m,
        "max {:.2} -> {:.2} m",
        plain.max_m,
        refined.max_m
    );
    let (before, after) =
        (summary.refined_median_before_px.unwrap(), summary.refined_median_after_px.unwrap());
    assert!(after < 0.2 * before, "sightings reproject {before:.1} -> {after:.1} px");
    assert!(dir.path().join("refined/attitude.csv").exists());
}

/// A photo survey (the coastline, a photo every 10 m, each photo's gimbal 3 deg off on
/// its own) with the photo-survey settings: aligning the photos by their tie points first
/// (`area.align_prior_deg`, `area::align`) lets the filters converge on twice the
/// landmarks, and puts them where the shore is (14 photos: 129 landmarks at 5.2 m mean
/// without, 267 at 1.1 m with).
#[test]
fn aligning_photos_by_their_tie_points_doubles_the_landmarks_and_halves_their_error() {
    let ds = crate::fixtures::coastline_photo_survey(14);
    let dir = tempfile::tempdir().unwrap();
    let survey = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/photo-survey.toml");
    let eval = |align: f64, name: &str| {
        let layers = mavloc::settings::Layers {
            file: None,
            dataset: Some(survey.clone()),
            env: Default::default(),
            overrides: vec![
                // The rendered masks, and the band at this resolution (the survey file's
                // 150 px are for 4000 px photos: here they would put landmarks 12 m inland).
                "area.segmenter=masks".into(),
                "area.band_px=25".into(),
                "area.downscale=1".into(),
                "area.attitude_prior_deg=0".into(),
                format!("area.align_prior_deg={align}"),
            ],
        };
        let s = mavloc::settings::load(&layers).unwrap().settings;
        let out = dir.path().join(name);
        ukf_against_truth(&ds, &out, &s)
    };
    let (plain, _) = eval(0.0, "tagged");
    let (aligned, summary) = eval(5.0, "aligned");
    println!("as tagged:\n{plain}\naligned:\n{aligned}\n{summary:?}");
    assert_eq!(summary.aligned_photos, Some(14), "{summary:?}");
    assert!(summary.align_median_after_px.unwrap() < 0.5, "{summary:?}");
    assert!(
        aligned.landmarks >= 2 * plain.landmarks - 10,
        "{} -> {} landmarks",
        plain.landmarks,
        aligned.landmarks
    );
    assert!(
        aligned.mean_m < 0.4 * plain.mean_m && aligned.mean_m < 1.5,
        "mean {:.2} -> {:.2} m",
        plain.mean_m,
        aligned.mean_m
    );
}

/// The reverse line, on a survey shaped like the held-back one
/// (`coastline-survey`: three nadir lines of six photos, the middle one flown back, each
/// photo's gimbal 3 deg off): tagged as flown, no photo is turned; with the middle line's
/// yaw tagged half a turn off (the DJI survey's tags were 177-179 deg off on its reverse
/// line), the import's overlap check (`area::imageup`, consecutive photos as
/// `mavloc import photos` pairs them) turns exactly that line's six photos, before any
/// landmark exists.
#[test]
fn a_surveys_reverse_line_tagged_half_a_turn_off_is_found_by_the_overlap() {
    use mavloc::area::imageup;
    let opts = RenderOptions { size: Some((1000, 562)), ..RenderOptions::default() };
    let dir = crate::fixtures::rendered("coastline-survey-1000x562", "coastline-survey", &opts);
    let ds = Dataset::open(&dir).unwrap();
    assert_eq!(ds.records.len(), 18);
    let k = ds.camera.intrinsics();
    let features: Vec<_> = ds
        .records
        .iter()
        .map(|r| {
            let img =
                mavloc::imaging::read_image(&ds.frame_path(r), opencv::imgcodecs::IMREAD_COLOR).unwrap();
            imageup::features(&img).unwrap()
        })
        .collect();
    let turned = |flip_middle: bool| {
        let poses: Vec<_> = ds
            .records
            .iter()
            .map(|r| {
                let mut m = r.measured;
                if flip_middle && (6..12).contains(&r.frame) {
                    m.gimbal_deg[0] += 180.0;
                }
                ds.camera_pose(&m, [0.0; 3])
            })
            .collect();
        let votes: Vec<_> = (1..poses.len())
            .filter_map(|i| {
                imageup::vote((i - 1, &features[i - 1], &poses[i - 1]), (i, &features[i], &poses[i]), &k, 0.0)
                    .unwrap()
            })
            .collect();
        imageup::verdicts(poses.len(), &votes)
    };
    assert!(turned(false).iter().all(|t| !t), "{:?}", turned(false));
    let expected: Vec<bool> = (0..18).map(|f| (6..12).contains(&f)).collect();
    assert_eq!(turned(true), expected);
}

/// The photo-survey path end to end on a survey shaped like the held-back one
/// (`coastline-survey` at a quarter of the FC300S's size, 1000x562, three nadir lines, each
/// photo's gimbal 3 deg off): the photos are aligned by their tie points, the water
/// segmenter finds the lake, landmarks converge along the shore on the true ground, and
/// the landmarks seen from two lines lie metres apart with the tags and within centimetres
/// aligned (measured, session 28: 147 landmarks, 0.97 m mean from the true shoreline, +0.06 m
/// above the true surface, 107 pairs 10.71 m -> 0.05 m). The height guards the alignment's match
/// gate: without it the simulator's mirrored ground linked photos that never overlapped
/// and the whole map floated +1.01 m (1.56 m mean). The band is the survey settings' 150
/// px scaled to the quarter-size photo.
///
/// A full-size run (18 photos of a million pixels, 11 s of CPU): in `make check-long`. The
/// suite keeps the parts on smaller inputs: the reverse line's overlap check on the same
/// photos (above), the tie-point alignment on one line
/// (`aligning_photos_by_their_tie_points_doubles_the_landmarks_and_halves_their_error`),
/// and two lines' agreement on real photos (`import_photos::seneca_lines_agree_*`).
#[test]
#[ignore = "a full-size photo survey: make check-long"]
fn a_rendered_three_line_survey_runs_with_the_photo_settings() {
    let opts = RenderOptions { size: Some((1000, 562)), ..RenderOptions::default() };
    let dir = crate::fixtures::rendered("coastline-survey-1000x562", "coastline-survey", &opts);
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/photo-survey.toml");
    let layers = mavloc::settings::Layers {
        file: Some(file),
        dataset: None,
        env: Default::default(),
        overrides: vec!["area.band_px=38".into()],
    };
    let s = mavloc::settings::load(&layers).unwrap().settings;
    let out = tempfile::tempdir().unwrap();
    let opts = traced(&dir, out.path());
    let summary = run(&opts, &s, |_, _| {}).unwrap();
    let landmarks = parse_landmarks_csv(
        &std::fs::read_to_string(out.path().join("landmarks.csv")).unwrap(),
        "landmarks.csv",
    )
    .unwrap();
    let border = parse_border_csv(&std::fs::read_to_string(out.path().join("border.csv")).unwrap());
    let ds = Dataset::open(&dir).unwrap();
    let surface = mavloc::simulated::surface::true_surface(&dir).unwrap().expect("a rendered dataset");
    let e = evaluate(&landmarks, &ds.ground_truth, &border, summary.frames_per_s)
        .with_surface(&landmarks, surface);
    println!("{e}\n{summary:?}");
    assert!(summary.aligned_photos >= Some(17), "{summary:?}");
    assert!(e.landmarks >= 60 && e.mean_m <= 1.3 && e.lt10 == e.landmarks, "{e}");
    let height = e.height_median_m.unwrap();
    assert!(height.abs() <= 0.4, "the map floats {height:+.2} m above the true ground");
    assert_eq!(summary.flight_lines, Some(3));
    assert!(summary.cross_line_pairs >= Some(50), "{summary:?}");
    let (tagged, aligned) =
        (summary.cross_line_tagged_median_m.unwrap(), summary.cross_line_median_m.unwrap());
    assert!(tagged > 4.0 && aligned < 0.2, "two lines {tagged:.2} m apart as tagged, {aligned:.2} m aligned");
}

/// The daemon's map adjusted after landing (`daemon::flightlog`): a live run over a flight
/// whose reported gimbal angles are a static offset off (yaw 1.5, pitch -2, roll 0.5 deg),
/// then the touchdown. The adjustment finds the offset, the set written after it holds
/// the adjusted landmarks (closer to the true shore than the filters'), and they are what
/// `mavloc area` with the same settings makes of the same frames offline: the live log
/// kept every sighting and each frame's pose.
///
/// Beside it, the same frames live with `area.adjust_first_frames` = 30: at 30 frames
/// nothing has converged and the next try is at 60, where the map is adjusted in flight
/// and the offset found is added to the frames after it; the landmarks that converge after
/// that lie closer to the true shore than the same frames' landmarks without it.
#[test]
fn the_map_adjusted_after_landing_finds_a_wrong_gimbal_offset_as_the_offline_run_does_and_in_flight_takes_it_out_of_later_frames(
) {
    use mavloc::align::{AlignedPose, VehicleSample};
    use mavloc::daemon::live::AreaLive;
    use mavloc::daemon::worker::{LiveFrame, LivePipeline, PipelineEvent};
    use opencv::imgcodecs;

    let ds_dir = crate::fixtures::offset_flight();
    let ds = Dataset::open(&ds_dir).unwrap();
    let mut s = Settings::default();
    s.area.attitude_prior_deg = 1.0;
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("results/area");
    let mut live = AreaLive::new(&s, ds.camera.intrinsics(), ds.camera.origin, &link, "run").unwrap();
    let in_flight_link = dir.path().join("in-flight/results/area");
    let mut in_flight = {
        let mut s = s.clone();
        s.area.adjust_first_frames = 30;
        AreaLive::new(&s, ds.camera.intrinsics(), ds.camera.origin, &in_flight_link, "run").unwrap()
    };
    let landmarks = |dir: &std::path::Path| {
        parse_landmarks_csv(&std::fs::read_to_string(dir.join("landmarks.csv")).unwrap(), "").unwrap()
    };
    let (mut applied_from, mut said, mut adjusted_in_flight) =
        (None, Vec::new(), std::collections::BTreeSet::new());
    for r in &ds.records {
        let read = |p: std::path::PathBuf, flags| mavloc::imaging::read_image(&p, flags).unwrap();
        let camera = ds.camera_pose(&r.measured, s.gimbal.offsets_deg());
        let a = r.measured.attitude_deg.map(f64::to_radians);
        let frame = LiveFrame {
            index: r.frame,
            capture_s: r.t,
            pose: AlignedPose {
                autopilot_time: r.t,
                vehicle: VehicleSample {
                    position: r.measured.position.into(),
                    velocity: r.measured.velocity.into(),
                    attitude: nalgebra::UnitQuaternion::from_euler_angles(a[0], a[1], a[2]),
                },
                camera,
                from_gimbal: true,
            },
            image: read(ds.frame_path(r), imgcodecs::IMREAD_COLOR),
            mask: Some(read(ds.mask_path(r), imgcodecs::IMREAD_GRAYSCALE)),
            origin: None,
            truth: None,
            motion_only: false,
        };
        assert!(live.process(&frame).processed, "frame {}", r.frame);
        let report = in_flight.process(&frame);
        if report.events.iter().any(|e| e.contains("frames logged; adjusting the map")) {
            // Waited for here, so the frames the offset is added to are known.
            let done = wait_for(&mut in_flight);
            said.push((r.frame, done));
            if applied_from.is_none() && in_flight.offset_added().is_some() {
                applied_from = Some(r.frame + 1);
                let set = landmarks(&in_flight_link);
                adjusted_in_flight = set.iter().map(|l| l.id).collect();
            }
        }
    }
    live.write_results().unwrap();
    in_flight.write_results().unwrap();
    let filters = landmarks(&link);
    let summary = |dir: &std::path::Path| -> mavloc::area::offline::RunSummary {
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap()
    };
    assert_eq!(summary(&link).refined_gimbal_offset_deg, None, "nothing adjusted in the air");

    let started = live.adjust_map("landed");
    assert!(
        matches!(&started[..], [PipelineEvent::Note(l)] if l.starts_with("area: landed; adjusting the map")),
        "{started:?}"
    );
    let done = wait_for(&mut live);
    assert!(matches!(&done[..], [PipelineEvent::Note(l)] if l.contains("map adjusted")), "{done:?}");
    let adjusted = landmarks(&link);
    let found = summary(&link);
    assert_eq!(found.gimbal_offset_applied_deg, None, "the offset is added to later frames only when asked");
    assert_eq!(live.offset_added(), None);
    // Offline, the same settings over the same frames: the same map.
    let out = dir.path().join("offline");
    let opts = traced(&ds_dir, &out);
    run(&opts, &s, |_, _| {}).unwrap();
    let offline = landmarks(&out);
    let offset = found.refined_gimbal_offset_deg.unwrap();
    let truth = &ds.ground_truth;
    let (before, after) = (evaluate(&filters, truth, &[], 1.0), evaluate(&adjusted, truth, &[], 1.0));
    println!("{done:?}\noffset found {offset:?}, offline {:?}", summary(&out).refined_gimbal_offset_deg);
    println!(
        "filters:\n{before}\nadjusted after landing:\n{after}\noffline:\n{}",
        evaluate(&offline, truth, &[], 1.0)
    );
    // Found: yaw -1.79, pitch 1.92, roll -0.31 deg. Pitch is the best determined; yaw and
    // roll of a camera looking 50-60 deg down turn its view alike and share their error.
    for ((found, reported), within) in offset.iter().zip([1.5, -2.0, 0.5]).zip([0.4, 0.2, 0.4]) {
        assert!((found + reported).abs() < within, "the offset taken back out: {offset:?}");
    }
    assert_eq!(found.refined_frames, Some(ds.records.len() as u64));

    assert_eq!(after.landmarks, before.landmarks, "the same landmarks, moved");
    // 2.58 -> 1.49 m.
    assert!(after.mean_m < 0.7 * before.mean_m, "mean {:.2} -> {:.2} m", before.mean_m, after.mean_m);

    assert_eq!(offline.len(), adjusted.len());
    for (x, y) in adjusted.iter().zip(&offline) {
        assert_eq!(x.id, y.id);
        assert!((x.position - y.position).norm() < 0.01, "{x:?} vs {y:?}");
    }

    // In flight: at 30 frames nothing has converged yet, and the next try is at twice
    // that; at 60 the offset found is added to the frames after.
    println!("in flight: {said:?}");
    assert_eq!(said.iter().map(|(f, _)| *f).collect::<Vec<_>>(), [29, 59], "{said:?}");
    assert!(
        matches!(&said[0].1[..], [PipelineEvent::Note(l)] if l.contains("not adjusted: no converged landmark")),
        "{said:?}"
    );
    assert!(
        matches!(&said[1].1[..], [PipelineEvent::Note(l)] if l.contains("added to later frames")),
        "{said:?}"
    );
    assert_eq!(applied_from, Some(60));
    let applied = summary(&in_flight_link).gimbal_offset_applied_deg.expect("the offset applied");
    for ((found, reported), within) in applied.iter().zip([1.5, -2.0, 0.5]).zip([0.4, 0.4, 0.4]) {
        assert!((found + reported).abs() < within, "the offset found in flight: {applied:?}");
    }
    // The landmarks that converged after it (those its adjustment did not move), against
    // those of the filters alone over the same frames.
    let later = |l: Vec<mavloc::output::LandmarkRecord>| -> Vec<_> {
        l.into_iter().filter(|l| !adjusted_in_flight.contains(&l.id)).collect()
    };
    let (without, with) = (
        evaluate(&later(filters), truth, &[], 1.0),
        evaluate(&later(landmarks(&in_flight_link)), truth, &[], 1.0),
    );
    println!("applied {applied:?} from frame 60\nconverged after, filters alone:\n{without}\nwith the offset taken out:\n{with}");
    assert!(with.landmarks >= 20 && without.landmarks >= 20, "{} and {}", with.landmarks, without.landmarks);
    // 2.46 -> 2.10 m (session 35): all of them were first seen before the offset was known,
    // and keep part of what they took from the frames before it.
    assert!(with.mean_m < 0.9 * without.mean_m, "mean {:.2} -> {:.2} m", without.mean_m, with.mean_m);
}

/// A traced UKF run of `dataset` into `out` (`mavloc area --trace`).
fn traced(dataset: &std::path::Path, out: &std::path::Path) -> RunOptions {
    RunOptions {
        dataset: dataset.into(),
        out: out.into(),
        method: AreaMethod::Ukf,
        trace: true,
        max_frames: None,
        debug_masks: false,
    }
}

/// Polls a live area pipeline until its adjustment has ended (at most two minutes).
fn wait_for(live: &mut mavloc::daemon::live::AreaLive) -> Vec<mavloc::daemon::worker::PipelineEvent> {
    use mavloc::daemon::worker::LivePipeline;
    let t0 = std::time::Instant::now();
    loop {
        let events = live.poll();
        if !events.is_empty() {
            return events;
        }
        assert!(t0.elapsed() < std::time::Duration::from_secs(120), "the adjustment did not end");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}
