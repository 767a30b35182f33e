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

/// Reads and decodes an image file (`flags`: `imgcodecs::IMREAD_*`), with the reason in
/// words and the file's name when it cannot be used: missing, unreadable, truncated JPEG,
/// or not an image.
pub fn read_image(path: &std::path::Path, flags: i32) -> Result<Mat, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: cannot read it ({e})", path.display()))?;
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

#[cfg(test)]
mod tests {
    use super::*;

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
    }
}
