//! `daemon.record`: the flight recorder. Every frame the live pipeline is given goes, with
//! the pose it was given, into a dataset (README, "The simulated world and the dataset
//! format") in `<daemon.record>/<run>/`, the run id the results of the same start carry.
//! A flight can then be replayed (`camera.source = "dataset"`) or run again offline with
//! other settings and the bundle adjustment (`mavloc area --dataset`).
//!
//! - **Never in the pipeline's way.** The recorder is a thread of its own with a short
//!   mailbox; a disk slower than the camera pushes out the oldest waiting frame (counted
//!   as not recorded), never a live one. A lossless replay (`camera.realtime = false`)
//!   has no live frame to protect, so there the offer waits for room instead (at most
//!   [`ROOM_WAIT`], for a disk that hangs) and the recording holds every frame.
//! - **A readable dataset at every moment, a power cut included.** `camera.toml` is
//!   written first; each frame's image is written whole under a hidden name and renamed
//!   into place. Once a second the images written since are synced, then their lines are
//!   appended to `telemetry.jsonl` in one write and synced (two syncs as each frame is
//!   written would cap an SD card's rate). A crash loses at most the last second, and
//!   leaves at most images without lines, or a torn last line, which
//!   [`mavloc_data::Dataset::open`] skips.
//! - **A full disk stops the recording, not the daemon**: one error naming the file, and
//!   the pipeline goes on. Before that, the recording stops when its disk's free space
//!   falls below `daemon.record_reserve_mb` (checked before each frame), so the results,
//!   the parameters and `status.json`, which share the disk in the usual layout, can
//!   still be written.
//! - **The pose as the pipeline had it.** The camera attitude is written as earth-frame
//!   angles in `gimbal.chain` with the gimbal offsets in force taken back out, so a replay
//!   with the same offsets gives the live attitude back exactly (and a replay with offsets
//!   found later by `mavloc calibrate gimbal` applies those instead). Positions stay in the
//!   first frame's local origin if the autopilot moves its origin during the flight
//!   (with none known, as indoors without GPS, they are written as given under a
//!   placeholder origin). Frames keep their live numbers, gaps included. The offsets are
//!   taken out of frames from a fixed mount too, which the live alignment does not offset:
//!   the dataset format has one gimbal for all frames, and this keeps "the same offsets
//!   give the live poses" true for every frame.
//!   A recording has no ground truth: each record's `true` pose repeats the measured one,
//!   as in imported photo sets. `autopilot_time` is the autopilot's clock at the capture
//!   (a replayed dataset's own `t`).
//! - **One recording per daemon start**: a pipeline reset starts new results but the
//!   recording goes on in the same folder.

use std::collections::VecDeque;
use std::io::Write;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use mavloc_data::dataset::{CameraFile, GimbalFrame, PoseRecord, TelemetryRecord};
use mavloc_geometry::{GimbalChain, Intrinsics, LocalFrame};

use opencv::prelude::*;

use super::worker::LiveFrame;
use crate::geometry::Geodetic;
pub use crate::settings::RecordFormat;

/// Frames waiting for the disk: about a second of a live area pipeline's frames.
const DEPTH: usize = 8;

/// JPEG quality of recorded frames (`daemon.record_format = "jpg"`).
const JPEG_QUALITY: i32 = 95;

fn extension(format: RecordFormat) -> &'static str {
    match format {
        RecordFormat::Jpg => "jpg",
        RecordFormat::Png => "png",
    }
}

/// What the recorder needs to know once, at start.
#[derive(Clone, Debug)]
pub struct RecordSpec {
    /// The recording's folder (`<daemon.record>/<run>`); created with the first frame.
    pub dir: PathBuf,
    pub format: RecordFormat,
    pub intrinsics: Intrinsics,
    /// The chain the camera's angles are written in (`gimbal.chain`).
    pub chain: GimbalChain,
    /// The camera source's own origin (a replayed dataset's, a scenario's), for frames
    /// that come before (or without) the autopilot's; as the live pipeline takes it.
    pub source_origin: Option<Geodetic>,
    /// The source waits for the pipeline (`camera.realtime = false`): an offer waits for
    /// room rather than pushing out a waiting frame.
    pub lossless: bool,
    /// Free space the recording leaves on its disk (`daemon.record_reserve_mb`): it stops
    /// before a frame that would start below it.
    pub reserve_bytes: u64,
}

/// How long a lossless offer waits for the disk before it drops the oldest waiting frame
/// after all: a disk that hangs must not hold the daemon's loop.
pub const ROOM_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// Counters the daemon logs and reports.
#[derive(Debug, Default)]
pub struct RecordStats {
    pub recorded: AtomicU64,
    /// Frames pushed out of the mailbox by newer ones (a slow disk), or left waiting when
    /// the recording failed.
    pub dropped: AtomicU64,
    /// The error that stopped the recording, if one did.
    pub failed: Mutex<Option<String>>,
}

