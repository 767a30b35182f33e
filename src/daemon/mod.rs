//! `mavloc run`: the daemon. Tokio tasks around the sans-IO [`core::Core`].
//!
//! Start-up order, and why:
//! 1. State directory (systemd's `$STATE_DIRECTORY`, else `daemon.state_dir`): tuned
//!    parameters and the signing timestamp live there and are needed before anything is
//!    sent.
//! 2. Tuned parameters from `params.json` over the configuration.
//! 3. Signing key (refused if others can read it) and timestamp.
//! 4. The link task; READY goes to systemd when it is first up, so `systemctl start`
//!    returns once mavloc can talk.
//! 5. The main loop: link frames -> core; timers (heartbeat, stream requests, counters,
//!    `status.json`); watchdog pings from this loop, so a hung loop gets restarted.
//!
//! Shutdown by broadcast: SIGTERM or SIGINT stops taking frames, asks the pipeline worker
//! to write its results, saves status and signing timestamp, and returns within 2 s.

pub mod core;
pub mod live;
pub mod worker;

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use mavlink::dialects::common::*;
use tokio::sync::broadcast;

use self::core::{Action, Core, PipelineState};
use self::worker::{Event as WorkerEvent, Factory, LiveFrame, LivePipeline, Request, Worker};
use crate::align::AlignError;
use crate::camera::{self, CameraEvent, Captured, Credits, SourceContext};
use crate::geometry::{Geodetic, LocalFrame, Vec3};
use crate::link::params::ParamStore;
use crate::link::signing::{self, Signer};
use crate::link::transport::{self, LinkEvent};
use crate::link::LinkAddress;
use crate::settings::{CameraSource, PipelineKind, Settings};

/// A frame whose telemetry has not arrived yet waits at most this long.
const MAX_ALIGN_WAIT_S: f64 = 0.5;

/// The live side: camera, frames waiting for telemetry, the pipeline worker.
struct Live {
    results: PathBuf,
    ctx: SourceContext,
    camera_rx: tokio::sync::mpsc::Receiver<CameraEvent>,
    camera_thread: Option<std::thread::JoinHandle<()>>,
    pending: VecDeque<Captured>,
    worker: Option<(PipelineKind, Worker)>,
    worker_tx: tokio::sync::mpsc::UnboundedSender<WorkerEvent>,
    worker_rx: tokio::sync::mpsc::UnboundedReceiver<WorkerEvent>,
    /// Frames dropped before the worker: no pose, too old, or no pipeline running.
    dropped_before: u64,
    last_align_error: Option<String>,
    /// Newest vehicle sample handed to the sim camera (autopilot time).
    fed_pose_t: f64,
}

impl Live {
    fn give_credit(&self) {
        if let Some(c) = &self.ctx.credits {
            c.give();
        }
    }

    /// The dropped-frame count the daemon reports: before and in the worker.
    fn dropped(&self) -> u64 {
        self.dropped_before
            + self.worker.as_ref().map(|(_, w)| w.dropped.load(Ordering::Relaxed)).unwrap_or(0)
    }
}

/// The WGS84 origin of the autopilot's local frame: HOME_POSITION gives both its
/// geodetic and its local position, so origin = home moved back by its local offset.
fn autopilot_origin(core: &Core) -> Option<Geodetic> {
    let h = core.home.as_ref()?;
    let home = Geodetic::new(h.latitude as f64 * 1e-7, h.longitude as f64 * 1e-7, h.altitude as f64 * 1e-3);
    home.validate().ok()?;
    Some(LocalFrame::new(home).to_geodetic(&-Vec3::new(h.x as f64, h.y as f64, h.z as f64)))
}

