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
        let target = &absolute(&followed(target)?);
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
        let parent = target.parent().map_or_else(|| PathBuf::from("/"), Path::to_path_buf);
        // The folder is written beside the target and swapped in: the working folder
        // itself would be swapped away from under the shell, and a mount point (or a
        // folder whose parent cannot be written) cannot be swapped at all, which would be
        // found only at the end of the run.
        if std::env::current_dir().is_ok_and(|cwd| cwd.starts_with(target)) {
            return Err(format!(
                "{} is the working folder (or holds it): give a folder inside it, e.g. {}",
                target.display(),
                target.join("out").display()
            ));
        }
        fs::create_dir_all(&parent).map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
        if let (Ok(t), Ok(p)) = (fs::metadata(target), fs::metadata(&parent)) {
            use std::os::unix::fs::MetadataExt;
            if t.dev() != p.dev() {
                return Err(format!(
                    "{} is a mount point: it is replaced whole from beside it, on the same file system; give a folder inside it, e.g. {}",
                    target.display(),
                    target.join(&name).display()
                ));
            }
        }
        // What interrupted runs left: a folder of a process still running is another
        // mavloc writing the same target; one with results (`summary.json`: checkpoints of
        // a long run) is kept, renamed to `NAME.interrupted-PID`; others are removed.
        let prefix = format!(".{name}.partial-");
        if let Ok(entries) = fs::read_dir(&parent) {
            for e in entries.flatten() {
                let file = e.file_name().to_string_lossy().into_owned();
                let Some(pid) = file.strip_prefix(&prefix) else { continue };
                let pid: i32 = pid.parse().unwrap_or(0);
                if pid > 0 && pid as u32 != std::process::id() && alive(pid) {
                    return Err(format!(
                        "another process (pid {pid}) is writing {}: wait for it or stop it",
                        target.display()
                    ));
                }
                if e.path().join("summary.json").is_file() {
                    // Complete results whose swap failed (a run that said so and kept them
                    // here) are not an interrupted run's: they were named as one.
                    let complete = fs::read_to_string(e.path().join("summary.json"))
                        .ok()
                        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                        .is_some_and(|v| v.get("complete") == Some(&serde_json::Value::Bool(true)));
                    let (kind, what) = if complete {
                        ("unswapped", "complete results left beside (a run's that could not put them in place, or those it replaced, if it ended as it removed them)")
                    } else {
                        ("interrupted", "the results an interrupted run left")
                    };
                    let kept = parent.join(format!("{name}.{kind}-{pid}"));
                    let _ = fs::remove_dir_all(&kept);
                    if fs::rename(e.path(), &kept).is_ok() {
                        eprintln!("mavloc: {what} are kept in {}", kept.display());
                        continue;
                    }
                }
                let _ = fs::remove_dir_all(e.path());
            }
        }
        let stage = parent.join(format!("{prefix}{}", std::process::id()));
        fs::create_dir(&stage).map_err(|e| {
            format!(
                "cannot create {} beside {} (its folder must be writable): {e}",
                stage.display(),
                target.display()
            )
        })?;
        Ok(Self { target: target.to_path_buf(), stage, committed: false })
    }

    /// Puts the finished folder beside the target instead, as `NAME.SUFFIX` (replacing one
    /// of that name), leaving the target as it was: what a run stopped part way made, when
    /// the target holds complete results it must not replace. Returns where it went.
    pub fn commit_beside(mut self, suffix: &str) -> Result<PathBuf, String> {
        let name = self.target.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let beside = self.target.with_file_name(format!("{name}.{suffix}"));
        // On disk before it is named, as in `commit`.
        flush(&self.stage).map_err(|e| format!("cannot flush {} to disk: {e}", self.stage.display()))?;
        let _ = fs::remove_dir_all(&beside);
        fs::rename(&self.stage, &beside).map_err(|e| {
            format!("cannot put {} in place: {e}; kept as {}", beside.display(), self.stage.display())
        })?;
        self.committed = true;
        Ok(beside)
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
        // A failure from here on keeps the stage, whole, and names it: the run's work is
        // not thrown away at its last step.
        let kept = |what: String, e: std::io::Error| {
            format!("{what}: {e}; the finished folder is kept as {}", self.stage.display())
        };
        // Everything written into the stage reaches the disk before the stage takes the
        // target's place: otherwise a crash soon after could leave the new folder with
        // empty files where the old one was whole. The writers do not sync file by file.
        if let Err(e) = flush(&self.stage) {
            self.committed = true;
            return Err(kept(format!("cannot flush {} to disk", self.stage.display()), e));
        }
        let placed = if self.target.exists() {
            // The stage then holds the old folder.
            swap(&self.stage, &self.target).map(|_| {
                let _ = fs::remove_dir_all(&self.stage);
            })
        } else {
            fs::rename(&self.stage, &self.target)
        };
        if let Err(e) = placed {
            self.committed = true;
            return Err(kept(format!("cannot put {} in place", self.target.display()), e));
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
    if holds_other_files(out, &["summary.json"]) {
        return Err(format!(
            "{} holds files that are not mavloc results (no summary.json): give a new or empty folder as --out",
            out.display()
        ));
    }
    StagedDir::begin(out, true)
}

/// Stages a dataset (`mavloc import photos`, `mavloc sim render`) to replace `out`: with
/// `replace` (`--force`) only a dataset is replaced, or an empty folder. `--force` on a
/// folder of other files (the message's own advice on any folder that was not empty)
/// deleted them.
pub fn begin_dataset(out: &Path, replace: bool) -> Result<StagedDir, String> {
    if holds_other_files(out, &[crate::dataset::CAMERA_FILE, crate::dataset::TELEMETRY_FILE]) {
        return Err(format!(
            "{} holds files that are not a mavloc dataset (no {} or {}): give a new or empty folder as --out (--force replaces only a dataset)",
            out.display(),
            crate::dataset::CAMERA_FILE,
            crate::dataset::TELEMETRY_FILE
        ));
    }
    StagedDir::begin(out, replace)
}

/// Whether `out` is a folder with something in it and none of the files that mark what
/// mavloc writes there (`marks`). Through a link as well: these calls follow it.
fn holds_other_files(out: &Path, marks: &[&str]) -> bool {
    out.is_dir()
        && !marks.iter().any(|m| out.join(m).is_file())
        && fs::read_dir(out).map(|mut d| d.next().is_some()).unwrap_or(false)
}

/// Whether process `pid` exists (`kill(pid, 0)`; EPERM: it exists under another user).
fn alive(pid: i32) -> bool {
    // SAFETY: signal 0 only checks that the process exists.
    unsafe { libc::kill(pid, 0) == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM) }
}

