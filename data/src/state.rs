//! State files that do not parse, and the UTC stamps mavloc names things with.
//!
//! A state file mavloc reads back at start (tuned parameters, a run's landmarks) can be
//! torn by a disk fault or edited by hand. Ignoring it would let the next write destroy
//! what is left of it; refusing to start would ground the vehicle over a convenience
//! file. So it is moved aside to `NAME.corrupt-<stamp>` beside it (kept for a person to
//! look at) and mavloc starts without it.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// `yyyymmddThhmmssZ` (UTC, ISO 8601 basic format): sorts by time as text and is safe in
/// a file name. Times before 1970 print as 1970.
pub fn utc_stamp(t: SystemTime) -> String {
    let secs = t.duration_since(UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let (days, rem) = (secs / 86_400, secs % 86_400);
    let (y, m, d) = civil_from_days(days as i64);
    format!("{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z", rem / 3600, rem % 3600 / 60, rem % 60)
}

/// Year, month, day of a day count since 1970-01-01 (Howard Hinnant's `civil_from_days`,
/// proleptic Gregorian calendar).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

/// `base`, or `base-2`, `base-3`, ... : the first that `taken` says is free.
pub fn unique_name(base: &str, taken: impl Fn(&str) -> bool) -> String {
    if !taken(base) {
        return base.to_string();
    }
    (2u32..).map(|i| format!("{base}-{i}")).find(|n| !taken(n)).expect("a free name")
}

/// A state file's bytes, read to at most `max`: `None` when it is longer, which no state
/// file mavloc writes is (a link to `/dev/zero` must not be read until memory runs out).
pub fn read_capped(path: &Path, max: u64) -> io::Result<Option<Vec<u8>>> {
    use std::io::Read;
    let mut bytes = Vec::new();
    fs::File::open(path)?.take(max + 1).read_to_end(&mut bytes)?;
    Ok((bytes.len() as u64 <= max).then_some(bytes))
}

/// Moves a state file that does not parse out of the way: renamed to
/// `NAME.corrupt-<UTC stamp>` in `into` (same file system, so a rename), never deleted.
/// Returns where it went. The caller says so at WARN, naming both paths.
pub fn move_aside_corrupt(path: &Path, into: &Path) -> io::Result<PathBuf> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let base = format!("{name}.corrupt-{}", utc_stamp(SystemTime::now()));
    let aside = into.join(unique_name(&base, |n| into.join(n).exists()));
    fs::rename(path, &aside)?;
    if let Ok(d) = fs::File::open(into) {
        let _ = d.sync_all();
    }
    Ok(aside)
}

/// [`move_aside_corrupt`] into `into` (`None`: the file's own folder), and the sentence
/// for the caller's WARN line: "`PATH`: not a valid WHAT (ERROR); moved aside to `ASIDE`",
/// or why it could not be. The caller adds what happens next.
pub fn set_aside(path: &Path, into: Option<&Path>, what: &str, error: &str) -> String {
    let beside = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    match move_aside_corrupt(path, into.unwrap_or(beside)) {
        Ok(aside) => {
            format!("{}: not a valid {what} ({error}); moved aside to {}", path.display(), aside.display())
        }
        Err(e) => format!("{}: not a valid {what} ({error}) and cannot be moved aside ({e})", path.display()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn stamps_are_utc_in_basic_format() {
        let at = |s| utc_stamp(UNIX_EPOCH + Duration::from_secs(s));
        assert_eq!(at(0), "19700101T000000Z");
        // 2000-02-29 (a leap day of a century leap year) 23:59:59.
        assert_eq!(at(951_868_799), "20000229T235959Z");
        assert_eq!(at(1_700_000_000), "20231114T221320Z");
        assert_eq!(at(4_102_444_800), "21000101T000000Z");
    }

    #[test]
    fn unique_names_count_up_from_2() {
        assert_eq!(unique_name("a", |_| false), "a");
        assert_eq!(unique_name("a", |n| n == "a" || n == "a-2"), "a-3");
    }

    #[test]
    fn a_corrupt_file_is_moved_aside_not_lost() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("params.json");
        fs::write(&p, b"{ torn").unwrap();
        let a = move_aside_corrupt(&p, dir.path()).unwrap();
        assert!(!p.exists());
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with("params.json.corrupt-") && name.ends_with('Z'), "{name}");
        assert_eq!(fs::read(&a).unwrap(), b"{ torn");
        // A second one in the same second gets its own name.
        fs::write(&p, b"again").unwrap();
        let b = move_aside_corrupt(&p, dir.path()).unwrap();
        assert_ne!(a, b);
        assert_eq!(fs::read(&b).unwrap(), b"again");
    }
}
