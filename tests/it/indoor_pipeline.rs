//! The indoor pipeline end to end on a small rendered dataset: train on 400 random views
//! (320x240, brightness, contrast and blur varied), fly 20 s of the Lissajous path with
//! another appearance (the seed's reality gap), evaluate. The bounds catch a regression
//! (without derotation or normalisation the median error is metres); the full-size
//! figures (5000 views, the whole flight) are in the README.

use std::path::PathBuf;

use mavloc::indoor::eval::evaluate;
use mavloc::indoor::model::Model;
use mavloc::indoor::offline::{run, RunOptions};
use mavloc::settings::{Indoor, MotionModel};
use mavloc_data::dataset::Appearance;
use mavloc_data::results::read_trajectory;
use mavloc_sim::RenderOptions;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn trains_on_views_and_tracks_a_flight() {
    let dir = tempfile::tempdir().unwrap();
    let size = Some((320, 240));
    // Rendered once and cached (see `fixtures`).
    let gap = Appearance { brightness: 15.0, contrast: 0.9, blur_px: 3 };
    let opts = RenderOptions { frames: Some(300), size, appearance: Some(gap), ..Default::default() };
    let flight = crate::fixtures::rendered("indoor-floor-flight-300-320x240-gap", "indoor-floor", &opts);

    let settings = Indoor::default();
    // Trained on the views with the default settings, once for every test that does so
    // and cached (the live flights' model).
    let (model_path, report) = crate::fixtures::small_indoor_training().clone();
    assert_eq!((report.images, report.rejected), (400, 0));
    // The nearest neighbour is right for most views (the robust fit's inlier fraction).
    assert!(report.inlier_fraction[0] > 0.5, "{report:?}");
    let model = Model::load(&model_path).unwrap();
    assert_eq!(model.histograms.len(), 400);
    assert_eq!(model.measurement_cov.len(), settings.k as usize);
    // By default frames are rescaled to the training views' median height (0.8-1.2 m).
    let h = model.frame.height_ref_m.expect("a reference height by default");
    assert!((0.9..1.1).contains(&h), "reference height {h} m");

    let errors_with = |out: &std::path::Path, s: &Indoor, no_velocity: bool, camera_velocity: bool| {
        let opts = RunOptions {
            dataset: flight.clone(),
            model: model_path.clone(),
            out: out.into(),
            max_frames: None,
            no_velocity,
            camera_velocity,
            seed: 3,
        };
        let summary = run(&opts, s, |_, _| {}).unwrap();
        if camera_velocity {
            // The camera's velocity on every pair of this flight (blur 3 px, brightness and
            // contrast changed), a few cm/s from the truth.
            assert_eq!(summary.camera_velocity_frames, Some(299), "{summary:?}");
            let rms = summary.camera_velocity_rms_m_s.unwrap();
            assert!(rms < 0.04, "camera velocity {rms:.3} m/s RMS per axis");
        } else {
            assert_eq!(summary.camera_velocity_frames, None);
        }
        assert!(summary.complete && summary.frames == 300);
        // Frames per second count whole frames: reading, preparing and localising.
        let whole_ms = summary.read_ms + summary.prepare_ms + summary.localize_ms;
        assert!(summary.read_ms > 0.0 && summary.prepare_ms > 0.0, "{summary:?}");
        assert!(
            (summary.frames_per_s - 1000.0 / whole_ms).abs() < 0.01 * summary.frames_per_s,
            "{summary:?}"
        );
        assert!(summary.localize_frames_per_s > summary.frames_per_s, "{summary:?}");
        let rows = read_trajectory(&out.join("trajectory.csv")).unwrap();
        let (e, _) = evaluate(&flight, out).unwrap();
        // After the first 2 s (global localisation from a uniform start).
        let late: Vec<f64> =
            rows.iter().filter(|r| r.t >= 2.0).map(|r| (r.x - r.true_x).hypot(r.y - r.true_y)).collect();
        (e, median(late.clone()), late.iter().filter(|d| **d < 0.5).count() as f64 / late.len() as f64)
    };
    let errors =
        |out: &std::path::Path, s: &Indoor, no_velocity: bool| errors_with(out, s, no_velocity, false);
    let (e, med, within) = errors(&dir.path().join("run"), &settings, false);
    // Measured: median 0.13 m, mean |error| 0.28 m / 0.17 m; 80 % of frames within 0.5 m.
    assert!(med < 0.3, "median error {med} m; {e:?}");
    assert!(within > 0.6, "only {within} of frames within 0.5 m; {e:?}");
    assert!(e.mean_err_x_m < 0.6 && e.mean_err_y_m < 0.6, "{e:?}");
    assert!(e.frames_per_s > 0.0);

    // Without telemetry velocity the velocity model fits one; still tracking. Run into
    // the first run's folder: its results are replaced as a set (a file beside them goes
    // with them) and name the dataset they were made from.
    let first = dir.path().join("run");
    std::fs::write(first.join("stale.txt"), "from before").unwrap();
    let (_, med_fit, _) = errors(&first, &settings, true);
    assert!(med_fit < 0.4, "median error {med_fit} m with fitted velocity");
    assert!(!first.join("stale.txt").exists(), "the earlier folder's file stayed beside the new results");
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(first.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["dataset_crc32"].as_str(), mavloc_data::dataset::telemetry_crc32(&flight).as_deref());
    // With the camera's own velocity, as the daemon flies without GPS: as good as with
    // the telemetry's.
    let (_, med_cam, _) = errors_with(&dir.path().join("camera"), &settings, false, true);
    assert!(med_cam < 0.3, "median error {med_cam} m with the camera's velocity");

    // The seed's noise-only motion model also runs (it lags more; not asserted here).
    let noise = Indoor { motion_model: MotionModel::Noise, ..settings.clone() };
    let (e_noise, _, _) = errors(&dir.path().join("noise"), &noise, false);
    assert!(e_noise.frames == 300);
}

