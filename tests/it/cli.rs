//! The `mavloc` binary as a user meets it: help texts, configuration checks, errors.

use assert_cmd::Command;
use std::io::Write;

fn mavloc() -> Command {
    let mut c = Command::cargo_bin("mavloc").unwrap();
    // Keep the caller's MAVLOC_* variables and /etc config out of these tests.
    for (k, _) in std::env::vars() {
        if k.starts_with("MAVLOC_") {
            c.env_remove(k);
        }
    }
    c.timeout(std::time::Duration::from_secs(60));
    c
}

fn temp_config(text: &str) -> tempfile::NamedTempFile {
    let mut f = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
    f.write_all(text.as_bytes()).unwrap();
    f
}

fn stdout_of(c: &mut Command) -> String {
    String::from_utf8(c.assert().success().get_output().stdout.clone()).unwrap()
}

#[test]
fn help_lists_every_subcommand() {
    let out = stdout_of(mavloc().arg("--help"));
    for sub in ["run", "demo", "sim", "area", "indoor", "eval", "config"] {
        assert!(out.lines().any(|l| l.trim_start().starts_with(sub)), "`{sub}` missing from:\n{out}");
    }
}

#[test]
fn every_subcommand_has_help() {
    for sub in ["run", "demo", "sim", "area", "indoor", "eval", "config"] {
        let out = stdout_of(mavloc().args([sub, "--help"]));
        assert!(out.contains("Usage: mavloc"), "{sub}: {out}");
    }
}

#[test]
fn documented_config_checks() {
    let out = stdout_of(mavloc().args(["config", "check", "config/mavloc.toml"]));
    assert!(out.contains("valid"), "{out}");
}

/// The file named on the command line is the one checked, whatever MAVLOC_CONFIG says;
/// `--config` and an argument that differ are refused; with no file at all the exit is 78,
/// as for a configuration `run` cannot use.
#[test]
fn config_check_checks_the_file_it_is_given() {
    let good = temp_config("[area]\nukf_alpha = 0.7\n");
    let bad = temp_config("[area]\nukf_alfa = 0.7\n");
    let a = mavloc()
        .env("MAVLOC_CONFIG", good.path())
        .args(["config", "check"])
        .arg(bad.path())
        .assert()
        .code(78);
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("area.ukf_alfa") && err.contains(&bad.path().display().to_string()), "{err}");
    let a = mavloc()
        .arg("--config")
        .arg(good.path())
        .args(["config", "check"])
        .arg(bad.path())
        .assert()
        .failure();
    assert!(String::from_utf8_lossy(&a.get_output().stderr).contains("two files to check"));
    if !std::path::Path::new("/etc/mavloc/mavloc.toml").exists() {
        let a = mavloc().args(["config", "check"]).assert().code(78);
        assert!(String::from_utf8_lossy(&a.get_output().stderr).contains("no configuration file"));
    }
}

/// A V4L2 camera that is not there, or not a device, is noted by `config check` as a
/// serial device is (`run` retries the camera); a present one is not.
#[test]
fn config_check_notes_a_camera_device_that_is_missing_or_not_a_device() {
    let dir = tempfile::tempdir().unwrap();
    let note = |device: &str| {
        let f = temp_config(&format!(
            "[daemon]\npipeline = \"area\"\n[area]\nsegmenter = \"water\"\n[camera]\nsource = \"v4l2\"\ndevice = \"{device}\"\n"
        ));
        let out = mavloc().args(["config", "check"]).arg(f.path()).assert().success();
        String::from_utf8_lossy(&out.get_output().stdout).to_string()
    };
    let missing = dir.path().join("video7");
    let said = note(&missing.display().to_string());
    assert!(
        said.contains("note: camera.device:") && said.contains("does not exist now (unplugged?"),
        "{said}"
    );
    let file = dir.path().join("not-a-camera");
    std::fs::write(&file, "").unwrap();
    assert!(note(&file.display().to_string()).contains("is not a video device"));
    let said = note("/dev/null");
    assert!(said.contains("valid") && !said.contains("note:"), "{said}");
}

