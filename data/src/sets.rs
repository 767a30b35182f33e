//! Result folders replaced as a unit, one folder per run.
//!
//! A pipeline's results are several files that belong together (the area pipeline's
//! landmarks and the border, KML and summary made from them). Writing each atomically is
//! not enough: a full disk half way through leaves a new `landmarks.csv` beside an old
//! `area.kml`. So a whole set is written into a fresh folder and published by one
//! `rename(2)` of a symbolic link. Readers keep using one fixed path,
//! `results/area/landmarks.csv`, and always see one complete set.
//!
//! Layout, for a link `results/area` (the name is the pipeline's):
//!
//! ```text
//! results/area -> area.runs/20250601T101500Z/set-12   relative symlink: the current set
//! results/area.runs/20250601T101500Z/set-12/          this run's newest complete set
//! results/area.runs/20250531T170000Z/set-40/          an earlier run's last set, kept
//! results/area.runs/legacy-20250530T120000Z/set-0/    what an older mavloc left in results/area
//! ```
//!
//! A run is one daemon start (named by its UTC start time, see [`new_run_id`]), so a
//! restart never mixes what it sees with what an earlier run saw. [`ResultSets::write`]
//! writes `set-N.partial/`, syncs every file and the folder, renames it to `set-N`, points
//! the link at it (a `.area.tmp` symlink renamed over `area`, then the parent folder
//! synced). A replaced set stays for [`REPLACED_SET_GRACE`] after the switch, so a slow
//! reader that resolved the link just before it still reads one whole set; older ones are
//! removed at the next write. On an error the new folder is removed, the previous set
//! stays current and the replaced sets still kept are removed to make room. After a crash, [`ResultSets::open`] tidies up: it
//! removes `*.partial` folders and `.area.tmp`, keeps only the newest complete set of each
//! run (moving the link to it if it pointed at an older one) and moves a real `area`
//! folder left by an older mavloc into `area.runs/legacy-<its mtime>/set-0`.
//!
//! Results that grow line by line (the indoor trajectory) have no sets: the link points at
//! the run's folder itself ([`open_run_dir`]).
//!
//! Only std: `symlink` and `rename` are all this needs. Unix only, like mavloc.

use std::fs;
use std::io;
use std::os::unix::fs::symlink;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use crate::state::{unique_name, utc_stamp};

/// A run id for a daemon start at `now`: `yyyymmddThhmmssZ` (UTC), with `-2`, `-3`, ...
/// when `taken` says a run of that name exists (two starts within a second).
pub fn new_run_id(now: SystemTime, taken: impl Fn(&str) -> bool) -> String {
    unique_name(&utc_stamp(now), taken)
}

/// How a run's folder is used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Layout {
    /// The run holds `set-N` folders; the link points at the newest.
    Sets,
    /// The run's folder holds the files; the link points at it.
    Plain,
}

/// The link `results/NAME` and its runs in `results/NAME.runs/`.
#[derive(Clone, Debug)]
pub struct Runs {
    link: PathBuf,
    root: PathBuf,
    name: String,
}

