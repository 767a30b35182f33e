//! `v4l2` and `file` sources through OpenCV's `VideoCapture` (the design card's choice:
//! OpenCV already decodes MJPG/YUYV and video files, so no second V4L2 stack).

use std::path::{Path, PathBuf};

use opencv::core::{Mat, Size};
use opencv::prelude::*;
use opencv::{calib3d, core, imgcodecs, imgproc, videoio};

use super::{Captured, FrameSource, SourceContext, SourceError};
use crate::settings::Camera;

enum Input {
    Capture(videoio::VideoCapture),
    /// The folder's images by name; the next to read. `dir` is watched: a folder that
    /// vanishes (a card unmounted, a network share dropped) is waited for, not read through.
    Images {
        dir: PathBuf,
        files: Vec<PathBuf>,
        next: usize,
    },
}

/// A V4L2 device, a video file or an image folder.
pub struct Video {
    what: String,
    input: Input,
    device: bool,
    ctx: SourceContext,
    size: (i32, i32),
    /// Seconds between frames when paced (files at their own rate), else 0.
    period: f64,
    next_due: f64,
    index: u64,
    /// Undistortion maps, when distortion coefficients are given.
    maps: Option<(Mat, Mat)>,
    /// CLOCK_MONOTONIC at the daemon's start, to read driver timestamps on our clock.
    mono_at_start: f64,
    /// Images of a folder that could not be read and were skipped.
    skipped: u64,
}

fn monotonic_now() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

