//! `mavloc run`: the daemon. A thin tokio shell around the sans-I/O [`core::Core`]: it
//! stamps inputs with the monotonic clock, hands them to the core, does the I/O the core
//! asks for (sends, worker requests, file writes, sd_notify) and sleeps until the core's
//! next deadline. All protocol decisions live in the core and are tested there on a
//! simulated clock; this file only moves data.
//!
//! Start-up order, and why:
//! 1. State directory (systemd's `$STATE_DIRECTORY`, else `daemon.state_dir`): tuned
//!    parameters and the signing timestamp live there and are needed before anything is
//!    sent.
//! 2. Tuned parameters from `params.json` over the configuration.
//! 3. Signing key (refused if others can read it) and timestamp.
//! 4. The link task. READY goes to systemd once 1-3 succeeded, before the link is up:
//!    an autopilot that is off at boot or a serial device that is not there yet must not
//!    get mavloc killed by the start timeout (the link's state is in `STATUS=`).
//! 5. The main loop: link frames, camera frames and worker events -> core; the core's
//!    deadlines drive heartbeat, stream requests, counters, `status.json` and the
//!    watchdog pings, so a hung loop gets restarted by systemd.
//!
//! Shutdown by broadcast: SIGTERM or SIGINT stops taking frames, asks the pipeline worker
//! to write its results, saves status and signing timestamp, and returns within 2 s.

pub mod core;
pub mod flightlog;
pub mod live;
pub mod record;
pub mod worker;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::broadcast;

use self::core::{
    Action, CameraEvent as CoreCamera, Core, Input, Mono, PipelineEvent, PipelineState, ShellStats,
    WorkerRequest,
};
use self::worker::{Event as WorkerEvent, Factory, LiveFrame, LivePipeline, Request, Worker};
use crate::align::AlignError;
use crate::camera::{self, CameraEvent, Captured, Credits, SourceContext};
use crate::geometry::Geodetic;
use crate::link::params::ParamStore;
use crate::link::peers::Trust;
use crate::link::signing::{self, Signer};
use crate::link::transport::{self, LinkEvent};
use crate::link::LinkAddress;
use crate::settings::{CameraSource, PipelineKind, Settings};

/// A configuration the daemon cannot run with (state directory unusable, signing key
/// unreadable, bad link address): restarting will not help, so `mavloc run` exits with
/// [`EXIT_UNUSABLE`], which the unit's `RestartPreventExitStatus=` lists.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct Unusable(pub String);

/// sysexits' EX_CONFIG: "configuration error".
pub const EXIT_UNUSABLE: u8 = 78;

fn unusable(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow::Error::new(Unusable(e.to_string()))
}

/// A pose stamped further ahead of mavloc's clock than this is not believed.
const MAX_POSE_LEAD_S: f64 = 0.5;

/// A frame whose telemetry has not arrived yet waits at most this long.
const MAX_ALIGN_WAIT_S: f64 = 0.5;

/// The live side: camera, frames waiting for telemetry, the pipeline worker.
struct Live {
    results: PathBuf,
    /// This start's run id: results go to `results/<pipeline>.runs/<run>/`.
    run: String,
    ctx: SourceContext,
    camera_rx: tokio::sync::mpsc::Receiver<CameraEvent>,
    camera_thread: Option<std::thread::JoinHandle<()>>,
    pending: VecDeque<Captured>,
    worker: Option<(PipelineKind, Worker)>,
    worker_tx: tokio::sync::mpsc::Sender<WorkerEvent>,
    worker_rx: tokio::sync::mpsc::Receiver<WorkerEvent>,
    /// Frames dropped before the worker: no pose, too old, or no pipeline running.
    dropped_before: u64,
    last_align_error: Option<String>,
    /// Newest vehicle sample handed to the sim camera (mavloc's clock, seconds).
    fed_pose_local: f64,
    /// The sim camera's scenario origin, read once (the truth is placed in its world).
    sim_origin: std::cell::OnceCell<Option<Geodetic>>,
    /// The simulator's true position between its quantised reports.
    truth_track: camera::sim::TruthTrack,
    next_drop_log: Mono,
    /// Frames dropped before the worker since the last 10 s line, by reason.
    recent_drops: Vec<(String, u64)>,
    /// Frames the workers dropped (a frame waiting when a newer came), stopped ones' too:
    /// a stopped worker's count used to leave the total, which then went down.
    busy_retired: u64,
    busy_logged: u64,
    /// The flight recorder (`daemon.record`).
    recorder: Option<record::Recorder>,
}

impl Live {
    fn new(
        results: PathBuf,
        ctx: SourceContext,
        camera_rx: tokio::sync::mpsc::Receiver<CameraEvent>,
        camera_thread: Option<std::thread::JoinHandle<()>>,
    ) -> Live {
        // Bounded: the worker sends without blocking and at most one frame is in flight.
        let (worker_tx, worker_rx) = tokio::sync::mpsc::channel(1024);
        Live {
            run: live::new_run(&results),
            results,
            ctx,
            camera_rx,
            camera_thread,
            pending: VecDeque::new(),
            worker: None,
            worker_tx,
            worker_rx,
            dropped_before: 0,
            last_align_error: None,
            fed_pose_local: f64::NEG_INFINITY,
            truth_track: Default::default(),
            sim_origin: std::cell::OnceCell::new(),
            next_drop_log: Mono::ZERO + Duration::from_secs(10),
            recent_drops: Vec::new(),
            busy_retired: 0,
            busy_logged: 0,
            recorder: None,
        }
    }

    fn give_credit(&self) {
        if let Some(c) = &self.ctx.credits {
            c.give();
        }
    }

    /// The dropped-frame count the daemon reports: before and in the workers.
    fn dropped(&self) -> u64 {
        self.dropped_before + self.busy()
    }

    /// Frames the workers dropped because their pipeline was busy.
    fn busy(&self) -> u64 {
        self.busy_retired + self.worker.as_ref().map(|(_, w)| w.dropped.load(Ordering::Relaxed)).unwrap_or(0)
    }

    /// A frame dropped before the worker, for `why`.
    fn drop_before(&mut self, why: &str) {
        self.dropped_before += 1;
        match self.recent_drops.iter_mut().find(|(w, _)| w == why) {
            Some((_, n)) => *n += 1,
            None => self.recent_drops.push((why.to_string(), 1)),
        }
    }

    /// Takes the worker out, keeping its drop count in the total.
    fn take_worker(&mut self) -> Option<(PipelineKind, Worker)> {
        let taken = self.worker.take();
        if let Some((_, w)) = &taken {
            self.busy_retired += w.dropped.load(Ordering::Relaxed);
        }
        taken
    }