impl Runs {
    /// For the link `link` (no I/O).
    pub fn new(link: &Path) -> io::Result<Runs> {
        let name = link
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| !n.is_empty())
            .ok_or_else(|| {
                io::Error::new(io::ErrorKind::InvalidInput, format!("{}: no name", link.display()))
            })?
            .to_string();
        Ok(Runs { link: link.to_path_buf(), root: link.with_file_name(format!("{name}.runs")), name })
    }

    /// `results/NAME`, the path users read through.
    pub fn link(&self) -> &Path {
        &self.link
    }

    /// `results/NAME.runs`.
    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn run_dir(&self, run: &str) -> PathBuf {
        self.root.join(run)
    }

    fn parent(&self) -> &Path {
        self.link.parent().unwrap_or(Path::new("."))
    }

    /// The temporary link renamed over the real one.
    fn tmp_link(&self) -> PathBuf {
        self.link.with_file_name(format!(".{}.tmp", self.name))
    }

    /// The link's target as written (relative), when it is a symlink.
    fn target(&self) -> Option<PathBuf> {
        fs::read_link(&self.link).ok()
    }

    /// `dir` (under [`Runs::root`]) relative to the link's folder: what the link holds, so
    /// the state folder can be moved or mounted elsewhere.
    fn relative(&self, dir: &Path) -> io::Result<PathBuf> {
        dir.strip_prefix(self.parent()).map(Path::to_path_buf).map_err(|_| {
            io::Error::new(io::ErrorKind::InvalidInput, format!("{} is not beside the link", dir.display()))
        })
    }

    /// Points the link at `dir` in one step: a new symlink `.NAME.tmp` is renamed over
    /// `NAME` (atomic on POSIX), then the parent folder is synced so the switch survives a
    /// power cut. On failure the link is as it was.
    pub fn point_at(&self, dir: &Path) -> io::Result<()> {
        let target = self.relative(dir)?;
        let tmp = self.tmp_link();
        remove_file_if_any(&tmp)?;
        symlink(&target, &tmp)?;
        if let Err(e) = fs::rename(&tmp, &self.link) {
            let _ = fs::remove_file(&tmp);
            return Err(e);
        }
        sync_dir(self.parent());
        Ok(())
    }

    /// Start-up tidying (see the module docs). Removals are best effort: what is left is
    /// tried again at the next start and never read as a result.
    /// `own`: the run being opened, whose complete sets are left as they are (a pipeline
    /// rebuilt in the same daemon keeps the sets still in their grace); a set it left half
    /// written (a panic while writing) goes.
    fn tidy(&self, layout: Layout, own: &str) -> io::Result<()> {
        fs::create_dir_all(&self.root)
            .map_err(|e| io::Error::new(e.kind(), format!("cannot create {}: {e}", self.root.display())))?;
        let _ = remove_file_if_any(&self.tmp_link());
        self.adopt_legacy(layout)?;
        if layout == Layout::Sets {
            for run in subdirs(&self.root)? {
                let dir = self.root.join(&run);
                if run == own {
                    for p in scan(&dir).map(|s| s.partial).unwrap_or_default() {
                        let _ = fs::remove_dir_all(dir.join(p));
                    }
                    continue;
                }
                self.tidy_run(&dir);
                // A run that never wrote a set (a start on the ground, stopped before its
                // first landmark) leaves nothing to keep: `remove_dir` takes only an empty one.
                let _ = fs::remove_dir(&dir);
            }
        }
        Ok(())
    }

    /// A real folder at the link (an older mavloc wrote results straight into it) becomes
    /// a run of its own, once, and the link points at it until the new run writes.
    fn adopt_legacy(&self, layout: Layout) -> io::Result<()> {
        let meta = match fs::symlink_metadata(&self.link) {
            Ok(m) if m.is_dir() => m,
            // Someone's file: replacing it with the link would delete it.
            Ok(m) if m.is_file() => {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "{} is a file where mavloc keeps its results link; move it away",
                        self.link.display()
                    ),
                ))
            }
            _ => return Ok(()),
        };
        if fs::read_dir(&self.link)?.next().is_none() {
            return fs::remove_dir(&self.link);
        }
        let stamp = utc_stamp(meta.modified().unwrap_or_else(|_| SystemTime::now()));
        let run = unique_name(&format!("legacy-{stamp}"), |n| self.root.join(n).exists());
        let run_dir = self.root.join(run);
        let dest = match layout {
            Layout::Sets => {
                fs::create_dir(&run_dir)?;
                run_dir.join("set-0")
            }
            Layout::Plain => run_dir,
        };
        fs::rename(&self.link, &dest)?;
        sync_dir(&self.root);
        self.point_at(&dest)
    }

    /// In one run: `*.partial` removed, only the newest complete set kept. The link is
    /// moved to the newest first if it pointed at an older set of this run (a crash
    /// between publishing a set and switching the link).
    fn tidy_run(&self, run_dir: &Path) {
        let Ok(sets) = scan(run_dir) else { return };
        for p in &sets.partial {
            let _ = fs::remove_dir_all(run_dir.join(p));
        }
        let Some(&newest) = sets.complete.iter().max() else { return };
        let target = self.target();
        for &n in sets.complete.iter().filter(|&&n| n != newest) {
            let old = run_dir.join(set_name(n));
            if target.is_some()
                && target == self.relative(&old).ok()
                && self.point_at(&run_dir.join(set_name(newest))).is_err()
            {
                continue; // still current: keep it
            }
            let _ = fs::remove_dir_all(&old);
        }
    }
}

