//! Helpers for tests, here and in mavloc's (`features = ["test-util"]` in its
//! dev-dependencies): not part of the file formats.

use std::path::Path;

/// A tmpfs mounted on a folder, unmounted when dropped: a real full disk for a test.
pub struct Tmpfs<'a>(&'a Path);

impl Drop for Tmpfs<'_> {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(self.0).status();
    }
}

/// Mounts a tmpfs of `size` (mount's syntax: `64k`) on `dir`. Where that is not allowed
/// (not root, no `mount`) the test is skipped: `None`, after printing so with `note`, which
/// says what covers the logic instead, if anything.
pub fn mount_tmpfs<'a>(dir: &'a Path, size: &str, note: &str) -> Option<Tmpfs<'a>> {
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
        .arg(dir)
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here (needs root){note}");
        return None;
    }
    Some(Tmpfs(dir))
}
