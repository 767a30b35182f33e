//! The pipeline worker: one blocking thread that owns the running pipeline, so the async
//! side (link, timers) never waits on image processing.
//!
//! Frames come through a short mailbox of `depth` frames: a frame arriving at a full
//! mailbox pushes out the oldest one waiting (counted as dropped). The indoor pipeline
//! waits with one frame at most, because a late pose estimate is worth less than the next
//! one; the area pipeline's results are a map, so it keeps a few
//! ([`super::live::AREA_QUEUE_FRAMES`]) to ride out moments when the camera and the
//! pipeline share the cores. A pipeline that panics on a frame is reported, rebuilt from its factory,
//! and the worker goes on with the next frame: one bad frame must not stop the daemon.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::{Arc, Condvar, Mutex};

use crate::align::AlignedPose;
use crate::settings::Settings;

/// A frame with its capture time (local monotonic seconds) and aligned pose.
pub struct LiveFrame {
    pub index: u64,
    pub capture_s: f64,
    pub pose: AlignedPose,
    /// BGR 8-bit image.
    pub image: opencv::core::Mat,
    /// Target mask (255 inside), when the source provides one.
    pub mask: Option<opencv::core::Mat>,
    /// WGS84 origin of the local NED frame, when the autopilot has told it.
    pub origin: Option<crate::geometry::Geodetic>,
    /// True camera position (simulation only), for evaluation files.
    pub truth: Option<[f64; 3]>,
    /// The camera is too low for the pipeline's position (indoor, below
    /// `indoor.min_height_m`): only the vehicle's motion is measured.
    pub motion_only: bool,
}

pub use super::core::{PipelineEvent, PositionEstimate, Report, VelocityEstimate};

/// A live pipeline: plain synchronous code, no tokio, no MAVLink.
pub trait LivePipeline: Send {
    fn process(&mut self, frame: &LiveFrame) -> Report;
    /// Applies tuned parameters without a restart.
    fn apply(&mut self, settings: &Settings);
    /// Writes the complete current results (as one unit, in the pipeline's own run: see
    /// [`super::live`]); returns the files written. On an error the results on disk are
    /// those of the last good write.
    fn write_results(&self) -> std::io::Result<Vec<PathBuf>>;
    /// The last write, at a clean stop: the results then say they are complete
    /// (`summary.json` `"complete": true`), which a checkpoint or a crash never does.
    fn finish(&mut self) -> std::io::Result<Vec<PathBuf>> {
        self.write_results()
    }
    /// Adjust the map now (the area pipeline; at a touchdown, or asked over MAVLink):
    /// `why` says which, for what the ground is told.
    fn adjust_map(&mut self, _why: &str) -> Vec<PipelineEvent> {
        Vec::new()
    }
    /// Called at least every [`POLL_PERIOD`], frames or not: work the pipeline finished
    /// outside a frame (the adjustment after landing).
    fn poll(&mut self) -> Vec<PipelineEvent> {
        Vec::new()
    }
}

/// The worker calls [`LivePipeline::poll`] at least this often, also when no frame comes
/// (a camera that stopped after the landing).
pub const POLL_PERIOD: std::time::Duration = std::time::Duration::from_millis(500);

/// Builds a fresh pipeline (at start, reset, and after a panic).
pub type Factory = Box<dyn Fn(&Settings) -> Result<Box<dyn LivePipeline>, String> + Send>;

