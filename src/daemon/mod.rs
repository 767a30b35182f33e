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
pub mod worker;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use mavlink::dialects::common::*;
use tokio::sync::broadcast;

use self::core::{Action, Core, PipelineState};
use crate::link::params::ParamStore;
use crate::link::signing::{self, Signer};
use crate::link::transport::{self, LinkEvent};
use crate::link::LinkAddress;
use crate::settings::{PipelineKind, Settings};

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
                Some(LinkEvent::Frame(f)) => core.handle(*f, now()),
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
            _ = tick.tick() => {
                let t = now();
                core.tick(t);
                if t >= next_heartbeat {
                    core.heartbeat();
                    next_heartbeat = t + heartbeat_period;
                }
                if t >= next_second {
                    next_second = t + 1.0;
                    publish_counters(&mut core, &link, t);
                    let _ = write_status(&dir, &core, &link, &link_state, t);
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
                // Results so far are the status file; pipeline results join it with live
                // frames. The ACK says whether the write succeeded.
                Action::Snapshot { requester } => {
                    let result = match write_status(&dir, &core, &link, &link_state, now()) {
                        Ok(()) => MavResult::MAV_RESULT_ACCEPTED,
                        Err(_) => MavResult::MAV_RESULT_FAILED,
                    };
                    core.ack(MavCmd::MAV_CMD_USER_2, result, requester);
                }
                a => act(&mut core, a),
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
    if let PipelineState::Running(k) = core.pipeline {
        tracing::info!("{k:?} pipeline stopped; results in {}", dir.display());
    }
    let _ = write_status(&dir, &core, &link, "shutting down", now());
    let _ = shutdown_tx.send(());
    if tokio::time::timeout(Duration::from_millis(1500), &mut link.task).await.is_err() {
        tracing::warn!("link task did not stop within 1.5 s; leaving it");
    }
    tracing::info!("stopped");
    Ok(())
}

fn act(core: &mut Core, a: Action) {
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
            if core.pipeline != PipelineState::Running(k) {
                core.pipeline = PipelineState::Running(k);
                let src = format!("{:?}", core.settings.camera.source).to_lowercase();
                core.status(
                    MavSeverity::MAV_SEVERITY_INFO,
                    &format!("{k:?} pipeline started; waiting for frames from camera source {src}"),
                );
            }
        }
        Action::StopPipeline => {
            if let PipelineState::Running(k) | PipelineState::Failed(k) = core.pipeline {
                core.pipeline = PipelineState::Stopped;
                core.status(MavSeverity::MAV_SEVERITY_INFO, &format!("{k:?} pipeline stopped"));
            }
        }
        Action::ResetPipeline => {
            if let PipelineState::Running(k) = core.pipeline {
                core.status(MavSeverity::MAV_SEVERITY_INFO, &format!("{k:?} pipeline reset"));
            }
        }
        Action::Snapshot { .. } | Action::Apply(_) => {}
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