/// A serial device that is not there, or not a device, is noted by `config check` (the
/// configuration stays valid: `run` waits for the device); a present one is not.
#[test]
fn config_check_notes_a_serial_device_that_is_missing_or_not_a_device() {
    let dir = tempfile::tempdir().unwrap();
    let note = |device: &str| {
        let f = temp_config(&format!("[mavlink]\nconnection = \"serial:{device}:921600\"\n"));
        let out = mavloc().args(["config", "check"]).arg(f.path()).assert().success();
        String::from_utf8_lossy(&out.get_output().stdout).to_string()
    };
    let missing = dir.path().join("ttyUSB9");
    let said = note(&missing.display().to_string());
    assert!(
        said.contains("note: mavlink.connection:") && said.contains("does not exist now (unplugged?"),
        "{said}"
    );
    let file = dir.path().join("not-a-tty");
    std::fs::write(&file, "").unwrap();
    let said = note(&file.display().to_string());
    assert!(said.contains("is not a serial device"), "{said}");
    // /dev/null is a character device anyone may open: nothing to note.
    let said = note("/dev/null");
    assert!(said.contains("valid") && !said.contains("note:"), "{said}");
    // Checked as root, a device is judged by what the service (in dialout) can open.
    if unsafe { libc::geteuid() } != 0 {
        eprintln!("skipped: the dialout checks of a device need root (mknod)");
        return;
    }
    let gid = |name: &str| -> u32 {
        let groups = std::fs::read_to_string("/etc/group").unwrap();
        let line = groups.lines().find(|l| l.starts_with(&format!("{name}:"))).unwrap();
        line.split(':').nth(2).unwrap().parse().unwrap()
    };
    let tty = dir.path().join("ttyS7");
    let path = std::ffi::CString::new(tty.as_os_str().as_encoded_bytes()).unwrap();
    // A character device with /dev/null's numbers, mode 0600 root:root.
    if unsafe { libc::mknod(path.as_ptr(), libc::S_IFCHR | 0o600, libc::makedev(1, 3)) } != 0 {
        eprintln!("skipped: mknod is not allowed here");
        return;
    }
    let device = tty.display().to_string();
    assert!(
        note(&device).contains("is not open to the dialout group (group root, mode 600)"),
        "{}",
        note(&device)
    );
    let own = |group: u32, mode: u32| {
        std::os::unix::fs::chown(&tty, Some(0), Some(group)).unwrap();
        std::fs::set_permissions(&tty, std::os::unix::fs::PermissionsExt::from_mode(mode)).unwrap();
    };
    own(gid("dialout"), 0o660);
    assert!(!note(&device).contains("note:"), "{}", note(&device));
    own(gid("tty"), 0o620);
    assert!(note(&device).contains("login console"), "{}", note(&device));
}

#[test]
fn misspelt_key_fails_naming_key_and_file() {
    let f = temp_config("[area]\nukf_alfa = 0.7\n");
    let a = mavloc().args(["config", "check"]).arg(f.path()).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("area.ukf_alfa"), "{err}");
    assert!(err.contains("did you mean `area.ukf_alpha`"), "{err}");
    assert!(err.contains(&f.path().display().to_string()), "{err}");
}

#[test]
fn out_of_range_fails_naming_key_value_range_and_file() {
    let f = temp_config("[indoor]\nparticles = 0\n");
    let a = mavloc().args(["config", "check"]).arg(f.path()).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    for needle in ["indoor.particles = 0", "1 ..= 100000", &f.path().display().to_string()] {
        assert!(err.contains(needle), "`{needle}` missing from: {err}");
    }
}

#[test]
fn environment_layer_is_checked_and_named() {
    // Exit 78 (EX_CONFIG), as `config check` and `run` on the same configuration.
    let a = mavloc().args(["config", "show"]).env("MAVLOC_AREA__L_MAX", "many").assert().code(78);
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("MAVLOC_AREA__L_MAX") && err.contains("expected an integer"), "{err}");
}

#[test]
fn show_reports_overrides_with_their_origin() {
    let out =
        stdout_of(mavloc().args(["config", "show", "--set", "area.l_max=300"]).env("MAVLOC_INDOOR__K", "7"));
    assert!(out.contains("l_max = 300  # from command line"), "{out}");
    assert!(out.contains("k = 7  # from environment variable MAVLOC_INDOOR__K"), "{out}");
}

#[test]
fn run_refuses_a_bad_mavlink_address() {
    let a = mavloc().args(["run", "--mavlink", "udp:14540"]).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("mavlink.connection") && err.contains("unknown scheme"), "{err}");
}

#[test]
fn sim_vehicle_names_a_bad_address() {
    let a = mavloc()
        .args(["sim", "vehicle", "--scenario", "indoor-floor", "--mavlink", "serial:/dev/x"])
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("serial:/dev/x"), "{err}");
}

#[test]
fn indoor_train_names_a_missing_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-dataset");
    let a = mavloc()
        .args(["indoor", "train", "--dataset"])
        .arg(&missing)
        .args(["--out"])
        .arg(dir.path().join("m.json"))
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("no-such-dataset"), "{err}");
    assert!(!dir.path().join("m.json").exists());
}

