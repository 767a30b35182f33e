use super::*;
use std::io::Write;

fn documented_file() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config/mavloc.toml")
}

fn write_temp(text: &str) -> tempfile::NamedTempFile {
    let mut f = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
    f.write_all(text.as_bytes()).unwrap();
    f
}

fn load_file(path: &Path) -> Result<Loaded, SettingsError> {
    load(&Layers { file: Some(path.to_path_buf()), ..Layers::default() })
}

/// File checks that pass every file and put the state directory in the temporary folder,
/// for tests of everything else.
const ANY_FILE: FileChecks<'static> = FileChecks {
    model: &|_| Ok(()),
    signing_key: &|_| Ok(()),
    state_dir: &|_| std::env::temp_dir(),
    scenario: &|_| Ok(()),
};

fn problems(r: Result<Loaded, SettingsError>) -> Vec<Problem> {
    match r {
        Err(SettingsError::Invalid(p)) => p,
        Err(other) => panic!("expected validation problems, got {other}"),
        Ok(_) => panic!("expected validation problems, got a configuration"),
    }
}

#[test]
fn documented_file_is_exactly_the_defaults() {
    let loaded = load_file(&documented_file()).unwrap();
    assert_eq!(loaded.settings, Settings::default());
}

#[test]
fn every_key_is_documented_with_a_unit() {
    let text = std::fs::read_to_string(documented_file()).unwrap();
    let mut section = String::new();
    let mut documented = Vec::new();
    for line in text.lines() {
        let line = line.trim();
        if let Some(s) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            section = s.to_string();
        } else if !line.starts_with('#') && line.contains('=') {
            let key = line.split('=').next().unwrap().trim();
            let comment = line.split_once('#').map(|(_, c)| c.trim()).unwrap_or("");
            assert!(comment.len() > 10, "{section}.{key} has no comment");
            assert!(
                comment.ends_with(']') && comment.contains('['),
                "{section}.{key}: comment must end with its unit in brackets: {comment}"
            );
            documented.push(format!("{section}.{key}"));
        }
    }
    let mut keys = all_keys();
    keys.sort();
    documented.sort();
    assert_eq!(documented, keys);
}

#[test]
fn misspelt_key_is_refused_with_suggestion_and_file() {
    let f = write_temp("[area]\nukf_alfa = 0.7\n");
    let p = problems(load_file(f.path()));
    assert_eq!(p.len(), 1);
    let msg = p[0].to_string();
    assert!(msg.contains("area.ukf_alfa"), "{msg}");
    assert!(msg.contains("area.ukf_alpha"), "{msg}");
    assert!(msg.contains(&f.path().display().to_string()), "{msg}");
    assert!(msg.contains("0.7"), "{msg}");
}

#[test]
fn out_of_range_value_names_key_value_range_and_file() {
    let f = write_temp("[area]\nukf_alpha = 1.5\n");
    let p = problems(load_file(f.path()));
    assert_eq!(p.len(), 1);
    let msg = p[0].to_string();
    for needle in ["area.ukf_alpha", "1.5", "0.001 ..= 1", &f.path().display().to_string()] {
        assert!(msg.contains(needle), "`{needle}` missing from: {msg}");
    }
}

/// Distortion coefficients of a calibration made at 640x360 given for a 1920x1080 camera
/// (focal length in pixels of the small size): the model turns over inside the image, which
/// OpenCV's undistortion would fold without a word. The same coefficients with the focal
/// length of this size load.
#[test]
fn a_lens_model_that_folds_inside_the_image_is_refused() {
    let camera = |fx: f64| {
        format!(
            "[camera]\nwidth = 1920\nheight = 1080\nfx = {fx}\ndistortion = [-0.3, 0.02, 0.0, 0.0, 0.0]\n"
        )
    };
    let f = write_temp(&camera(466.7));
    let p = problems(load_file(f.path()));
    assert_eq!(p.len(), 1, "{p:?}");
    let msg = p[0].to_string();
    for needle in ["camera.distortion", "1920x1080", "turns back on itself", "another image size"] {
        assert!(msg.contains(needle), "`{needle}` missing from: {msg}");
    }
    let f = write_temp(&camera(1400.0));
    load_file(f.path()).unwrap();
}