/// Builds the factory of the selected pipeline.
fn factory(kind: PipelineKind, results: PathBuf) -> Factory {
    Box::new(move |s: &Settings| -> Result<Box<dyn LivePipeline>, String> {
        let k = camera::intrinsics(s)?;
        match kind {
            PipelineKind::Area => {
                let origin = camera::origin(s)
                    .or_else(|| mavloc_sim::Scenario::load(&s.camera.scenario).ok().map(|sc| sc.origin))
                    .unwrap_or(Geodetic::new(0.0, 0.0, 0.0));
                Ok(Box::new(live::AreaLive::new(s, k, origin, results.join("area"))?))
            }
            PipelineKind::Indoor => Ok(Box::new(live::IndoorLive::new(s, k, results.join("indoor"))?)),
            PipelineKind::None => Err("no pipeline selected".into()),
        }
    })
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
    system_id: u8,
    mav_state: String,
    pipeline: String,
    counters: &'a core::Counters,
    frames_in: u64,
    frames_out: u64,
    dropped_out: u64,
    skipped: SkippedJson,
    clock_source: String,
    clock_offset_s: Option<f64>,
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

/// Runs the daemon until SIGTERM/SIGINT. Returns after a clean shutdown.
pub async fn run(mut settings: Settings) -> anyhow::Result<()> {
    let started = Instant::now();
    let now = || started.elapsed().as_secs_f64();

    // 1. State directory.
    let dir = state_dir(&settings);
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("cannot create the state directory {}", dir.display()))?;
    let probe = dir.join(".mavloc-write-test");
    std::fs::write(&probe, b"")
        .with_context(|| format!("state directory {} is not writable", dir.display()))?;
    let _ = std::fs::remove_file(&probe);

    // 2. Tuned parameters.
    let (store, notes) = ParamStore::open(&dir.join("params.json"), &mut settings);
    for n in notes {
        tracing::info!("{n}");
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
                    anyhow::anyhow!("mavlink.signing_key = credential:{name}, but $CREDENTIALS_DIRECTORY is unset (not started by systemd with LoadCredential=)")
                })?;
                let path = Path::new(&dir).join(name);
                let text = std::fs::read_to_string(&path)
                    .with_context(|| format!("signing key credential {}", path.display()))?;
                signing::parse_key(text.trim())
                    .map_err(|e| anyhow::anyhow!("signing key credential {}: {e}", path.display()))?
            }
            None => {
                signing::load_key(Path::new(&settings.mavlink.signing_key)).map_err(anyhow::Error::msg)?
            }
        };
        Some(Signer::new(key, 0, Some(dir.join("signing-timestamp"))))
    };
    let signing = signer.is_some();

    // 4. Link.
    let address = LinkAddress::parse(&settings.mavlink.connection).map_err(anyhow::Error::msg)?;
    let (shutdown_tx, _) = broadcast::channel::<()>(4);
    let mut link = transport::spawn(address.clone(), signer, shutdown_tx.subscribe());
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
    let lossless = !settings.camera.realtime
        && matches!(settings.camera.source, CameraSource::File | CameraSource::Dataset);
    let ctx = SourceContext {
        started,
        latest_pose: Arc::new(Mutex::new(None)),
        stop: Arc::new(AtomicBool::new(false)),
        credits: lossless.then(|| Arc::new(Credits::new(1))),
    };
    let (camera_tx, camera_rx) = tokio::sync::mpsc::channel(4);
    let camera_thread = (settings.camera.source != CameraSource::None)
        .then(|| camera::spawn(settings.clone(), ctx.clone(), camera_tx));
    let (worker_tx, worker_rx) = tokio::sync::mpsc::unbounded_channel();
    let mut live = Live {
        results: dir.join("results"),
        ctx,
        camera_rx,
        camera_thread,
        pending: VecDeque::new(),
        worker: None,
        worker_tx,
        worker_rx,
        dropped_before: 0,
        last_align_error: None,
        fed_pose_t: f64::NEG_INFINITY,
    };

    let mut core = Core::new(settings.clone(), store, signing);
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())?;
    let mut watchdog_usec = 0u64;
    let watchdog = sd_notify::watchdog_enabled(false, &mut watchdog_usec);
    let mut tick = tokio::time::interval(Duration::from_millis(100));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let heartbeat_period = 1.0 / core.settings.mavlink.heartbeat_hz;
    let mut next_heartbeat = 0.0;
    let mut next_second = 1.0;
    // Dropped frames are logged every 10 s when there were any, not one line per frame.
    let (mut next_drop_log, mut dropped_logged) = (10.0, 0u64);
    let mut next_watchdog = 0.0;
    let mut link_state = String::from("opening");
    let mut ready = false;

    // Start the configured pipeline, as a drone would at boot.
    if core.settings.daemon.pipeline != PipelineKind::None {
        core.actions.push(Action::StartPipeline(core.settings.daemon.pipeline));
    }

    loop {
        tokio::select! {
            ev = link.events.recv() => match ev {
                Some(LinkEvent::Frame(f)) => {
                    core.handle(*f, now());
                    feed_pose(&core, &mut live, now());
                    offer_pending(&mut core, &mut live, now());
                }
                Some(LinkEvent::Up(what)) => {
                    link_state = format!("up: {what}");
                    if !ready {
                        ready = true;
                        notify(&[sd_notify::NotifyState::Ready, sd_notify::NotifyState::Status(&link_state)]);
                    }
                }
                Some(LinkEvent::Down(why)) => link_state = format!("down: {why}"),
                None => anyhow::bail!("the link task ended unexpectedly"),
            },
            ev = live.camera_rx.recv(), if live.camera_thread.is_some() => match ev {
                Some(CameraEvent::Frame(c)) => {
                    live.pending.push_back(*c);
                    offer_pending(&mut core, &mut live, now());
                }
                Some(CameraEvent::Up(what)) => {
                    core.camera_live = true;
                    core.status(MavSeverity::MAV_SEVERITY_INFO, &format!("camera up: {what}"));
                }
                Some(CameraEvent::Down { why, fatal }) => {
                    core.camera_live = false;
                    let what = if fatal { "camera failed" } else { "camera lost (retrying)" };
                    core.status(MavSeverity::MAV_SEVERITY_ERROR, &format!("{what}: {why}"));
                }
                Some(CameraEvent::Ended(what)) => {
                    core.camera_live = false;
                    core.status(MavSeverity::MAV_SEVERITY_INFO, &format!("camera source ended: {what}"));
                }
                None => live.camera_thread = None,
            },
            ev = live.worker_rx.recv() => if let Some(ev) = ev {
                worker_event(&mut core, &mut live, ev, now());
            },
            _ = tick.tick() => {
                let t = now();
                core.tick(t);
                offer_pending(&mut core, &mut live, t);
                core.counters.frames_dropped = live.dropped();
                if t >= next_heartbeat {
                    core.heartbeat();
                    next_heartbeat = t + heartbeat_period;
                }
                if t >= next_second {
                    next_second = t + 1.0;
                    publish_counters(&mut core, &link, t);
                    let _ = write_status(&dir, &core, &link, &link_state, t);
                }
                if t >= next_drop_log {
                    next_drop_log = t + 10.0;
                    let dropped = core.counters.frames_dropped;
                    if dropped > dropped_logged {
                        tracing::warn!(
                            "{} frames dropped in the last 10 s ({dropped} in all): the pipeline is slower than the camera, or telemetry is late",
                            dropped - dropped_logged
                        );
                        dropped_logged = dropped;
                    }
                }
                if watchdog && t >= next_watchdog {
                    notify(&[sd_notify::NotifyState::Watchdog]);
                    next_watchdog = t + watchdog_usec as f64 * 1e-6 / 3.0;
                }
            },
            _ = sigterm.recv() => { tracing::info!("SIGTERM: shutting down"); break; }
            _ = sigint.recv() => { tracing::info!("SIGINT: shutting down"); break; }
        }
        for a in std::mem::take(&mut core.actions) {
            match a {
                // Status and the pipeline's results; the ACK says whether both were written.
                Action::Snapshot { requester } => {
                    let status = write_status(&dir, &core, &link, &link_state, now());
                    let results = snapshot(&live);
                    if let Err(e) = &results {
                        core.status(MavSeverity::MAV_SEVERITY_ERROR, &format!("snapshot failed: {e}"));
                    }
                    let result = match (status, results) {
                        (Ok(()), Ok(_)) => MavResult::MAV_RESULT_ACCEPTED,
                        _ => MavResult::MAV_RESULT_FAILED,
                    };
                    core.ack(MavCmd::MAV_CMD_USER_2, result, requester);
                }
                a => act(&mut core, &mut live, a),
            }
        }
        for o in std::mem::take(&mut core.out) {
            if link.outgoing.try_send(o).is_err() {
                link.stats.dropped_out.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }
    }

    // Shutdown: stop frames, flush results, tell the link (which saves the signing
    // timestamp), all within systemd's patience and our 2 s promise.
    notify(&[sd_notify::NotifyState::Stopping]);
    live.ctx.stop.store(true, Ordering::Relaxed);
    if let Some((k, w)) = live.worker.take() {
        tokio::task::block_in_place(|| w.stop());
        tracing::info!("{k:?} pipeline stopped; results in {}", live.results.display());
    }
    let _ = write_status(&dir, &core, &link, "shutting down", now());
    let _ = shutdown_tx.send(());
    if tokio::time::timeout(Duration::from_millis(1500), &mut link.task).await.is_err() {
        tracing::warn!("link task did not stop within 1.5 s; leaving it");
    }
    tracing::info!("stopped");
    Ok(())
}