    /// The drops since the last call: their count, and in words by reason ("3 autopilot
    /// clock not synchronised yet, 2 ..."); None when there were none.
    fn drops_said(&mut self) -> Option<(u64, String)> {
        let busy = self.busy().saturating_sub(self.busy_logged);
        self.busy_logged = self.busy();
        let mut count = busy;
        let mut parts = Vec::new();
        for (why, n) in self.recent_drops.drain(..) {
            count += n;
            parts.push(format!("{n} {why}"));
        }
        if busy > 0 {
            parts.push(format!(
                "{busy} replaced by a newer frame while the pipeline was busy (slower than the camera)"
            ));
        }
        (count > 0).then(|| (count, parts.join(", ")))
    }
}

/// Builds the factory of the selected pipeline.
fn factory(kind: PipelineKind, results: PathBuf, run: String) -> Factory {
    Box::new(move |s: &Settings| -> Result<Box<dyn LivePipeline>, String> {
        let k = camera::intrinsics(s)?;
        match kind {
            PipelineKind::Area => {
                // Until the autopilot's HOME_POSITION gives the real one (each frame
                // carries it then), the camera's own origin, if it has one.
                let origin = camera::origin(s).unwrap_or(Geodetic::new(0.0, 0.0, 0.0));
                Ok(Box::new(live::AreaLive::new(s, k, origin, &results.join("area"), &run)?))
            }
            PipelineKind::Indoor => Ok(Box::new(live::IndoorLive::new(s, k, &results.join("indoor"), &run)?)),
            PipelineKind::None => Err("no pipeline selected".into()),
        }
    })
}

/// The state directory's lock (`.lock`, holding the pid of the daemon that has it), or
/// the error naming the daemon that holds it.
fn lock_state_dir(dir: &std::path::Path) -> anyhow::Result<std::fs::File> {
    use std::io::{Read, Seek, Write};
    let path = dir.join(".lock");
    let mut file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| unusable(format!("cannot open {}: {e}", path.display())))?;
    match file.try_lock() {
        Ok(()) => {
            file.set_len(0)?;
            file.seek(std::io::SeekFrom::Start(0))?;
            writeln!(file, "{}", std::process::id())?;
            Ok(file)
        }
        Err(std::fs::TryLockError::WouldBlock) => {
            let mut pid = String::new();
            let _ = file.read_to_string(&mut pid);
            Err(anyhow::anyhow!(
                "state directory {} is in use by another mavloc (pid {}): stop it, or give this one its own daemon.state_dir",
                dir.display(),
                pid.trim()
            ))
        }
        Err(std::fs::TryLockError::Error(e)) => Err(unusable(format!("cannot lock {}: {e}", path.display()))),
    }
}

/// The state directory: systemd's `$STATE_DIRECTORY` (first entry) wins over the config.
pub fn state_dir(settings: &Settings) -> PathBuf {
    match std::env::var("STATE_DIRECTORY") {
        Ok(v) if !v.is_empty() => PathBuf::from(v.split(':').next().unwrap_or(&v)),
        _ => PathBuf::from(&settings.daemon.state_dir),
    }
}

fn notify(state: &[sd_notify::NotifyState]) {
    // Outside systemd NOTIFY_SOCKET is unset and this is a no-op.
    if let Err(e) = sd_notify::notify(false, state) {
        tracing::debug!("sd_notify: {e}");
    }
}

/// What `status.json` holds: the daemon's state, rewritten atomically every second.
#[derive(serde::Serialize)]
struct Status<'a> {
    uptime_s: f64,
    link: &'a str,
    autopilot_found: bool,
    /// Why no autopilot yet, once mavloc has waited long enough to say (null otherwise).
    autopilot_missing: Option<&'static str>,
    system_id: u8,
    mav_state: String,
    pipeline: String,
    counters: &'a core::Counters,
    frames_in: u64,
    frames_out: u64,
    dropped_out: u64,
    /// Peers disconnected for not reading or falling silent; peers turned away (full).
    peers_dropped: u64,
    peers_refused: u64,
    skipped: SkippedJson,
    clock_source: String,
    clock_offset_s: Option<f64>,
    /// The autopilot's pre-arm checks (SYS_STATUS); null until it said.
    autopilot_prearm_ok: Option<bool>,
    /// `indoor.gps_denied`: where the origin stands (waiting, sent, confirmed, ...).
    gps_denied_origin: Option<String>,
    /// The newest autopilot EVENTs in words (PX4's refusals).
    autopilot_events: Vec<String>,
    /// The flight recorder (`daemon.record`), when it is on.
    recording: Option<RecordingJson>,
}

#[derive(serde::Serialize)]
struct RecordingJson {
    dir: String,
    frames: u64,
    /// Not recorded: pushed out by newer frames (a slow disk) or before the origin was known.
    dropped: u64,
    /// What stopped the recording (a full disk), if something did.
    error: Option<String>,
}

impl RecordingJson {
    fn of(r: &record::Recorder) -> RecordingJson {
        RecordingJson::from_stats(&r.dir, &r.stats)
    }

    fn from_stats(dir: &Path, stats: &record::RecordStats) -> RecordingJson {
        RecordingJson {
            dir: dir.display().to_string(),
            frames: stats.recorded.load(Ordering::Relaxed),
            dropped: stats.dropped.load(Ordering::Relaxed),
            error: stats.failed.lock().expect("record stats").clone(),
        }
    }
}

#[derive(serde::Serialize)]
struct SkippedJson {
    garbage_bytes: u64,
    bad_crc: u64,
    unknown_id: u64,
    unparseable: u64,
    truncated: u64,
    unsupported_flags: u64,
    bad_signature: u64,
}

/// Messages pulled from the core per turn of the loop before yielding (quinn's
/// `MAX_TRANSMIT_DATAGRAMS`): a burst cannot starve the other inputs.
const MAX_TRANSMIT: usize = 64;

/// The shell's side: I/O handles and the clock.
struct Shell {
    started: tokio::time::Instant,
    dir: PathBuf,
    link: transport::LinkHandle,
    link_state: String,
    /// The last STATUS= told to systemd (`systemctl status` shows it).
    told: String,
    live: Live,
    /// The link's queue was full on the last flush: retry shortly instead of spinning.
    link_full: bool,
    /// The area result set last handed to the core for MAVLink FTP (the link's target).
    served_area: Option<PathBuf>,
    /// `status.json` writes failing since the last line said so (a full disk fails every
    /// second): said once, then once a minute with the count.
    status_failing: Option<(Mono, u64)>,
}

/// How often a `status.json` that keeps failing is said again.
const STATUS_FAILURE_EVERY: Duration = Duration::from_secs(60);

/// A result file larger than this is not served over MAVLink FTP (at its 239 bytes a
/// packet and 4 ms between packets, 8 MB take over two minutes).
const MAX_SERVED_BYTES: u64 = 8 << 20;