/// Where no origin is known (a V4L2 camera, no GPS): local positions are written as they
/// are, under a placeholder origin, as the live pipeline does (`daemon::factory`).
const NO_ORIGIN: Geodetic = Geodetic { lat_deg: 0.0, lon_deg: 0.0, alt_m: 0.0 };

/// The telemetry of frames written since the last sync is held back until then: a
/// power cut must not leave a line whose image is not on the disk.
const SYNC_EVERY_S: f64 = 1.0;

struct Item {
    /// The live frame number: gaps (frames the pipeline was not given) are kept, since
    /// the area pipeline's landmark quality counts frames.
    index: u64,
    image: opencv::core::Mat,
    mask: Option<opencv::core::Mat>,
    capture_s: f64,
    pose: crate::align::AlignedPose,
    /// `None`: no origin known yet.
    origin: Option<Geodetic>,
    offsets_deg: [f64; 3],
}

#[derive(Default)]
struct Mailbox {
    items: VecDeque<Item>,
    stop: bool,
    /// Set (with the error in the stats) when the recording failed: offers are ignored.
    failed: bool,
}

/// The daemon's handle on the recorder thread.
pub struct Recorder {
    shared: Arc<(Mutex<Mailbox>, Condvar)>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Closed when the thread ends, so a stop can wait with a deadline.
    ended: Option<std::sync::mpsc::Receiver<()>>,
    pub stats: Arc<RecordStats>,
    pub dir: PathBuf,
    source_origin: Option<Geodetic>,
    lossless: bool,
}

/// How long a stop waits for the last frames and the final sync (the daemon promises to
/// stop within 2 s; a disk that hangs must not hold it).
const STOP_WAIT: std::time::Duration = std::time::Duration::from_millis(1000);

impl Recorder {
    pub fn start(spec: RecordSpec) -> Recorder {
        let shared = Arc::new((Mutex::new(Mailbox::default()), Condvar::new()));
        let stats = Arc::new(RecordStats::default());
        let (s2, st2, dir, source_origin, lossless) =
            (shared.clone(), stats.clone(), spec.dir.clone(), spec.source_origin, spec.lossless);
        let (done_tx, done_rx) = std::sync::mpsc::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("mavloc-record".into())
            .spawn(move || {
                let _done = done_tx;
                let s3 = s2.clone();
                let st3 = st2.clone();
                // A panic is a failed recording, reported as such; never the daemon's end.
                if catch_unwind(AssertUnwindSafe(|| run(spec, s2, st2))).is_err() {
                    fail(&s3, &st3, "the recorder panicked".into());
                }
            })
            .expect("spawn recorder thread");
        Recorder { shared, thread: Some(thread), ended: Some(done_rx), stats, dir, source_origin, lossless }
    }