/// A pipeline's result sets in one run (see the module docs).
#[derive(Clone, Debug)]
pub struct ResultSets {
    runs: Runs,
    run: String,
}

impl ResultSets {
    /// Tidies `link`'s runs after a crash or an older mavloc. The folder of `run` is made
    /// by its first set, so a run that writes none leaves none behind. Opening the run
    /// again (a pipeline rebuilt in the same daemon) continues it.
    pub fn open(link: &Path, run: &str) -> io::Result<ResultSets> {
        let runs = Runs::new(link)?;
        runs.tidy(Layout::Sets, run)?;
        Ok(ResultSets { runs, run: run.to_string() })
    }

    pub fn runs(&self) -> &Runs {
        &self.runs
    }

    pub fn run(&self) -> &str {
        &self.run
    }

    pub fn run_dir(&self) -> PathBuf {
        self.runs.run_dir(&self.run)
    }

    /// This run's newest complete set, if it wrote one.
    pub fn current(&self) -> Option<PathBuf> {
        let sets = scan(&self.run_dir()).ok()?;
        sets.complete.iter().max().map(|&n| self.run_dir().join(set_name(n)))
    }

    /// Writes a new set: `fill(folder)` writes the files into a fresh folder, which
    /// becomes current only once everything is on disk; this run's sets replaced more
    /// than [`REPLACED_SET_GRACE`] ago are then removed. Returns the new set's folder. On any error (from `fill` or the disk) the
    /// new folder is removed, the previous set stays current and the error is returned.
    pub fn write(&self, fill: impl FnOnce(&Path) -> io::Result<()>) -> io::Result<PathBuf> {
        self.write_at(SystemTime::now(), fill)
    }

    /// [`ResultSets::write`] at the wall-clock time `now`, which decides which replaced
    /// sets have outlived [`REPLACED_SET_GRACE`].
    pub fn write_at(
        &self,
        now: SystemTime,
        fill: impl FnOnce(&Path) -> io::Result<()>,
    ) -> io::Result<PathBuf> {
        let run_dir = self.run_dir();
        fs::create_dir_all(&run_dir)?;
        let sets = scan(&run_dir)?;
        let n = sets.complete.iter().chain(&sets.partial_numbers).max().map_or(1, |h| h + 1);
        let set = run_dir.join(set_name(n));
        let partial = run_dir.join(format!("{}.partial", set_name(n)));
        // A run's folder is made by its first set: one that failed (a full disk at the
        // start) leaves none (an outside trial found the empty folder).
        let forget_empty_run = || {
            if sets.complete.is_empty() {
                let _ = fs::remove_dir(&run_dir);
            }
        };
        let written = (|| {
            fs::create_dir(&partial)?;
            fill(&partial)?;
            sync_tree(&partial)?;
            fs::rename(&partial, &set)?;
            sync_dir(&run_dir);
            Ok(())
        })();
        if let Err(e) = written {
            let _ = fs::remove_dir_all(&partial);
            forget_empty_run();
            if let Some(&current) = sets.complete.iter().max() {
                // Whatever failed (a full disk most likely), the replaced sets kept for
                // slow readers give their room to the next attempt.
                self.remove_replaced(&run_dir, &sets.complete, current, now, Duration::ZERO);
            }
            return Err(e);
        }
        if let Err(e) = self.runs.point_at(&set) {
            // Complete but never current: removed, so the next start cannot take it for newer.
            let _ = fs::remove_dir_all(&set);
            forget_empty_run();
            sync_dir(&run_dir);
            return Err(e);
        }
        // The folder's time becomes its publishing time (a rename keeps the time its last
        // file was made, before the sync, which takes seconds on a busy SD card): the
        // grace of the set it replaced counts from here.
        if let Ok(f) = fs::File::open(&set) {
            let _ = f.set_modified(now);
        }
        self.remove_replaced(&run_dir, &sets.complete, n, now, REPLACED_SET_GRACE);
        Ok(set)
    }