#[test]
fn wrong_type_and_unknown_section_are_refused() {
    let f = write_temp("[area]\nl_max = \"lots\"\n[aera]\nx = 1\n");
    let p = problems(load_file(f.path()));
    let text: Vec<String> = p.iter().map(|p| p.to_string()).collect();
    assert!(text.iter().any(|m| m.contains("area.l_max") && m.contains("expected an integer")), "{text:?}");
    assert!(text.iter().any(|m| m.contains("aera") && m.contains("unknown section")), "{text:?}");
    // A key above every section header is a key out of place, not a section.
    let f = write_temp("l_max = 300\nfoo = 1\n[area]\nratio_test = 0.6\n");
    let text: Vec<String> = problems(load_file(f.path())).iter().map(|p| p.to_string()).collect();
    assert!(
        text.iter().any(|m| m.contains("l_max") && m.contains("outside any section: write it below [area]")),
        "{text:?}"
    );
    assert!(text.iter().any(|m| m.contains("foo") && m.contains("no section has it")), "{text:?}");
}

#[test]
fn bad_enum_value_names_the_key() {
    let f = write_temp("[gimbal]\nchain = \"pitch-yaw-roll\"\n");
    let err = load_file(f.path()).unwrap_err().to_string();
    assert!(err.contains("gimbal.chain"), "{err}");
    assert!(err.contains("expected one of yaw-pitch-roll, yaw-roll-pitch"), "{err}");
    assert!(err.contains("\"pitch-yaw-roll\""), "{err}");
}

#[test]
fn all_problems_are_reported_together() {
    let f = write_temp("[area]\nukf_alpha = 2.0\nratio_test = 0.0\n[indoor]\nlanding_frames = 1\n");
    let p = problems(load_file(f.path()));
    let keys: Vec<&str> = p.iter().map(|p| p.key.as_str()).collect();
    assert_eq!(keys, ["area.ratio_test", "area.ukf_alpha", "indoor.landing_frames"]);
}

#[test]
fn cross_field_turnover_below_l_max() {
    let f = write_temp("[area]\nl_max = 10\nturnover = 10\n");
    let p = problems(load_file(f.path()));
    assert_eq!(p[0].key, "area.turnover");
    assert!(p[0].expected.contains("0 ..= 9"), "{}", p[0]);
    // An l_max out of range is the one problem: the default turnover is not blamed.
    let f = write_temp("[area]\nl_max = 0\n");
    let p = problems(load_file(f.path()));
    assert_eq!(p.iter().map(|p| p.key.as_str()).collect::<Vec<_>>(), ["area.l_max"], "{p:?}");
    // A negative value for an unsigned key says the key's range, not its Rust type.
    let f = write_temp("[area]\nl_max = -5\n");
    let p = problems(load_file(f.path()));
    assert!(p[0].key == "area.l_max" && p[0].expected == "out of range; allowed 1 ..= 20000", "{p:?}");
}

#[test]
fn layers_env_over_file_and_cli_over_env() {
    let f = write_temp("[area]\nl_max = 300\nturnover = 30\n[camera]\nsource = \"v4l2\"\n");
    let mut env = BTreeMap::new();
    env.insert("MAVLOC_AREA__L_MAX".to_string(), "400".to_string());
    env.insert("MAVLOC_CAMERA__DISTORTION".to_string(), "0.1,0,0,0,0".to_string());
    env.insert("MAVLOC_CONFIG".to_string(), "/ignored.toml".to_string());
    env.insert("HOME".to_string(), "/root".to_string());
    let layers = Layers {
        file: Some(f.path().to_path_buf()),
        dataset: None,
        env: env.clone(),
        overrides: vec!["area.l_max=500".into(), "mavlink.connection=udpout:127.0.0.1:14550".into()],
    };
    let loaded = load(&layers).unwrap();
    let s = &loaded.settings;
    assert_eq!(s.area.l_max, 500, "command line wins");
    assert_eq!(s.area.turnover, 30, "file value kept");
    assert_eq!(s.camera.source, CameraSource::V4l2);
    assert_eq!(s.camera.distortion, vec![0.1, 0.0, 0.0, 0.0, 0.0]);
    assert_eq!(s.mavlink.connection, "udpout:127.0.0.1:14550");
    assert!(loaded.origins["area.l_max"].contains("command line"));
    assert!(loaded.origins["camera.distortion"].contains("MAVLOC_CAMERA__DISTORTION"));

    // Without the override the environment wins over the file.
    let loaded = load(&Layers { overrides: vec![], ..layers }).unwrap();
    assert_eq!(loaded.settings.area.l_max, 400);
}

