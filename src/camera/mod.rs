//! Frame sources, chosen by `camera.source`: each runs on its own thread and hands the
//! daemon [`Captured`] frames stamped with the local monotonic time of capture (seconds
//! since the daemon started, the clock the time-alignment stage maps autopilot time to).
//!
//! - [`video`]: `v4l2` (a camera through OpenCV's V4L2 backend, reopened with backoff when
//!   it disappears) and `file` (a video file or a folder of images).
//! - [`replay`]: `dataset`, a recorded dataset replayed with its own poses, so a live run
//!   can be compared with the offline one frame for frame.
//! - [`sim`]: the SITL camera adapter, rendering each frame from the pose the daemon
//!   receives over MAVLink.
//!
//! A source never blocks the daemon: frames go through a bounded channel, and with
//! `camera.realtime = false` (file and dataset) a credit system makes the source wait for
//! the pipeline instead of dropping frames.

pub mod replay;
pub mod sim;
pub mod video;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use opencv::core::Mat;

use crate::align::AlignedPose;
use crate::geometry::{CameraPose, Geodetic, Intrinsics};
use crate::settings::{CameraSource, Settings};

/// One frame from a source.
pub struct Captured {
    pub index: u64,
    /// Local monotonic capture time, seconds since the daemon's start.
    pub capture_s: f64,
    /// BGR 8-bit image at the configured size.
    pub image: Mat,
    /// Target mask (255 inside the target area), where the source knows it.
    pub mask: Option<Mat>,
    /// The pose, where the source knows it (a replayed dataset); otherwise the daemon
    /// aligns the frame with telemetry.
    pub pose: Option<AlignedPose>,
    /// The true camera position, where known (simulation), for evaluation.
    pub truth: Option<[f64; 3]>,
}

/// Why a source failed; `Gone` is worth retrying (a camera unplugged), `Fatal` is not.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("{0}")]
    Gone(String),
    #[error("{0}")]
    Fatal(String),
}

impl From<opencv::Error> for SourceError {
    fn from(e: opencv::Error) -> Self {
        SourceError::Gone(format!("OpenCV: {e}"))
    }
}

/// A frame source: `next` blocks until a frame is there; `Ok(None)` at the end of a file
/// or dataset.
pub trait FrameSource: Send {
    fn next(&mut self) -> Result<Option<Captured>, SourceError>;
    /// What it reads, for logs.
    fn describe(&self) -> String;
    /// Frames this source skipped since it opened because they could not be used (an
    /// unreadable or wrong-size file): each is warned of by name, and the daemon counts
    /// them in `status.json` (`frames_unreadable`).
    fn unreadable(&self) -> u64 {
        0
    }
    /// After a `Gone` error, whether `next` may be called again on this source (it waits
    /// where it stopped, like a folder of images that vanished) instead of reopening it
    /// (a device, which starts afresh).
    fn resumable(&self) -> bool {
        false
    }
}

/// What sources share with the daemon: its clock, the latest pose (for the sim camera),
/// the flow-control credits and the stop flag.
#[derive(Clone)]
pub struct SourceContext {
    pub started: Instant,
    pub latest_pose: Arc<Mutex<Option<(f64, CameraPose)>>>,
    pub stop: Arc<AtomicBool>,
    /// With `realtime = false`: the daemon gives one credit back per frame it has finished
    /// with; the source sends a frame only with a credit in hand.
    pub credits: Option<Arc<Credits>>,
}

impl SourceContext {
    pub fn now(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    pub fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Sleeps until local time `t` or until stopped; false when stopped.
    pub fn sleep_until(&self, t: f64) -> bool {
        loop {
            if self.stopped() {
                return false;
            }
            let left = t - self.now();
            if left <= 0.0 {
                return true;
            }
            std::thread::sleep(Duration::from_secs_f64(left.min(0.05)));
        }
    }
}

/// A counting semaphore for lossless replay.
#[derive(Default)]
pub struct Credits {
    count: Mutex<u32>,
    cv: std::sync::Condvar,
}

impl Credits {
    pub fn new(initial: u32) -> Credits {
        Credits { count: Mutex::new(initial), cv: std::sync::Condvar::new() }
    }