#[test]
#[ignore = "two live flights, minutes of wall-clock time: make check-long"]
fn demo_runs_both_flights_and_prints_its_report() {
    let dir = tempfile::tempdir().unwrap();
    // A short version (25 s of coastline, a small indoor model) checks that the demo runs
    // to completion and reports: exit 0 (PASS) or 2 (ran, but missed its accuracy bar),
    // never 1 (an error). Accuracy itself is asserted by closed_loop and indoor_live.
    let out = mavloc()
        .timeout(std::time::Duration::from_secs(300))
        .args(["demo", "--coast-s", "25", "--indoor-s", "45", "--views", "400", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        matches!(out.status.code(), Some(0) | Some(2)),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for needle in ["coastline", "landmarks", "indoor floor", "RMS error in flight", "landing", "result "] {
        assert!(stdout.contains(needle), "`{needle}` missing: {stdout}");
    }
    assert!(!stdout.contains("frames processed 0,"), "both flights processed frames: {stdout}");
    assert!(dir.path().join("coastline/state/results/area/views.png").exists());
    assert!(dir.path().join("indoor/state/results/indoor/trajectory.png").exists());
}

#[test]
fn area_on_a_missing_dataset_names_the_folder() {
    let dir = tempfile::tempdir().unwrap();
    let a = mavloc()
        .args(["area", "--dataset"])
        .arg(dir.path().join("nope"))
        .arg("--out")
        .arg(dir.path().join("out"))
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    // The folder, not a file inside it (it said "nope/camera.toml: No such file").
    assert!(err.contains("dataset ") && err.contains("nope: No such file or directory"), "{err}");
    assert!(!err.contains("camera.toml"), "{err}");
}

#[test]
fn indoor_map_eval_prints_the_global_loss_and_writes_the_heat_map() {
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("eval.png");
    let out = assert_cmd::Command::cargo_bin("mavloc")
        .unwrap()
        .args(["indoor", "map-eval", "--map", "sim/assets/aukerman.png", "--metres-per-px", "0.01"])
        .args(["--views", "40", "--json", "--out"])
        .arg(&png)
        .timeout(std::time::Duration::from_secs(300))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let loss = v["global_loss"].as_f64().unwrap();
    assert!(loss.is_finite() && loss > -1.0 && loss < 1.0, "{loss}");
    assert!(png.exists());
    let bad = assert_cmd::Command::cargo_bin("mavloc")
        .unwrap()
        .args(["indoor", "map-eval", "--map", "no-such.png"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("no-such.png"));
    // An --out it cannot write is refused before the views are rendered, naming it.
    for (out, says) in
        [(dir.path().to_path_buf(), "is a folder"), (dir.path().join("no/x.png"), "does not exist")]
    {
        let a = mavloc()
            .args(["indoor", "map-eval", "--map", "sim/assets/aukerman.png", "--out"])
            .arg(&out)
            .assert()
            .failure();
        let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
        assert!(err.contains(says) && err.contains(&out.display().to_string()), "{err}");
    }
}

/// A value tuned over MAVLink is a visible layer: `config show` names it, `--set` beats
/// it, `params list` lists it and `params reset` forgets it.
#[test]
fn tuned_values_are_a_visible_layer_below_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).unwrap();
    std::fs::write(state.join("params.json"), r#"{"IND_LAND_R": 1.0}"#).unwrap();
    let mavloc = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_mavloc"))
            .args(["--set", &format!("daemon.state_dir={}", state.display())])
            .args(args)
            .env_remove("STATE_DIRECTORY")
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let show = mavloc(&["config", "show"]);
    assert!(show.contains("landing_radius_m = 1.0  # from tuned over MAVLink"), "{show}");
    let show = mavloc(&["--set", "indoor.landing_radius_m=2", "config", "show"]);
    assert!(show.contains("landing_radius_m = 2.0  # from command line"), "{show}");
    assert!(
        show.contains("IND_LAND_R = 1 is tuned in") && show.contains("--set indoor.landing_radius_m wins"),
        "{show}"
    );
    let list = mavloc(&["params", "list"]);
    assert!(
        list.contains("IND_LAND_R") && list.contains("indoor.landing_radius_m") && list.contains("yes"),
        "{list}"
    );
    mavloc(&["params", "reset", "IND_LAND_R"]);
    assert!(mavloc(&["params", "list"]).contains("no values tuned"));
    assert!(!mavloc(&["config", "show"]).contains("# from tuned over MAVLink"));
}

/// `mavloc ... | head`: a reader that goes away ends the command quietly (SIGPIPE, as any
/// Unix tool), never a Rust panic (exit 101).
#[test]
fn a_closed_output_pipe_ends_quietly_not_in_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .args(["config", "show"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The reader goes away before mavloc has printed: every line meets a closed pipe.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_ne!(out.status.code(), Some(101), "{stderr}");
    assert!(out.status.success() || out.status.signal() == Some(libc::SIGPIPE), "{:?}", out.status);
}

/// `config check` refuses what `run` cannot use (a missing model, a camera with no path),
/// and `run` refuses the same with exit 78 instead of running without a pipeline.
#[test]
fn config_check_and_run_refuse_the_files_run_needs() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("mavloc.toml");
    std::fs::write(
        &file,
        "[daemon]\npipeline = \"indoor\"\n[indoor]\nmodel = \"floor.model\"\n[camera]\nsource = \"file\"\n",
    )
    .unwrap();
    let mavloc = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_mavloc"))
            .args(args)
            .env_remove("STATE_DIRECTORY")
            .output()
            .unwrap()
    };
    let check = mavloc(&["config", "check", file.to_str().unwrap()]);
    let said = String::from_utf8_lossy(&check.stderr);
    assert!(!check.status.success(), "{said}");
    // Both problems in one report; the model is looked for beside the file.
    assert!(
        said.contains("2 problems") && said.contains("indoor.model") && said.contains("camera.path"),
        "{said}"
    );
    assert!(said.contains(&dir.path().join("floor.model").display().to_string()), "{said}");
    let state = dir.path().join("state");
    let run = mavloc(&[
        "--config",
        file.to_str().unwrap(),
        "--set",
        &format!("daemon.state_dir={}", state.display()),
        "run",
    ]);
    assert_eq!(run.status.code(), Some(78), "{}", String::from_utf8_lossy(&run.stderr));
    // Files that exist but are not what they should be: refused the same way (before,
    // `check` said valid and `run` stayed up without a pipeline).
    std::fs::write(dir.path().join("floor.model"), b"").unwrap();
    std::fs::write(dir.path().join("empty.mp4"), b"").unwrap();
    let video = format!("camera.path={}", dir.path().join("empty.mp4").display());
    let check = mavloc(&["config", "check", "--set", &video, file.to_str().unwrap()]);
    let said = String::from_utf8_lossy(&check.stderr);
    assert!(
        said.contains("2 problems")
            && said.contains("not a mavloc model")
            && said.contains("empty.mp4 is empty"),
        "{said}"
    );
    std::fs::copy(crate::fixtures::small_indoor_model(), dir.path().join("floor.model")).unwrap();
    let check = mavloc(&["config", "check", file.to_str().unwrap()]);
    let said = String::from_utf8_lossy(&check.stderr);
    assert!(said.contains("1 problem") && !said.contains("indoor.model"), "{said}");
}

/// `sim render --force` replaces a dataset whole: a 2-frame render over a 5-frame one
/// leaves 2 frames, not 5 beside 2 lines of telemetry. A failed render leaves no folder.
#[test]
fn a_forced_render_replaces_the_dataset_whole_and_a_failed_one_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let render = |frames: &str, force: bool| {
        let mut c = mavloc();
        c.args([
            "sim",
            "render",
            "--scenario",
            "coastline",
            "--width",
            "96",
            "--height",
            "54",
            "--frames",
            frames,
        ])
        .arg("--out")
        .arg(&ds);
        if force {
            c.arg("--force");
        }
        c.assert()
    };
    let first = render("5", false).success();
    // Not a terminal here: progress comes as lines, from the first frame to the last.
    let err = String::from_utf8_lossy(&first.get_output().stderr).to_string();
    assert!(err.contains("rendering coastline: 1/5 frames") && err.contains("5/5 frames (100 %)"), "{err}");
    assert_eq!(std::fs::read_dir(ds.join("frames")).unwrap().count(), 5);
    let err = String::from_utf8_lossy(&render("2", false).failure().get_output().stderr).to_string();
    assert!(err.contains("--force"), "{err}");
    render("2", true).success();
    assert_eq!(std::fs::read_dir(ds.join("frames")).unwrap().count(), 2, "no stale frames");
    assert_eq!(mavloc_data::Dataset::open(&ds).unwrap().records.len(), 2);
    // A render that fails part way (an invalid size here) leaves nothing to block a retry.
    let bad = dir.path().join("bad");
    mavloc()
        .args(["sim", "render", "--scenario", "coastline", "--width", "0", "--height", "54", "--out"])
        .arg(&bad)
        .assert()
        .failure();
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left, ["ds"], "{left:?}");
}