    /// Offers a copy of a frame the pipeline is given, with the gimbal offsets (yaw,
    /// pitch, roll, degrees) that were added to its camera attitude. Returns at once,
    /// unless the recording is lossless and its mailbox full: then it waits for room (at
    /// most [`ROOM_WAIT`]). Called from the daemon's loop (a multi-threaded runtime) or
    /// any plain thread.
    pub fn offer(&self, frame: &LiveFrame, offsets_deg: [f64; 3]) {
        // Takes the mailbox's lock twice, briefly: the copy below is made without it.
        let (m, cv) = &*self.shared;
        if m.lock().expect("record mailbox").failed {
            return;
        }
        // The worker owns the frame's image; a copy (a few hundred kB at the usual sizes)
        // costs less than making every pipeline share its frames.
        let (Ok(image), Ok(mask)) =
            (frame.image.try_clone(), frame.mask.as_ref().map(|m| m.try_clone()).transpose())
        else {
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        };
        let item = Item {
            index: frame.index,
            image,
            mask,
            capture_s: frame.capture_s,
            pose: frame.pose,
            origin: frame.origin.or(self.source_origin),
            offsets_deg,
        };
        let mut mb = m.lock().expect("record mailbox");
        if self.lossless && mb.items.len() >= DEPTH {
            let wait = |mb| {
                cv.wait_timeout_while(mb, ROOM_WAIT, |mb: &mut Mailbox| {
                    mb.items.len() >= DEPTH && !mb.failed && !mb.stop
                })
                .expect("record mailbox")
                .0
            };
            // Blocking a runtime's worker thread would stall its other tasks
            // (`block_in_place` panics on a current-thread runtime, which has no other).
            let flavor = tokio::runtime::Handle::try_current().map(|h| h.runtime_flavor());
            mb = match flavor {
                Ok(tokio::runtime::RuntimeFlavor::MultiThread) => tokio::task::block_in_place(|| wait(mb)),
                _ => wait(mb),
            };
        }
        if mb.failed {
            return;
        }
        if mb.items.len() >= DEPTH {
            mb.items.pop_front();
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
        mb.items.push_back(item);
        // Both sides wait on the one condition variable: the recorder for frames, a
        // lossless offer for room.
        cv.notify_all();
    }

    /// Writes what is waiting, syncs and ends the thread (waiting at most [`STOP_WAIT`]).
    pub fn stop(mut self) -> Arc<RecordStats> {
        self.finish();
        self.stats.clone()
    }

    fn finish(&mut self) {
        {
            let (m, cv) = &*self.shared;
            m.lock().expect("record mailbox").stop = true;
            cv.notify_one();
        }
        let Some(thread) = self.thread.take() else { return };
        let ended = self.ended.take().map(|rx| rx.recv_timeout(STOP_WAIT));
        if matches!(ended, Some(Err(std::sync::mpsc::RecvTimeoutError::Timeout))) {
            // What still waits will not be written: counted, so the status adds up.
            let mut mb = self.shared.0.lock().unwrap_or_else(|p| p.into_inner());
            let left = mb.items.len();
            self.stats.dropped.fetch_add(left as u64, Ordering::Relaxed);
            mb.items.clear();
            tracing::warn!(
                "recording: the disk did not take the last frames within {STOP_WAIT:?}; not waiting for it \
                 ({left} not recorded)"
            );
            return;
        }
        let _ = thread.join();
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        self.finish();
    }
}

/// Marks the recording failed: the error is kept, what waits is counted as dropped, and
/// later offers are ignored (all under the mailbox's lock, so none slips in between).
fn fail(shared: &(Mutex<Mailbox>, Condvar), stats: &RecordStats, e: String) {
    tracing::error!("recording stopped: {e}; the pipeline goes on, the recording keeps the frames before");
    let mut mb = shared.0.lock().unwrap_or_else(|p| p.into_inner());
    mb.failed = true;
    stats.dropped.fetch_add(mb.items.len() as u64, Ordering::Relaxed);
    mb.items.clear();
    *stats.failed.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
    // A lossless offer waiting for room gives up at once.
    shared.1.notify_all();
}

fn run(spec: RecordSpec, shared: Arc<(Mutex<Mailbox>, Condvar)>, stats: Arc<RecordStats>) {
    let mut writer: Option<Writer> = None;
    let mut last_sync = std::time::Instant::now();
    loop {
        let (item, stopping) = {
            let (m, cv) = &*shared;
            let mut mb = m.lock().expect("record mailbox");
            loop {
                if let Some(i) = mb.items.pop_front() {
                    cv.notify_all();
                    break (Some(i), false);
                }
                if mb.stop {
                    break (None, true);
                }
                // Wake for the periodic sync while frames are held back.
                let pending = writer.as_ref().is_some_and(|w| !w.pending.is_empty());
                if pending {
                    let (g, _) = cv
                        .wait_timeout(mb, std::time::Duration::from_secs_f64(SYNC_EVERY_S))
                        .expect("mailbox");
                    mb = g;
                    if mb.items.is_empty() && !mb.stop {
                        break (None, false);
                    }
                } else {
                    mb = cv.wait(mb).expect("record mailbox");
                }
            }
        };
        let mut result = Ok(());
        if let Some(item) = item {
            result = match &mut writer {
                Some(w) => w.write(&item),
                None => Writer::create(&spec, &item).and_then(|w| {
                    tracing::info!("recording the frames the pipeline is given to {}", spec.dir.display());
                    writer.insert(w).write(&item)
                }),
            };
        }
        if result.is_ok() && (stopping || last_sync.elapsed().as_secs_f64() >= SYNC_EVERY_S) {
            if let Some(w) = &mut writer {
                let n = w.pending_frames();
                result = w.sync();
                if result.is_ok() {
                    stats.recorded.fetch_add(n, Ordering::Relaxed);
                }
            }
            last_sync = std::time::Instant::now();
        }
        if let Err(e) = result {
            // The frames written before the failure keep their lines if the disk still
            // takes them (a lossless replay fills a second's worth fast: without this, a
            // full disk left every image of such a recording without a line); if not,
            // they are counted as not recorded.
            if let Some(w) = &mut writer {
                let n = w.pending_frames();
                match w.sync() {
                    Ok(()) => stats.recorded.fetch_add(n, Ordering::Relaxed),
                    Err(_) => stats.dropped.fetch_add(n, Ordering::Relaxed),
                };
            }
            fail(&shared, &stats, e);
            return;
        }
        if stopping {
            return;
        }
    }
}

/// An open recording.
struct Writer {
    dir: PathBuf,
    format: RecordFormat,
    chain: GimbalChain,
    /// The recording's origin; `None`: the placeholder, positions written as given.
    origin: Option<Geodetic>,
    first_capture_s: f64,
    /// The last `t` written: a dataset's time never goes back (`Dataset::open` refuses it),
    /// and a camera's stamps can, a driver's stamp after a grab time (`camera::video`).
    last_t: f64,
    /// The last live frame number written and its number in the recording.
    last: Option<(u64, u64)>,
    /// Lines of frames whose images are written but not yet synced, and those images.
    pending: String,
    pending_files: Vec<PathBuf>,
    telemetry: std::fs::File,
    telemetry_path: PathBuf,
    reserve_bytes: u64,
    /// The free space could not be read, and that was said.
    reserve_unknown_said: bool,
}

/// Refuses to write on when `dir`'s file system has less than `reserve` bytes free for an
/// unprivileged writer (root's reserved blocks do not count: the results may be written
/// by another user). A file system that does not tell its free space (`statvfs` fails) is
/// said once, in `unknown_said`, and recorded on: the disk filling up stops the recording
/// anyway, as it did before the reserve.
fn check_reserve(dir: &Path, reserve: u64, unknown_said: &mut bool) -> Result<(), String> {
    if reserve == 0 {
        return Ok(());
    }
    let st = match rustix::fs::statvfs(dir) {
        Ok(st) => st,
        Err(e) => {
            if !std::mem::replace(unknown_said, true) {
                tracing::warn!(
                    "cannot read the free space of {} ({e}): recording without daemon.record_reserve_mb",
                    dir.display()
                );
            }
            return Ok(());
        }
    };
    let free = st.f_bavail.saturating_mul(st.f_frsize);
    if free < reserve {
        return Err(format!(
            "{:.1} MB left on the disk of {}, below daemon.record_reserve_mb = {:.1} MB kept for results and state",
            free as f64 / 1e6,
            dir.display(),
            reserve as f64 / 1e6
        ));
    }
    Ok(())
}

impl Writer {
    fn create(spec: &RecordSpec, first: &Item) -> Result<Writer, String> {
        let dir = &spec.dir;
        if dir.join(mavloc_data::dataset::TELEMETRY_FILE).exists() {
            // Run ids are unique per start: an existing recording is never appended to.
            return Err(format!("{} already holds a recording", dir.display()));
        }
        let mut reserve_unknown_said = false;
        if let Some(parent) = dir.parent() {
            check_reserve(parent, spec.reserve_bytes, &mut reserve_unknown_said)?;
        }
        mavloc_data::dataset::prepare(dir)?;
        let camera = CameraFile::new(
            spec.intrinsics,
            spec.chain,
            GimbalFrame::Earth,
            first.origin.unwrap_or(NO_ORIGIN),
        );
        mavloc_data::dataset::write_camera(dir, &camera)?;
        let telemetry_path = dir.join(mavloc_data::dataset::TELEMETRY_FILE);
        let telemetry = std::fs::OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&telemetry_path)
            .map_err(|e| format!("cannot create {}: {e}", telemetry_path.display()))?;
        Ok(Writer {
            dir: dir.clone(),
            format: spec.format,
            chain: spec.chain,
            origin: first.origin,
            first_capture_s: first.capture_s,
            last_t: f64::NEG_INFINITY,
            last: None,
            pending: String::new(),
            pending_files: Vec::new(),
            telemetry,
            telemetry_path,
            reserve_bytes: spec.reserve_bytes,
            reserve_unknown_said,
        })
    }