#[test]
fn a_datasets_settings_beat_the_file_and_lose_to_the_command_line() {
    let file = write_temp("[area]\nl_max = 300\nsegmenter = \"masks\"\nturnover = 30\n");
    let dataset = write_temp("[area]\nl_max = 1500\nsegmenter = \"water\"\n");
    let layers = Layers {
        file: Some(file.path().to_path_buf()),
        dataset: Some(dataset.path().to_path_buf()),
        overrides: vec!["area.l_max=700".into()],
        ..Layers::default()
    };
    let loaded = load(&layers).unwrap();
    assert_eq!(loaded.settings.area.segmenter, Segmenter::Water, "the dataset's over the file's");
    assert_eq!(loaded.settings.area.turnover, 30, "the file's where the dataset is silent");
    assert_eq!(loaded.settings.area.l_max, 700, "the command line's over both");
    assert_eq!(loaded.origins["area.segmenter"], dataset.path().display().to_string());
    // The shipped photo-survey settings load as a dataset layer.
    let survey = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/photo-survey.toml");
    let loaded = load(&Layers { dataset: Some(survey), ..Layers::default() }).unwrap();
    assert_eq!(loaded.settings.area.ukf_iterations, 5);
    // A wrong key in a dataset's settings is named with the file.
    let bad = write_temp("[area]\nsegmentr = \"water\"\n");
    let p = problems(load(&Layers { dataset: Some(bad.path().to_path_buf()), ..Layers::default() }));
    assert_eq!(p.len(), 1, "{p:?}");
    assert_eq!(p[0].key, "area.segmentr");
    assert_eq!(p[0].origin, bad.path().display().to_string());
}

#[test]
fn unknown_environment_key_names_the_variable() {
    let mut env = BTreeMap::new();
    env.insert("MAVLOC_AREA__LMAX".to_string(), "300".to_string());
    let p = problems(load(&Layers { env, ..Layers::default() }));
    let msg = p[0].to_string();
    assert!(msg.contains("MAVLOC_AREA__LMAX") && msg.contains("area.l_max"), "{msg}");
}

#[test]
fn other_mavloc_variables_are_not_configuration() {
    let mut env = BTreeMap::new();
    env.insert("MAVLOC_FOO".to_string(), "1".to_string());
    env.insert("MAVLOC_PYTHON".to_string(), "/x/python".to_string());
    assert!(load(&Layers { env, ..Layers::default() }).is_ok());
}

#[test]
fn bad_command_line_override_is_refused() {
    let p = problems(load(&Layers { overrides: vec!["area.downscale=16".into()], ..Layers::default() }));
    assert!(p[0].to_string().contains("command line") && p[0].to_string().contains("1 ..= 8"), "{}", p[0]);
    let p = problems(load(&Layers { overrides: vec!["nonsense".into()], ..Layers::default() }));
    assert!(p[0].expected.contains("section.key=value"));
}

#[test]
fn bad_connection_string_is_refused() {
    let f = write_temp("[mavlink]\nconnection = \"udp:14540\"\n");
    let p = problems(load_file(f.path()));
    assert_eq!(p[0].key, "mavlink.connection");
}

#[test]
fn syntax_error_and_missing_file_name_the_file() {
    let f = write_temp("[area\nl_max = 3\n");
    let err = load_file(f.path()).unwrap_err();
    assert!(matches!(err, SettingsError::Syntax { .. }));
    assert!(err.to_string().contains(&f.path().display().to_string()));
    let err = load_file(Path::new("/nonexistent/mavloc.toml")).unwrap_err();
    assert!(err.to_string().contains("/nonexistent/mavloc.toml"));
}

#[test]
fn effective_rendering_parses_back() {
    let loaded = load(&Layers { overrides: vec!["indoor.k=7".into()], ..Layers::default() }).unwrap();
    let text = render_effective(&loaded);
    assert!(text.contains("k = 7  # from command line"));
    let f = write_temp(&text);
    assert_eq!(load_file(f.path()).unwrap().settings, loaded.settings);
}

#[test]
fn intrinsics_follow_the_camera_settings() {
    let mut c = Camera::default();
    let k = c.intrinsics();
    assert!((k.fx - 960.0).abs() < 1e-9 && (k.cx - 959.5).abs() < 1e-9);
    c.fx = 1000.0;
    c.cx = 900.0;
    let k = c.intrinsics();
    assert_eq!((k.fx, k.fy, k.cx), (1000.0, 1000.0, 900.0));
}

#[test]
fn enum_names_match_the_schema() {
    for (key, names) in ENUM_KEYS {
        for name in *names {
            let loaded = load(&Layers { overrides: vec![format!("{key}={name}")], ..Layers::default() });
            assert!(loaded.is_ok(), "{key}={name}: {:?}", loaded.err());
        }
        let (section, field) = key.split_once('.').unwrap();
        let table = toml::Table::try_from(Settings::default()).unwrap();
        let default = table[section][field].as_str().unwrap().to_string();
        assert!(names.contains(&default.as_str()), "{key} default {default} not listed");
    }
}