    pub fn give(&self) {
        *self.count.lock().expect("credits") += 1;
        self.cv.notify_one();
    }

    /// Takes a credit, waiting up to `timeout`; false on timeout.
    pub fn take(&self, timeout: Duration) -> bool {
        let guard = self.count.lock().expect("credits");
        let (mut guard, _) = self.cv.wait_timeout_while(guard, timeout, |c| *c == 0).expect("credits");
        if *guard > 0 {
            *guard -= 1;
            true
        } else {
            false
        }
    }
}

/// The intrinsics of the frames a source delivers: a dataset's own, a simulated scenario's
/// field of view at the configured size, else the configuration's.
pub fn intrinsics(s: &Settings) -> Result<Intrinsics, String> {
    let c = &s.camera;
    match c.source {
        CameraSource::Dataset => {
            let ds = mavloc_data::Dataset::open(std::path::Path::new(&c.path))?;
            Ok(ds.camera.intrinsics())
        }
        CameraSource::Sim if c.fx <= 0.0 => sim::intrinsics(s),
        _ => Ok(c.intrinsics()),
    }
}

/// The WGS84 origin of the local frame, where the source defines it (datasets, scenarios).
pub fn origin(s: &Settings) -> Option<Geodetic> {
    match s.camera.source {
        CameraSource::Dataset => {
            mavloc_data::Dataset::open(std::path::Path::new(&s.camera.path)).ok().map(|d| d.camera.origin)
        }
        // The simulated world's origin, which the simulated vehicle's home matches.
        CameraSource::Sim => sim::origin(s),
        _ => None,
    }
}

/// Opens the configured source. Errors name the device, file or scenario.
pub fn open(s: &Settings, ctx: &SourceContext) -> Result<Box<dyn FrameSource>, SourceError> {
    let c = &s.camera;
    match c.source {
        CameraSource::V4l2 => Ok(Box::new(video::Video::open_device(c, ctx.clone())?)),
        CameraSource::File => Ok(Box::new(video::Video::open_file(c, ctx.clone())?)),
        CameraSource::Dataset => Ok(Box::new(replay::Replay::open(s, ctx.clone())?)),
        CameraSource::Sim => Ok(Box::new(sim::SimCamera::open(s, ctx.clone())?)),
        CameraSource::None => Err(SourceError::Fatal("camera.source is \"none\"".into())),
    }
}

/// What the source thread tells the daemon.
pub enum CameraEvent {
    Frame(Box<Captured>),
    /// The source is up (first frame, or again after it was lost).
    Up(String),
    /// The source failed; it is retried with backoff unless `fatal`.
    Down {
        why: String,
        fatal: bool,
    },
    /// A file or dataset ended.
    Ended(String),
    /// Frames skipped as unusable since the daemon started (the new total).
    Unreadable(u64),
}

/// Runs the configured source on its own thread until `ctx.stop` or the end of its input,
/// reopening a lost camera with backoff (0.5 s doubling to 5 s) and logging one line per
/// state change, not per retry.
pub fn spawn(
    s: Settings,
    ctx: SourceContext,
    tx: tokio::sync::mpsc::Sender<CameraEvent>,
) -> std::thread::JoinHandle<()> {
    std::thread::Builder::new()
        .name("mavloc-camera".into())
        .spawn(move || {
            let mut backoff = 0.5;
            let mut up = false;
            let mut last_error = String::new();
            // Unusable frames of the sources closed before this one, and the total last told.
            let (mut unreadable_before, mut unreadable_told) = (0, 0);
            while !ctx.stopped() {
                let mut source = match open(&s, &ctx) {
                    Ok(src) => src,
                    Err(e) => {
                        let fatal = matches!(e, SourceError::Fatal(_));
                        let why = e.to_string();
                        if why != last_error || up {
                            let _ = tx.blocking_send(CameraEvent::Down { why: why.clone(), fatal });
                            last_error = why;
                            up = false;
                        }
                        if fatal || !ctx.sleep_until(ctx.now() + backoff) {
                            return;
                        }
                        backoff = (backoff * 2.0_f64).min(5.0);
                        continue;
                    }
                };
                loop {
                    if ctx.stopped() {
                        return;
                    }
                    if let Some(c) = &ctx.credits {
                        if !c.take(Duration::from_millis(200)) {
                            continue;
                        }
                    }
                    let result = source.next();
                    let unreadable = unreadable_before + source.unreadable();
                    if unreadable != unreadable_told {
                        unreadable_told = unreadable;
                        let _ = tx.blocking_send(CameraEvent::Unreadable(unreadable));
                    }
                    match result {
                        Ok(Some(frame)) => {
                            if !up {
                                up = true;
                                backoff = 0.5;
                                last_error.clear();
                                let _ = tx.blocking_send(CameraEvent::Up(source.describe()));
                            }
                            if tx.blocking_send(CameraEvent::Frame(Box::new(frame))).is_err() {
                                return;
                            }
                        }
                        Ok(None) => {
                            let _ = tx.blocking_send(CameraEvent::Ended(source.describe()));
                            return;
                        }
                        Err(e) => {
                            if let Some(c) = &ctx.credits {
                                c.give();
                            }
                            let fatal = matches!(e, SourceError::Fatal(_));
                            let why = e.to_string();
                            if why != last_error || up {
                                let _ = tx.blocking_send(CameraEvent::Down { why: why.clone(), fatal });
                            }
                            last_error = why;
                            up = false;
                            if fatal {
                                return;
                            }
                            if source.resumable() {
                                if !ctx.sleep_until(ctx.now() + backoff) {
                                    return;
                                }
                                backoff = (backoff * 2.0_f64).min(5.0);
                                continue;
                            }
                            break;
                        }
                    }
                }
                unreadable_before += source.unreadable();
                if !ctx.sleep_until(ctx.now() + backoff) {
                    return;
                }
                backoff = (backoff * 2.0_f64).min(5.0);
            }
        })
        .expect("spawn camera thread")
}

/// For tests: a 32x24 grey image in `dir` for each `(file name, shade)`, in the format
/// its extension names.
#[cfg(test)]
pub(crate) fn write_grey_frames(dir: &std::path::Path, frames: &[(&str, f64)]) {
    use opencv::{core, imgcodecs};
    for (name, shade) in frames {
        let m = Mat::new_rows_cols_with_default(24, 32, core::CV_8UC3, core::Scalar::all(*shade)).unwrap();
        imgcodecs::imwrite(dir.join(name), &m, &core::Vector::new()).unwrap();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn credits_block_until_given() {
        let c = Arc::new(Credits::new(1));
        assert!(c.take(Duration::from_millis(1)));
        assert!(!c.take(Duration::from_millis(20)), "no credit left");
        let c2 = c.clone();
        let t = std::thread::spawn(move || c2.take(Duration::from_secs(5)));
        std::thread::sleep(Duration::from_millis(20));
        c.give();
        assert!(t.join().unwrap());
    }

    /// The source thread tells the daemon how many frames its camera could not use, as
    /// they happen, so `status.json` counts what the log names one by one.
    #[test]
    fn the_source_thread_tells_the_unreadable_frames_it_skipped() {
        let dir = tempfile::tempdir().unwrap();
        write_grey_frames(dir.path(), &[("1.png", 90.0), ("4.png", 90.0)]);
        std::fs::write(dir.path().join("2.jpg"), b"").unwrap();
        std::fs::write(dir.path().join("3.png"), b"not a picture").unwrap();
        let mut s = Settings::default();
        s.camera.source = CameraSource::File;
        s.camera.path = dir.path().to_string_lossy().into();
        (s.camera.width, s.camera.height, s.camera.realtime) = (32, 24, false);
        let ctx = SourceContext {
            started: Instant::now(),
            latest_pose: Arc::new(Mutex::new(None)),
            stop: Arc::new(AtomicBool::new(false)),
            credits: None,
        };
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        spawn(s, ctx, tx).join().unwrap();
        let mut told = Vec::new();
        let mut frames = 0;
        while let Ok(e) = rx.try_recv() {
            match e {
                CameraEvent::Frame(_) => frames += 1,
                CameraEvent::Unreadable(n) => told.push(n),
                _ => {}
            }
        }
        assert_eq!(frames, 2);
        assert_eq!(told, vec![2], "two unreadable images, told once with their total");
    }

    /// A folder camera whose folder vanishes says so once, sends nothing while it is gone
    /// (it used to skip every remaining image in one burst, a warning each, and end for
    /// good), and goes on at the image it stopped at when the folder is back.
    #[test]
    fn a_folder_camera_that_vanishes_says_so_once_and_goes_on_where_it_stopped() {
        let root = tempfile::tempdir().unwrap();
        let dir = root.path().join("card");
        std::fs::create_dir(&dir).unwrap();
        write_grey_frames(&dir, &[("0.png", 0.0), ("1.png", 40.0), ("2.png", 80.0)]);
        let mut s = Settings::default();
        s.camera.source = CameraSource::File;
        s.camera.path = dir.to_string_lossy().into();
        (s.camera.width, s.camera.height, s.camera.realtime) = (32, 24, false);
        let credits = Arc::new(Credits::new(1));
        let ctx = SourceContext {
            started: Instant::now(),
            latest_pose: Arc::new(Mutex::new(None)),
            stop: Arc::new(AtomicBool::new(false)),
            credits: Some(credits.clone()),
        };
        let (tx, mut rx) = tokio::sync::mpsc::channel(16);
        let thread = spawn(s, ctx.clone(), tx);
        // The next event within 10 s, or none.
        let mut next = |wait: Duration| {
            let until = Instant::now() + wait;
            loop {
                match rx.try_recv() {
                    Ok(e) => return Some(e),
                    Err(_) if Instant::now() < until => std::thread::sleep(Duration::from_millis(5)),
                    Err(_) => return None,
                }
            }
        };
        let long = Duration::from_secs(10);
        let frame_index = |e: Option<CameraEvent>| match e {
            Some(CameraEvent::Frame(f)) => f.index,
            _ => panic!("a frame expected"),
        };
        assert!(matches!(next(long), Some(CameraEvent::Up(_))));
        assert_eq!(frame_index(next(long)), 0);
        let away = root.path().join("unmounted");
        std::fs::rename(&dir, &away).unwrap();
        credits.give();
        match next(long) {
            Some(CameraEvent::Down { why, fatal: false }) => assert!(why.contains("card is gone"), "{why}"),
            _ => panic!("the folder's loss is told, as a loss that is retried"),
        }
        // Two retries (after 0.5 and 1 s) pass unsaid: no burst, no end, no repeat.
        assert!(next(Duration::from_millis(1700)).is_none(), "nothing while the folder is gone");
        std::fs::rename(&away, &dir).unwrap();
        assert!(matches!(next(long), Some(CameraEvent::Up(_))));
        assert_eq!(frame_index(next(long)), 1, "on at the image it stopped at");
        credits.give();
        assert_eq!(frame_index(next(long)), 2);
        credits.give();
        assert!(matches!(next(long), Some(CameraEvent::Ended(_))));
        ctx.stop.store(true, Ordering::Relaxed);
        thread.join().unwrap();
    }
}
