//! The one atomic file writer every result, dataset and state file goes through.
//!
//! The bytes go to a hidden temporary file in the same folder (a rename is only atomic
//! within one file system), are synced, and the temporary is renamed over the target; the
//! folder is then synced so the rename itself survives a power cut. A crash at any moment
//! leaves either the previous complete file or the new complete file, never a torn one.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the folder).
/// On failure the temporary file is removed and `path` is left as it was.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |f| f.write_all(bytes))
}

/// As [`write_atomic`], for writers that fill the file themselves (an encoder, an image
/// library): `fill` writes into the temporary file, which keeps the target's extension
/// (`.name.tmp.png`) for libraries that choose the format from it.
pub fn write_atomic_with(path: &Path, fill: impl FnOnce(&mut fs::File) -> io::Result<()>) -> io::Result<()> {
    let tmp = temporary(path);
    let result = (|| {
        let mut f = fs::File::create(&tmp)?;
        fill(&mut f)?;
        f.sync_all()?;
        drop(f);
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result?;
    sync_parent(path);
    Ok(())
}

/// As [`write_atomic`], for a writer that only takes a path (OpenCV's `imwrite`):
/// `fill(tmp)` must create the file at `tmp`, which keeps the target's extension.
pub fn write_atomic_path(path: &Path, fill: impl FnOnce(&Path) -> io::Result<()>) -> io::Result<()> {
    let tmp = temporary(path);
    let result = (|| {
        fill(&tmp)?;
        fs::File::open(&tmp)?.sync_all()?;
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result?;
    sync_parent(path);
    Ok(())
}

/// `.NAME.tmp.EXT` beside `path`: hidden, and still ending in the target's extension.
fn temporary(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = match path.extension() {
        Some(ext) => format!(".{name}.tmp.{}", ext.to_string_lossy()),
        None => format!(".{name}.tmp"),
    };
    path.with_file_name(tmp)
}

/// Makes a rename in `path`'s folder durable; best effort (not every platform can).
fn sync_parent(path: &Path) {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        if let Ok(d) = fs::File::open(dir) {
            let _ = d.sync_all();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_whole_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"two");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
    }

    #[test]
    fn a_failed_write_keeps_the_old_file_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.json");
        write_atomic(&p, b"old").unwrap();
        let e = write_atomic_with(&p, |f| {
            f.write_all(b"half")?;
            Err(io::Error::other("encoder failed"))
        })
        .unwrap_err();
        assert_eq!(e.to_string(), "encoder failed");
        assert_eq!(fs::read(&p).unwrap(), b"old");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
        assert!(write_atomic_path(&p, |_| Err(io::Error::other("no"))).is_err());
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn the_temporary_keeps_the_extension_and_is_hidden() {
        assert_eq!(temporary(Path::new("d/masks.png")), Path::new("d/.masks.png.tmp.png"));
        assert_eq!(temporary(Path::new("counter")), Path::new(".counter.tmp"));
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.txt");
        write_atomic_path(&p, |tmp| {
            assert_eq!(tmp.extension().unwrap(), "txt");
            fs::write(tmp, b"via path")
        })
        .unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"via path");
    }
}