#[test]
fn relative_paths_in_a_file_are_beside_the_file_and_on_the_command_line_in_the_working_folder() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("mavloc.toml");
    std::fs::write(
        &file,
        "[indoor]\nmodel = \"floor.model\"\n[camera]\npath = \"/abs/frames\"\n[mavlink]\npx4_events = \"px4/all_events.json\"\n",
    )
    .unwrap();
    let loaded = load_file(&file).unwrap();
    assert_eq!(Path::new(&loaded.settings.indoor.model), dir.path().join("floor.model"));
    // Every path key (px4_events was taken from the working folder, `/` under systemd).
    assert_eq!(Path::new(&loaded.settings.mavlink.px4_events), dir.path().join("px4/all_events.json"));
    assert_eq!(loaded.settings.camera.path, "/abs/frames", "absolute paths stay");
    let cli = load(&Layers {
        file: Some(file.clone()),
        overrides: vec!["indoor.model=here.model".into()],
        ..Layers::default()
    })
    .unwrap();
    assert_eq!(cli.settings.indoor.model, "here.model");
}

#[test]
fn the_installed_drone_configuration_is_a_real_drone_one() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/drone.toml");
    let loaded = load_file(&path).unwrap();
    let s = &loaded.settings;
    assert_eq!(s.camera.source, CameraSource::V4l2, "never the simulated camera on a drone");
    assert!(
        s.mavlink.connection.starts_with("serial:") || s.mavlink.connection.starts_with("udpin:127.0.0.1")
    );
    assert_ne!(s.area.segmenter, crate::settings::Segmenter::Masks, "a real camera gives no masks");
    // The SITL configuration beside it loads too, and its state folder is beside it.
    let sitl = load_file(&path.with_file_name("sitl.toml")).unwrap().settings;
    assert_eq!(sitl.camera.source, CameraSource::Sim);
    assert_eq!(Path::new(&sitl.daemon.state_dir), path.with_file_name("sitl-state"));
}

/// A live camera gives no masks: `mavloc run` (and `config check`) refuse the area pipeline
/// with `masks` or `learned` there, naming the key, instead of skipping every frame.
#[test]
fn a_live_camera_with_a_segmenter_that_needs_masks_is_refused() {
    for (segmenter, source) in [("masks", "v4l2"), ("learned", "v4l2"), ("learned", "file")] {
        let layers = Layers {
            overrides: vec![
                format!("area.segmenter={segmenter}"),
                format!("camera.source={source}"),
                // A folder with images in it, so the path itself passes.
                format!("camera.path={}/docs", env!("CARGO_MANIFEST_DIR")),
            ],
            ..Layers::default()
        };
        let p = problems(check(&layers, &ANY_FILE));
        assert_eq!(p.len(), 1, "{p:?}");
        assert_eq!(p[0].key, "area.segmenter");
        assert!(
            p[0].expected.contains("gives no masks") && p[0].expected.contains(source),
            "{}",
            p[0].expected
        );
    }
    // Rules that make their own masks, and cameras that carry masks, are fine.
    for sets in
        [["area.segmenter=water", "camera.source=v4l2"], ["area.segmenter=masks", "camera.source=sim"]]
    {
        let layers = Layers { overrides: sets.map(String::from).to_vec(), ..Layers::default() };
        assert!(check(&layers, &ANY_FILE).is_ok(), "{sets:?}");
    }
}

/// The photo-survey settings hold the alignment's per-photo shifts to the positions' own
/// noise: a looser shift prior lets photos move where they turned
/// (`area::align::tests::the_shift_prior_keeps_photos_from_moving_where_they_turned`; the
/// rendered three-line survey's map rose 2.5 m with 5 m).
#[test]
fn photo_surveys_hold_the_alignment_shifts_to_the_position_noise() {
    let survey = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/photo-survey.toml");
    let layers = Layers { dataset: Some(survey), ..Layers::default() };
    let a = load(&layers).unwrap().settings.area;
    let noise = a.position_noise_m.iter().cloned().fold(0.0, f64::max);
    assert!(a.align_prior_deg > 0.0, "photo surveys are aligned");
    assert!(a.align_shift_m > 0.0 && a.align_shift_m <= noise, "{} m against {noise} m", a.align_shift_m);
}