impl Shell {
    /// Tells systemd the link's state, and why no autopilot yet once that has been said,
    /// when either changed.
    fn tell_status(&mut self, core: &Core) {
        let line = match core.autopilot_missing() {
            Some(why) => format!("link {}; {why}", self.link_state),
            None => format!("link {}", self.link_state),
        };
        if line != self.told {
            notify(&[sd_notify::NotifyState::Status(&line)]);
            self.told = line;
        }
    }

    /// Rewrites `status.json` with the daemon's state now; a failure is logged once a
    /// minute while it lasts, and the recovery once.
    fn write_status(&mut self, core: &Core, now: Mono) -> std::io::Result<()> {
        let recording = self.live.recorder.as_ref().map(RecordingJson::of);
        let r = write_status(&self.dir, core, &self.link, &self.link_state, now, recording);
        let path = self.dir.join("status.json");
        match (&r, &mut self.status_failing) {
            (Err(e), None) => {
                tracing::warn!(
                    "cannot write {}: {e} (said again once a minute while it fails)",
                    path.display()
                );
                self.status_failing = Some((now, 0));
            }
            (Err(e), Some((said, unsaid))) => {
                *unsaid += 1;
                if now.saturating_sub(*said) >= STATUS_FAILURE_EVERY {
                    tracing::warn!("cannot write {}: {e} ({unsaid} more failures)", path.display());
                    *said = now;
                    *unsaid = 0;
                }
            }
            (Ok(()), Some(_)) => {
                tracing::info!("{} written again", path.display());
                self.status_failing = None;
            }
            (Ok(()), None) => {}
        }
        r
    }

    fn now(&self) -> Mono {
        self.mono(tokio::time::Instant::now())
    }

    /// Hands the area pipeline's current result set to the core, which serves it over
    /// MAVLink FTP: read once per set, since a published set never changes (a new one is
    /// a new folder, `mavloc_data::sets`). A set removed while being read (the next was
    /// published) is read at the next report instead.
    fn serve_area_results(&mut self, core: &mut Core, now: Mono) {
        let link = self.dir.join("results").join("area");
        let Ok(target) = std::fs::read_link(&link) else { return };
        if self.served_area.as_ref() == Some(&target) {
            return;
        }
        // The link is relative to its folder (`area.runs/<run>/set-N`).
        let set = link.parent().map_or_else(|| target.clone(), |d| d.join(&target));
        let Ok(entries) = std::fs::read_dir(set) else { return };
        let mut files = Vec::new();
        for e in entries.flatten() {
            if !e.metadata().is_ok_and(|m| m.is_file() && m.len() <= MAX_SERVED_BYTES) {
                continue;
            }
            match std::fs::read(e.path()) {
                Ok(bytes) => files.push((e.file_name().to_string_lossy().into_owned(), bytes)),
                Err(_) => return,
            }
        }
        files.sort();
        self.served_area = Some(target);
        core.handle(Input::AreaResults { now, files });
    }

    fn mono(&self, t: tokio::time::Instant) -> Mono {
        Mono(t.saturating_duration_since(self.started).as_micros() as u64)
    }

    /// After every input: expire timers, do the core's actions, send what it has.
    fn flush(&mut self, core: &mut Core) {
        let now = self.now();
        if core.poll_timeout().is_some_and(|t| t <= now) {
            core.handle_timeout(now);
        }
        while let Some(a) = core.poll_action() {
            self.act(core, a);
        }
        self.link_full = false;
        for _ in 0..MAX_TRANSMIT {
            let Ok(permit) = self.link.outgoing.try_reserve() else {
                self.link_full = true;
                break;
            };
            match core.poll_transmit(now) {
                Some(o) => permit.send(o),
                None => break,
            }
        }
    }

    /// When the loop must wake up next.
    fn wake_at(&self, core: &Core) -> tokio::time::Instant {
        let now = tokio::time::Instant::now();
        let at = match core.poll_timeout() {
            Some(t) => self.started + Duration::from_micros(t.0),
            None => now + Duration::from_secs(1),
        };
        if self.link_full {
            at.max(now + Duration::from_millis(5))
        } else {
            at
        }
    }

    fn act(&mut self, core: &mut Core, a: Action) {
        let now = self.now();
        match a {
            Action::Worker(WorkerRequest::Start { kind, token }) => {
                let result = self.start_pipeline(core, kind);
                core.handle(Input::Done { now, token, result });
            }
            Action::Worker(WorkerRequest::Stop) => stop_worker(&mut self.live),
            Action::Worker(WorkerRequest::Reset) => self.reset_pipeline(core),
            Action::Worker(WorkerRequest::Apply(s)) => {
                if let Some((_, w)) = &self.live.worker {
                    w.request(Request::Apply(s));
                }
            }
            Action::Worker(WorkerRequest::AdjustMap(why)) => {
                if let Some((_, w)) = &self.live.worker {
                    w.request(Request::AdjustMap(why));
                }
            }
            // Status and the pipeline's results; the ACK says whether both were written.
            Action::Snapshot { token } => {
                let status = self.write_status(core, now);
                let results = snapshot(&self.live);
                let result = match (status, results) {
                    (Ok(()), Ok(_)) => Ok(()),
                    (Err(e), _) => Err(format!("status.json: {e}")),
                    (_, Err(e)) => Err(e),
                };
                core.handle(Input::Done { now, token, result });
            }
            Action::SaveParams { token, json } => {
                let result = crate::output::write_atomic(&self.dir.join("params.json"), json.as_bytes())
                    .map_err(|e| e.to_string());
                core.handle(Input::Done { now, token, result });
            }
            Action::Report => {
                use std::sync::atomic::Ordering::Relaxed;
                let skipped = *self.link.stats.skipped.lock().expect("stats");
                let stats = ShellStats {
                    link_up: self.link_state.starts_with("up"),
                    link_in: self.link.stats.frames_in.load(Relaxed),
                    link_bad_frames: skipped.total_frames(),
                    link_bad_signatures: skipped.bad_signature,
                    link_garbage_bytes: skipped.garbage_bytes,
                    frames_dropped: self.live.dropped(),
                };
                // Dropped frames are logged every 10 s when there were any, not one line per
                // frame, with their reasons: "the pipeline is slower than the camera, or
                // telemetry is late" was said when the autopilot's clock was not known yet.
                if now >= self.live.next_drop_log {
                    self.live.next_drop_log = now + Duration::from_secs(10);
                    if let Some((newly, why)) = self.live.drops_said() {
                        tracing::warn!(
                            "{newly} frames dropped in the last 10 s ({} in all): {why}",
                            stats.frames_dropped
                        );
                    }
                }
                core.handle(Input::Stats { now, stats });
                self.tell_status(core);
                let _ = self.write_status(core, now);
                self.serve_area_results(core, now);
            }
            Action::Watchdog => notify(&[sd_notify::NotifyState::Watchdog]),
        }
    }