/// Textons are not scale invariant: a model trained on views from 0.8-1.2 m does not
/// know the floor from 0.5 m. Rescaled to the floor's scale from a reference height (by
/// default the views' median, `height_ref_m`; at training and, through the model, at run
/// time) it tracks there.
#[test]
fn a_model_rescaled_to_a_reference_height_tracks_a_flight_below_its_views() {
    let dir = tempfile::tempdir().unwrap();
    let flight = crate::fixtures::low_indoor_flight(200);
    let median_error = |name: &str, model_path: PathBuf| {
        let out = dir.path().join(name);
        let opts = RunOptions {
            dataset: flight.clone(),
            model: model_path,
            out: out.clone(),
            max_frames: None,
            no_velocity: false,
            camera_velocity: false,
            seed: 3,
        };
        // The run takes the rescaling from the model, not from its own settings.
        run(&opts, &Indoor::default(), |_, _| {}).unwrap();
        let rows = read_trajectory(&out.join("trajectory.csv")).unwrap();
        median(rows.iter().filter(|r| r.t >= 2.0).map(|r| (r.x - r.true_x).hypot(r.y - r.true_y)).collect())
    };
    // Plain: trained without rescaling (`height_ref_m` < 0).
    let plain_model = crate::fixtures::plain_indoor_model();
    assert_eq!(Model::load(&plain_model).unwrap().frame.height_ref_m, None);
    let plain = median_error("plain", plain_model);
    // Rescaled: the default, to the views' median height (the live flights' model, trained
    // once and cached).
    let rescaled_model = crate::fixtures::small_indoor_model().to_path_buf();
    let h = Model::load(&rescaled_model).unwrap().frame.height_ref_m.expect("rescaled by default");
    assert!((0.9..1.1).contains(&h), "reference height {h} m");
    let rescaled = median_error("rescaled", rescaled_model);
    println!("flight at 0.5 m, median error: plain model {plain:.3} m, rescaled {rescaled:.3} m");
    // Measured: plain 0.173-0.292 m, rescaled 0.102 m (0.061 m before the tracking
    // filter's renewed particles were kept within 0.15 m instead of 0.5 m, which cut the
    // largest errors over ten unseen floors from 0.46-0.81 m to 0.25-0.53 m; with 5000
    // views and 400 frames at 640x480: 0.383 and 0.072 m, README). Since the tracking
    // filter tempers correlated frames (session 14) the plain model holds too on this
    // flight (0.096 m, rescaled 0.101 m). Session 22 rescales to the views' median height
    // (the default, 0.9-1.1 m) instead of exactly 1 m, sharing the live flights' model:
    // 0.056 m. The rescaled model must track within 0.12 m and be no worse than the plain
    // one beyond noise.
    assert!(rescaled < 0.12 && rescaled < 1.15 * plain, "plain {plain:.3} m, rescaled {rescaled:.3} m");
}