/// A run that can use no frame (every frame a truncated image here) exits non-zero and
/// names the file and the reason; results inside the dataset, or raw photos given as a
/// dataset, are refused with what to do instead.
#[test]
fn an_area_run_that_processes_nothing_fails_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    mavloc()
        .args([
            "sim",
            "render",
            "--scenario",
            "coastline",
            "--width",
            "96",
            "--height",
            "54",
            "--frames",
            "3",
        ])
        .arg("--out")
        .arg(&ds)
        .assert()
        .success();
    for e in std::fs::read_dir(ds.join("frames")).unwrap() {
        let p = e.unwrap().path();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 3]).unwrap();
    }
    let a = mavloc()
        .args(["area", "--dataset"])
        .arg(&ds)
        .arg("--out")
        .arg(dir.path().join("out"))
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("no frame") && err.contains("3 skipped") && err.contains("000000.png"), "{err}");

    let a = mavloc().args(["area", "--dataset"]).arg(&ds).arg("--out").arg(ds.join("out")).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("inside"), "{err}");
    assert!(!ds.join("out").exists());

    let photos = dir.path().join("photos");
    std::fs::create_dir(&photos).unwrap();
    std::fs::write(photos.join("DJI_0001.JPG"), b"x").unwrap();
    let a = mavloc()
        .args(["area", "--dataset"])
        .arg(&photos)
        .arg("--out")
        .arg(dir.path().join("o2"))
        .assert()
        .failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("mavloc import photos"), "{err}");
}

/// A file with problems of every kind gets them all in one run of `config check`, each
/// with its key, file and what is allowed (an integer beyond its type with the range), and
/// exits 78 like `run`; the same file given twice ways, or two different files, is clear.
#[test]
fn config_check_reports_every_problem_of_every_layer_in_one_pass() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("mavloc.toml");
    std::fs::write(
        &file,
        "[area]\nukf_alfa = 0.7\nmethod = \"magic\"\n[indoor]\nparticles = 0\nmodel = \"gone.model\"\n\
         [mavlink]\nsystem_id = 300\n[daemon]\npipeline = \"indoor\"\n",
    )
    .unwrap();
    let a = mavloc()
        .args(["config", "check"])
        .arg(&file)
        .env("MAVLOC_AREA__L_MAX", "many")
        .args(["--set", "area.downscale=x"])
        .assert()
        .code(78);
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    let f = file.display().to_string();
    for needle in [
        "7 problems",
        "area.ukf_alfa",
        "area.method = \"magic\"",
        "indoor.particles = 0",
        "mavlink.system_id = 300",
        "an integer from 0 to 255",
        "MAVLOC_AREA__L_MAX",
        "area.downscale",
        "gone.model",
        &f,
    ] {
        assert!(err.contains(needle), "`{needle}` missing from: {err}");
    }
    let sysid = err.lines().find(|l| l.contains("mavlink.system_id")).unwrap();
    assert!(sysid.contains(&f), "the file is named: {sysid}");

    let other = dir.path().join("other.toml");
    std::fs::write(&other, "").unwrap();
    let a = mavloc().arg("--config").arg(&other).args(["config", "check"]).arg(&file).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("two files"), "{err}");
    let out = stdout_of(mavloc().arg("--config").arg(&other).args(["config", "check"]));
    assert!(out.contains("other.toml: valid"), "--config is what is checked: {out}");
}