    /// Whether a pipeline has what it needs, then starts it (unless it already runs).
    fn start_pipeline(&mut self, core: &Core, k: PipelineKind) -> Result<(), String> {
        let s = core.settings();
        if k == PipelineKind::Indoor && !Path::new(&s.indoor.model).exists() {
            return Err(format!("model {} does not exist", s.indoor.model));
        }
        if matches!(&self.live.worker, Some((running, _)) if *running == k) {
            return Ok(());
        }
        stop_worker(&mut self.live);
        start_worker(core, &mut self.live, k);
        Ok(())
    }

    /// A new run: the old one keeps its last results in `results/<pipeline>.runs/`, the
    /// new one starts empty.
    fn reset_pipeline(&mut self, core: &Core) {
        let Some((k, _)) = &self.live.worker else { return };
        let k = *k;
        stop_worker(&mut self.live);
        self.live.run = live::new_run(&self.live.results);
        tracing::info!("{k:?} pipeline reset: new run {}", self.live.run);
        start_worker(core, &mut self.live, k);
    }

    fn on_worker(&mut self, core: &mut Core, ev: WorkerEvent) {
        let now = self.now();
        let event = match ev {
            WorkerEvent::Pipeline(e) => e,
            WorkerEvent::Stopped { files } => {
                // A run that found nothing writes nothing: an empty list was a bare
                // "pipeline results: " line.
                if files.is_empty() {
                    tracing::info!("pipeline stopped: no results to write");
                } else {
                    tracing::info!(
                        "pipeline results: {}",
                        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
                    );
                }
                return;
            }
        };
        match &event {
            // The frame is done: the camera may deliver the next (lossless replay).
            PipelineEvent::Report { .. } | PipelineEvent::Panicked { frame: Some(_), .. } => {
                self.live.give_credit()
            }
            PipelineEvent::Panicked { frame: None, .. } => {}
            PipelineEvent::Failed(_) => {
                self.live.take_worker();
            }
            PipelineEvent::WriteFailed(_) | PipelineEvent::Note(_) => {}
        }
        core.handle(Input::Pipeline { now, event });
    }
}

/// Runs the daemon until `shutdown` completes (SIGTERM or SIGINT in `mavloc run`).
/// Returns after a clean shutdown.
/// `pinned`: configuration keys set on the command line, which win over values tuned
/// over MAVLink.
pub async fn run(
    mut settings: Settings,
    pinned: std::collections::BTreeSet<String>,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    let started = tokio::time::Instant::now();

    // 1. State directory.
    let dir = state_dir(&settings);
    std::fs::create_dir_all(&dir)
        .map_err(|e| unusable(format!("cannot create the state directory {}: {e}", dir.display())))?;
    let probe = dir.join(".mavloc-write-test");
    std::fs::write(&probe, b"").map_err(|e| {
        unusable(format!(
            "state directory {} is not writable ({e}); set daemon.state_dir or fix its owner and mode",
            dir.display()
        ))
    })?;
    let _ = std::fs::remove_file(&probe);
    // One daemon per state directory: a second (`mavloc run` by hand beside the service)
    // wrote its own empty sets, status and parameters over the first's (outside audit).
    // Held until this function returns; the kernel lets go if the process dies. Not exit
    // 78: the service, if it is the one refused, is restarted until the other is gone.
    let _lock = lock_state_dir(&dir)?;

    // 2. Tuned parameters.
    let (store, notes) = ParamStore::open(&dir.join("params.json"), &mut settings, &pinned);
    for (level, n) in notes {
        if level == tracing::Level::WARN {
            tracing::warn!("{n}");
        } else {
            tracing::info!("{n}");
        }
    }

    // 3. Signing.
    let signer = if settings.mavlink.signing_key.is_empty() {
        None
    } else {
        let key = match settings.mavlink.signing_key.strip_prefix("credential:") {
            // systemd's LoadCredential= hands the key over privately, owned by the
            // service's dynamic user: no ownership or mode check applies.
            Some(name) => {
                let dir = std::env::var("CREDENTIALS_DIRECTORY").map_err(|_| {
                    unusable(format!("mavlink.signing_key = credential:{name}, but $CREDENTIALS_DIRECTORY is unset (not started by systemd with LoadCredential=)"))
                })?;
                let path = Path::new(&dir).join(name);
                let text = std::fs::read_to_string(&path)
                    .map_err(|e| unusable(format!("signing key credential {}: {e}", path.display())))?;
                signing::parse_key(text.trim())
                    .map_err(|e| unusable(format!("signing key credential {}: {e}", path.display())))?
            }
            None => signing::load_key(Path::new(&settings.mavlink.signing_key)).map_err(unusable)?,
        };
        Some(Signer::new(key, 0, Some(dir.join("signing-timestamp"))))
    };
    let signing = signer.is_some();

    // 4. Link.
    let address = LinkAddress::parse(&settings.mavlink.connection)
        .map_err(|e| unusable(format!("mavlink.connection: {e}")))?;
    let (shutdown_tx, _) = broadcast::channel::<()>(4);
    let trust = Trust {
        autopilot_system_id: settings.mavlink.autopilot_system_id,
        gcs_system_id: settings.mavlink.gcs_system_id,
        signing: signer.is_some(),
        accept_unsigned_telemetry: settings.mavlink.accept_unsigned_telemetry,
    };
    let link = transport::spawn(address.clone(), trust, signer, shutdown_tx.subscribe());
    tracing::info!(
        "mavloc {} starting: link {address}, component {}, pipeline {:?}, signing {}, state in {}",
        env!("CARGO_PKG_VERSION"),
        settings.mavlink.component_id,
        settings.daemon.pipeline,
        if signing { "on" } else { "off" },
        dir.display()
    );

    // 5. Camera: its own thread, frames over a small channel. Lossless replay (file or
    //    dataset with realtime = false) waits for the pipeline through credits.
    let lossless = lossless(&settings);
    let ctx = SourceContext {
        started: started.into_std(),
        latest_pose: Arc::new(Mutex::new(None)),
        stop: Arc::new(AtomicBool::new(false)),
        credits: lossless.then(|| Arc::new(Credits::new(1))),
    };
    let (camera_tx, camera_rx) = tokio::sync::mpsc::channel(4);
    let camera_thread = (settings.camera.source != CameraSource::None)
        .then(|| camera::spawn(settings.clone(), ctx.clone(), camera_tx));
    let mut live = Live::new(dir.join("results"), ctx, camera_rx, camera_thread);
    live.recorder = start_recorder(&settings, &dir, &live.run).map_err(unusable)?;

    let mut watchdog_usec = 0u64;
    let watchdog = sd_notify::watchdog_enabled(false, &mut watchdog_usec)
        .then(|| Duration::from_micros(watchdog_usec / 3));
    let events_path = settings.mavlink.px4_events.clone();
    let mut core = Core::new(settings, store.into_tuned(), signing, watchdog);
    if !events_path.is_empty() {
        // Read once at start; a bad file costs the words, never the start.
        match std::fs::read_to_string(&events_path)
            .map_err(|e| e.to_string())
            .and_then(|t| core::events::EventMetadata::parse(&t))
        {
            Ok(m) => {
                tracing::info!("autopilot events: {} definitions from {events_path}", m.len());
                core.set_event_metadata(m);
            }
            Err(e) => tracing::warn!("mavlink.px4_events = {events_path}: {e}; events shown by number"),
        }
    }
    let mut shell = Shell {
        started,
        dir,
        link,
        link_state: String::from("opening"),
        told: String::from("link opening"),
        live,
        link_full: false,
        served_area: None,
        status_failing: None,
    };
    serve(&mut core, &mut shell, shutdown).await?;
    core.shutting_down();
    shell.flush(&mut core);

    // Shutdown: stop frames, flush results, tell the link (which saves the signing
    // timestamp), all within systemd's patience and our 2 s promise.
    notify(&[sd_notify::NotifyState::Stopping]);
    let Shell { dir, mut link, mut live, started: _, .. } = shell;
    live.ctx.stop.store(true, Ordering::Relaxed);
    if let Some((k, w)) = live.take_worker() {
        match tokio::task::block_in_place(|| w.stop()) {
            Ok(0) => tracing::info!("{k:?} pipeline stopped with no new results"),
            Ok(_) => tracing::info!("{k:?} pipeline stopped; results in {}", live.results.display()),
            Err(e) => tracing::warn!(
                "{k:?} pipeline stopped without its final results ({e}); {} holds the last complete set",
                live.results.display()
            ),
        }
    }
    let recording = live.recorder.take().map(|r| {
        let dir = r.dir.clone();
        let stats = tokio::task::block_in_place(|| r.stop());
        let json = RecordingJson::from_stats(&dir, &stats);
        tracing::info!(
            "recording ended: {} frames in {} ({} not recorded)",
            json.frames,
            json.dir,
            json.dropped
        );
        json
    });
    let now = Mono(started.elapsed().as_micros() as u64);
    if let Err(e) = write_status(&dir, &core, &link, "shutting down", now, recording) {
        tracing::warn!("cannot write {}/status.json: {e}", dir.display());
    }
    let _ = shutdown_tx.send(());
    if tokio::time::timeout(Duration::from_millis(1500), &mut link.task).await.is_err() {
        tracing::warn!("link task did not stop within 1.5 s; leaving it");
    }
    tracing::info!("stopped");
    Ok(())
}

