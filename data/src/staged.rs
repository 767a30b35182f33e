//! Folders written whole: a dataset or an import is written into a hidden sibling folder
//! and put in place in one step, so an interrupted or failed run never leaves a
//! half-written folder (which would block the corrected retry), and `--force` replaces the
//! old folder as a whole instead of writing over it (stale frames beside new telemetry).
//!
//! On Linux the finished folder and the old one are swapped by `renameat2(RENAME_EXCHANGE)`
//! — one atomic step — and the old one is then removed; elsewhere the old one is first
//! moved aside. A crash before the swap leaves the old folder untouched and a
//! `.NAME.partial-PID` sibling that the next run removes.

use std::fs;
use std::path::{Path, PathBuf};

/// A folder being written beside its final place; dropped without [`StagedDir::commit`]
/// it is removed.
#[derive(Debug)]
pub struct StagedDir {
    target: PathBuf,
    stage: PathBuf,
    committed: bool,
}

impl StagedDir {
    /// Starts writing `target`. It must be absent or empty unless `replace` (`--force`).
    /// A `target` that is a symbolic link is followed: the folder it points to is
    /// replaced and the link stays (on a drone `data -> /mnt/sd/data` would otherwise
    /// become a real folder on the root file system).
    pub fn begin(target: &Path, replace: bool) -> Result<Self, String> {
        let target = &followed(target)?;
        if target.exists() {
            if !target.is_dir() {
                return Err(format!("{} exists and is not a folder", target.display()));
            }
            let non_empty = fs::read_dir(target)
                .map_err(|e| format!("cannot read {}: {e}", target.display()))?
                .next()
                .is_some();
            if non_empty && !replace {
                return Err(format!("{} is not empty; pass --force to replace it whole", target.display()));
            }
        }
        let name = target
            .file_name()
            .ok_or_else(|| format!("{} does not name a folder", target.display()))?
            .to_string_lossy()
            .into_owned();
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        fs::create_dir_all(&parent).map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
        // An interrupted earlier run's leftovers were never complete: remove them.
        let prefix = format!(".{name}.partial-");
        if let Ok(entries) = fs::read_dir(&parent) {
            for e in entries.flatten() {
                if e.file_name().to_string_lossy().starts_with(&prefix) {
                    let _ = fs::remove_dir_all(e.path());
                }
            }
        }
        let stage = parent.join(format!("{prefix}{}", std::process::id()));
        fs::create_dir(&stage).map_err(|e| format!("cannot create {}: {e}", stage.display()))?;
        Ok(Self { target: target.to_path_buf(), stage, committed: false })
    }

    /// Where to write: the hidden folder beside the target.
    pub fn path(&self) -> &Path {
        &self.stage
    }

    /// The folder the result will be: for messages and for reading what is there now.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Puts the finished folder in the target's place in one step and removes the old one.
    pub fn commit(mut self) -> Result<(), String> {
        // Everything written into the stage reaches the disk before the stage takes the
        // target's place: otherwise a crash soon after could leave the new folder with
        // empty files where the old one was whole. The writers do not sync file by file.
        flush(&self.stage).map_err(|e| format!("cannot flush {} to disk: {e}", self.stage.display()))?;
        let err = |e: std::io::Error| format!("cannot put {} in place: {e}", self.target.display());
        if self.target.exists() {
            swap(&self.stage, &self.target).map_err(err)?;
            // The stage now holds the old folder.
            let _ = fs::remove_dir_all(&self.stage);
        } else {
            fs::rename(&self.stage, &self.target).map_err(err)?;
        }
        if let Some(d) = self.target.parent().filter(|d| !d.as_os_str().is_empty()) {
            if let Ok(d) = fs::File::open(d) {
                let _ = d.sync_all();
            }
        }
        self.committed = true;
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_dir_all(&self.stage);
        }
    }
}