#[test]
fn a_model_of_another_version_is_refused_by_run() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.json");
    std::fs::write(&path, r#"{"format":"mavloc-indoor-model","version":0}"#).unwrap();
    let err = Model::load(&path).unwrap_err();
    assert!(err.contains("version 0") && err.contains(&path.display().to_string()), "{err}");
}

/// A run stopped on request (Ctrl-C in `mavloc indoor run` sets the flag; here the
/// progress callback sets it after 40 frames) ends after the frame in hand: its 40 frames
/// are the results (`complete: false`), put in place over nothing, and beside complete
/// earlier results as `NAME.stopped` instead of over them, which stay as they were.
#[test]
fn a_stopped_run_puts_the_frames_so_far_beside_complete_earlier_results() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let dir = tempfile::tempdir().unwrap();
    let flight = crate::fixtures::low_indoor_flight(200);
    let opts = |out: &str| RunOptions {
        dataset: flight.clone(),
        model: crate::fixtures::small_indoor_model().to_path_buf(),
        out: dir.path().join(out),
        max_frames: None,
        no_velocity: false,
        camera_velocity: false,
        seed: 1,
    };
    let stopped_after_40 = |o: &RunOptions| {
        let stop = AtomicBool::new(false);
        let progress = |done: usize, _: usize| {
            if done == 40 {
                stop.store(true, Ordering::SeqCst);
            }
        };
        mavloc::indoor::offline::run_stoppable(o, &Indoor::default(), progress, &stop).unwrap()
    };
    let summary = |p: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p.join("summary.json")).unwrap()).unwrap()
    };
    let rows =
        |p: &std::path::Path| std::fs::read_to_string(p.join("trajectory.csv")).unwrap().lines().count() - 1;

    // Into a new folder: the frames so far are the results.
    let fresh = opts("fresh");
    let s = stopped_after_40(&fresh);
    assert_eq!((s.frames, s.complete), (40, false), "{s:?}");
    assert_eq!(s.written_to, fresh.out);
    assert_eq!(summary(&fresh.out)["complete"], false);
    assert_eq!(rows(&fresh.out), 40);

    // Over complete results: they stay, the stopped run's go beside.
    let full = opts("full");
    let done = run(&full, &Indoor::default(), |_, _| {}).unwrap();
    assert!(done.complete && done.frames == 200, "{done:?}");
    let before = std::fs::read(full.out.join("trajectory.csv")).unwrap();
    let s = stopped_after_40(&full);
    assert_eq!(s.written_to, dir.path().join("full.stopped"));
    assert_eq!(std::fs::read(full.out.join("trajectory.csv")).unwrap(), before);
    assert_eq!(summary(&full.out)["complete"], true);
    assert_eq!((summary(&s.written_to)["complete"].as_bool(), rows(&s.written_to)), (Some(false), 40));
    // Nothing else: no staging folder is left.
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into())
        .collect();
    names.sort();
    assert_eq!(names, ["fresh", "full", "full.stopped"]);
}