    fn write(&mut self, item: &Item) -> Result<(), String> {
        // Live numbers with their gaps; a camera that reconnects counts from 0 again, so a
        // number never goes back.
        let n = match self.last {
            None => 0,
            Some((index, n)) => n + item.index.saturating_sub(index).max(1),
        };
        check_reserve(&self.dir, self.reserve_bytes, &mut self.reserve_unknown_said)?;
        let image = self.dir.join("frames").join(format!("{n:06}.{}", extension(self.format)));
        write_image(&image, &item.image, self.format)?;
        self.pending_files.push(image);
        if let Some(mask) = &item.mask {
            let path = self.dir.join("masks").join(format!("{n:06}.png"));
            write_image(&path, mask, RecordFormat::Png)?;
            self.pending_files.push(path);
        }
        let pose =
            pose_record(&item.pose, self.chain, item.offsets_deg, |p| match (self.origin, item.origin) {
                (Some(ours), Some(theirs)) if ours != theirs => {
                    LocalFrame::new(ours).to_ned(&LocalFrame::new(theirs).to_geodetic(&p))
                }
                _ => p,
            });
        self.last_t = self.last_t.max(item.capture_s - self.first_capture_s);
        let record = TelemetryRecord {
            frame: n,
            t: self.last_t,
            truth: pose,
            measured: pose,
            appearance: None,
            autopilot_time: Some(item.pose.autopilot_time),
        };
        self.pending.push_str(&serde_json::to_string(&record).map_err(|e| e.to_string())?);
        self.pending.push('\n');
        self.last = Some((item.index, n));
        Ok(())
    }

    /// Frames written whose lines wait for the next sync (one line a frame).
    fn pending_frames(&self) -> u64 {
        self.pending.bytes().filter(|b| *b == b'\n').count() as u64
    }