/// The main loop: each input goes to the core, then one flush; the loop sleeps until
/// the core's next deadline. Returns when `shutdown` completes.
async fn serve(
    core: &mut Core,
    shell: &mut Shell,
    shutdown: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    // READY as soon as the configuration, state directory and key are good (they are, to
    // get here): the link and the camera come and go afterwards and are reported in
    // STATUS=, STATUSTEXT and status.json. Waiting for the link would let systemd's start
    // timeout kill a mavloc whose autopilot is off at boot, in a restart loop.
    notify(&[sd_notify::NotifyState::Ready, sd_notify::NotifyState::Status("link opening")]);
    shell.flush(core);
    tokio::pin!(shutdown);

    loop {
        let wake = tokio::time::sleep_until(shell.wake_at(core));
        tokio::select! {
            ev = shell.link.events.recv() => match ev {
                Some(LinkEvent::Frame { rx, frame }) => {
                    let rx = shell.mono(rx);
                    core.handle(Input::Mav { rx, frame: *frame });
                    let now = shell.now();
                    feed_pose(core, &mut shell.live, now);
                    offer_pending(core, &mut shell.live, now);
                }
                Some(LinkEvent::Up(what)) => {
                    shell.link_state = format!("up: {what}");
                    shell.tell_status(core);
                }
                Some(LinkEvent::Down(why)) => {
                    shell.link_state = format!("down: {why}");
                    shell.tell_status(core);
                }
                None => anyhow::bail!("the link task ended unexpectedly"),
            },
            ev = shell.live.camera_rx.recv(), if shell.live.camera_thread.is_some() => {
                let now = shell.now();
                let event = match ev {
                    Some(CameraEvent::Frame(c)) => {
                        shell.live.pending.push_back(*c);
                        offer_pending(core, &mut shell.live, now);
                        None
                    }
                    Some(CameraEvent::Up(what)) => Some(CoreCamera::Up(what)),
                    Some(CameraEvent::Down { why, fatal }) => Some(CoreCamera::Down { why, fatal }),
                    Some(CameraEvent::Ended(what)) => Some(CoreCamera::Ended(what)),
                    Some(CameraEvent::Unreadable(n)) => Some(CoreCamera::Unreadable(n)),
                    None => {
                        shell.live.camera_thread = None;
                        None
                    }
                };
                if let Some(event) = event {
                    core.handle(Input::Camera { now, event });
                }
            },
            ev = shell.live.worker_rx.recv() => if let Some(ev) = ev {
                shell.on_worker(core, ev);
            },
            _ = wake => {
                // Frames waiting for late telemetry give up on time, not only on input.
                let now = shell.now();
                offer_pending(core, &mut shell.live, now);
            },
            _ = &mut shutdown => break,
        }
        shell.flush(core);
    }

    Ok(())
}

/// Hands the sim camera the newest pose the telemetry gives. Compared on mavloc's own
/// clock, not the autopilot's: an autopilot reboot restarts its clock (the camera must
/// not wait for it to pass the old one), and a stamp from the future (a bad clock, a
/// spoofed frame) is not taken, so it cannot hold back every true pose after it.
fn feed_pose(core: &Core, live: &mut Live, now: Mono) {
    if core.settings().camera.sim_pose == crate::settings::SimPose::Truth {
        return feed_truth(core, live, now);
    }
    let now = now.secs();
    let a = core.aligner();
    let Some(t) = a.newest_complete(now) else { return };
    let Some(local) = a.clock.to_local(t) else { return };
    if local <= live.fed_pose_local || local > now + MAX_POSE_LEAD_S {
        return;
    }
    if let Ok(p) = a.align(local, now) {
        live.fed_pose_local = local;
        *live.ctx.latest_pose.lock().expect("pose") = Some((local, p.camera));
    }
}

