//! `make install` into a DESTDIR with PREFIX=/usr: the files, the unit pointing at the
//! binary, and a second install that keeps an edited unit and configuration.

use std::path::Path;
use std::process::Command;

fn install(dest: &Path) -> String {
    let out = Command::new("make")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["--no-print-directory", "-s", "install-files", "PREFIX=/usr"])
        .arg(format!("DESTDIR={}", dest.display()))
        .arg(format!("BIN={}", env!("CARGO_BIN_EXE_mavloc")))
        .output()
        .expect("make runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn install_honours_prefix_and_keeps_what_the_user_edited() {
    let dest = tempfile::tempdir().unwrap();
    let d = dest.path();
    install(d);
    assert!(d.join("usr/bin/mavloc").exists());
    let unit_path = d.join("etc/systemd/system/mavloc.service");
    let unit = std::fs::read_to_string(&unit_path).unwrap();
    assert!(unit.contains("ExecStart=/usr/bin/mavloc run"), "{unit}");
    assert!(unit.contains("RestartPreventExitStatus=78"));
    let config = std::fs::read_to_string(d.join("etc/mavloc/mavloc.toml")).unwrap();
    assert!(config.contains("source = \"v4l2\""), "the real-drone configuration is installed");

    // A reinstall over an untouched unit replaces it quietly.
    install(d);
    assert!(!d.join("etc/systemd/system/mavloc.service.new").exists());
    // An edited unit and configuration are kept; the new unit goes beside.
    std::fs::write(&unit_path, format!("{unit}\n# mine\n")).unwrap();
    std::fs::write(d.join("etc/mavloc/mavloc.toml"), "# mine\n").unwrap();
    let said = install(d);
    assert!(said.contains("was edited"), "{said}");
    assert!(std::fs::read_to_string(&unit_path).unwrap().ends_with("# mine\n"));
    assert!(d.join("etc/systemd/system/mavloc.service.new").exists());
    assert_eq!(std::fs::read_to_string(d.join("etc/mavloc/mavloc.toml")).unwrap(), "# mine\n");
}

/// `make sitl` without a PX4 build says what is missing and is skipped (exit 0): PX4 is
/// never part of this project.
#[test]
fn make_sitl_without_px4_is_skipped_with_a_message() {
    let out = Command::new("make")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["--no-print-directory", "-s", "sitl"])
        .env_remove("MAVLOC_PX4_DIR")
        .output()
        .expect("make runs");
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{said}{}", String::from_utf8_lossy(&out.stderr));
    assert!(said.contains("skipped") && said.contains("MAVLOC_PX4_DIR"), "{said}");
}
