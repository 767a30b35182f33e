//! Fixtures several test modules share, built once per run of the test binary.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

pub const BIN: &str = env!("CARGO_BIN_EXE_mavloc");

/// The small indoor model the live indoor tests fly on: 400 rendered views of the
/// indoor-floor scenario at 320x240, trained by the binary. Kept in cargo's test scratch
/// folder and rebuilt whenever the binary is newer than it, so a rerun of an unchanged
/// build does not train again.
pub fn small_indoor_model() -> &'static Path {
    static MODEL: OnceLock<PathBuf> = OnceLock::new();
    MODEL.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("indoor-floor-400");
        let model = dir.join("floor.model");
        let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
        if modified(&model).is_some() && modified(&model) >= modified(Path::new(BIN)) {
            return model;
        }
        let _ = std::fs::remove_dir_all(&dir);
        let views = dir.join("views");
        let out = Command::new(BIN)
            .args([
                "sim",
                "render",
                "--scenario",
                "indoor-floor",
                "--views",
                "400",
                "--width",
                "320",
                "--height",
                "240",
            ])
            .arg("--out")
            .arg(&views)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let out = Command::new(BIN)
            .args(["indoor", "train", "--dataset"])
            .arg(&views)
            .arg("--out")
            .arg(&model)
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        model
    })
}