/// The sim camera's pose from the simulator's ground truth (HIL_STATE_QUATERNION): the
/// vehicle where it truly is, in the scenario's world (the geodetic truth in the
/// scenario's local frame), with the camera turned on the body as the telemetry says the
/// gimbal is (mount or gimbal attitude relative to the estimated body). No truth, no
/// picture: rendering from the estimate instead would let mavloc confirm whatever the
/// autopilot believes.
fn feed_truth(core: &Core, live: &mut Live, now: Mono) {
    let Some((rx, h)) = core.truth() else { return };
    let local = rx.secs();
    if local <= live.fed_pose_local || now.secs() - local > MAX_POSE_LEAD_S {
        return;
    }
    // Not on every truth message: it reads the scenario's file.
    let Some(origin) = *live.sim_origin.get_or_init(|| camera::origin(core.settings())) else { return };
    // The camera's turn on the body from the newest telemetry up to the truth's time (the
    // truth often arrives before the telemetry of the same instant).
    let newest = core.aligner().vehicle.newest().and_then(|(t, _)| core.aligner().clock.to_local(t));
    let Some(at) = newest.map(|n| n.min(local)) else { return };
    let Ok(est) = core.aligner().align(at, now.secs()) else { return };
    let [w, x, y, z] = h.attitude_quaternion.map(f64::from);
    let body = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
    // Camera relative to the body, as the telemetry has it; put on the true body.
    let body_to_camera = est.vehicle.attitude.to_rotation_matrix().inverse() * est.camera.attitude;
    let geo = Geodetic::new(h.lat as f64 * 1e-7, h.lon as f64 * 1e-7, h.alt as f64 * 1e-3);
    let quantised = crate::geometry::LocalFrame::new(origin).to_ned(&geo);
    let velocity = crate::geometry::Vec3::new(h.vx as f64, h.vy as f64, h.vz as f64) * 0.01;
    let pose = crate::geometry::CameraPose {
        position: live.truth_track.update(local, quantised, velocity),
        attitude: body.to_rotation_matrix() * body_to_camera,
    };
    live.fed_pose_local = local;
    *live.ctx.latest_pose.lock().expect("pose") = Some((local, pose));
}

/// Gives waiting frames their pose and the worker the newest that has one. A frame
/// whose telemetry is late waits (boundedly); one that cannot be aligned is dropped,
/// counted, and logged once per kind of reason.
fn offer_pending(core: &Core, live: &mut Live, now: Mono) {
    let now = now.secs();
    while let Some(c) = live.pending.pop_front() {
        let running = matches!(core.pipeline(), PipelineState::Running(_)) && live.worker.is_some();
        // Live frames are not processed while the vehicle is on the ground; while the
        // camera is too low to see the floor as trained, the indoor pipeline only measures
        // the motion from them (replayed ones carry their own pose and are processed).
        if !running || (c.pose.is_none() && core.on_ground()) {
            live.give_credit();
            continue;
        }
        let pose = match c.pose {
            Some(p) => Ok(p),
            None => core.aligner().align(c.capture_s, now),
        };
        let pose = match pose {
            Ok(p) => p,
            Err(AlignError::Wait) if now - c.capture_s < MAX_ALIGN_WAIT_S => {
                live.pending.push_front(c);
                return;
            }
            Err(e) => {
                live.give_credit();
                let why = if matches!(e, AlignError::Wait) {
                    format!("no telemetry within {MAX_ALIGN_WAIT_S} s of the capture")
                } else {
                    e.to_string()
                };
                // Said and counted by its kind: the full text carries this frame's times, so
                // "further drops for this reason" were said again for every frame too old.
                let kind = if matches!(e, AlignError::Wait) { why.clone() } else { e.kind() };
                live.drop_before(&kind);
                if live.last_align_error.as_deref() != Some(kind.as_str()) {
                    tracing::warn!(
                        "frame {} dropped: {why} (further drops for this reason are only counted)",
                        c.index
                    );
                    live.last_align_error = Some(kind);
                }
                continue;
            }
        };
        if now - c.capture_s > core.settings().daemon.max_frame_age_s && c.pose.is_none() {
            live.drop_before("older than daemon.max_frame_age_s when the pipeline was free");
            live.give_credit();
            continue;
        }
        live.last_align_error = None;
        let frame = LiveFrame {
            index: c.index,
            capture_s: c.capture_s,
            pose,
            image: c.image,
            mask: c.mask,
            origin: core.origin(),
            truth: c.truth,
            motion_only: c.pose.is_none() && core.outside_heights(),
        };
        if let Some(r) = &live.recorder {
            let g = &core.settings().gimbal;
            r.offer(&frame, [g.yaw_offset_deg, g.pitch_offset_deg, g.roll_offset_deg]);
        }
        if let Some((_, w)) = &live.worker {
            w.offer(frame);
        }
    }
}

/// A file or dataset replayed as fast as the pipeline takes it: no frame is dropped,
/// neither by the pipeline nor by the recorder.
fn lossless(settings: &Settings) -> bool {
    !settings.camera.realtime && matches!(settings.camera.source, CameraSource::File | CameraSource::Dataset)
}

/// Starts the flight recorder when `daemon.record` names a folder (relative: in the state
/// directory). A recorder that cannot start is an error the start-up reports, as a
/// setting the daemon cannot honour.
fn start_recorder(settings: &Settings, state: &Path, run: &str) -> Result<Option<record::Recorder>, String> {
    let d = &settings.daemon;
    if d.record.is_empty() {
        return Ok(None);
    }
    let root = state.join(&d.record);
    std::fs::create_dir_all(&root)
        .map_err(|e| format!("daemon.record = {}: cannot create {}: {e}", d.record, root.display()))?;
    let intrinsics = camera::intrinsics(settings).map_err(|e| format!("daemon.record: {e}"))?;
    Ok(Some(record::Recorder::start(record::RecordSpec {
        dir: root.join(run),
        format: d.record_format,
        intrinsics,
        chain: settings.gimbal.chain,
        source_origin: camera::origin(settings),
        lossless: lossless(settings),
        reserve_bytes: (d.record_reserve_mb * 1e6) as u64,
    })))
}

/// Asks the worker for its results now (between frames); waits at most 3 s.
fn snapshot(live: &Live) -> Result<Vec<PathBuf>, String> {
    let Some((_, w)) = &live.worker else { return Ok(Vec::new()) };
    let (tx, rx) = std::sync::mpsc::channel();
    w.request(Request::Snapshot(tx));
    tokio::task::block_in_place(|| rx.recv_timeout(Duration::from_secs(3)))
        .map_err(|_| "the pipeline did not answer within 3 s".to_string())?
}

fn stop_worker(live: &mut Live) {
    if let Some((_, w)) = live.take_worker() {
        // A failed write is already a warning from the worker and a WriteFailed event.
        let _ = tokio::task::block_in_place(|| w.stop());
    }
    // Frames waiting for the old pipeline are void.
    while live.pending.pop_front().is_some() {
        live.give_credit();
    }
}

fn start_worker(core: &Core, live: &mut Live, k: PipelineKind) {
    let factory = factory(k, live.results.clone(), live.run.clone());
    let depth = if k == PipelineKind::Area { live::AREA_QUEUE_FRAMES } else { 1 };
    let w = Worker::start(factory, core.settings().clone(), depth, live.worker_tx.clone());
    live.worker = Some((k, w));
}