/// Requests to the worker.
pub enum Request {
    Apply(Box<Settings>),
    Reset,
    Snapshot(std::sync::mpsc::Sender<Result<Vec<PathBuf>, String>>),
    /// Adjust the map now: why ("landed", "asked to").
    AdjustMap(&'static str),
    Stop,
}

/// What the worker tells the daemon: the core's pipeline events as they are, and the
/// end of the worker.
// A report is a few hundred bytes, one per frame through a bounded channel: boxing it
// would cost an allocation per frame to save a few kilobytes of channel.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
pub enum Event {
    Pipeline(PipelineEvent),
    /// The worker has ended after a stop; the files its last write left.
    Stopped {
        files: Vec<PathBuf>,
    },
}

#[derive(Default)]
struct Mailbox {
    frames: std::collections::VecDeque<LiveFrame>,
    depth: usize,
    requests: Vec<Request>,
}

/// The daemon's handle on a running worker.
pub struct Worker {
    shared: Arc<(Mutex<Mailbox>, Condvar)>,
    thread: Option<std::thread::JoinHandle<()>>,
    pub dropped: Arc<std::sync::atomic::AtomicU64>,
    /// How the stop went, once the worker handled it: the final write's outcome.
    stopped: Arc<Mutex<Option<Result<usize, String>>>>,
}

impl Worker {
    /// Starts a worker whose mailbox holds `depth` frames (at least one); `events`
    /// receives reports (the daemon's side is async, so the worker only ever does
    /// non-blocking sends).
    pub fn start(
        factory: Factory,
        settings: Settings,
        depth: usize,
        events: tokio::sync::mpsc::Sender<Event>,
    ) -> Worker {
        let mailbox = Mailbox { depth: depth.max(1), ..Mailbox::default() };
        let shared = Arc::new((Mutex::new(mailbox), Condvar::new()));
        let dropped = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let s2 = shared.clone();
        let stopped = Arc::new(Mutex::new(None));
        let f2 = stopped.clone();
        let thread = std::thread::Builder::new()
            .name("mavloc-pipeline".into())
            .spawn(move || run(factory, settings, s2, events, f2))
            .expect("spawn pipeline thread");
        Worker { shared, thread: Some(thread), dropped, stopped }
    }