    /// Removes the sets of this run that were replaced at least `grace` before `now`;
    /// `current` and whatever the link points at are never removed. A set was replaced
    /// when the next one was published, which [`ResultSets::write_at`] stamps as that
    /// one's folder's modification time. The set replaced just now always stays. A time
    /// further ahead of `now` than the grace (the clock was set back, as a computer with
    /// no battery clock does when it gets the time) counts as expired, or those sets
    /// would stay until the clock caught up.
    fn remove_replaced(
        &self,
        run_dir: &Path,
        complete: &[u64],
        current: u64,
        now: SystemTime,
        grace: Duration,
    ) {
        // After a failed switch whose clean-up failed too, the newest complete set may
        // not be the link's target: that one is never removed, or the link would dangle.
        let target = self.runs.target();
        let linked =
            |n: u64| target.is_some() && target == self.runs.relative(&run_dir.join(set_name(n))).ok();
        let mut all: Vec<u64> = complete.iter().copied().filter(|&o| o != current).collect();
        all.push(current);
        all.sort_unstable();
        // Whether the set `n` was published at least `grace` before `now`.
        let aged = |n: u64| {
            let published = fs::metadata(run_dir.join(set_name(n))).and_then(|m| m.modified());
            match published.map(|t| now.duration_since(t)) {
                Ok(Ok(age)) => age >= grace,
                Ok(Err(ahead)) => ahead.duration() > grace,
                Err(_) => true, // gone: nothing says when; not kept forever
            }
        };
        for pair in all.windows(2) {
            let (old, successor) = (pair[0], pair[1]);
            let expired = grace.is_zero() || (successor != current && aged(successor));
            if expired && !linked(old) {
                let _ = fs::remove_dir_all(run_dir.join(set_name(old)));
            }
        }
    }
}

/// How long a replaced set stays on disk after the next one became current. A reader
/// that resolved `results/area` a moment before the switch (rsync or scp over a slow
/// link, a script opening one file after another by the resolved path) reads one whole
/// set, old or new, for this long; the link itself always points at the newest. Sets
/// are written every few seconds in a live run, so a handful stay beside the current one.
/// A write that fails (a full disk) removes them all at once, to make room for the next.
pub const REPLACED_SET_GRACE: Duration = Duration::from_secs(30);

/// Creates `run` under `link`'s runs (tidying as [`ResultSets::open`] does, without sets)
/// and points the link at it: for results appended line by line. Returns the folder.
pub fn open_run_dir(link: &Path, run: &str) -> io::Result<PathBuf> {
    let runs = Runs::new(link)?;
    runs.tidy(Layout::Plain, run)?;
    let dir = runs.run_dir(run);
    fs::create_dir_all(&dir)?;
    if runs.target() != runs.relative(&dir).ok() {
        runs.point_at(&dir)?;
    }
    Ok(dir)
}

fn set_name(n: u64) -> String {
    format!("set-{n}")
}

/// What a run's folder holds.
#[derive(Debug, Default)]
struct Scan {
    complete: Vec<u64>,
    /// Names of `*.partial` folders.
    partial: Vec<String>,
    /// Their numbers, when they are `set-N.partial`: never reused.
    partial_numbers: Vec<u64>,
}