/// Rewrites `status.json` atomically; a failure is logged and returned.
fn write_status(
    dir: &Path,
    core: &Core,
    link: &transport::LinkHandle,
    link_state: &str,
    now: Mono,
    recording: Option<RecordingJson>,
) -> std::io::Result<()> {
    use std::sync::atomic::Ordering::Relaxed;
    let s = *link.stats.skipped.lock().expect("stats");
    let (offset, source) = core.aligner().clock.offset();
    let status = Status {
        uptime_s: now.secs(),
        link: link_state,
        autopilot_found: core.autopilot_found(),
        autopilot_missing: core.autopilot_missing(),
        system_id: core.system_id(),
        mav_state: format!("{:?}", core.mav_state()),
        pipeline: format!("{:?}", core.pipeline()),
        counters: core.counters(),
        frames_in: link.stats.frames_in.load(Relaxed),
        frames_out: link.stats.frames_out.load(Relaxed),
        dropped_out: link.stats.dropped_out.load(Relaxed),
        peers_dropped: link.stats.peers_dropped.load(Relaxed),
        peers_refused: link.stats.peers_refused.load(Relaxed),
        skipped: SkippedJson {
            garbage_bytes: s.garbage_bytes,
            bad_crc: s.bad_crc,
            unknown_id: s.unknown_id,
            unparseable: s.unparseable,
            truncated: s.truncated,
            unsupported_flags: s.unsupported_flags,
            bad_signature: s.bad_signature,
        },
        clock_source: format!("{source:?}"),
        clock_offset_s: offset,
        autopilot_prearm_ok: core.prearm_ok(),
        gps_denied_origin: core
            .gps_denied()
            .enabled()
            .then(|| format!("{:?}", core.gps_denied().origin_state())),
        autopilot_events: core.autopilot_events().recent().map(|e| e.text.clone()).collect(),
        recording,
    };
    let json = serde_json::to_string_pretty(&status).expect("status serialises");
    crate::output::write_atomic(&dir.join("status.json"), json.as_bytes())
}

#[cfg(test)]
mod shell_tests {
    //! The shell on tokio's paused clock, over in-memory channels instead of sockets:
    //! time-driven behaviour (heartbeats, pacing) checked in virtual seconds.
    use super::*;
    use crate::link::codec::{Auth, Frame};
    use crate::link::transport::{LinkHandle, LinkStats, Outgoing};
    use mavlink::dialects::common::*;
    use mavlink::{MavHeader, MavlinkVersion};
    use tokio::sync::mpsc;

    struct Harness {
        events: mpsc::Sender<LinkEvent>,
        outgoing: mpsc::Receiver<Outgoing>,
        stop: Option<tokio::sync::oneshot::Sender<()>>,
        task: tokio::task::JoinHandle<anyhow::Result<()>>,
        /// What the shell hands the sim camera: (mavloc time, camera pose).
        latest_pose: Arc<Mutex<Option<(f64, crate::geometry::CameraPose)>>>,
        _dir: tempfile::TempDir,
    }

    /// A frame sources' context for a shell under test: no credits, not stopped.
    fn source_context() -> SourceContext {
        SourceContext {
            started: std::time::Instant::now(),
            latest_pose: Arc::new(Mutex::new(None)),
            stop: Arc::new(AtomicBool::new(false)),
            credits: None,
        }
    }

    fn start() -> Harness {
        let mut settings = Settings::default();
        settings.daemon.pipeline = PipelineKind::None;
        start_with(settings)
    }

    /// The 10 s line on dropped frames says why they were dropped (it used to blame a slow
    /// pipeline for frames dropped before the autopilot's clock was known), and a stopped
    /// worker's drops stay in the total, which therefore never goes down (the line's count
    /// was the total less the last one logged: after a pipeline reset it underflowed).
    #[test]
    fn dropped_frames_are_said_by_reason_and_a_stopped_workers_stay_counted() {
        let (_camera_tx, camera_rx) = mpsc::channel(1);
        let ctx = source_context();
        let mut live = Live::new(PathBuf::from("results"), ctx, camera_rx, None);
        assert_eq!(live.drops_said(), None);
        live.drop_before("autopilot clock not synchronised yet");
        live.drop_before("autopilot clock not synchronised yet");
        live.drop_before("older than daemon.max_frame_age_s when the pipeline was free");
        assert_eq!(
            live.drops_said(),
            Some((
                3,
                "2 autopilot clock not synchronised yet, 1 older than daemon.max_frame_age_s when the pipeline was free"
                    .into()
            ))
        );
        assert_eq!(live.drops_said(), None, "each drop is said once");
        let factory: Factory = Box::new(|_: &Settings| Err("no pipeline in this test".to_string()));
        live.worker = Some((
            PipelineKind::Area,
            Worker::start(factory, Settings::default(), 1, live.worker_tx.clone()),
        ));
        live.worker.as_ref().unwrap().1.dropped.fetch_add(4, Ordering::Relaxed);
        assert_eq!(live.dropped(), 7);
        let (n, why) = live.drops_said().unwrap();
        assert_eq!(n, 4);
        assert!(why.starts_with("4 replaced by a newer frame while the pipeline was busy"), "{why}");
        drop(live.take_worker());
        assert_eq!(live.dropped(), 7, "the stopped worker's drops stay counted");
        assert_eq!(live.drops_said(), None, "and are not said again");
    }

    fn start_with(settings: Settings) -> Harness {
        let dir = tempfile::tempdir().unwrap();
        let (out_tx, out_rx) = mpsc::channel(256);
        let (ev_tx, ev_rx) = mpsc::channel(1024);
        let link = LinkHandle {
            outgoing: out_tx,
            events: ev_rx,
            stats: Arc::new(LinkStats::default()),
            task: tokio::spawn(async {}),
        };
        let (_camera_tx, camera_rx) = mpsc::channel(1);
        let ctx = source_context();
        let latest_pose = ctx.latest_pose.clone();
        let live = Live::new(dir.path().join("results"), ctx, camera_rx, None);
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let path = dir.path().to_path_buf();
        let task = tokio::spawn(async move {
            let mut core = Core::new(settings, Default::default(), false, None);
            let mut shell = Shell {
                started: tokio::time::Instant::now(),
                dir: path,
                link,
                link_state: "test".into(),
                told: String::new(),
                live,
                link_full: false,
                served_area: None,
                status_failing: None,
            };
            serve(&mut core, &mut shell, async {
                let _ = stop_rx.await;
            })
            .await
        });
        Harness { events: ev_tx, outgoing: out_rx, stop: Some(stop_tx), task, latest_pose, _dir: dir }
    }

    impl Harness {
        /// Everything sent within the next `d` of virtual time, with its virtual time.
        async fn collect(&mut self, d: Duration) -> Vec<(tokio::time::Instant, MavMessage)> {
            let end = tokio::time::Instant::now() + d;
            let mut got = Vec::new();
            while let Ok(Some(o)) = tokio::time::timeout_at(end, self.outgoing.recv()).await {
                got.push((tokio::time::Instant::now(), o.message));
            }
            got
        }