/// `path` made absolute and free of `.` and `..` (lexically, after its links were
/// followed): `--out .` names the working folder, not a folder called ".".
fn absolute(path: &Path) -> PathBuf {
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(path)
    };
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            std::path::Component::CurDir => {}
            std::path::Component::ParentDir => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    out
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

    /// What interrupted runs left: a live process's folder means another writer (refused,
    /// its folder left alone); a dead one's checkpoint (`summary.json`) is kept in sight as
    /// `NAME.interrupted-PID`; anything else is removed.
    #[test]
    fn leftovers_of_live_and_dead_runs_are_told_apart() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("d");
        // pid 1 always runs.
        fs::create_dir(root.path().join(".d.partial-1")).unwrap();
        let e = StagedDir::begin(&out, false).unwrap_err();
        assert!(e.contains("another process (pid 1) is writing"), "{e}");
        assert!(root.path().join(".d.partial-1").is_dir(), "a live writer's folder is left alone");
        fs::remove_dir(root.path().join(".d.partial-1")).unwrap();
        // No process has a pid this high (Linux's pid_max is at most 2^22).
        let dead = root.path().join(".d.partial-99999999");
        fs::create_dir(&dead).unwrap();
        fs::write(dead.join("summary.json"), "{}").unwrap();
        fs::create_dir(root.path().join(".d.partial-99999998")).unwrap();
        // A finished set whose swap failed is kept as such, not as an interrupted run's.
        let unswapped = root.path().join(".d.partial-99999997");
        fs::create_dir(&unswapped).unwrap();
        fs::write(unswapped.join("summary.json"), r#"{"complete": true, "frames": 3}"#).unwrap();
        let s = StagedDir::begin(&out, false).unwrap();
        s.commit().unwrap();
        assert_eq!(names(root.path()), ["d", "d.interrupted-99999999", "d.unswapped-99999997"]);
        assert!(root.path().join("d.interrupted-99999999/summary.json").is_file());
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