fn scan(run_dir: &Path) -> io::Result<Scan> {
    let mut s = Scan::default();
    for name in subdirs(run_dir)? {
        if let Some(stem) = name.strip_suffix(".partial") {
            if let Some(n) = stem.strip_prefix("set-").and_then(|n| n.parse().ok()) {
                s.partial_numbers.push(n);
            }
            s.partial.push(name);
        } else if let Some(n) = name.strip_prefix("set-").and_then(|n| n.parse().ok()) {
            s.complete.push(n);
        }
    }
    Ok(s)
}

/// Names of the real folders (not symlinks) in `dir`.
fn subdirs(dir: &Path) -> io::Result<Vec<String>> {
    let mut names = Vec::new();
    for e in fs::read_dir(dir)? {
        let e = e?;
        if e.file_type()?.is_dir() {
            if let Some(n) = e.file_name().to_str() {
                names.push(n.to_string());
            }
        }
    }
    Ok(names)
}

/// Syncs every file under `dir`, then `dir`: the set is on disk before it is published,
/// however `fill` wrote it (an image library, an encoder).
fn sync_tree(dir: &Path) -> io::Result<()> {
    for e in fs::read_dir(dir)? {
        let e = e?;
        let t = e.file_type()?;
        if t.is_dir() {
            sync_tree(&e.path())?;
        } else if t.is_file() {
            fs::File::open(e.path())?.sync_all()?;
        }
    }
    fs::File::open(dir)?.sync_all()
}