/// A missing file's OS error is said once, not once more as its cause.
#[test]
fn a_missing_configuration_file_is_named_once() {
    let a = mavloc().args(["config", "check", "/nonexistent/mavloc.toml"]).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert_eq!(err.matches("No such file").count(), 1, "{err}");
}

/// The native library lines OpenCV's decoders write to fd 2 (here libjpeg's on JPEG frames
/// with stray bytes before their end, which a `file` camera still reads) reach the log
/// through `tracing`, target `opencv`, not as raw lines; and a file that is no video is
/// refused before `run` starts without OpenCV's backends' raw `[ WARN:0@...]` lines.
#[test]
fn opencv_log_lines_go_through_tracing() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bad.mp4"), b"not a video").unwrap();
    let bad = mavloc()
        .args(["config", "check", "--set", "camera.source=file", "--set", "area.segmenter=water"])
        .arg("--set")
        .arg(format!("camera.path={}", dir.path().join("bad.mp4").display()))
        .arg(temp_config("").path())
        .assert()
        .code(78);
    let err = String::from_utf8_lossy(&bad.get_output().stderr).to_string();
    assert!(err.contains("bad.mp4 is not a video OpenCV can read"), "{err}");
    assert!(!err.lines().any(|l| l.starts_with("[ WARN:")), "{err}");
    // Frames whose scan is followed by stray bytes: libjpeg decodes them and warns.
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let img = opencv::core::Mat::new_rows_cols_with_default(
        48,
        64,
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(120.0),
    )
    .unwrap();
    let mut jpeg = opencv::core::Vector::<u8>::new();
    opencv::imgcodecs::imencode(".jpg", &img, &mut jpeg, &opencv::core::Vector::new()).unwrap();
    let mut bytes: Vec<u8> = jpeg.iter().collect();
    let end = bytes.len() - 2;
    bytes.splice(end..end, [0x12u8, 0x34, 0x56, 0x78]);
    for i in 0..30 {
        std::fs::write(frames.join(format!("{i:04}.jpg")), &bytes).unwrap();
    }
    let port = std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let config = dir.path().join("mavloc.toml");
    std::fs::write(
        &config,
        format!(
            "[camera]\nsource = \"file\"\npath = \"frames\"\nwidth = 64\nheight = 48\n[area]\nsegmenter = \"water\"\n[mavlink]\nconnection = \"udpin:127.0.0.1:{port}\"\n\
             [daemon]\nstate_dir = \"{}\"\n",
            dir.path().join("state").display(),
        ),
    )
    .unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .arg("--config")
        .arg(&config)
        .arg("run")
        .env_remove("STATE_DIRECTORY")
        .env_remove("NOTIFY_SOCKET")
        .stderr(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_secs(3));
    // SAFETY: signalling our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let started = std::time::Instant::now();
    while child.try_wait().unwrap().is_none() && started.elapsed().as_secs() < 10 {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let _ = child.kill();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("WARN opencv: image decoder: Corrupt JPEG data"), "{err}");
    assert!(!err.lines().any(|l| l.starts_with("Corrupt JPEG") || l.starts_with("[ WARN:")), "{err}");
}

/// The README's parameter table is the one the code generates (`mavloc params doc`).
#[test]
fn the_readme_parameter_table_matches_the_code() {
    let generated = stdout_of(mavloc().args(["params", "doc"]));
    let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let start = readme.find("<!-- params:begin -->\n").expect("README has the table's start marker");
    let end = readme.find("<!-- params:end -->").expect("README has the table's end marker");
    let table = &readme[start + "<!-- params:begin -->\n".len()..end];
    assert_eq!(table, generated, "regenerate with `mavloc params doc` between the markers");
    assert!(
        generated.contains("| `IND_LAND_R` | `indoor.landing_radius_m` | float | m | 0.05 ..= 100 | 0.6 |")
    );
}

/// `--debug-masks` shows every frame, 12 to a page (a survey's 18 photos used to get a
/// sheet of at most 12, spread out).
#[test]
fn contact_sheets_show_every_frame_twelve_to_a_page() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    mavloc()
        .args([
            "sim",
            "render",
            "--scenario",
            "coastline",
            "--width",
            "192",
            "--height",
            "108",
            "--frames",
            "14",
        ])
        .arg("--out")
        .arg(&ds)
        .assert()
        .success();
    let out = dir.path().join("out");
    mavloc().args(["area", "--debug-masks", "--dataset"]).arg(&ds).arg("--out").arg(&out).assert().success();
    let page = |n: &str| {
        opencv::imgcodecs::imread(out.join(n).to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap()
    };
    use opencv::prelude::*;
    let (first, second) = (page("masks-01.png"), page("masks-02.png"));
    assert!(!out.join("masks.png").exists() && !out.join("masks-03.png").exists());
    let tile_h = 270; // 480 px wide tiles of a 16:9 frame
    assert_eq!((first.rows(), second.rows()), (12 * tile_h, 2 * tile_h), "12 frames, then the other 2");
}