/// Hands the sim camera the newest pose the telemetry gives.
fn feed_pose(core: &Core, live: &mut Live, now: f64) {
    let Some((t, _)) = core.aligner.vehicle.newest() else { return };
    if t <= live.fed_pose_t {
        return;
    }
    let Some(local) = core.aligner.clock.to_local(t) else { return };
    if let Ok(p) = core.aligner.align(local, now) {
        live.fed_pose_t = t;
        *live.ctx.latest_pose.lock().expect("pose") = Some((local, p.camera));
    }
}

/// Gives waiting frames their pose and the worker the newest that has one. A frame
/// whose telemetry is late waits (boundedly); one that cannot be aligned is dropped,
/// counted, and logged once per kind of reason.
fn offer_pending(core: &mut Core, live: &mut Live, now: f64) {
    while let Some(c) = live.pending.pop_front() {
        let running = matches!(core.pipeline, PipelineState::Running(_)) && live.worker.is_some();
        // Live frames are not processed while the vehicle is on the ground (replayed ones
        // carry their own pose and are).
        if !running || (c.pose.is_none() && core.on_ground()) {
            live.give_credit();
            continue;
        }
        let pose = match c.pose {
            Some(p) => Ok(p),
            None => core.aligner.align(c.capture_s, now),
        };
        let pose = match pose {
            Ok(p) => p,
            Err(AlignError::Wait) if now - c.capture_s < MAX_ALIGN_WAIT_S => {
                live.pending.push_front(c);
                return;
            }
            Err(e) => {
                live.dropped_before += 1;
                live.give_credit();
                let why = if matches!(e, AlignError::Wait) {
                    format!("no telemetry within {MAX_ALIGN_WAIT_S} s of the capture")
                } else {
                    e.to_string()
                };
                if live.last_align_error.as_deref() != Some(why.as_str()) {
                    tracing::warn!(
                        "frame {} dropped: {why} (further drops for this reason are only counted)",
                        c.index
                    );
                    live.last_align_error = Some(why);
                }
                continue;
            }
        };
        if now - c.capture_s > core.settings.daemon.max_frame_age_s && c.pose.is_none() {
            live.dropped_before += 1;
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
            origin: autopilot_origin(core),
            truth: c.truth,
        };
        if let Some((_, w)) = &live.worker {
            w.offer(frame);
        }
    }
}