fn undistort_maps(c: &Camera) -> Result<Option<(Mat, Mat)>, SourceError> {
    if c.distortion.iter().all(|d| *d == 0.0) {
        return Ok(None);
    }
    let k = c.intrinsics();
    let m = Mat::from_slice_2d(&[[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])?;
    let d = Mat::from_slice(&c.distortion)?.try_clone()?;
    let (mut m1, mut m2) = (Mat::default(), Mat::default());
    calib3d::init_undistort_rectify_map(
        &m,
        &d,
        &core::no_array(),
        &m,
        Size::new(c.width as i32, c.height as i32),
        core::CV_16SC2,
        &mut m1,
        &mut m2,
    )?;
    Ok(Some((m1, m2)))
}

impl Video {
    /// Opens a V4L2 device with the configured size, rate and pixel format.
    pub fn open_device(c: &Camera, ctx: SourceContext) -> Result<Video, SourceError> {
        let dev = &c.device;
        if !Path::new(dev).exists() {
            return Err(SourceError::Gone(format!("V4L2 device {dev} does not exist (camera.device)")));
        }
        let mut cap = videoio::VideoCapture::from_file(dev, videoio::CAP_V4L2)
            .map_err(|e| SourceError::Gone(format!("V4L2 device {dev}: {e}")))?;
        if !cap.is_opened().unwrap_or(false) {
            return Err(SourceError::Gone(format!(
                "V4L2 device {dev} cannot be opened (not a capture device, busy, or no permission: is mavloc in group video?)"
            )));
        }
        let f: Vec<char> = c.pixel_format.chars().collect();
        let fourcc = videoio::VideoWriter::fourcc(f[0], f[1], f[2], f[3])?;
        cap.set(videoio::CAP_PROP_FOURCC, fourcc as f64)?;
        cap.set(videoio::CAP_PROP_FRAME_WIDTH, c.width as f64)?;
        cap.set(videoio::CAP_PROP_FRAME_HEIGHT, c.height as f64)?;
        cap.set(videoio::CAP_PROP_FPS, c.fps)?;
        let got =
            (cap.get(videoio::CAP_PROP_FRAME_WIDTH)? as i32, cap.get(videoio::CAP_PROP_FRAME_HEIGHT)? as i32);
        if got != (c.width as i32, c.height as i32) {
            return Err(SourceError::Fatal(format!(
                "V4L2 device {dev} delivers {}x{}, but camera.width x camera.height is {}x{}: set them to a size the camera supports (v4l2-ctl --list-formats-ext)",
                got.0, got.1, c.width, c.height
            )));
        }
        let mono_at_start = monotonic_now() - ctx.now();
        Ok(Video {
            what: format!("V4L2 {dev} {}x{} {} at {} Hz", c.width, c.height, c.pixel_format, c.fps),
            input: Input::Capture(cap),
            device: true,
            size: got,
            period: 0.0,
            next_due: 0.0,
            index: 0,
            maps: undistort_maps(c)?,
            mono_at_start,
            skipped: 0,
            ctx,
        })
    }

    /// Opens a video file or a folder of images (PNG, JPEG, BMP, TIFF, sorted by name).
    pub fn open_file(c: &Camera, ctx: SourceContext) -> Result<Video, SourceError> {
        let path = Path::new(&c.path);
        if c.path.is_empty() {
            return Err(SourceError::Fatal("camera.source = \"file\" needs camera.path".into()));
        }
        let size = (c.width as i32, c.height as i32);
        let (input, rate, what) = if path.is_dir() {
            let files = crate::imaging::image_files(path)
                .map_err(|e| SourceError::Fatal(format!("{}: {e}", path.display())))?;
            if files.is_empty() {
                return Err(SourceError::Fatal(format!("{} holds no images", path.display())));
            }
            let n = files.len();
            (
                Input::Images { dir: path.to_path_buf(), files, next: 0 },
                c.fps,
                format!("{n} images in {}", path.display()),
            )
        } else {
            if !path.exists() {
                return Err(SourceError::Fatal(format!("video file {} does not exist", path.display())));
            }
            let cap = videoio::VideoCapture::from_file(&c.path, videoio::CAP_ANY)?;
            if !cap.is_opened().unwrap_or(false) {
                return Err(SourceError::Fatal(format!("{} is not a video OpenCV can read", path.display())));
            }
            let fps = cap.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
            let rate = if fps > 0.0 && fps.is_finite() { fps } else { c.fps };
            (Input::Capture(cap), rate, format!("video {}", path.display()))
        };
        Ok(Video {
            what,
            input,
            device: false,
            size,
            period: if c.realtime { 1.0 / rate } else { 0.0 },
            next_due: ctx.now(),
            index: 0,
            maps: undistort_maps(c)?,
            mono_at_start: 0.0,
            skipped: 0,
            ctx,
        })
    }

    fn read(&mut self) -> Result<Option<(Mat, f64)>, SourceError> {
        match &mut self.input {
            Input::Capture(cap) => {
                let mut frame = Mat::default();
                let ok =
                    cap.read(&mut frame).map_err(|e| SourceError::Gone(format!("{}: {e}", self.what)))?;
                let grabbed = self.ctx.now();
                if !ok || frame.empty() {
                    return if self.device {
                        Err(SourceError::Gone(format!("{}: no frame (device unplugged?)", self.what)))
                    } else {
                        Ok(None)
                    };
                }
                // The driver's buffer timestamp (CLOCK_MONOTONIC on V4L2) when it is plausible,
                // else the time of the grab.
                let mut t = grabbed;
                if self.device {
                    let ms = cap.get(videoio::CAP_PROP_POS_MSEC).unwrap_or(0.0);
                    let stamped = ms / 1000.0 - self.mono_at_start;
                    if ms > 0.0 && stamped <= grabbed && grabbed - stamped < 1.0 {
                        t = stamped;
                    }
                }
                Ok(Some((frame, t)))
            }
            // One bad file (truncated by a full card, garbage) must not end a folder of
            // good ones: it is skipped, named and counted.
            Input::Images { dir, files, next } => loop {
                let Some(p) = files.get(*next).cloned() else { return Ok(None) };
                // `read_image`, not `imread`: OpenCV decodes a JPEG cut inside its image
                // data without an error, grey below the cut.
                let why = match crate::imaging::read_image(&p, imgcodecs::IMREAD_COLOR) {
                    Ok(img) => {
                        *next += 1;
                        return Ok(Some((img, self.ctx.now())));
                    }
                    Err(e) => e,
                };
                // The folder itself gone, or emptied (a card's mount point after it was
                // unmounted): every file would fail in one burst and the camera end for
                // good. This image is read again once the folder is back. A file missing
                // from a folder that still holds others is skipped below, like a bad one.
                let emptied = || std::fs::read_dir(&*dir).map_or(true, |mut d| d.next().is_none());
                if !dir.is_dir() || (!p.exists() && emptied()) {
                    return Err(SourceError::Gone(format!(
                        "image folder {} is gone or empty (unmounted?); waiting for it at image {} of {}",
                        dir.display(),
                        *next + 1,
                        files.len()
                    )));
                }
                *next += 1;
                self.skipped += 1;
                tracing::warn!("{why}; skipped ({} skipped in all)", self.skipped);
            },
        }
    }
}

impl FrameSource for Video {
    fn next(&mut self) -> Result<Option<Captured>, SourceError> {
        if self.period > 0.0 {
            // After a pause (a folder waited for) the pace starts again from now instead
            // of catching up in a burst.
            self.next_due = self.next_due.max(self.ctx.now() - self.period);
            if !self.ctx.sleep_until(self.next_due) {
                return Ok(None);
            }
            self.next_due += self.period;
        }
        let Some((mut frame, capture_s)) = self.read()? else { return Ok(None) };
        if (frame.cols(), frame.rows()) != self.size {
            if self.device {
                return Err(SourceError::Fatal(format!(
                    "{} changed its frame size to {}x{}",
                    self.what,
                    frame.cols(),
                    frame.rows()
                )));
            }
            let mut resized = Mat::default();
            imgproc::resize(
                &frame,
                &mut resized,
                Size::new(self.size.0, self.size.1),
                0.0,
                0.0,
                imgproc::INTER_AREA,
            )?;
            frame = resized;
        }
        if let Some((m1, m2)) = &self.maps {
            let mut out = Mat::default();
            imgproc::remap(
                &frame,
                &mut out,
                m1,
                m2,
                imgproc::INTER_LINEAR,
                core::BORDER_CONSTANT,
                core::Scalar::all(0.0),
            )?;
            frame = out;
        }
        let index = self.index;
        self.index += 1;
        Ok(Some(Captured { index, capture_s, image: frame, mask: None, pose: None, truth: None }))
    }

    fn describe(&self) -> String {
        match self.skipped {
            0 => self.what.clone(),
            n => format!("{} ({n} unreadable skipped)", self.what),
        }
    }

    fn unreadable(&self) -> u64 {
        self.skipped
    }

    fn resumable(&self) -> bool {
        matches!(self.input, Input::Images { .. })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::write_grey_frames;
    use std::sync::atomic::AtomicBool;
    use std::sync::{Arc, Mutex};

    fn ctx() -> SourceContext {
        SourceContext {
            started: std::time::Instant::now(),
            latest_pose: Arc::new(Mutex::new(None)),
            stop: Arc::new(AtomicBool::new(false)),
            credits: None,
        }
    }

    #[test]
    fn a_missing_device_is_named() {
        let c = Camera { device: "/dev/video-mavloc-missing".into(), ..Camera::default() };
        let e = Video::open_device(&c, ctx()).err().expect("no such device");
        assert!(e.to_string().contains("/dev/video-mavloc-missing"), "{e}");
        assert!(matches!(e, SourceError::Gone(_)), "a camera may come back: retried");
    }

    /// A `file` camera on a folder of 32x24 images, as fast as it is read.
    fn folder_camera(dir: &std::path::Path) -> Video {
        let c = Camera {
            path: dir.to_string_lossy().into(),
            width: 32,
            height: 24,
            realtime: false,
            ..Camera::default()
        };
        Video::open_file(&c, ctx()).unwrap()
    }

    #[test]
    fn an_image_folder_plays_in_name_order_and_ends() {
        let dir = tempfile::tempdir().unwrap();
        write_grey_frames(dir.path(), &[("1.png", 10.0), ("0.png", 200.0)]);
        let mut v = folder_camera(dir.path());
        let a = v.next().unwrap().unwrap();
        assert_eq!(*a.image.at_2d::<core::Vec3b>(0, 0).unwrap(), core::Vec3b::from([200, 200, 200]));
        assert_eq!(v.next().unwrap().unwrap().index, 1);
        assert!(v.next().unwrap().is_none());
    }

    /// A folder that vanishes (a card unmounted) is waited for: nothing is skipped, and
    /// the camera goes on at the image it stopped at once the folder is back.
    #[test]
    fn a_vanished_folder_is_waited_for_and_resumed_where_it_stopped() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("frames");
        std::fs::create_dir(&dir).unwrap();
        write_grey_frames(&dir, &[("0.png", 0.0), ("1.png", 10.0), ("2.png", 20.0)]);
        let mut v = folder_camera(&dir);
        assert!(v.resumable());
        assert_eq!(v.next().unwrap().unwrap().index, 0);
        let away = root.path().join("unmounted");
        std::fs::rename(&dir, &away).unwrap();
        for _ in 0..2 {
            let e = v.next().err().expect("no frame while the folder is gone");
            assert!(matches!(e, SourceError::Gone(_)), "retried, not fatal: {e}");
            assert!(
                e.to_string().contains("frames is gone") && e.to_string().contains("image 2 of 3"),
                "{e}"
            );
        }
        assert_eq!(v.unreadable(), 0, "nothing skipped while it was gone");
        std::fs::rename(&away, &dir).unwrap();
        let back = v.next().unwrap().unwrap();
        assert_eq!(back.index, 1);
        assert_eq!(
            *back.image.at_2d::<core::Vec3b>(0, 0).unwrap(),
            core::Vec3b::from([10, 10, 10]),
            "image 1"
        );
        // The mount point left empty by an unmount, with the folder still there.
        let card = root.path().join("card");
        std::fs::rename(&dir, &card).unwrap();
        std::fs::create_dir(&dir).unwrap();
        let e = v.next().err().expect("no frame while the folder is empty");
        assert!(e.to_string().contains("image 3 of 3"), "{e}");
        std::fs::remove_dir(&dir).unwrap();
        std::fs::rename(&card, &dir).unwrap();
        assert_eq!(v.next().unwrap().unwrap().index, 2);
        assert!(v.next().unwrap().is_none());
        assert_eq!(v.unreadable(), 0);
    }

    #[test]
    fn a_bad_image_in_a_folder_is_skipped_and_the_next_plays() {
        let dir = tempfile::tempdir().unwrap();
        let shade =
            |v: f64| Mat::new_rows_cols_with_default(24, 32, core::CV_8UC3, core::Scalar::all(v)).unwrap();
        write_grey_frames(dir.path(), &[("1.png", 10.0), ("3.jpg", 200.0)]);
        // Between them, JPEGs cut off as a full card leaves them: after their first bytes,
        // and just before their end (which OpenCV alone decodes without an error).
        let mut jpeg = core::Vector::<u8>::new();
        imgcodecs::imencode(".jpg", &shade(100.0), &mut jpeg, &core::Vector::new()).unwrap();
        let jpeg = jpeg.to_vec();
        std::fs::write(dir.path().join("2.jpg"), &jpeg[..20]).unwrap();
        std::fs::write(dir.path().join("2a.jpg"), &jpeg[..jpeg.len() - 2]).unwrap();
        let mut v = folder_camera(dir.path());
        let shade_of = |f: &Captured| f.image.at_2d::<core::Vec3b>(0, 0).unwrap()[0];
        let first = v.next().unwrap().unwrap();
        assert_eq!(shade_of(&first), 10);
        let third = v.next().expect("the camera goes on").unwrap();
        assert!((shade_of(&third) as i32 - 200).abs() <= 2, "frame 3 follows frame 1");
        assert_eq!(v.unreadable(), 2);
        assert!(v.describe().contains("2 unreadable skipped"), "{}", v.describe());
        assert!(v.next().unwrap().is_none());
    }
}