/// The value and the SD of `gimbal.KEY` in `calibrate gimbal`'s output.
fn calibrated(out: &str, key: &str) -> (f64, f64) {
    let line =
        out.lines().find(|l| l.starts_with(&format!("gimbal.{key} = "))).unwrap_or_else(|| panic!("{out}"));
    let v: f64 = line.split(' ').nth(2).unwrap().parse().unwrap();
    let sd: f64 = line.split("(SD ").nth(1).unwrap().split(' ').next().unwrap().parse().unwrap();
    (v, sd)
}

/// `calibrate gimbal` recovers a static gimbal offset (seed sec. 6.11) from a flight's own
/// landmarks, states its uncertainty, and writes it into a configuration file keeping the
/// file's other lines; with a surveyed marker (a shore point, its pixel in each frame where
/// the true camera sees it) the marker anchors it, as the seed's reference marker does.
#[test]
fn calibrate_gimbal_recovers_a_static_offset_and_writes_it() {
    let dir = tempfile::tempdir().unwrap();
    let ds = crate::fixtures::offset_flight();
    let config = dir.path().join("mavloc.toml");
    std::fs::write(
        &config,
        "# my drone\n[gimbal]\nchain = \"yaw-pitch-roll\" # kept\npitch_offset_deg = 0.0 # deg, from the bench\n",
    )
    .unwrap();
    let out =
        stdout_of(mavloc().args(["calibrate", "gimbal", "--dataset"]).arg(&ds).arg("--write").arg(&config));
    // The reported angles carry the offset; the correction is its opposite.
    let want = [("yaw_offset_deg", -1.5), ("pitch_offset_deg", 2.0), ("roll_offset_deg", -0.5)];
    for (key, want) in want {
        let (v, sd) = calibrated(&out, key);
        assert!((v - want).abs() < 0.2, "{key}: {v} (want {want})\n{out}");
        assert!(sd < 0.2, "{key}: SD {sd}\n{out}");
    }
    let written = std::fs::read_to_string(&config).unwrap();
    assert!(
        written.starts_with("# my drone\n")
            && written.contains("chain = \"yaw-pitch-roll\" # kept")
            && written.contains(" # deg, from the bench"),
        "{written}"
    );
    let check = stdout_of(mavloc().args(["config", "check"]).arg(&config));
    assert!(check.contains("valid"), "{check}");
    let doc: toml::Table = written.parse().unwrap();
    let pitch = doc["gimbal"]["pitch_offset_deg"].as_float().unwrap();
    assert!((pitch - 2.0).abs() < 0.2, "{written}");

    // The marker.
    let d = mavloc_data::Dataset::open(&ds).unwrap();
    let k = d.camera.intrinsics();
    let candidates: Vec<_> = d.ground_truth.iter().flatten().step_by(7).copied().collect();
    let seen_in = |p: &mavloc_geometry::Vec3| -> Vec<(u64, mavloc_geometry::Pixel)> {
        d.records
            .iter()
            .filter_map(|r| {
                let pose = r.truth.camera_pose(d.camera.chain, d.camera.gimbal_frame);
                pose.project(&k, p).filter(|px| k.contains(*px)).map(|px| (r.frame, px))
            })
            .collect()
    };
    let marker = candidates.iter().max_by_key(|p| seen_in(p).len()).unwrap();
    let sightings = seen_in(marker);
    assert!(sightings.len() >= 20, "{} sightings", sightings.len());
    let csv: String = std::iter::once("frame,u,v\n".to_string())
        .chain(sightings.iter().map(|(f, px)| format!("{f},{:.3},{:.3}\n", px.u, px.v)))
        .collect();
    let pixels = dir.path().join("marker.csv");
    std::fs::write(&pixels, csv).unwrap();
    // With the marker, and an SD bound no flight meets: the offsets are printed, nothing
    // is written, exit 2.
    let before = std::fs::read_to_string(&config).unwrap();
    let a = mavloc()
        .args(["calibrate", "gimbal", "--dataset"])
        .arg(&ds)
        .arg(format!("--marker={},{},{}", marker.x, marker.y, marker.z))
        .arg("--marker-pixels")
        .arg(&pixels)
        .args(["--max-sd-deg", "0.001", "--write"])
        .arg(&config)
        .assert()
        .code(2);
    let out = String::from_utf8_lossy(&a.get_output().stdout).to_string();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(
        err.contains("not determined within --max-sd-deg 0.001") && err.contains("left unchanged"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&config).unwrap(), before, "an unsure calibration is not written");
    assert!(out.contains("and the marker"), "{out}");
    for (key, want) in want {
        let (v, _) = calibrated(&out, key);
        assert!((v - want).abs() < 0.2, "with the marker, {key}: {v} (want {want})\n{out}");
    }
}

