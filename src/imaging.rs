//! OpenCV image helpers shared by the pipelines, the frame sources and the commands. They
//! live below all of them so that a camera source need not import a pipeline to use one.

use opencv::core::Mat;
use opencv::imgproc;
use opencv::prelude::*;

/// An 8-bit RGB buffer (the simulator's frames) as an OpenCV BGR image.
pub fn bgr_from_rgb(rgb: &[u8], height: u32) -> opencv::Result<Mat> {
    let m = Mat::from_slice(rgb)?;
    let m = m.reshape(3, height as i32)?;
    let mut bgr = Mat::default();
    imgproc::cvt_color(&m, &mut bgr, imgproc::COLOR_RGB2BGR, 0)?;
    Ok(bgr)
}

/// Whether a JPEG's bytes end before its image does: no end-of-image marker (`FF D9`)
/// after the last start-of-scan (`FF DA`). Entropy-coded data never holds `FF DA` or
/// `FF D9` (an `FF` there is stuffed as `FF 00`), so a file cut anywhere after its headers
/// is caught; trailing bytes after the marker (some cameras append them) are fine.
/// OpenCV decodes such a file without an error, grey below the cut, with only libjpeg's
/// line on stderr, so this is checked before decoding.
pub fn jpeg_truncated(bytes: &[u8]) -> bool {
    let sos = bytes.windows(2).rposition(|w| w == [0xFF, 0xDA]);
    match sos {
        Some(at) => !bytes[at..].windows(2).any(|w| w == [0xFF, 0xD9]),
        None => true,
    }
}

/// The images of a folder a `file` camera reads (PNG, JPEG, BMP, TIFF by extension),
/// sorted by name.
pub fn image_files(dir: &std::path::Path) -> std::io::Result<Vec<std::path::PathBuf>> {
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
            ["png", "jpg", "jpeg", "bmp", "tif", "tiff"].contains(&ext.as_str())
        })
        .collect();
    files.sort();
    Ok(files)
}

/// Whether a video file gives a frame: opened and one frame read, as the `file` camera
/// will. A file of something else (notes named `.mp4`) passed the start checks, and the
/// daemon then idled with no camera (outside audit).
pub fn probe_video(path: &std::path::Path) -> Result<(), String> {
    use opencv::{core, videoio};
    let not_video = || format!("{} is not a video OpenCV can read", path.display());
    let name = path.to_str().ok_or_else(not_video)?;
    // The verdict is said in words: OpenCV's backends each logging why they could not open
    // the file would come before it, raw, as the checks run before the log is set up.
    let before = core::set_log_level(core::LogLevel::LOG_LEVEL_SILENT).ok();
    let frame = videoio::VideoCapture::from_file(name, videoio::CAP_ANY).ok().and_then(|mut cap| {
        if !cap.is_opened().unwrap_or(false) {
            return None;
        }
        let mut frame = Mat::default();
        Some(matches!(cap.read(&mut frame), Ok(true) if !frame.empty()))
    });
    if let Some(level) = before {
        let _ = core::set_log_level(level);
    }
    match frame {
        None => Err(not_video()),
        Some(false) => Err(format!("{}: OpenCV opens it but decodes no frame from it", path.display())),
        Some(true) => Ok(()),
    }
}

/// Reads and decodes an image file (`flags`: `imgcodecs::IMREAD_*`), with the reason in
/// words and the file's name when it cannot be used: missing, unreadable, truncated JPEG,
/// or not an image.
pub fn read_image(path: &std::path::Path, flags: i32) -> Result<Mat, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: cannot read it ({e})", path.display()))?;
    // OpenCV answers an empty buffer with its raw assertion text (`!buf.empty()`).
    if bytes.is_empty() {
        return Err(format!("{}: empty file (0 bytes)", path.display()));
    }
    if let Some(img) = plain_png(&bytes, flags) {
        return img.map_err(|e| format!("{}: {e}", path.display()));
    }
    let is_jpeg = bytes.starts_with(&[0xFF, 0xD8]);
    if is_jpeg && jpeg_truncated(&bytes) {
        return Err(format!("{}: truncated JPEG (the image data ends early)", path.display()));
    }
    let buf = opencv::core::Vector::<u8>::from_slice(&bytes);
    let img = opencv::imgcodecs::imdecode(&buf, flags).map_err(|e| format!("{}: {e}", path.display()))?;
    if img.empty() {
        return Err(format!("{}: not an image OpenCV can decode", path.display()));
    }
    Ok(img)
}