    /// Offers a frame; at a full mailbox the oldest waiting frame is dropped (and counted).
    pub fn offer(&self, frame: LiveFrame) {
        let (m, cv) = &*self.shared;
        let mut mb = m.lock().expect("mailbox");
        if mb.frames.len() >= mb.depth {
            mb.frames.pop_front();
            self.dropped.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        mb.frames.push_back(frame);
        cv.notify_one();
    }

    pub fn request(&self, r: Request) {
        let (m, cv) = &*self.shared;
        m.lock().expect("mailbox").requests.push(r);
        cv.notify_one();
    }

    /// Stops the worker after its current frame and waits for it to write its results: how
    /// many files it wrote (none when it had nothing worth a set, as an area run with no
    /// landmark); an error says why they could not be (the last complete set stays current).
    pub fn stop(mut self) -> Result<usize, String> {
        self.request(Request::Stop);
        if let Some(t) = self.thread.take() {
            // `finish` runs outside the per-frame panic guard: a panic there is a failed stop.
            if let Err(p) = t.join() {
                return Err(format!("the pipeline panicked at its stop: {}", panic_message(&*p)));
            }
        }
        // No outcome: the worker had ended before (a rebuild that failed), so it wrote no
        // final set either.
        let outcome = self.stopped.lock().unwrap_or_else(|p| p.into_inner()).take();
        outcome.unwrap_or_else(|| Err("the pipeline had ended before it was asked to stop".into()))
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        if self.thread.is_some() {
            self.request(Request::Stop);
        }
    }
}

fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

fn run(
    factory: Factory,
    mut settings: Settings,
    shared: Arc<(Mutex<Mailbox>, Condvar)>,
    events: tokio::sync::mpsc::Sender<Event>,
    stopped: Arc<Mutex<Option<Result<usize, String>>>>,
) {
    let build = |s: &Settings| match catch_unwind(AssertUnwindSafe(|| factory(s))) {
        Ok(r) => r,
        Err(p) => Err(format!("pipeline construction panicked: {}", panic_message(&*p))),
    };
    let mut pipeline = match build(&settings) {
        Ok(p) => p,
        Err(e) => {
            let _ = events.try_send(Event::Pipeline(PipelineEvent::Failed(e)));
            return;
        }
    };
    let (m, cv) = &*shared;
    loop {
        let (frame, requests) = {
            let mut mb = m.lock().expect("mailbox");
            if mb.frames.is_empty() && mb.requests.is_empty() {
                mb = cv.wait_timeout(mb, POLL_PERIOD).expect("mailbox").0;
            }
            (mb.frames.pop_front(), std::mem::take(&mut mb.requests))
        };
        let send = |list: Vec<PipelineEvent>| {
            for e in list {
                let _ = events.try_send(Event::Pipeline(e));
            }
        };
        // After a panic (on a frame, or outside one), said, and a new pipeline: the old
        // one's state may be half-updated. Results written so far stay on disk. None when
        // no pipeline can be built (said too): the worker ends.
        let rebuilt = |frame: Option<u64>, p: &(dyn std::any::Any + Send), settings: &Settings| {
            let message = panic_message(p);
            let _ = events.try_send(Event::Pipeline(PipelineEvent::Panicked { frame, message }));
            match build(settings) {
                Ok(p) => Some(p),
                Err(e) => {
                    let _ = events.try_send(Event::Pipeline(PipelineEvent::Failed(e)));
                    None
                }
            }
        };
        for r in requests {
            match r {
                Request::Apply(s) => {
                    settings = *s;
                    pipeline.apply(&settings);
                }
                Request::Reset => match build(&settings) {
                    Ok(p) => pipeline = p,
                    Err(e) => {
                        let _ = events.try_send(Event::Pipeline(PipelineEvent::Failed(e)));
                        return;
                    }
                },
                Request::Snapshot(reply) => {
                    let _ = reply.send(pipeline.write_results().map_err(|e| e.to_string()));
                }
                Request::AdjustMap(why) => {
                    match catch_unwind(AssertUnwindSafe(|| pipeline.adjust_map(why))) {
                        Ok(list) => send(list),
                        Err(p) => match rebuilt(None, &*p, &settings) {
                            Some(p) => pipeline = p,
                            None => return,
                        },
                    }
                }
                Request::Stop => {
                    let finished = pipeline.finish();
                    *stopped.lock().unwrap_or_else(|p| p.into_inner()) =
                        Some(finished.as_ref().map(Vec::len).map_err(|e| e.to_string()));
                    let files = finished.unwrap_or_else(|e| {
                        // Logged here too: at shutdown nobody reads the event.
                        let line = format!("cannot write the pipeline's results at stop: {e}");
                        tracing::warn!("{line}");
                        let _ = events.try_send(Event::Pipeline(PipelineEvent::WriteFailed(line)));
                        Vec::new()
                    });
                    let _ = events.try_send(Event::Stopped { files });
                    return;
                }
            }
        }
        match catch_unwind(AssertUnwindSafe(|| pipeline.poll())) {
            Ok(list) => send(list),
            Err(p) => match rebuilt(None, &*p, &settings) {
                Some(p) => pipeline = p,
                None => return,
            },
        }
        if let Some(f) = frame {
            match catch_unwind(AssertUnwindSafe(|| pipeline.process(&f))) {
                Ok(report) => {
                    let attitude = f.pose.vehicle.attitude.euler_angles();
                    let event = PipelineEvent::Report { capture: f.capture_s, attitude, report };
                    let _ = events.try_send(Event::Pipeline(event));
                }
                Err(p) => match rebuilt(Some(f.index), &*p, &settings) {
                    Some(p) => pipeline = p,
                    None => return,
                },
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::{AlignedPose, VehicleSample};
    use mavloc_geometry::{CameraPose, Rot3, Vec3};

    /// Counts frames; panics on frame 3.
    struct Fragile {
        seen: u64,
        dir: PathBuf,
    }

    impl LivePipeline for Fragile {
        fn process(&mut self, f: &LiveFrame) -> Report {
            if f.index == 3 {
                panic!("bad frame");
            }
            self.seen += 1;
            Report {
                counters: vec![("SEEN", self.seen as f32), ("FRAME", f.index as f32)],
                ..Report::default()
            }
        }
        fn apply(&mut self, _: &Settings) {}
        fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
            let p = self.dir.join("seen.txt");
            crate::output::write_atomic(&p, self.seen.to_string().as_bytes())?;
            Ok(vec![p])
        }
    }

    fn frame(index: u64) -> LiveFrame {
        LiveFrame {
            index,
            capture_s: index as f64,
            pose: AlignedPose {
                autopilot_time: 0.0,
                vehicle: VehicleSample {
                    position: Vec3::zeros(),
                    velocity: Vec3::zeros(),
                    attitude: nalgebra::UnitQuaternion::identity(),
                },
                camera: CameraPose { position: Vec3::zeros(), attitude: Rot3::identity() },
                from_gimbal: false,
            },
            image: opencv::core::Mat::default(),
            mask: None,
            origin: None,
            truth: None,
            motion_only: false,
        }
    }

    #[test]
    fn a_panicking_frame_restarts_the_pipeline_not_the_worker() {
        let dir = tempfile::tempdir().unwrap();
        let (tx, mut rx) = tokio::sync::mpsc::channel(64);
        let out = dir.path().to_path_buf();
        let factory: Factory =
            Box::new(move |_| Ok(Box::new(Fragile { seen: 0, dir: out.clone() }) as Box<dyn LivePipeline>));
        let w = Worker::start(factory, Settings::default(), 1, tx);
        let mut events = Vec::new();
        for i in 0..6 {
            w.offer(frame(i));
            // Wait for this frame's event so none is replaced in the mailbox.
            events.push(rx.blocking_recv().unwrap());
        }
        w.stop().unwrap();
        events.push(rx.blocking_recv().unwrap());
        assert!(
            matches!(&events[3], Event::Pipeline(PipelineEvent::Panicked { frame: Some(3), message }) if message == "bad frame")
        );
        // After the restart the count starts again: frames 4 and 5.
        assert!(matches!(&events[5], Event::Pipeline(PipelineEvent::Report { report, .. })
            if report.counters == [("SEEN", 2.0), ("FRAME", 5.0)]));
        assert!(matches!(&events[6], Event::Stopped { files } if files.len() == 1));
        assert_eq!(std::fs::read_to_string(dir.path().join("seen.txt")).unwrap(), "2");
    }

    #[test]
    fn a_failed_write_at_stop_is_reported_not_only_logged() {
        let dir = tempfile::tempdir().unwrap();
        let (tx, mut rx) = tokio::sync::mpsc::channel(64);
        // A results folder that is not there: the write at stop fails.
        let out = dir.path().join("gone");
        let factory: Factory =
            Box::new(move |_| Ok(Box::new(Fragile { seen: 0, dir: out.clone() }) as Box<dyn LivePipeline>));
        let w = Worker::start(factory, Settings::default(), 1, tx);
        let e = w.stop().unwrap_err();
        assert!(e.contains("No such file"), "the stop says why, for its log line: {e}");
        let failed = rx.blocking_recv().unwrap();
        assert!(
            matches!(&failed, Event::Pipeline(PipelineEvent::WriteFailed(e)) if e.contains("cannot write the pipeline's results")),
            "{failed:?}"
        );
        assert!(matches!(rx.blocking_recv().unwrap(), Event::Stopped { files } if files.is_empty()));
    }

    /// Panics when asked for its results.
    struct PanicsAtStop;

    impl LivePipeline for PanicsAtStop {
        fn process(&mut self, _: &LiveFrame) -> Report {
            Report::default()
        }
        fn apply(&mut self, _: &Settings) {}
        fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
            panic!("no results for you")
        }
    }

    /// The stop's outcome is what the daemon's last line says: a panic in the final write
    /// and a worker that had already ended (its pipeline could not be built) are failed
    /// stops, not "results in …".
    #[test]
    fn a_stop_that_panicked_or_found_the_worker_ended_is_a_failed_stop() {
        let (tx, _rx) = tokio::sync::mpsc::channel(64);
        let factory: Factory = Box::new(|_| Ok(Box::new(PanicsAtStop) as Box<dyn LivePipeline>));
        let e = Worker::start(factory, Settings::default(), 1, tx).stop().unwrap_err();
        assert!(e.contains("panicked at its stop: no results for you"), "{e}");
        let (tx, _rx) = tokio::sync::mpsc::channel(64);
        let factory: Factory = Box::new(|_| Err("no camera intrinsics".into()));
        let e = Worker::start(factory, Settings::default(), 1, tx).stop().unwrap_err();
        assert!(e.contains("had ended before"), "{e}");
    }

    /// Writes the files it is given at its stop.
    struct Writes(Vec<PathBuf>);

    impl LivePipeline for Writes {
        fn process(&mut self, _: &LiveFrame) -> Report {
            Report::default()
        }
        fn apply(&mut self, _: &Settings) {}
        fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
            Ok(self.0.clone())
        }
    }

    /// The stop says how many files the final set has, so the daemon's last line says
    /// "results in …" only when there are some (an area run with no landmark writes none).
    #[test]
    fn a_stop_counts_the_files_of_the_final_set() {
        for files in [vec![], vec![PathBuf::from("a.csv"), PathBuf::from("summary.json")]] {
            let n = files.len();
            let (tx, _rx) = tokio::sync::mpsc::channel(64);
            let factory: Factory =
                Box::new(move |_| Ok(Box::new(Writes(files.clone())) as Box<dyn LivePipeline>));
            assert_eq!(Worker::start(factory, Settings::default(), 1, tx).stop(), Ok(n));
        }
    }

    /// Holds each frame until the test lets it go.
    struct Gated {
        started: std::sync::mpsc::Sender<u64>,
        gate: std::sync::mpsc::Receiver<()>,
    }

    impl LivePipeline for Gated {
        fn process(&mut self, f: &LiveFrame) -> Report {
            let _ = self.started.send(f.index);
            let _ = self.gate.recv();
            Report { counters: vec![("FRAME", f.index as f32)], ..Report::default() }
        }
        fn apply(&mut self, _: &Settings) {}
        fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
            Ok(Vec::new())
        }
    }