/// The names in a folder, sorted.
fn names_in(dir: &std::path::Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// Waits (at most 60 s) until `child` has written a checkpoint (`summary.json`, every 100
/// frames) into its staging folder `.NAME.partial-PID` in `parent`.
fn wait_for_checkpoint(parent: &std::path::Path, name: &str, child: &mut std::process::Child) {
    let stage = parent.join(format!(".{name}.partial-{}", child.id()));
    let start = std::time::Instant::now();
    while !stage.join("summary.json").exists() {
        assert!(child.try_wait().unwrap().is_none(), "the run ended before its first checkpoint");
        assert!(start.elapsed().as_secs() < 60, "no checkpoint after 60 s");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
}

/// `mavloc area --out R` replaces R's results as a set. A later run leaves no file of an
/// earlier one beside its own (the earlier run's trace and contact sheets); a run killed
/// part way leaves the earlier set exactly as it was (each file written atomically was
/// not enough: such a run left a new `landmarks.csv` beside the old `summary.json`), and
/// its checkpoint is kept by the next run as `r.interrupted-PID`; Ctrl-C ends a run after
/// its frame, putting the frames so far in place (`complete: false`, ended by SIGINT), or
/// beside complete earlier results as `r.stopped`; a result is not measured against
/// another dataset; a folder of other files is refused, not replaced.
#[test]
fn area_results_are_replaced_as_a_set_and_an_interrupted_run_leaves_the_last_one() {
    let short = crate::fixtures::small_flight("coastline", 30);
    let long = crate::fixtures::small_flight("coastline", 240);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("r");
    let small = ["--set", "area.downscale=1", "--set", "area.band_px=13"];
    let area = |ds: &std::path::Path| {
        let mut c = mavloc();
        c.args(["area", "--dataset"]).arg(ds).arg("--out").arg(&out).args(small);
        c
    };
    stdout_of(area(&short).args(["--trace", "--debug-masks"]));
    let first = names_in(&out);
    assert!(
        first.contains(&"trace.csv".to_string()) && first.iter().any(|n| n.starts_with("masks")),
        "{first:?}"
    );
    stdout_of(area(&short).args(["--method", "ground-plane"]));
    let second = names_in(&out);
    assert!(
        !second.iter().any(|n| n == "trace.csv" || n.starts_with("masks")),
        "the ground-plane run's folder holds the earlier run's files: {second:?}"
    );
    let summary = |p: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p.join("summary.json")).unwrap()).unwrap()
    };
    assert_eq!(summary(&out)["method"], "ground-plane");
    let snapshot = |p: &std::path::Path| -> Vec<(String, Vec<u8>)> {
        names_in(p).into_iter().map(|n| (n.clone(), std::fs::read(p.join(&n)).unwrap())).collect()
    };
    let before = snapshot(&out);
    // Measured against another dataset than the one it was made from: refused, its plots
    // left alone.
    let a =
        mavloc().args(["eval", "area", "--dataset"]).arg(&long).arg("--result").arg(&out).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("made from another dataset"), "{err}");
    assert!(snapshot(&out) == before, "a refused evaluation changed the result");

    // Killed part way through a longer run, after its first checkpoint.
    let spawn = |to: &std::path::Path| {
        crate::fixtures::ctrl_c_reaches(&mut std::process::Command::new(crate::fixtures::BIN))
            .args(["area", "--dataset"])
            .arg(&long)
            .arg("--out")
            .arg(to)
            .args(small)
            .env_remove("MAVLOC_CONFIG")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    let mut child = spawn(&out);
    let killed = child.id();
    wait_for_checkpoint(dir.path(), "r", &mut child);
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(snapshot(&out) == before, "a killed run changed the earlier results: {:?}", names_in(&out));

    // Ctrl-C after a checkpoint; SIGINT is handled from before the staging folder exists.
    let interrupt = |to: &std::path::Path, name: &str| {
        let mut child = spawn(to);
        wait_for_checkpoint(dir.path(), name, &mut child);
        // SAFETY: a plain kill(2) of our own child.
        assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
        let stderr = crate::fixtures::read_in_background(child.stderr.take().unwrap());
        let start = std::time::Instant::now();
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break s;
            }
            assert!(start.elapsed().as_secs() < 60, "Ctrl-C did not end the run within 60 s");
            std::thread::sleep(std::time::Duration::from_millis(50));
        };
        let stderr = stderr.join().unwrap();
        // Ended by SIGINT itself (the shell's 130), so a script running it stops too.
        assert_eq!(std::os::unix::process::ExitStatusExt::signal(&status), Some(libc::SIGINT), "{stderr}");
        assert!(stderr.contains("stopped by Ctrl-C"), "{stderr}");
        stderr
    };
    let stopped_partial = |p: &std::path::Path| {
        let s = summary(p);
        assert_eq!((s["method"].as_str(), s["complete"].as_bool()), (Some("ukf"), Some(false)), "{s}");
        let frames = s["frames"].as_u64().unwrap();
        assert!((100..240).contains(&frames), "{frames} frames");
    };
    // Over the complete ground-plane results: they stay, the stopped run's go beside.
    let said = interrupt(&out, "r");
    assert!(said.contains("beside the complete results"), "{said}");
    assert!(snapshot(&out) == before, "a stopped run replaced complete results");
    stopped_partial(&dir.path().join("r.stopped"));
    // The killed run's checkpoint, kept by the run after it.
    let kept = dir.path().join(format!("r.interrupted-{killed}"));
    assert_eq!(summary(&kept)["complete"], false, "{:?}", names_in(dir.path()));
    // Into a new folder: the frames so far are the results.
    let fresh = dir.path().join("r2");
    interrupt(&fresh, "r2");
    stopped_partial(&fresh);
    let left: Vec<String> = names_in(dir.path()).into_iter().filter(|n| n.starts_with('.')).collect();
    assert!(left.is_empty(), "staging folders left: {left:?}");

    // A folder that holds something else.
    let other = dir.path().join("notes");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("a.txt"), "mine").unwrap();
    let a = mavloc().args(["area", "--dataset"]).arg(&short).arg("--out").arg(&other).assert().failure();
    let err = String::from_utf8_lossy(&a.get_output().stderr).to_string();
    assert!(err.contains("not mavloc results"), "{err}");
    assert_eq!(names_in(&other), ["a.txt"]);
}