/// A plain 8-bit PNG (every rendered frame and mask) decoded by [`mavloc_data::pngfile`]
/// into what `imdecode` gives for `flags`, pixel for pixel; `None` when that decoder
/// declines the file, or for a colour file read as grey (libpng's own RGB-to-grey
/// weights), which `imdecode` then reads.
fn plain_png(bytes: &[u8], flags: i32) -> Option<opencv::Result<Mat>> {
    use mavloc_data::pngfile::Channels;
    let (colour, accept): (bool, &[Channels]) = match flags {
        opencv::imgcodecs::IMREAD_COLOR => (true, &[Channels::Grey, Channels::Rgb]),
        opencv::imgcodecs::IMREAD_GRAYSCALE => (false, &[Channels::Grey]),
        _ => return None,
    };
    let d = mavloc_data::pngfile::decode(bytes, accept)?;
    let convert = |code| -> opencv::Result<Mat> {
        let n = if d.channels == Channels::Rgb { 3 } else { 1 };
        let flat = Mat::from_slice(&d.pixels)?;
        let m = flat.reshape(n, d.height as i32)?;
        let mut out = Mat::default();
        match code {
            Some(code) => imgproc::cvt_color(&m, &mut out, code, 0)?,
            None => m.copy_to(&mut out)?,
        }
        Ok(out)
    };
    Some(match (d.channels, colour) {
        // A grey read accepts grey files only, so an RGB file here is read as colour.
        (Channels::Rgb, _) => convert(Some(imgproc::COLOR_RGB2BGR)),
        (Channels::Grey, true) => convert(Some(imgproc::COLOR_GRAY2BGR)),
        (Channels::Grey, false) => convert(None),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames and masks as the simulator writes them, and kinds the `png` crate path
    /// declines (alpha, 16 bits, colour read as grey), read exactly as OpenCV reads them.
    #[test]
    fn pngs_read_as_opencv_reads_them() {
        use mavloc_data::pngfile::{encode, Channels};
        use opencv::imgcodecs::{imdecode, IMREAD_COLOR, IMREAD_GRAYSCALE};
        let dir = tempfile::tempdir().unwrap();
        let (w, h) = (61u32, 23u32);
        let noise = |n: u32| -> Vec<u8> {
            (0..w * h * n).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect()
        };
        let rgba = {
            let img = Mat::from_slice(&noise(4)).unwrap().reshape(4, h as i32).unwrap().try_clone().unwrap();
            let mut buf = opencv::core::Vector::<u8>::new();
            opencv::imgcodecs::imencode(".png", &img, &mut buf, &opencv::core::Vector::new()).unwrap();
            buf.to_vec()
        };
        let files = [
            ("rgb", encode(w, h, &noise(3), Channels::Rgb).unwrap()),
            ("grey", encode(w, h, &noise(1), Channels::Grey).unwrap()),
            ("rgba", rgba),
        ];
        for (name, bytes) in files {
            let p = dir.path().join(format!("{name}.png"));
            std::fs::write(&p, &bytes).unwrap();
            for flags in [IMREAD_COLOR, IMREAD_GRAYSCALE] {
                let ours = read_image(&p, flags).unwrap();
                let theirs = imdecode(&opencv::core::Vector::<u8>::from_slice(&bytes), flags).unwrap();
                assert_eq!(
                    (ours.typ(), ours.cols(), ours.rows()),
                    (theirs.typ(), theirs.cols(), theirs.rows())
                );
                assert_eq!(ours.data_bytes().unwrap(), theirs.data_bytes().unwrap(), "{name} {flags}");
            }
        }
    }

    fn jpeg(w: i32, h: i32) -> Vec<u8> {
        let img =
            Mat::new_rows_cols_with_default(h, w, opencv::core::CV_8UC3, (90, 120, 30, 0).into()).unwrap();
        let mut buf = opencv::core::Vector::<u8>::new();
        opencv::imgcodecs::imencode(".jpg", &img, &mut buf, &opencv::core::Vector::new()).unwrap();
        buf.to_vec()
    }

    #[test]
    fn a_cut_jpeg_is_named_as_truncated_and_a_whole_one_decodes() {
        let dir = tempfile::tempdir().unwrap();
        let whole = jpeg(64, 48);
        assert!(!jpeg_truncated(&whole));
        let mut trailing = whole.clone();
        trailing.extend_from_slice(b"camera trailer");
        assert!(!jpeg_truncated(&trailing), "bytes after the end marker are allowed");
        let p = dir.path().join("ok.jpg");
        std::fs::write(&p, &trailing).unwrap();
        assert_eq!(read_image(&p, opencv::imgcodecs::IMREAD_COLOR).unwrap().cols(), 64);
        for cut in [whole.len() - 2, whole.len() * 2 / 3, 30] {
            assert!(jpeg_truncated(&whole[..cut]), "cut at {cut}");
            std::fs::write(&p, &whole[..cut]).unwrap();
            let e = read_image(&p, opencv::imgcodecs::IMREAD_COLOR).unwrap_err();
            assert!(e.contains("ok.jpg") && e.contains("truncated"), "{e}");
        }
        std::fs::write(&p, b"\x89PNG not really").unwrap();
        let e = read_image(&p, opencv::imgcodecs::IMREAD_COLOR).unwrap_err();
        assert!(e.contains("not an image"), "{e}");
        let e = read_image(&dir.path().join("gone.png"), opencv::imgcodecs::IMREAD_COLOR).unwrap_err();
        assert!(e.contains("gone.png") && e.contains("cannot read"), "{e}");
        // A frame left empty by a full card: named, not OpenCV's assertion text.
        std::fs::write(&p, b"").unwrap();
        let e = read_image(&p, opencv::imgcodecs::IMREAD_COLOR).unwrap_err();
        assert!(e.contains("ok.jpg") && e.contains("empty file"), "{e}");
        assert!(!e.contains("Assertion"), "{e}");
    }
}