        async fn send(&self, sys: u8, comp: u8, message: MavMessage) {
            let frame = Frame {
                version: MavlinkVersion::V2,
                header: MavHeader { system_id: sys as u32, component_id: comp, sequence: 0 },
                message,
                auth: Auth::Unsigned,
                unknown_command: None,
            };
            let ev = LinkEvent::Frame { rx: tokio::time::Instant::now(), frame: Box::new(frame) };
            self.events.send(ev).await.unwrap();
        }

        async fn stop(mut self) {
            self.stop.take().unwrap().send(()).unwrap();
            self.task.await.unwrap().unwrap();
        }
    }

    #[tokio::test(start_paused = true)]
    async fn heartbeats_keep_their_period_in_virtual_time() {
        let mut h = start();
        let got = h.collect(Duration::from_secs(30)).await;
        let beats: Vec<_> =
            got.iter().filter(|(_, m)| matches!(m, MavMessage::HEARTBEAT(_))).map(|(t, _)| *t).collect();
        assert!((30..=31).contains(&beats.len()), "{} heartbeats in 30 s", beats.len());
        for w in beats.windows(2) {
            let gap = (w[1] - w[0]).as_secs_f64();
            assert!((0.999..=1.001).contains(&gap), "gap {gap}");
        }
        h.stop().await;
    }

    /// Telemetry at 20 Hz from the autopilot's boot clock `boot_ms`, for `ms`.
    async fn fly(h: &mut Harness, boot_ms: &mut u32, ms: u32) {
        for _ in 0..ms / 50 {
            *boot_ms += 50;
            let t = *boot_ms;
            h.send(1, 1, MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: t, ..Default::default() })).await;
            let p = LOCAL_POSITION_NED_DATA { time_boot_ms: t, z: -10.0, ..Default::default() };
            h.send(1, 1, MavMessage::LOCAL_POSITION_NED(p)).await;
            h.collect(Duration::from_millis(50)).await;
        }
    }

    fn pose_time(h: &Harness) -> f64 {
        h.latest_pose.lock().unwrap().map(|(t, _)| t).unwrap_or(f64::NEG_INFINITY)
    }

    /// The sim camera renders from the newest pose the shell hands it; after an autopilot
    /// reboot (its clock restarts) and after a stamp from the future, it keeps getting new
    /// ones.
    #[tokio::test(start_paused = true)]
    async fn the_sim_camera_keeps_its_poses_through_a_reboot_and_a_future_stamp() {
        let mut h = start();
        let mut boot_ms = 600_000;
        fly(&mut h, &mut boot_ms, 2000).await;
        let before = pose_time(&h);
        assert!(before > 1.5, "poses fed: {before}");
        // The autopilot reboots: its clock starts again near zero.
        boot_ms = 0;
        fly(&mut h, &mut boot_ms, 2000).await;
        let after_reboot = pose_time(&h);
        assert!(after_reboot > before + 1.5, "fed after the reboot: {before} -> {after_reboot}");
        // One stamp an hour ahead, then true ones again.
        let future = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: boot_ms + 3_600_000,
            ..Default::default()
        });
        h.send(1, 1, future).await;
        fly(&mut h, &mut boot_ms, 2000).await;
        let after_future = pose_time(&h);
        assert!(
            after_future > after_reboot + 1.5,
            "fed after the future stamp: {after_reboot} -> {after_future}"
        );
        h.stop().await;
    }

    /// With `sim_pose = "truth"` the sim camera renders from the simulator's ground truth
    /// (HIL_STATE_QUATERNION), never from the estimate the autopilot reports: with PX4 the
    /// estimate is partly mavloc's own output, and rendering from it would only confirm it.
    #[tokio::test(start_paused = true)]
    async fn the_sim_camera_renders_from_the_truth_not_the_estimate() {
        let mut settings = Settings::default();
        settings.daemon.pipeline = PipelineKind::None;
        settings.camera.source = crate::settings::CameraSource::Sim;
        settings.camera.sim_pose = crate::settings::SimPose::Truth;
        let origin = camera::origin(&settings).unwrap();
        let mut h = start_with(settings);
        // The estimate says 10 m up over the origin; no truth yet: no picture.
        let mut boot_ms = 600_000;
        fly(&mut h, &mut boot_ms, 1000).await;
        assert!(h.latest_pose.lock().unwrap().is_none(), "rendered from the estimate");
        // The truth: 5 m north, 20 m up, yawed 90 degrees.
        let truth = crate::geometry::LocalFrame::new(origin)
            .to_geodetic(&crate::geometry::Vec3::new(5.0, 0.0, -20.0));
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2);
        // PX4 SIH sends w < 0: the same rotation.
        let hil = HIL_STATE_QUATERNION_DATA {
            attitude_quaternion: [-q.w as f32, -q.i as f32, -q.j as f32, -q.k as f32],
            lat: (truth.lat_deg * 1e7).round() as i32,
            lon: (truth.lon_deg * 1e7).round() as i32,
            alt: (truth.alt_m * 1e3).round() as i32,
            ..Default::default()
        };
        h.send(1, 1, MavMessage::HIL_STATE_QUATERNION(hil)).await;
        fly(&mut h, &mut boot_ms, 100).await;
        let (_, pose) = h.latest_pose.lock().unwrap().expect("a pose from the truth");
        assert!(
            (pose.position - crate::geometry::Vec3::new(5.0, 0.0, -20.0)).norm() < 0.05,
            "{:?}",
            pose.position
        );
        // The camera (straight down on the default mount) turned with the true body: its
        // right (FRD y) points south now, as the truth's 90 degrees of yaw say; from the
        // estimate (yaw 0) it would point east.
        assert!((pose.attitude * crate::geometry::Vec3::x()).z > 0.99, "still looking down");
        let right = pose.attitude * crate::geometry::Vec3::y();
        assert!(right.x < -0.99, "camera y axis {right:?}");
        h.stop().await;
    }

    #[tokio::test(start_paused = true)]
    async fn a_parameter_list_is_paced_by_the_shell() {
        let mut h = start();
        h.collect(Duration::from_millis(100)).await;
        h.send(
            255,
            190,
            MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
                target_system: 1,
                target_component: 191,
            }),
        )
        .await;
        let got = h.collect(Duration::from_secs(2)).await;
        let values: Vec<_> =
            got.iter().filter(|(_, m)| matches!(m, MavMessage::PARAM_VALUE(_))).map(|(t, _)| *t).collect();
        assert_eq!(values.len(), crate::link::params::PARAMS.len());
        for w in values.windows(2) {
            assert!(w[1] - w[0] >= core::params::PARAM_INTERVAL, "{:?}", w[1] - w[0]);
        }
        h.stop().await;
    }
}