/// A pipeline's results folder (`mavloc area` or `mavloc indoor run` over a dataset),
/// written whole: `out` must be absent, empty, or an earlier run's results (it holds
/// `summary.json`), which are replaced whole, so no file of the earlier run stays beside the
/// new ones. A folder of other files, given as `--out` by mistake, is refused, not replaced.
pub fn begin_results(out: &Path) -> Result<StagedDir, String> {
    let out = followed(out)?;
    let other_files = out.is_dir()
        && !out.join("summary.json").is_file()
        && fs::read_dir(&out).map(|mut d| d.next().is_some()).unwrap_or(false);
    if other_files {
        return Err(format!(
            "{} holds files that are not mavloc results (no summary.json): give a new or empty folder as --out",
            out.display()
        ));
    }
    StagedDir::begin(&out, true)
}

/// `path` with the symbolic links at its end followed (to a target that need not exist).
fn followed(path: &Path) -> Result<PathBuf, String> {
    let mut p = path.to_path_buf();
    // As the kernel does, give up after 40 links (a loop).
    for _ in 0..40 {
        match fs::symlink_metadata(&p) {
            Ok(m) if m.file_type().is_symlink() => {
                let to =
                    fs::read_link(&p).map_err(|e| format!("cannot read the link {}: {e}", p.display()))?;
                p = match p.parent() {
                    Some(dir) if to.is_relative() => dir.join(to),
                    _ => to,
                };
            }
            _ => return Ok(p),
        }
    }
    Err(format!("{}: too many levels of symbolic links", path.display()))
}

/// Flushes a folder's files and the folder itself to disk: on Linux by one `syncfs` of
/// its file system (hundreds of frames, one flush; `std` has no wrapper), elsewhere file
/// by file.
#[cfg(target_os = "linux")]
fn flush(dir: &Path) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let d = fs::File::open(dir)?;
    // SAFETY: `d` is an open descriptor for the duration of the call.
    if unsafe { libc::syncfs(d.as_raw_fd()) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(target_os = "linux"))]
fn flush(dir: &Path) -> std::io::Result<()> {
    for e in fs::read_dir(dir)? {
        let e = e?;
        if e.file_type()?.is_dir() {
            flush(&e.path())?;
        } else {
            fs::File::open(e.path())?.sync_all()?;
        }
    }
    fs::File::open(dir)?.sync_all()
}

/// Swaps two folders: atomically on Linux (`renameat2` has no wrapper in std).
#[cfg(target_os = "linux")]
fn swap(a: &Path, b: &Path) -> std::io::Result<()> {
    use std::ffi::CString;
    use std::os::unix::ffi::OsStrExt;
    let ca = CString::new(a.as_os_str().as_bytes())?;
    let cb = CString::new(b.as_os_str().as_bytes())?;
    // SAFETY: both are valid NUL-terminated paths that outlive the call.
    let r = unsafe {
        libc::renameat2(libc::AT_FDCWD, ca.as_ptr(), libc::AT_FDCWD, cb.as_ptr(), libc::RENAME_EXCHANGE)
    };
    if r == 0 {
        return Ok(());
    }
    let e = std::io::Error::last_os_error();
    // Some file systems cannot exchange: fall back to two renames.
    if matches!(e.raw_os_error(), Some(libc::EINVAL) | Some(libc::ENOSYS)) {
        return swap_by_renames(a, b);
    }
    Err(e)
}

#[cfg(not(target_os = "linux"))]
fn swap(a: &Path, b: &Path) -> std::io::Result<()> {
    swap_by_renames(a, b)
}

/// `b` aside, `a` into its place, the old `b` to `a`'s name (so the caller removes it).
fn swap_by_renames(a: &Path, b: &Path) -> std::io::Result<()> {
    let aside = a.with_extension("old");
    fs::rename(b, &aside)?;
    if let Err(e) = fs::rename(a, b) {
        let _ = fs::rename(&aside, b);
        return Err(e);
    }
    fs::rename(&aside, a)
}

/// Whether one of two paths is the other or inside it (after resolving what exists of
/// them), so an output folder never lands inside its input or replaces it.
pub fn nested(a: &Path, b: &Path) -> bool {
    let (a, b) = (resolve(a), resolve(b));
    a.starts_with(&b) || b.starts_with(&a)
}