    /// Makes the images written so far durable, then appends their lines (in one write:
    /// a crash tears at most the last line) and makes those durable.
    fn sync(&mut self) -> Result<(), String> {
        if self.pending.is_empty() {
            return Ok(());
        }
        // Our own files only (a syncfs would wait for everything else on the disk too), a
        // second's worth at a time rather than two syncs as each frame is written.
        let sync = |p: &Path| {
            std::fs::File::open(p)
                .and_then(|f| f.sync_all())
                .map_err(|e| format!("cannot sync {}: {e}", p.display()))
        };
        for f in self.pending_files.drain(..) {
            sync(&f)?;
        }
        sync(&self.dir.join("frames"))?;
        sync(&self.dir.join("masks"))?;
        let io = |e: std::io::Error| format!("cannot write {}: {e}", self.telemetry_path.display());
        self.telemetry.write_all(self.pending.as_bytes()).map_err(io)?;
        self.telemetry.sync_data().map_err(io)?;
        self.pending.clear();
        Ok(())
    }
}

/// Encodes in memory, then writes under a hidden name and renames: a reader never sees
/// half an image.
fn write_image(path: &Path, image: &opencv::core::Mat, format: RecordFormat) -> Result<(), String> {
    use opencv::core::Vector;
    let mut params = Vector::<i32>::new();
    if format == RecordFormat::Jpg {
        params.push(opencv::imgcodecs::IMWRITE_JPEG_QUALITY);
        params.push(JPEG_QUALITY);
    } else {
        // Fast compression: a recording is written during the flight.
        params.push(opencv::imgcodecs::IMWRITE_PNG_COMPRESSION);
        params.push(1);
    }
    let mut bytes = Vector::<u8>::new();
    let ext = format!(".{}", extension(format));
    match opencv::imgcodecs::imencode(&ext, image, &mut bytes, &params) {
        Ok(true) => {}
        Ok(false) => return Err(format!("cannot encode {}", path.display())),
        Err(e) => return Err(format!("cannot encode {}: {e}", path.display())),
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    let result = std::fs::write(&tmp, bytes.as_slice()).and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(format!("cannot write {}: {e}", path.display()));
    }
    Ok(())
}

