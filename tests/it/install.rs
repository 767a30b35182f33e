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
    // Back within PX4's 5 s without vision (GPS-denied), and never given up on.
    let restart_s: f64 = unit
        .lines()
        .find_map(|l| l.strip_prefix("RestartSec="))
        .and_then(|v| v.trim().parse().ok())
        .expect("RestartSec in seconds");
    assert!(restart_s <= 1.0 && unit.contains("StartLimitIntervalSec=0"), "{unit}");
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

fn dpkg_deb(args: &[&str], deb: &Path) -> String {
    let out = Command::new("dpkg-deb").args(args).arg(deb).output().expect("dpkg-deb runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// `make deb` (here its packaging step on the debug binary, uncompressed): the binary, the
/// unit under /usr/lib pointing at it, the real-drone configuration as the one conffile,
/// the demo and SITL configurations as examples, library dependencies worked out, and
/// maintainer scripts that reload systemd and stop and disable the service on removal,
/// and the README with every page and picture it links to.
#[test]
fn the_debian_package_holds_the_service_and_keeps_the_configuration_as_a_conffile() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new("make")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["--no-print-directory", "-s", "deb-files", "DEB_COMPRESS=none"])
        .arg(format!("DEB_DIR={}", dir.path().display()))
        .arg(format!("BIN={}", env!("CARGO_BIN_EXE_mavloc")))
        .output()
        .expect("make runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let deb = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "deb"))
        .expect("a .deb was written");
    assert!(!dir.path().join("stage").exists(), "the staging tree is cleaned up");

    let contents = dpkg_deb(&["-c"], &deb);
    for file in [
        "./usr/bin/mavloc",
        "./usr/lib/systemd/system/mavloc.service",
        "./etc/mavloc/mavloc.toml",
        "./usr/share/doc/mavloc/copyright",
        "./usr/share/doc/mavloc/examples/sitl.toml",
        "./usr/share/doc/mavloc/examples/demo.toml",
    ] {
        assert!(contents.lines().any(|l| l.ends_with(file)), "{file} missing from:\n{contents}");
    }
    assert!(contents.lines().all(|l| l.contains("root/root")), "files owned by root:\n{contents}");
    assert_eq!(dpkg_deb(&["-I"], &deb).matches("conffiles").count(), 1);
    let ctrl = tempfile::tempdir().unwrap();
    let status = Command::new("dpkg-deb").arg("-e").arg(&deb).arg(ctrl.path()).status().unwrap();
    assert!(status.success());
    let read = |name: &str| std::fs::read_to_string(ctrl.path().join(name)).unwrap();
    assert_eq!(read("conffiles").trim(), "/etc/mavloc/mavloc.toml");
    let control = read("control");
    assert!(control.contains(&format!("Version: {}", env!("CARGO_PKG_VERSION"))), "{control}");
    let depends = control.lines().find(|l| l.starts_with("Depends:")).unwrap_or_default();
    assert!(depends.contains("libc6") && depends.contains("libopencv"), "{control}");
    assert!(read("postinst").contains("systemctl daemon-reload"));
    assert!(read("prerm").contains("systemctl disable --now mavloc.service"));
    assert!(read("postrm").contains("systemctl daemon-reload"));

    // The unit inside points at the packaged binary and stops restarting on bad config.
    let unit_dir = tempfile::tempdir().unwrap();
    let status = Command::new("dpkg-deb").arg("-x").arg(&deb).arg(unit_dir.path()).status().unwrap();
    assert!(status.success());
    let unit =
        std::fs::read_to_string(unit_dir.path().join("usr/lib/systemd/system/mavloc.service")).unwrap();
    assert!(unit.contains("ExecStart=/usr/bin/mavloc run --config /etc/mavloc/mavloc.toml"), "{unit}");
    assert!(unit.contains("RestartPreventExitStatus=78"));
    let config = std::fs::read_to_string(unit_dir.path().join("etc/mavloc/mavloc.toml")).unwrap();
    assert!(config.contains("source = \"v4l2\""), "the real-drone configuration is the conffile");

    // The packaged manual reads whole: every relative link of the README and of the notes
    // it links to (pictures, licences, the example configuration) resolves inside the
    // package.
    let doc = unit_dir.path().join("usr/share/doc/mavloc");
    let mut pages = vec![doc.join("README.md")];
    let mut seen = std::collections::HashSet::new();
    let mut checked = 0;
    while let Some(page) = pages.pop() {
        if !seen.insert(page.canonicalize().unwrap()) {
            continue;
        }
        let text = std::fs::read_to_string(&page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
        for target in relative_links(&text) {
            let path = page.parent().unwrap().join(&target);
            assert!(path.exists(), "{} links to {target}, not in the package", page.display());
            if target.ends_with(".md") {
                pages.push(path);
            }
            checked += 1;
        }
    }
    assert!(checked >= 20, "the README and its notes link to their pictures and notes ({checked} links)");
    assert!(doc.join("docs/dji-masks.LICENSE.txt").exists(), "a picture's licence travels with it");
}

/// The targets of a Markdown text's relative links (`[text](target)`), without anchors.
fn relative_links(text: &str) -> Vec<String> {
    let mut links = Vec::new();
    for (i, _) in text.match_indices("](") {
        let rest = &text[i + 2..];
        let Some(end) = rest.find(')') else { continue };
        let target = rest[..end].split('#').next().unwrap();
        if !target.is_empty() && !target.contains("://") && !target.starts_with("mailto:") {
            links.push(target.to_string());
        }
    }
    links
}