/// `--frames-from` a dataset with fewer frames than the render asks for says so (it said
/// the frame was "dropped when it was rendered", which nothing was).
#[test]
fn frames_from_a_shorter_dataset_says_where_it_ends() {
    let dir = tempfile::tempdir().unwrap();
    let short = dir.path().join("short");
    let render = ["sim", "render", "--scenario", "coastline", "--width", "160", "--height", "90"];
    stdout_of(mavloc().args(render).args(["--frames", "2", "--out"]).arg(&short));
    let out = mavloc()
        .args(render)
        .args(["--frames", "4", "--gimbal-sd-deg", "1", "--frames-from"])
        .arg(&short)
        .arg("--out")
        .arg(dir.path().join("longer"))
        .assert()
        .failure();
    let said = String::from_utf8_lossy(&out.get_output().stderr).to_string();
    assert!(
        said.contains("it ends at frame 1 (rendered with fewer frames")
            && said.contains("needs frame 2")
            && said.contains("--frames 2"),
        "{said}"
    );
    assert!(!said.contains("dropped when it was rendered"), "{said}");
}

/// Ctrl-C stops `mavloc sim render` after the frame in hand: the staging folder with the
/// frames so far removed, the dataset the render was replacing (`--force`) left as it was,
/// and the process ended by SIGINT (so a shell script running it stops as well). Before,
/// SIGINT killed the process at once and the hidden `.NAME.partial-PID` folder stayed
/// until the next render into the same folder. Started with SIGINT ignored (a background
/// job of a script), the render keeps ignoring it and completes.
#[test]
fn ctrl_c_stops_a_render_leaving_the_earlier_dataset_and_no_staging_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ds");
    let render = ["sim", "render", "--scenario", "coastline", "--width", "480", "--height", "270"];
    stdout_of(mavloc().args(render).args(["--frames", "3", "--out"]).arg(&out));
    let before: Vec<(String, Vec<u8>)> = names_in(&out.join("frames"))
        .into_iter()
        .map(|n| (n.clone(), std::fs::read(out.join("frames").join(&n)).unwrap()))
        .collect();
    let telemetry = std::fs::read(out.join("telemetry.jsonl")).unwrap();
    let mut child = crate::fixtures::ctrl_c_reaches(&mut std::process::Command::new(crate::fixtures::BIN))
        .args(render)
        .args(["--frames", "2000", "--force", "--out"])
        .arg(&out)
        .env_remove("MAVLOC_CONFIG")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = crate::fixtures::read_in_background(child.stderr.take().unwrap());
    let stage = dir.path().join(format!(".ds.partial-{}", child.id()));
    let start = std::time::Instant::now();
    interrupt_after_three_frames(&stage, &mut child);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed().as_secs() < 60, "Ctrl-C did not end the render");
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    let said = stderr.join().unwrap();
    assert_eq!(std::os::unix::process::ExitStatusExt::signal(&status), Some(libc::SIGINT), "{said}");
    assert!(said.contains("stopped by Ctrl-C; nothing written") && said.contains("left as it was"), "{said}");
    assert!(!stage.exists(), "the staging folder is left: {:?}", names_in(dir.path()));
    assert_eq!(names_in(dir.path()), ["ds"]);
    let after: Vec<(String, Vec<u8>)> = names_in(&out.join("frames"))
        .into_iter()
        .map(|n| (n.clone(), std::fs::read(out.join("frames").join(&n)).unwrap()))
        .collect();
    assert!(after == before, "the earlier dataset's frames changed");
    assert_eq!(std::fs::read(out.join("telemetry.jsonl")).unwrap(), telemetry);

    // SIGINT ignored from the start: the signal changes nothing.
    let mut child = {
        use std::os::unix::process::CommandExt;
        let mut c = std::process::Command::new(crate::fixtures::BIN);
        c.args(render).args(["--frames", "30", "--force", "--out"]).arg(&out);
        c.env_remove("MAVLOC_CONFIG").stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null());
        // SAFETY: signal(2) only, between fork and exec.
        unsafe {
            c.pre_exec(|| {
                libc::signal(libc::SIGINT, libc::SIG_IGN);
                Ok(())
            })
        };
        c.spawn().unwrap()
    };
    interrupt_after_three_frames(&dir.path().join(format!(".ds.partial-{}", child.id())), &mut child);
    assert!(child.wait().unwrap().success());
    assert_eq!(names_in(&out.join("frames")).len(), 30, "the render went on to its end");
}

/// Sends SIGINT to a render once it has some frames in its staging folder `stage`, not yet
/// the whole flight.
fn interrupt_after_three_frames(stage: &std::path::Path, child: &mut std::process::Child) {
    let start = std::time::Instant::now();
    while std::fs::read_dir(stage.join("frames")).map_or(0, |d| d.count()) < 3 {
        assert!(child.try_wait().unwrap().is_none(), "the render ended before it was interrupted");
        assert!(start.elapsed().as_secs() < 60, "no frame rendered after 60 s");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    // SAFETY: a plain kill(2) of our own child.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
}