fn worker_event(core: &mut Core, live: &mut Live, ev: WorkerEvent, now: f64) {
    match ev {
        WorkerEvent::Report { capture_s, attitude, report, .. } => {
            live.give_credit();
            core.publish(&report, capture_s, attitude);
            if let Some((yaw, pitch)) = report.aim {
                core.aim_gimbal(yaw, pitch, now);
            }
            if report.landing_requested {
                core.request_landing(now);
            }
        }
        WorkerEvent::Panicked { frame, message } => {
            live.give_credit();
            core.counters.pipeline_panics += 1;
            core.status(
                MavSeverity::MAV_SEVERITY_ERROR,
                &format!("pipeline panicked on frame {frame}: {message}; restarted"),
            );
        }
        WorkerEvent::Failed(e) => {
            if let PipelineState::Running(k) = core.pipeline {
                core.pipeline = PipelineState::Failed(k);
            }
            live.worker = None;
            core.status(MavSeverity::MAV_SEVERITY_ERROR, &format!("pipeline failed: {e}"));
        }
        WorkerEvent::Stopped { files } => {
            tracing::info!(
                "pipeline results: {}",
                files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
            );
        }
    }
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
    if let Some((_, w)) = live.worker.take() {
        tokio::task::block_in_place(|| w.stop());
    }
    // Frames waiting for the old pipeline are void.
    while live.pending.pop_front().is_some() {
        live.give_credit();
    }
}

fn start_worker(core: &mut Core, live: &mut Live, k: PipelineKind) {
    let w = Worker::start(factory(k, live.results.clone()), core.settings.clone(), live.worker_tx.clone());
    live.worker = Some((k, w));
}