/// Once aligned, photo surveys trust the poses more than the tags, never less: a tighter
/// bearing noise and no more sightings a landmark (`area.aligned_*`; the tags' values stay
/// for a survey the alignment reaches less than half of).
#[test]
fn photo_surveys_trust_aligned_poses_more_than_the_tags() {
    let survey = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/photo-survey.toml");
    let layers = Layers { dataset: Some(survey), ..Layers::default() };
    let a = load(&layers).unwrap().settings.area;
    assert!(a.aligned_bearing_noise_deg > 0.0 && a.aligned_bearing_noise_deg < a.bearing_noise_deg, "{a:?}");
    assert!(a.aligned_min_observations >= 2 && a.aligned_min_observations < a.min_observations, "{a:?}");
    // The defaults leave video as it was.
    let d = crate::settings::Settings::default().area;
    assert_eq!((d.aligned_bearing_noise_deg, d.aligned_min_observations), (0.0, 0));
}

/// A `file` camera on something that gives no frames is refused before `run` starts (it
/// used to start and idle with "camera failed" in its log): an empty folder, a folder of
/// other files, a device (a camera set as a file), an empty file, a file that is no video.
#[test]
fn a_file_camera_on_what_gives_no_frames_is_refused_before_run() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("notes")).unwrap();
    std::fs::write(dir.path().join("notes/readme.txt"), "flight notes").unwrap();
    std::fs::create_dir(dir.path().join("frames")).unwrap();
    std::fs::write(dir.path().join("frames/0001.JPG"), b"\xff\xd8").unwrap();
    std::fs::write(dir.path().join("empty.mp4"), b"").unwrap();
    let check = |path: &Path| {
        let layers = Layers {
            overrides: vec![
                "camera.source=file".into(),
                "area.segmenter=water".into(),
                format!("camera.path={}", path.display()),
            ],
            ..Layers::default()
        };
        check(&layers, &ANY_FILE).err().map(|e| e.to_string())
    };
    std::fs::create_dir(dir.path().join("empty")).unwrap();
    let said = check(&dir.path().join("empty")).expect("an empty folder is refused");
    assert!(said.contains("camera.path") && said.contains("holds no images"), "{said}");
    let said = check(&dir.path().join("notes")).expect("a folder of notes is refused");
    assert!(said.contains("holds no images"), "{said}");
    let said = check(Path::new("/dev/null")).expect("a device is refused");
    assert!(said.contains("is a device") && said.contains("camera.source = \"v4l2\""), "{said}");
    let said = check(&dir.path().join("empty.mp4")).expect("an empty file is refused");
    assert!(said.contains("empty.mp4 is empty"), "{said}");
    std::fs::write(dir.path().join("notes.mp4"), "flight notes").unwrap();
    let said = check(&dir.path().join("notes.mp4")).expect("a file that is no video is refused");
    assert!(said.contains("notes.mp4 is not a video OpenCV can read"), "{said}");
    // A folder with an image in it (by its extension, in any case) passes, and so does a
    // video OpenCV decodes.
    assert_eq!(check(&dir.path().join("frames")), None);
    let video = dir.path().join("flight.avi");
    {
        use opencv::{core, prelude::*, videoio};
        let fourcc = videoio::VideoWriter::fourcc('M', 'J', 'P', 'G').unwrap();
        let mut w =
            videoio::VideoWriter::new(video.to_str().unwrap(), fourcc, 10.0, core::Size::new(64, 48), true)
                .unwrap();
        assert!(w.is_opened().unwrap(), "OpenCV writes MJPEG AVI");
        let frame =
            core::Mat::new_rows_cols_with_default(48, 64, core::CV_8UC3, core::Scalar::all(90.0)).unwrap();
        for _ in 0..3 {
            w.write(&frame).unwrap();
        }
    }
    assert_eq!(check(&video), None);
}

/// The state directory is judged as `run` will meet it: a folder to make under a writable
/// one passes; under a file, or on the kernel's own file systems (where access() says yes
/// to root but nothing can be made), it is refused with the reason.
#[test]
fn a_state_directory_that_cannot_be_made_is_named_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(unmakeable_dir(&dir.path().join("state/deeper")), None);
    std::fs::write(dir.path().join("file"), "").unwrap();
    let why = unmakeable_dir(&dir.path().join("file/state")).expect("under a file");
    assert!(why.ends_with("file is not a directory"), "{why}");
    if Path::new("/proc/self").exists() {
        let why = unmakeable_dir(Path::new("/proc/forbidden/state")).expect("under /proc");
        // As root access() allows it and the file system is named; as anyone else, not writable.
        assert!(why.contains("/proc is on proc") || why.contains("not writable"), "{why}");
    }
    if Path::new("/sys/kernel").exists() {
        let why = unmakeable_dir(Path::new("/sys/kernel/x")).expect("under /sys");
        assert!(why.contains("on sysfs") || why.contains("not writable"), "{why}");
    }
}