    /// Five frames arrive while the pipeline is busy with one: a mailbox of three keeps
    /// the newest three and drops two, a mailbox of one keeps the newest.
    #[test]
    fn a_busy_pipeline_keeps_the_newest_depth_frames_and_counts_the_rest_dropped() {
        for (depth, kept) in [(3usize, vec![0u64, 3, 4, 5]), (1, vec![0, 5])] {
            let (tx, mut rx) = tokio::sync::mpsc::channel(64);
            let (started_tx, started) = std::sync::mpsc::channel();
            let (gate_tx, gate) = std::sync::mpsc::channel();
            let parts = Mutex::new(Some((started_tx, gate)));
            let factory: Factory = Box::new(move |_| {
                let (started, gate) = parts.lock().unwrap().take().expect("built once");
                Ok(Box::new(Gated { started, gate }) as Box<dyn LivePipeline>)
            });
            let w = Worker::start(factory, Settings::default(), depth, tx);
            w.offer(frame(0));
            assert_eq!(started.recv_timeout(std::time::Duration::from_secs(5)).unwrap(), 0);
            for i in 1..=5 {
                w.offer(frame(i));
            }
            for _ in 0..kept.len() {
                gate_tx.send(()).unwrap();
            }
            let mut done = Vec::new();
            while done.len() < kept.len() {
                if let Event::Pipeline(PipelineEvent::Report { report, .. }) = rx.blocking_recv().unwrap() {
                    done.push(report.counters[0].1 as u64);
                }
            }
            assert_eq!(done, kept, "depth {depth}");
            assert_eq!(w.dropped.load(std::sync::atomic::Ordering::Relaxed), 5 - (kept.len() as u64 - 1));
            w.stop().unwrap();
        }
    }