/// The dataset record of an aligned pose: the vehicle as the telemetry had it, the camera
/// as earth-frame angles in `chain` with `offsets_deg` taken out (the dataset reader adds
/// the configured offsets back), the position through `place` (into the recording's
/// origin).
pub fn pose_record(
    pose: &crate::align::AlignedPose,
    chain: GimbalChain,
    offsets_deg: [f64; 3],
    place: impl Fn(mavloc_geometry::Vec3) -> mavloc_geometry::Vec3,
) -> PoseRecord {
    let (roll, pitch, yaw) = pose.vehicle.attitude.euler_angles();
    let a = chain.angles(&pose.camera.attitude);
    let position = place(pose.camera.position);
    PoseRecord {
        position: position.into(),
        attitude_deg: [roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees()],
        gimbal_deg: [
            a.yaw.to_degrees() - offsets_deg[0],
            a.pitch.to_degrees() - offsets_deg[1],
            a.roll.to_degrees() - offsets_deg[2],
        ],
        velocity: pose.vehicle.velocity.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::{AlignedPose, VehicleSample};
    use mavloc_geometry::{CameraPose, GimbalAngles, Vec3};
    use nalgebra::UnitQuaternion;
    use proptest::prelude::*;

    fn aligned(camera: CameraPose, vehicle_rpy: (f64, f64, f64)) -> AlignedPose {
        AlignedPose {
            autopilot_time: 12.0,
            vehicle: VehicleSample {
                position: camera.position,
                velocity: Vec3::new(1.0, -2.0, 0.5),
                attitude: UnitQuaternion::from_euler_angles(vehicle_rpy.0, vehicle_rpy.1, vehicle_rpy.2),
            },
            camera,
            from_gimbal: true,
        }
    }

    fn frame(index: u64, origin: Option<Geodetic>) -> LiveFrame {
        let image = opencv::core::Mat::new_rows_cols_with_default(
            48,
            64,
            opencv::core::CV_8UC3,
            opencv::core::Scalar::all(index as f64 * 10.0),
        )
        .unwrap();
        let camera = CameraPose::from_gimbal(
            Vec3::new(index as f64, 2.0, -30.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(10.0, -70.0, 0.0),
            mavloc_geometry::Mount::Earth,
        );
        let mut pose = aligned(camera, (0.0, 0.0, 0.3));
        pose.autopilot_time = 50.0 + index as f64 * 0.25;
        LiveFrame {
            index,
            capture_s: 100.0 + index as f64 * 0.25,
            pose,
            image,
            mask: None,
            origin,
            truth: None,
            motion_only: false,
        }
    }

    fn spec(dir: &Path, format: RecordFormat) -> RecordSpec {
        RecordSpec {
            dir: dir.to_path_buf(),
            format,
            intrinsics: Intrinsics { width: 64, height: 48, fx: 50.0, fy: 50.0, cx: 31.5, cy: 23.5 },
            chain: GimbalChain::YawPitchRoll,
            source_origin: None,
            lossless: false,
            reserve_bytes: 0,
        }
    }

    /// The frames offered become a dataset that opens: lossless pixels in PNG, times from
    /// the first recorded frame, the autopilot's clock, each frame's pose, and the live
    /// frame numbers with their gaps (frame 3 was not given to the pipeline), which the
    /// area pipeline's landmark quality counts.
    #[test]
    fn a_recording_is_a_dataset_of_the_frames_offered() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(spec(&rec_dir, RecordFormat::Png));
        let origin = Geodetic::new(57.0, 10.0, 12.0);
        // Fewer than the mailbox holds: none is pushed out, however slow the disk.
        for i in [1, 2, 4, 5, 6] {
            r.offer(&frame(i, Some(origin)), [0.0; 3]);
        }
        let stats = r.stop();
        assert_eq!(stats.recorded.load(Ordering::Relaxed), 5);
        assert_eq!(stats.dropped.load(Ordering::Relaxed), 0);
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        let numbers: Vec<u64> = ds.records.iter().map(|r| r.frame).collect();
        assert_eq!(numbers, [0, 1, 3, 4, 5]);
        assert_eq!(ds.camera.origin, origin);
        assert_eq!(ds.records[0].t, 0.0);
        assert!((ds.records[4].t - 1.25).abs() < 1e-12);
        assert_eq!(ds.records[4].autopilot_time, Some(51.5), "the autopilot's clock at frame 6's capture");
        let img = crate::imaging::read_image(&ds.frame_path(&ds.records[1]), opencv::imgcodecs::IMREAD_COLOR)
            .unwrap();
        use opencv::prelude::*;
        assert_eq!(
            *img.at_2d::<opencv::core::Vec3b>(10, 10).unwrap(),
            opencv::core::Vec3b::from([20, 20, 20])
        );
        let pose = ds.camera_pose(&ds.records[1].measured, [0.0; 3]);
        assert!((pose.position - Vec3::new(2.0, 2.0, -30.0)).norm() < 1e-9);
        // Nothing half written is left.
        let hidden: Vec<_> = std::fs::read_dir(rec_dir.join("frames"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with('.'))
            .collect();
        assert!(hidden.is_empty(), "{hidden:?}");
    }

    /// A capture stamp that steps back (a V4L2 driver's stamp after a grab time, after a
    /// stall) is written as the time before it: a dataset's time never goes back, and one
    /// such line made the whole recording unreadable.
    #[test]
    fn a_capture_stamp_that_steps_back_keeps_the_recording_readable() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(spec(&rec_dir, RecordFormat::Png));
        let origin = Some(Geodetic::new(57.0, 10.0, 12.0));
        let mut back = frame(3, origin);
        back.capture_s = 100.2; // frame 2 was captured at 100.5
        for f in [frame(1, origin), frame(2, origin), back, frame(4, origin)] {
            r.offer(&f, [0.0; 3]);
        }
        r.stop();
        let ds = mavloc_data::Dataset::open(&rec_dir).expect("the recording opens");
        let t: Vec<f64> = ds.records.iter().map(|r| r.t).collect();
        assert_eq!(t, [0.0, 0.25, 0.25, 0.75]);
    }

    /// A lossless replay (`camera.realtime = false`) records every frame however slow the
    /// disk: offers faster than the disk wait for room. A live recorder given the same
    /// burst pushes frames out (the CI failure this guards against: 55 of 60 replayed
    /// frames recorded on a loaded machine).
    #[test]
    fn a_lossless_recording_waits_for_the_disk_and_keeps_every_frame() {
        // Noise, so each PNG takes the disk (the encoder) far longer than an offer.
        let mut big = opencv::core::Mat::new_rows_cols_with_default(
            800,
            800,
            opencv::core::CV_8UC3,
            opencv::core::Scalar::all(0.0),
        )
        .unwrap();
        opencv::core::randu(&mut big, &opencv::core::Scalar::all(0.0), &opencv::core::Scalar::all(255.0))
            .unwrap();
        let burst = 3 * DEPTH as u64;
        let dir = tempfile::tempdir().unwrap();
        let mut recorded = Vec::new();
        for lossless in [false, true] {
            let rec_dir = dir.path().join(format!("lossless-{lossless}"));
            let r = Recorder::start(RecordSpec { lossless, ..spec(&rec_dir, RecordFormat::Png) });
            for i in 0..burst {
                let mut f = frame(i, Some(Geodetic::new(57.0, 10.0, 12.0)));
                f.image = big.clone();
                r.offer(&f, [0.0; 3]);
            }
            // Every frame offered is recorded or counted out once the disk is through
            // (not left to the stop, which waits at most STOP_WAIT: a loaded machine
            // takes longer for the frames still waiting).
            let start = std::time::Instant::now();
            let settled = |s: &RecordStats| {
                s.recorded.load(Ordering::Relaxed) + s.dropped.load(Ordering::Relaxed) == burst
            };
            while !settled(&r.stats) {
                assert!(start.elapsed().as_secs() < 60, "lossless {lossless}: the recorder never caught up");
                std::thread::sleep(std::time::Duration::from_millis(20));
            }
            let stats = r.stop();
            let (n, dropped) =
                (stats.recorded.load(Ordering::Relaxed), stats.dropped.load(Ordering::Relaxed));
            assert_eq!(n + dropped, burst, "lossless {lossless}: every frame recorded or counted");
            assert_eq!(mavloc_data::Dataset::open(&rec_dir).unwrap().records.len() as u64, n);
            recorded.push((n, dropped));
        }
        assert!(recorded[0].1 > 0, "the live recorder keeps up with nothing: {recorded:?}");
        assert_eq!(recorded[1], (burst, 0), "lossless: every frame, none dropped");
    }

    /// With no origin at all (a V4L2 camera without GPS, indoors) frames are still
    /// recorded, their local positions as given, under a placeholder origin; one that
    /// comes later does not move them.
    #[test]
    fn without_an_origin_positions_are_recorded_as_given() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(spec(&rec_dir, RecordFormat::Jpg));
        r.offer(&frame(0, None), [0.0; 3]);
        r.offer(&frame(1, Some(Geodetic::new(57.0, 10.0, 12.0))), [0.0; 3]);
        r.stop();
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        assert_eq!(ds.camera.origin, NO_ORIGIN);
        let p: Vec<Vec3> = ds.records.iter().map(|r| Vec3::from(r.measured.position)).collect();
        assert_eq!(p, [Vec3::new(0.0, 2.0, -30.0), Vec3::new(1.0, 2.0, -30.0)]);
    }

    /// A write that fails (here the frames' folder is a file; a full disk fails the same
    /// way) stops the recording with an error naming the file; the frames before stay a
    /// readable dataset and later offers are ignored.
    #[test]
    fn a_failed_write_stops_the_recording_and_keeps_the_frames_before() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(spec(&rec_dir, RecordFormat::Jpg));
        let origin = Some(Geodetic::new(57.0, 10.0, 12.0));
        r.offer(&frame(0, origin), [0.0; 3]);
        let start = std::time::Instant::now();
        while r.stats.recorded.load(Ordering::Relaxed) < 1 {
            assert!(start.elapsed().as_secs() < 10, "the first frame was not recorded");
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        std::fs::remove_dir_all(rec_dir.join("frames")).unwrap();
        std::fs::write(rec_dir.join("frames"), b"not a folder").unwrap();
        r.offer(&frame(1, origin), [0.0; 3]);
        while r.stats.failed.lock().unwrap().is_none() {
            assert!(start.elapsed().as_secs() < 10, "the failure was not reported");
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        r.offer(&frame(2, origin), [0.0; 3]);
        let stats = r.stop();
        let e = stats.failed.lock().unwrap().clone().unwrap();
        assert!(e.contains("frames/000001.jpg"), "{e}");
        assert_eq!(stats.recorded.load(Ordering::Relaxed), 1);
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        assert_eq!(ds.records.len(), 1);
    }

    /// On a disk shared with the results, the recording stops before the free space falls
    /// below the reserve: the frames before stay a dataset, and the room is left (a real
    /// 512 KiB tmpfs; needs root and mount, skipped with a message otherwise).
    #[test]
    fn the_recording_stops_at_the_reserve_and_leaves_the_room() {
        let dir = tempfile::tempdir().unwrap();
        let Some(_tmpfs) = mavloc_data::testing::mount_tmpfs(dir.path(), "512k", "") else { return };
        let rec_dir = dir.path().join("run-1");
        let reserve = 256 * 1024;
        let r = Recorder::start(RecordSpec {
            lossless: true,
            reserve_bytes: reserve,
            ..spec(&rec_dir, RecordFormat::Png)
        });
        let origin = Some(Geodetic::new(57.0, 10.0, 12.0));
        // Noise does not compress: about 9 KB a frame.
        use rand::SeedableRng;
        for i in 0..60 {
            let mut f = frame(i, origin);
            let mut rng = rand::rngs::StdRng::seed_from_u64(i);
            rand::RngCore::fill_bytes(&mut rng, f.image.data_bytes_mut().unwrap());
            r.offer(&f, [0.0; 3]);
        }
        let stats = r.stop();
        let e = stats.failed.lock().unwrap().clone().expect("stopped at the reserve");
        assert!(e.contains("below daemon.record_reserve_mb = 0.3 MB"), "{e}");
        let free = {
            let st = rustix::fs::statvfs(dir.path()).unwrap();
            st.f_bavail * st.f_frsize
        };
        // At most one frame past the check (about 9 KB, 12 KiB in tmpfs pages) and the
        // lines written at the stop.
        assert!(free + 24 * 1024 >= reserve, "{free} bytes left");
        let recorded = stats.recorded.load(Ordering::Relaxed);
        assert!((10..60).contains(&recorded), "{recorded} frames recorded");
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        assert_eq!(ds.records.len() as u64, recorded, "the frames before are a dataset");
    }

    /// Frames written before a failed write, within the second their lines wait for the
    /// sync, keep their lines (the audit's lossless replay onto a full disk left 36 images
    /// and an empty `telemetry.jsonl`, counted as neither recorded nor lost).
    #[test]
    fn a_failed_write_keeps_the_lines_of_the_frames_written_before_it() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(RecordSpec { lossless: true, ..spec(&rec_dir, RecordFormat::Png) });
        let origin = Some(Geodetic::new(57.0, 10.0, 12.0));
        r.offer(&frame(0, origin), [0.0; 3]);
        let start = std::time::Instant::now();
        while !rec_dir.join("frames/000000.png").exists() {
            assert!(start.elapsed().as_secs() < 10, "the first frame was not written");
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        // Frame 3's image cannot be put in place: a folder is in its way.
        std::fs::create_dir(rec_dir.join("frames/000003.png")).unwrap();
        for i in 1..=4 {
            r.offer(&frame(i, origin), [0.0; 3]);
        }
        while r.stats.failed.lock().unwrap().is_none() {
            assert!(start.elapsed().as_secs() < 10, "the failure was not reported");
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let stats = r.stop();
        assert!(stats.failed.lock().unwrap().clone().unwrap().contains("000003.png"));
        assert_eq!(stats.recorded.load(Ordering::Relaxed), 3);
        // Frame 4 is counted if it was waiting when the write failed; offered after, it
        // is ignored with the recording stopped.
        assert!(stats.dropped.load(Ordering::Relaxed) <= 1);
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        assert_eq!(ds.records.iter().map(|r| r.frame).collect::<Vec<_>>(), [0, 1, 2]);
    }

    /// A position in another origin (the autopilot moved its EKF origin during the flight)
    /// is written in the recording's first origin.
    #[test]
    fn positions_stay_in_the_first_origin() {
        let dir = tempfile::tempdir().unwrap();
        let rec_dir = dir.path().join("run-1");
        let r = Recorder::start(spec(&rec_dir, RecordFormat::Jpg));
        let first = Geodetic::new(57.0, 10.0, 12.0);
        r.offer(&frame(0, Some(first)), [0.0; 3]);
        // 100 m north of the first origin: frame 1's position (1, 2, -30) there is (101, 2, -30).
        let moved = LocalFrame::new(first).to_geodetic(&Vec3::new(100.0, 0.0, 0.0));
        std::thread::sleep(std::time::Duration::from_millis(50));
        r.offer(&frame(1, Some(moved)), [0.0; 3]);
        r.stop();
        let ds = mavloc_data::Dataset::open(&rec_dir).unwrap();
        let p = Vec3::from(ds.records[1].measured.position);
        assert!((p - Vec3::new(101.0, 2.0, -30.0)).norm() < 0.01, "{p:?}");
    }

    proptest! {
        /// What the replay of a recording computes (`Dataset::camera_pose` with the offsets
        /// configured) is the attitude the live pipeline had, for either chain and any
        /// offsets: the recorder takes out exactly what the reader puts back.
        #[test]
        fn a_recorded_pose_replays_as_the_live_attitude(
            yaw in -180.0..180.0f64, pitch in -90.0..=90.0f64, roll in -60.0..60.0f64,
            oy in -5.0..5.0f64, op in -5.0..5.0f64, or in -5.0..5.0f64,
            ryp in any::<bool>(),
        ) {
            let chain = if ryp { GimbalChain::YawRollPitch } else { GimbalChain::YawPitchRoll };
            let live = CameraPose::from_gimbal(
                Vec3::new(10.0, -4.0, -30.0),
                chain,
                GimbalAngles::from_degrees(yaw, pitch, roll),
                mavloc_geometry::Mount::Earth,
            );
            let rec = pose_record(&aligned(live, (0.1, -0.05, 1.0)), chain, [oy, op, or], |p| p);
            let camera = CameraFile::new(spec(Path::new(""), RecordFormat::Jpg).intrinsics, chain,
                GimbalFrame::Earth, Geodetic::new(57.0, 10.0, 12.0));
            let ds = mavloc_data::Dataset {
                dir: PathBuf::new(), camera, records: Vec::new(), ground_truth: Vec::new(), torn_line: None,
            };
            let replayed = ds.camera_pose(&rec, [oy, op, or]);
            // Matrices, not `angle()`: its arccos cannot resolve below about 1e-8 rad.
            let off = (replayed.attitude.matrix() - live.attitude.matrix()).norm();
            prop_assert!(off < 1e-9, "replayed attitude {off:e} off the live one");
            prop_assert!((replayed.position - live.position).norm() < 1e-9);
        }
    }
}