fn act(core: &mut Core, live: &mut Live, a: Action) {
    match a {
        Action::StartPipeline(k) => {
            if let Err(why) = core.can_start(k) {
                core.status(
                    MavSeverity::MAV_SEVERITY_ERROR,
                    &format!("cannot start the {k:?} pipeline: {why}"),
                );
                core.pipeline = PipelineState::Failed(k);
                return;
            }
            if core.pipeline != PipelineState::Running(k) || live.worker.is_none() {
                stop_worker(live);
                start_worker(core, live, k);
                core.pipeline = PipelineState::Running(k);
                let src = format!("{:?}", core.settings.camera.source).to_lowercase();
                core.status(
                    MavSeverity::MAV_SEVERITY_INFO,
                    &format!("{k:?} pipeline started; frames from camera source {src}"),
                );
            }
        }
        Action::StopPipeline => {
            if let PipelineState::Running(k) | PipelineState::Failed(k) = core.pipeline {
                stop_worker(live);
                core.pipeline = PipelineState::Stopped;
                core.status(
                    MavSeverity::MAV_SEVERITY_INFO,
                    &format!("{k:?} pipeline stopped; results written"),
                );
            }
        }
        Action::ResetPipeline => {
            if let PipelineState::Running(k) = core.pipeline {
                // The old results are kept, moved aside; the new run starts empty.
                stop_worker(live);
                let sub = live.results.join(format!("{k:?}").to_lowercase());
                if sub.exists() {
                    let stamp = std::time::SystemTime::now()
                        .duration_since(std::time::UNIX_EPOCH)
                        .map(|d| d.as_secs())
                        .unwrap_or(0);
                    let aside = sub.with_file_name(format!(
                        "{}-{stamp}",
                        sub.file_name().unwrap_or_default().to_string_lossy()
                    ));
                    if let Err(e) = std::fs::rename(&sub, &aside) {
                        tracing::warn!("cannot move {} aside: {e}", sub.display());
                    }
                }
                start_worker(core, live, k);
                core.status(
                    MavSeverity::MAV_SEVERITY_INFO,
                    &format!("{k:?} pipeline reset; earlier results kept aside"),
                );
            }
        }
        Action::Apply(s) => {
            if let Some((_, w)) = &live.worker {
                w.request(Request::Apply(s));
            }
        }
        Action::Snapshot { .. } => {}
    }
}

fn publish_counters(core: &mut Core, link: &transport::LinkHandle, t: f64) {
    use std::sync::atomic::Ordering::Relaxed;
    let skipped = *link.stats.skipped.lock().expect("stats");
    let (bad_frames, garbage) = (skipped.total_frames(), skipped.garbage_bytes);
    let ms = (t * 1000.0) as u32;
    let values: [(&str, f32); 5] = [
        ("LINK_BAD", bad_frames as f32),
        ("LINK_JUNK", garbage as f32),
        ("LINK_IN", link.stats.frames_in.load(Relaxed) as f32),
        ("FR_DONE", core.counters.frames_processed as f32),
        ("FR_DROP", core.counters.frames_dropped as f32),
    ];
    for (name, value) in values {
        let msg = MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
            time_boot_ms: ms,
            value,
            name: name.into(),
        });
        core.out.push(transport::Outgoing {
            system_id: core.system_id(),
            component_id: core.settings.mavlink.component_id,
            message: msg,
        });
    }
}

/// Rewrites `status.json` atomically; a failure is logged and returned.
fn write_status(
    dir: &Path,
    core: &Core,
    link: &transport::LinkHandle,
    link_state: &str,
    t: f64,
) -> std::io::Result<()> {
    use std::sync::atomic::Ordering::Relaxed;
    let s = *link.stats.skipped.lock().expect("stats");
    let (offset, source) = core.aligner.clock.offset();
    let status = Status {
        uptime_s: t,
        link: link_state,
        autopilot_found: core.autopilot_found(),
        system_id: core.system_id(),
        mav_state: format!("{:?}", core.mav_state()),
        pipeline: format!("{:?}", core.pipeline),
        counters: &core.counters,
        frames_in: link.stats.frames_in.load(Relaxed),
        frames_out: link.stats.frames_out.load(Relaxed),
        dropped_out: link.stats.dropped_out.load(Relaxed),
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
    };
    let json = serde_json::to_string_pretty(&status).expect("status serialises");
    crate::output::write_atomic(&dir.join("status.json"), json.as_bytes())
        .inspect_err(|e| tracing::warn!("cannot write {}/status.json: {e}", dir.display()))
}