    /// Says when it hears of the landing, and that it is done at the second poll after.
    struct Lands {
        polls: Option<u32>,
    }

    impl LivePipeline for Lands {
        fn process(&mut self, _: &LiveFrame) -> Report {
            Report::default()
        }
        fn apply(&mut self, _: &Settings) {}
        fn write_results(&self) -> std::io::Result<Vec<PathBuf>> {
            Ok(Vec::new())
        }
        fn adjust_map(&mut self, why: &str) -> Vec<PipelineEvent> {
            self.polls = Some(0);
            vec![PipelineEvent::Note(why.into())]
        }
        fn poll(&mut self) -> Vec<PipelineEvent> {
            let Some(n) = self.polls.as_mut() else { return Vec::new() };
            *n += 1;
            if *n < 2 {
                return Vec::new();
            }
            self.polls = None;
            vec![PipelineEvent::Note("done".into())]
        }
    }

    /// A landing reaches the pipeline, and what it finishes afterwards goes out with no
    /// frame or request coming (a camera that stopped after the landing): the worker
    /// polls on its own.
    #[test]
    fn a_landing_reaches_the_pipeline_and_its_later_work_goes_out_without_frames() {
        let (tx, mut rx) = tokio::sync::mpsc::channel(64);
        let factory: Factory = Box::new(|_| Ok(Box::new(Lands { polls: None }) as Box<dyn LivePipeline>));
        let w = Worker::start(factory, Settings::default(), 1, tx);
        w.request(Request::AdjustMap("landed"));
        let t0 = std::time::Instant::now();
        let mut notes = Vec::new();
        while notes.len() < 2 {
            match rx.try_recv() {
                Ok(Event::Pipeline(PipelineEvent::Note(n))) => notes.push(n),
                Ok(e) => panic!("{e:?}"),
                Err(_) => {
                    // Two polls take a second; the bound only ends a test whose worker
                    // never polls, with room for a loaded machine.
                    assert!(t0.elapsed() < 20 * POLL_PERIOD, "no poll without frames: {notes:?}");
                    std::thread::sleep(std::time::Duration::from_millis(10));
                }
            }
        }
        assert_eq!(notes, ["landed", "done"]);
        w.stop().unwrap();
    }
}