/// The absolute, symlink-free form of a path whose tail may not exist yet.
fn resolve(p: &Path) -> PathBuf {
    let abs =
        if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir().unwrap_or_default().join(p) };
    let mut tail = Vec::new();
    let mut head = abs.as_path();
    loop {
        if let Ok(c) = head.canonicalize() {
            return tail.iter().rev().fold(c, |acc: PathBuf, t| acc.join(t));
        }
        match (head.parent(), head.file_name()) {
            (Some(parent), Some(name)) => {
                tail.push(name.to_os_string());
                head = parent;
            }
            _ => return abs,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_replaced_folder_holds_only_the_new_files() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("set");
        let s = StagedDir::begin(&out, false).unwrap();
        for f in ["a", "b", "c"] {
            fs::write(s.path().join(f), f).unwrap();
        }
        s.commit().unwrap();
        assert_eq!(names(&out), ["a", "b", "c"]);
        let e = StagedDir::begin(&out, false).unwrap_err();
        assert!(e.contains("--force"), "{e}");
        let s = StagedDir::begin(&out, true).unwrap();
        fs::write(s.path().join("a"), "new").unwrap();
        // Until the commit the old folder is untouched.
        assert_eq!(names(&out), ["a", "b", "c"]);
        s.commit().unwrap();
        assert_eq!(names(&out), ["a"], "no stale file of the old folder");
        assert_eq!(fs::read_to_string(out.join("a")).unwrap(), "new");
        assert_eq!(names(root.path()), ["set"], "no hidden folder left");
    }

    #[test]
    fn a_failed_run_leaves_nothing_that_blocks_the_retry() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("d");
        {
            let s = StagedDir::begin(&out, false).unwrap();
            fs::write(s.path().join("half"), "x").unwrap();
            // Dropped without commit: the run failed.
        }
        assert!(!out.exists());
        assert!(names(root.path()).is_empty());
        // A crash (no drop) leaves a partial folder; the next run removes it.
        let s = StagedDir::begin(&out, false).unwrap();
        std::mem::forget(s);
        assert_eq!(names(root.path()).len(), 1);
        let s = StagedDir::begin(&out, false).unwrap();
        s.commit().unwrap();
        assert_eq!(names(root.path()), ["d"]);
    }

    #[test]
    fn a_target_that_is_a_link_keeps_the_link_and_fills_the_folder_it_points_to() {
        let root = tempfile::tempdir().unwrap();
        let real = root.path().join("sd/data");
        fs::create_dir_all(&real).unwrap();
        fs::write(real.join("old"), "x").unwrap();
        let link = root.path().join("data");
        std::os::unix::fs::symlink("sd/data", &link).unwrap();
        let s = StagedDir::begin(&link, true).unwrap();
        assert!(
            s.path().starts_with(root.path().join("sd")),
            "staged beside the real folder: {:?}",
            s.path()
        );
        fs::write(s.path().join("new"), "y").unwrap();
        s.commit().unwrap();
        assert!(fs::symlink_metadata(&link).unwrap().file_type().is_symlink(), "the link stays a link");
        assert_eq!(names(&real), ["new"]);
        assert_eq!(names(&root.path().join("sd")), ["data"], "no hidden folder left");
        // A link to a folder not made yet: made where the link points.
        let later = root.path().join("later");
        std::os::unix::fs::symlink(root.path().join("sd/later"), &later).unwrap();
        StagedDir::begin(&later, false).unwrap().commit().unwrap();
        assert!(
            root.path().join("sd/later").is_dir()
                && fs::symlink_metadata(&later).unwrap().file_type().is_symlink()
        );
    }

    #[test]
    fn nesting_is_seen_through_relative_and_missing_paths() {
        let root = tempfile::tempdir().unwrap();
        let data = root.path().join("data");
        fs::create_dir(&data).unwrap();
        assert!(nested(&data, &data.join("out")));
        let link = root.path().join("link");
        std::os::unix::fs::symlink(&data, &link).unwrap();
        assert!(nested(&link.join("out"), &data), "through a symbolic link");
        assert!(nested(&data.join("x/y"), &data));
        assert!(!nested(&data, &root.path().join("data2")));
        assert!(nested(&root.path().join("."), &data));
    }
}