/// Best effort, as `atomic::sync_parent`: not every file system can sync a folder.
fn sync_dir(dir: &Path) {
    if let Ok(d) = fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

fn remove_file_if_any(p: &Path) -> io::Result<()> {
    match fs::remove_file(p) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
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

    fn write_set(sets: &ResultSets, text: &str) -> PathBuf {
        sets.write(|d| {
            fs::write(d.join("a.csv"), text)?;
            fs::write(d.join("b.json"), text)
        })
        .unwrap()
    }

    #[test]
    fn a_set_is_read_through_the_link_and_replaced_whole() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        assert!(sets.current().is_none(), "a new run starts empty");
        let first = write_set(&sets, "one");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "one");
        assert_eq!(fs::read_link(&link).unwrap(), Path::new("area.runs/r1/set-1"), "relative");
        let second = write_set(&sets, "two");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "two");
        assert_eq!(fs::read_to_string(link.join("b.json")).unwrap(), "two");
        assert_eq!(sets.current(), Some(second.clone()));
        assert_eq!(fs::read_to_string(first.join("a.csv")).unwrap(), "one", "kept for a slow reader");
        assert_eq!(names(dir.path()), ["area", "area.runs"], "no temporary left");
    }

    /// A reader that resolved the link just before a switch (rsync over WiFi) finds the
    /// whole set it started on for the grace period; older replaced sets go at the next
    /// write after it.
    #[test]
    fn a_replaced_set_stays_for_slow_readers_until_its_grace_is_over() {
        let dir = tempfile::tempdir().unwrap();
        let sets = ResultSets::open(&dir.path().join("area"), "r1").unwrap();
        let now = SystemTime::now();
        // Each set published at `t` (which `write_at` stamps on its folder).
        let w = |t: SystemTime, text: &str| {
            sets.write_at(t, |d| fs::write(d.join("a.csv"), text)).unwrap();
        };
        w(now, "one");
        w(now, "two");
        w(now + Duration::from_secs(5), "three");
        assert_eq!(names(&sets.run_dir()), ["set-1", "set-2", "set-3"], "all within the grace");
        // set-1 was replaced (set-2 published) more than the grace ago; set-2 was replaced
        // by set-3 less than it ago; set-3 was replaced just now.
        w(now + REPLACED_SET_GRACE + Duration::from_secs(2), "four");
        assert_eq!(names(&sets.run_dir()), ["set-2", "set-3", "set-4"]);
        w(now + REPLACED_SET_GRACE * 3, "five");
        assert_eq!(names(&sets.run_dir()), ["set-4", "set-5"], "the one replaced just now stays");
        assert_eq!(fs::read_to_string(sets.runs().link().join("a.csv")).unwrap(), "five");
        // The pipeline rebuilt in the same daemon (after a panic while writing set-6)
        // opens its run again: the sets in their grace stay, the half-written one goes.
        fs::create_dir(sets.run_dir().join("set-6.partial")).unwrap();
        let again = ResultSets::open(sets.runs().link(), "r1").unwrap();
        assert_eq!(names(&again.run_dir()), ["set-4", "set-5"]);
        // The clock set back by an hour (a computer getting the time): set-4, replaced
        // by a set stamped in the clock's new "future", is not kept until the clock
        // catches up; set-5, replaced just now by set-6, is.
        let back = now + REPLACED_SET_GRACE * 3 - Duration::from_secs(3600);
        again.write_at(back, |d| fs::write(d.join("a.csv"), "six")).unwrap();
        again.write_at(back, |d| fs::write(d.join("a.csv"), "seven")).unwrap();
        assert_eq!(names(&again.run_dir()), ["set-5", "set-6", "set-7"]);
    }

    /// A set the link points at is never removed as replaced, even when a failed switch
    /// (whose clean-up failed too) left a newer complete set beside it.
    #[test]
    fn the_sets_removal_spares_what_the_link_points_at() {
        let dir = tempfile::tempdir().unwrap();
        let sets = ResultSets::open(&dir.path().join("area"), "r1").unwrap();
        write_set(&sets, "one");
        // set-2 complete but never made current.
        fs::create_dir(sets.run_dir().join("set-2")).unwrap();
        fs::write(sets.run_dir().join("set-2/a.csv"), "two").unwrap();
        let full = sets.write(|_| Err(io::Error::new(io::ErrorKind::StorageFull, "No space left on device")));
        assert!(full.is_err());
        assert_eq!(
            fs::read_to_string(sets.runs().link().join("a.csv")).unwrap(),
            "one",
            "the link still resolves"
        );
    }

    /// On a full disk the sets kept for slow readers give up their room, the current one
    /// stays.
    #[test]
    fn a_failed_write_removes_the_replaced_sets_and_keeps_the_current() {
        let dir = tempfile::tempdir().unwrap();
        let sets = ResultSets::open(&dir.path().join("area"), "r1").unwrap();
        write_set(&sets, "one");
        write_set(&sets, "two");
        assert_eq!(names(&sets.run_dir()), ["set-1", "set-2"]);
        let full = sets.write(|_| Err(io::Error::new(io::ErrorKind::StorageFull, "No space left on device")));
        assert_eq!(full.unwrap_err().kind(), io::ErrorKind::StorageFull);
        assert_eq!(names(&sets.run_dir()), ["set-2"]);
        assert_eq!(fs::read_to_string(sets.runs().link().join("a.csv")).unwrap(), "two");
    }

    #[test]
    fn a_failed_fill_leaves_the_previous_set_current_and_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        write_set(&sets, "old");
        // The disk fills up after the first file of the new set.
        let e = sets
            .write(|d| {
                fs::write(d.join("a.csv"), "new")?;
                Err(io::Error::new(io::ErrorKind::StorageFull, "No space left on device"))
            })
            .unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::StorageFull);
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "old");
        assert_eq!(fs::read_to_string(link.join("b.json")).unwrap(), "old", "one set, not a mix");
        assert_eq!(names(&sets.run_dir()), ["set-1"], "no .partial left");
        assert_eq!(names(dir.path()), ["area", "area.runs"], "no .tmp left");
        // The next write works and takes the next number.
        write_set(&sets, "new");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "new");
        assert_eq!(names(&sets.run_dir()), ["set-1", "set-2"], "set-1 kept for its grace");
    }

    /// A real full disk: a 64 KiB tmpfs (needs root and mount; skipped with a message
    /// otherwise).
    #[test]
    fn a_full_disk_leaves_the_previous_set_current_and_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        let Some(_tmpfs) =
            crate::testing::mount_tmpfs(dir.path(), "64k", "; the injected-error test covers the logic")
        else {
            return;
        };
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        write_set(&sets, "old");
        let e = sets
            .write(|d| {
                fs::write(d.join("a.csv"), "new")?;
                fs::write(d.join("b.json"), vec![b'x'; 256 * 1024])
            })
            .unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::StorageFull, "{e}");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "old");
        assert_eq!(fs::read_to_string(link.join("b.json")).unwrap(), "old");
        assert_eq!(names(&sets.run_dir()), ["set-1"], "no .partial left");
        assert_eq!(names(dir.path()), ["area", "area.runs"], "no .tmp left");
    }

    #[test]
    fn a_failed_switch_removes_the_new_set_and_keeps_the_old() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        write_set(&sets, "old");
        // Something in the way of the temporary link: the switch itself fails.
        fs::create_dir_all(dir.path().join(".area.tmp/x")).unwrap();
        assert!(sets.write(|d| fs::write(d.join("a.csv"), "new")).is_err());
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "old");
        assert_eq!(names(&sets.run_dir()), ["set-1"]);
    }

    #[test]
    fn a_new_run_starts_empty_and_earlier_runs_keep_their_last_set() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let r1 = ResultSets::open(&link, "r1").unwrap();
        write_set(&r1, "first run");
        write_set(&r1, "first run, last");
        let r2 = ResultSets::open(&link, "r2").unwrap();
        assert!(r2.current().is_none());
        // Until the new run writes, the link shows the last results there are.
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "first run, last");
        write_set(&r2, "second run");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "second run");
        let kept = dir.path().join("area.runs/r1/set-2/a.csv");
        assert_eq!(fs::read_to_string(kept).unwrap(), "first run, last");
        // The same run opened again (a pipeline rebuilt in the same daemon) continues.
        let again = ResultSets::open(&link, "r2").unwrap();
        assert_eq!(again.current(), r2.current());
    }

    /// Starts that wrote no set (stopped on the ground) leave no empty run folders, now or
    /// from before.
    #[test]
    fn a_run_that_writes_no_set_leaves_no_folder() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let r1 = ResultSets::open(&link, "r1").unwrap();
        write_set(&r1, "first");
        ResultSets::open(&link, "r2").unwrap();
        fs::create_dir(dir.path().join("area.runs/r0-empty-from-an-older-mavloc")).unwrap();
        let r3 = ResultSets::open(&link, "r3").unwrap();
        assert_eq!(names(r3.runs().root()), ["r1"], "no r2, no older empty run, no r3 yet");
        assert!(r3.current().is_none());
        write_set(&r3, "third");
        assert_eq!(names(r3.runs().root()), ["r1", "r3"]);
    }

    /// A run's first set that cannot be written (a full disk at the start) leaves no
    /// folder for the run either.
    #[test]
    fn a_first_set_that_fails_leaves_no_run_folder() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let r1 = ResultSets::open(&link, "r1").unwrap();
        write_set(&r1, "first");
        let r2 = ResultSets::open(&link, "r2").unwrap();
        let full = || io::Error::new(io::ErrorKind::StorageFull, "No space left on device");
        assert!(r2.write(|_| Err(full())).is_err());
        assert_eq!(names(r2.runs().root()), ["r1"], "no empty r2");
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "first", "r1's set stays current");
        write_set(&r2, "second");
        assert!(r2.write(|_| Err(full())).is_err());
        assert_eq!(names(r2.runs().root()), ["r1", "r2"], "a run with a set keeps its folder");
    }

    #[test]
    fn start_up_removes_what_a_crash_left_and_keeps_the_newest_set() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        let sets = ResultSets::open(&link, "r1").unwrap();
        write_set(&sets, "one");
        let run = sets.run_dir();
        // A crash after set-2 was published but before the link moved and set-1 went, and
        // another in the middle of writing set-3; a temporary link left behind.
        fs::create_dir(run.join("set-2")).unwrap();
        fs::write(run.join("set-2/a.csv"), "two").unwrap();
        fs::create_dir(run.join("set-3.partial")).unwrap();
        fs::write(run.join("set-3.partial/a.csv"), "thr").unwrap();
        symlink("area.runs/r1/set-1", dir.path().join(".area.tmp")).unwrap();
        let sets = ResultSets::open(&link, "r2").unwrap();
        assert_eq!(names(&run), ["set-2"]);
        assert_eq!(fs::read_to_string(link.join("a.csv")).unwrap(), "two", "the link moved to the newest");
        assert_eq!(names(dir.path()), ["area", "area.runs"]);
        assert_eq!(names(sets.runs().root()), ["r1"], "r2 is made by its first set");
    }

    /// A file where the link goes is someone's: named, kept, and nothing opened (the link
    /// renamed over it deleted it). A file where the runs go is named too.
    #[test]
    fn a_file_in_the_results_places_is_named_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        fs::write(&link, "my notes").unwrap();
        let e = ResultSets::open(&link, "r1").unwrap_err().to_string();
        assert!(e.contains(&format!("{} is a file", link.display())), "{e}");
        assert_eq!(fs::read_to_string(&link).unwrap(), "my notes");
        let other = dir.path().join("indoor");
        fs::write(dir.path().join("indoor.runs"), "x").unwrap();
        let e = open_run_dir(&other, "r1").unwrap_err().to_string();
        assert!(e.contains(&format!("cannot create {}", dir.path().join("indoor.runs").display())), "{e}");
    }

    #[test]
    fn a_folder_left_by_an_older_mavloc_becomes_a_legacy_run_once() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("area");
        fs::create_dir(&link).unwrap();
        fs::write(link.join("landmarks.csv"), "old format").unwrap();
        let sets = ResultSets::open(&link, "r1").unwrap();
        assert!(fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        assert_eq!(fs::read_to_string(link.join("landmarks.csv")).unwrap(), "old format");
        let runs = names(sets.runs().root());
        assert_eq!(runs.len(), 1, "{runs:?}");
        assert!(runs[0].starts_with("legacy-"), "{runs:?}");
        let legacy = sets.runs().root().join(&runs[0]);
        assert_eq!(names(&legacy), ["set-0"]);
        // Once: opening again adopts nothing more.
        ResultSets::open(&link, "r1").unwrap();
        assert_eq!(names(sets.runs().root()).len(), 1);
        write_set(&sets, "new");
        assert_eq!(names(sets.runs().root()).len(), 2, "the legacy run and r1");
        assert_eq!(fs::read_to_string(legacy.join("set-0/landmarks.csv")).unwrap(), "old format");
    }

    #[test]
    fn a_plain_run_folder_is_linked_and_legacy_files_adopted() {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("indoor");
        fs::create_dir(&link).unwrap();
        fs::write(link.join("trajectory.csv"), "old").unwrap();
        let run = open_run_dir(&link, "r1").unwrap();
        fs::write(run.join("trajectory.csv"), "new").unwrap();
        assert_eq!(fs::read_to_string(link.join("trajectory.csv")).unwrap(), "new");
        let runs = names(&dir.path().join("indoor.runs"));
        assert!(runs[0].starts_with("legacy-") && runs[1] == "r1", "{runs:?}");
        let old = dir.path().join("indoor.runs").join(&runs[0]).join("trajectory.csv");
        assert_eq!(fs::read_to_string(old).unwrap(), "old");
        assert_eq!(open_run_dir(&link, "r1").unwrap(), run, "the same run continues");
    }

    #[test]
    fn run_ids_are_utc_start_times_made_unique() {
        let t = SystemTime::UNIX_EPOCH + std::time::Duration::from_secs(1_700_000_000);
        assert_eq!(new_run_id(t, |_| false), "20231114T221320Z");
        assert_eq!(new_run_id(t, |n| n == "20231114T221320Z"), "20231114T221320Z-2");
    }
}
