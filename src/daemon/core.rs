//! The daemon's MAVLink logic without sockets or tasks: frames and clock ticks in,
//! messages and pipeline requests out. The async shell ([`super::run`]) only routes.
//!
//! Command ids (documented in the README):
//! * `MAV_CMD_USER_1` (31010), pipeline control: param1 = pipeline (0 the configured one,
//!   1 area, 2 indoor), param2 = action (0 stop, 1 start, 2 reset).
//! * `MAV_CMD_USER_2` (31011), result snapshot: writes the current results to the state
//!   directory; acknowledged `IN_PROGRESS`, then `ACCEPTED` or `FAILED`.
//! * `MAV_CMD_REQUEST_MESSAGE` (512) for HEARTBEAT (0) and PARAM_VALUE (22, param2 = index).

use mavlink::dialects::common::*;

use crate::align::{AlignParams, Aligner, FixedMount, GimbalOffsets, GimbalSample, VehicleSample};
use crate::link::codec::{Auth, Frame};
use crate::link::params::{self, ParamStore, SetError, Wire};
use crate::link::transport::Outgoing;
use crate::settings::{PipelineKind, Settings};
use mavloc_geometry::GimbalAngles;

pub const CMD_PIPELINE: u32 = 31010;
pub const CMD_SNAPSHOT: u32 = 31011;

/// Streams requested from the autopilot: (message id, name, interval in microseconds).
pub const STREAMS: &[(u32, &str, i32)] = &[
    (30, "ATTITUDE", 20_000),
    (32, "LOCAL_POSITION_NED", 20_000),
    (33, "GLOBAL_POSITION_INT", 100_000),
    (242, "HOME_POSITION", 1_000_000),
    (285, "GIMBAL_DEVICE_ATTITUDE_STATUS", 20_000),
    (2, "SYSTEM_TIME", 1_000_000),
    (245, "EXTENDED_SYS_STATE", 200_000),
];
/// MAV_CMD_NAV_LAND is sent until acknowledged, at most this many times, once a second.
const LANDING_TRIES: u32 = 5;
const STREAM_RETRIES: u32 = 5;

/// Something the shell must do besides sending messages.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Start (or restart with) this pipeline.
    StartPipeline(PipelineKind),
    StopPipeline,
    ResetPipeline,
    /// Write results now; answer the command when done.
    Snapshot {
        requester: (u8, u8),
    },
    /// Settings changed over MAVLink; hand them to the running pipeline.
    Apply(Box<Settings>),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum StreamState {
    Pending { tries: u32, next_s: u64 },
    Accepted,
    Refused,
}

/// Pipeline state as the daemon sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PipelineState {
    Stopped,
    Running(PipelineKind),
    Failed(PipelineKind),
}

/// Counters reported to the ground and in `status.json`.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Counters {
    pub frames_processed: u64,
    pub frames_dropped: u64,
    pub pipeline_panics: u64,
    pub commands_refused: u64,
    pub params_refused: u64,
    pub autopilot_reboots: u64,
}

pub struct Core {
    pub settings: Settings,
    store: ParamStore,
    system_id: u8,
    component_id: u8,
    signing: bool,
    /// Local time (s) of the autopilot's last heartbeat.
    autopilot_seen: Option<f64>,
    autopilot_found: bool,
    streams: Vec<StreamState>,
    pub aligner: Aligner,
    latest_attitude: Option<(f64, nalgebra::UnitQuaternion<f64>)>,
    pub home: Option<HOME_POSITION_DATA>,
    pub global: Option<GLOBAL_POSITION_INT_DATA>,
    /// Our TIMESYNC requests in flight: ts1 (ns) -> local send time.
    timesync_sent: Vec<(i64, f64)>,
    pub pipeline: PipelineState,
    pub camera_live: bool,
    pub counters: Counters,
    pub out: Vec<Outgoing>,
    pub actions: Vec<Action>,
    statustext_id: u16,
    landed_state: Option<MavLandedState>,
    pub armed: bool,
    /// A landing command in flight: tries so far, time of the next try.
    landing: Option<(u32, f64)>,
    /// Gimbal-manager control taken (with `gimbal.aim = "border"`), and when the last
    /// pitch/yaw setpoint went out.
    gimbal_control: bool,
    last_aim: f64,
    aim_refused: bool,
}

fn align_params(s: &Settings) -> (AlignParams, FixedMount, GimbalOffsets) {
    let g = &s.gimbal;
    (
        AlignParams { use_gimbal: g.use_telemetry, ..AlignParams::default() },
        FixedMount {
            chain: g.chain,
            angles: GimbalAngles::from_degrees(g.mount_yaw_deg, g.mount_pitch_deg, g.mount_roll_deg),
        },
        GimbalOffsets {
            chain: g.chain,
            yaw: g.yaw_offset_deg.to_radians(),
            pitch: g.pitch_offset_deg.to_radians(),
            roll: g.roll_offset_deg.to_radians(),
        },
    )
}

impl Core {
    pub fn new(settings: Settings, store: ParamStore, signing: bool) -> Core {
        let (ap, mount, offsets) = align_params(&settings);
        let m = &settings.mavlink;
        let system_id = if m.system_id == 0 { m.autopilot_system_id } else { m.system_id };
        Core {
            component_id: m.component_id,
            system_id,
            settings,
            store,
            signing,
            autopilot_seen: None,
            autopilot_found: false,
            streams: vec![StreamState::Pending { tries: 0, next_s: 0 }; STREAMS.len()],
            aligner: Aligner::new(ap, mount, offsets),
            latest_attitude: None,
            home: None,
            global: None,
            timesync_sent: Vec::new(),
            pipeline: PipelineState::Stopped,
            camera_live: false,
            counters: Counters::default(),
            out: Vec::new(),
            actions: Vec::new(),
            statustext_id: 0,
            landed_state: None,
            armed: false,
            landing: None,
            gimbal_control: false,
            last_aim: f64::NEG_INFINITY,
            aim_refused: false,
        }
    }

    pub fn system_id(&self) -> u8 {
        self.system_id
    }

    pub fn autopilot_found(&self) -> bool {
        self.autopilot_found
    }

    fn send(&mut self, message: MavMessage) {
        self.out.push(Outgoing { system_id: self.system_id, component_id: self.component_id, message });
    }

    /// A STATUSTEXT (and the same line in the log). Long texts are chunked as the
    /// protocol allows (50 characters per chunk, shared id).
    pub fn status(&mut self, severity: MavSeverity, text: &str) {
        match severity {
            MavSeverity::MAV_SEVERITY_EMERGENCY
            | MavSeverity::MAV_SEVERITY_ALERT
            | MavSeverity::MAV_SEVERITY_CRITICAL
            | MavSeverity::MAV_SEVERITY_ERROR => tracing::error!("{text}"),
            MavSeverity::MAV_SEVERITY_WARNING => tracing::warn!("{text}"),
            _ => tracing::info!("{text}"),
        }
        let line = format!("mavloc: {text}");
        let bytes = line.as_bytes();
        let chunks: Vec<&[u8]> = bytes.chunks(50).collect();
        let id = if chunks.len() > 1 {
            self.statustext_id = self.statustext_id.wrapping_add(1).max(1);
            self.statustext_id
        } else {
            0
        };
        for (i, c) in chunks.iter().enumerate() {
            let mut text = [0u8; 50];
            text[..c.len()].copy_from_slice(c);
            self.send(MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                severity,
                text: text.into(),
                id,
                chunk_seq: i as u8,
            }));
        }
    }

    /// MAV_STATE reflecting reality: ACTIVE only while a pipeline runs with frames and
    /// telemetry; STANDBY while idle or waiting; CRITICAL when the pipeline failed.
    pub fn mav_state(&self) -> MavState {
        match self.pipeline {
            PipelineState::Failed(_) => MavState::MAV_STATE_CRITICAL,
            PipelineState::Running(_)
                if self.autopilot_found && self.camera_live && self.aligner.clock.offset().0.is_some() =>
            {
                MavState::MAV_STATE_ACTIVE
            }
            _ => MavState::MAV_STATE_STANDBY,
        }
    }

    pub fn heartbeat(&mut self) {
        let state = self.mav_state();
        self.send(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_ONBOARD_CONTROLLER,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: MavModeFlag::empty(),
            system_status: state,
            mavlink_version: 3,
        }));
    }

    /// Called about ten times a second: autopilot timeout, stream requests, timesync.
    pub fn tick(&mut self, now: f64) {
        let timeout = self.settings.mavlink.autopilot_timeout_s;
        if self.autopilot_found && matches!(self.autopilot_seen, Some(t) if now - t > timeout) {
            self.autopilot_found = false;
            self.status(
                MavSeverity::MAV_SEVERITY_WARNING,
                &format!("autopilot lost (no heartbeat for {timeout} s)"),
            );
        }
        if !self.autopilot_found {
            return;
        }
        let target = self.settings.mavlink.autopilot_system_id;
        let now_whole = (now * 10.0) as u64;
        for (i, &(id, name, interval)) in STREAMS.iter().enumerate() {
            if let StreamState::Pending { tries, next_s } = self.streams[i] {
                if now_whole < next_s {
                    continue;
                }
                if tries >= STREAM_RETRIES {
                    self.streams[i] = StreamState::Refused;
                    self.status(
                        MavSeverity::MAV_SEVERITY_WARNING,
                        &format!("autopilot did not acknowledge the {name} stream request"),
                    );
                    continue;
                }
                self.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                    param1: id as f32,
                    param2: interval as f32,
                    param3: 0.0,
                    param4: 0.0,
                    param5: 0.0,
                    param6: 0.0,
                    param7: 0.0,
                    command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                    target_system: target,
                    target_component: 1,
                    confirmation: tries.min(255) as u8,
                }));
                // One request in flight at a time: PX4 acknowledges by command id only.
                self.streams[i] = StreamState::Pending { tries: tries + 1, next_s: now_whole + 10 };
                break;
            }
        }
        if let Some((tries, next)) = self.landing {
            if now >= next {
                if tries >= LANDING_TRIES {
                    self.landing = None;
                    self.status(
                        MavSeverity::MAV_SEVERITY_ERROR,
                        &format!("autopilot did not acknowledge MAV_CMD_NAV_LAND after {tries} tries"),
                    );
                } else {
                    self.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                        // Yaw and position NaN: land here, keep the heading (PX4, ArduPilot).
                        param1: 0.0,
                        param2: 0.0,
                        param3: 0.0,
                        param4: f32::NAN,
                        param5: f32::NAN,
                        param6: f32::NAN,
                        param7: 0.0,
                        command: MavCmd::MAV_CMD_NAV_LAND,
                        target_system: target,
                        target_component: 1,
                        confirmation: tries.min(255) as u8,
                    }));
                    self.landing = Some((tries + 1, now + 1.0));
                }
            }
        }
        // TIMESYNC once a second.
        if self.timesync_sent.last().is_none_or(|&(_, t)| now - t >= 1.0) {
            let ts1 = (now * 1e9) as i64;
            self.timesync_sent.push((ts1, now));
            if self.timesync_sent.len() > 8 {
                self.timesync_sent.remove(0);
            }
            self.send(MavMessage::TIMESYNC(TIMESYNC_DATA {
                tc1: 0,
                ts1,
                target_system: target,
                target_component: 1,
            }));
        }
    }

    fn is_autopilot(&self, f: &Frame) -> bool {
        f.header.system_id == self.settings.mavlink.autopilot_system_id as u32 && f.header.component_id == 1
    }

    fn is_autopilot_system(&self, f: &Frame) -> bool {
        f.header.system_id == self.settings.mavlink.autopilot_system_id as u32
    }

    /// Commands and parameter sets: only from the ground station or the autopilot, and
    /// only signed when signing is on. Returns the reason for a refusal.
    fn trusted(&self, f: &Frame) -> Result<(), String> {
        let m = &self.settings.mavlink;
        let sys = f.header.system_id;
        if sys != m.gcs_system_id as u32 && sys != m.autopilot_system_id as u32 {
            return Err(format!("system {sys} is neither the ground station nor the autopilot"));
        }
        if self.signing && f.auth != Auth::Signed {
            return Err("unsigned, and signing is required".into());
        }
        Ok(())
    }

    fn for_us(&self, target_system: u8, target_component: u8, allow_broadcast: bool) -> bool {
        (target_system == self.system_id || (allow_broadcast && target_system == 0))
            && (target_component == self.component_id || (allow_broadcast && target_component == 0))
    }

    /// Handles one frame from the link. `now` is local monotonic seconds.
    pub fn handle(&mut self, f: Frame, now: f64) {
        // Our own messages echoed back by a router or PX4's forwarding.
        if f.header.system_id == self.system_id as u32 && f.header.component_id == self.component_id {
            return;
        }
        if self.signing && f.auth != Auth::Signed && !self.settings.mavlink.accept_unsigned_telemetry {
            return;
        }
        match &f.message {
            MavMessage::HEARTBEAT(h)
                if self.is_autopilot(&f) && h.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID =>
            {
                self.autopilot_seen = Some(now);
                self.armed = h.base_mode.contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
                if !self.autopilot_found {
                    self.autopilot_found = true;
                    if self.settings.mavlink.system_id == 0 {
                        self.system_id = f.header.system_id as u8;
                    }
                    self.streams = vec![StreamState::Pending { tries: 0, next_s: 0 }; STREAMS.len()];
                    let text = format!(
                        "autopilot found: system {} ({:?}, MAVLink {:?})",
                        f.header.system_id, h.autopilot, f.version
                    );
                    self.status(MavSeverity::MAV_SEVERITY_INFO, &text);
                }
            }
            MavMessage::COMMAND_ACK(a)
                if self.is_autopilot(&f) && a.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL =>
            {
                // PX4 acknowledges by command id: the ack is for the request in flight.
                let in_flight =
                    |s: &StreamState| matches!(s, StreamState::Pending { tries, .. } if *tries > 0);
                if let Some(i) = self.streams.iter().position(in_flight) {
                    self.streams[i] = match a.result {
                        MavResult::MAV_RESULT_ACCEPTED => StreamState::Accepted,
                        MavResult::MAV_RESULT_IN_PROGRESS => self.streams[i],
                        other => {
                            let name = STREAMS[i].1;
                            tracing::warn!("autopilot refused the {name} stream: {other:?}");
                            StreamState::Refused
                        }
                    };
                }
            }
            MavMessage::COMMAND_ACK(a)
                if self.is_autopilot(&f)
                    && a.command == MavCmd::MAV_CMD_NAV_LAND
                    && self.landing.is_some() =>
            {
                match a.result {
                    MavResult::MAV_RESULT_ACCEPTED => {
                        self.landing = None;
                        self.status(MavSeverity::MAV_SEVERITY_NOTICE, "autopilot accepted the landing");
                    }
                    // Still working on it: wait, do not resend.
                    MavResult::MAV_RESULT_IN_PROGRESS => {
                        self.landing = self.landing.map(|(tries, _)| (tries, now + 5.0));
                    }
                    other => {
                        self.landing = None;
                        self.status(
                            MavSeverity::MAV_SEVERITY_ERROR,
                            &format!("autopilot refused the landing: {other:?}"),
                        );
                    }
                }
            }
            MavMessage::COMMAND_ACK(a)
                if self.is_autopilot(&f)
                    && matches!(
                        a.command,
                        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
                            | MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
                    )
                    && !matches!(
                        a.result,
                        MavResult::MAV_RESULT_ACCEPTED | MavResult::MAV_RESULT_IN_PROGRESS
                    ) =>
            {
                // Refused: say so once, and take control again before the next setpoint.
                self.gimbal_control = false;
                if !self.aim_refused {
                    self.aim_refused = true;
                    self.status(
                        MavSeverity::MAV_SEVERITY_WARNING,
                        &format!(
                            "autopilot refused {:?}: {:?}; is it a gimbal manager (PX4: MNT_MODE_IN=4)?",
                            a.command, a.result
                        ),
                    );
                }
            }
            MavMessage::TIMESYNC(t) if self.is_autopilot_system(&f) => {
                if t.tc1 == 0 {
                    // The autopilot syncing to us: answer with our time.
                    self.send(MavMessage::TIMESYNC(TIMESYNC_DATA {
                        tc1: (now * 1e9) as i64,
                        ts1: t.ts1,
                        target_system: f.header.system_id as u8,
                        target_component: f.header.component_id,
                    }));
                } else if let Some(i) = self.timesync_sent.iter().position(|&(ts1, _)| ts1 == t.ts1) {
                    let (_, sent) = self.timesync_sent.remove(i);
                    self.aligner.clock.observe_timesync(sent, now, t.tc1 as f64 * 1e-9);
                }
            }
            MavMessage::ATTITUDE(a) if self.is_autopilot(&f) => {
                let stamp = a.time_boot_ms as f64 * 1e-3;
                self.observe_stamp(stamp, now);
                let q =
                    nalgebra::UnitQuaternion::from_euler_angles(a.roll as f64, a.pitch as f64, a.yaw as f64);
                self.latest_attitude = Some((stamp, q));
            }
            MavMessage::LOCAL_POSITION_NED(p) if self.is_autopilot(&f) => {
                let stamp = p.time_boot_ms as f64 * 1e-3;
                self.observe_stamp(stamp, now);
                // Position and attitude come at the same rate from the same estimator;
                // pair the position with the latest attitude.
                if let Some((_, q)) = self.latest_attitude {
                    self.aligner.push_vehicle(
                        stamp,
                        VehicleSample {
                            position: nalgebra::Vector3::new(p.x as f64, p.y as f64, p.z as f64),
                            velocity: nalgebra::Vector3::new(p.vx as f64, p.vy as f64, p.vz as f64),
                            attitude: q,
                        },
                    );
                }
            }
            MavMessage::GLOBAL_POSITION_INT(g) if self.is_autopilot(&f) => {
                self.observe_stamp(g.time_boot_ms as f64 * 1e-3, now);
                self.global = Some(g.clone());
            }
            MavMessage::HOME_POSITION(h) if self.is_autopilot(&f) => self.home = Some(h.clone()),
            MavMessage::EXTENDED_SYS_STATE(e) if self.is_autopilot(&f) => {
                self.landed_state = Some(e.landed_state)
            }
            MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(g) if self.is_autopilot_system(&f) => {
                if let Some(s) = GimbalSample::from_status(g.q, g.flags.bits()) {
                    self.aligner.push_gimbal(g.time_boot_ms as f64 * 1e-3, s, now);
                }
            }
            MavMessage::PARAM_REQUEST_LIST(r) if self.for_us(r.target_system, r.target_component, true) => {
                for i in 0..params::PARAMS.len() {
                    self.send_param(i);
                }
            }
            MavMessage::PARAM_REQUEST_READ(r) if self.for_us(r.target_system, r.target_component, false) => {
                let i = if r.param_index >= 0 {
                    Some(r.param_index as usize).filter(|&i| i < params::PARAMS.len())
                } else {
                    r.param_id
                        .to_str()
                        .ok()
                        .and_then(|n| params::find(n.trim_end_matches('\0')))
                        .map(|(i, _)| i)
                };
                match i {
                    Some(i) => self.send_param(i),
                    None => {
                        let id = r.param_id.to_str().unwrap_or("?").trim_end_matches('\0').to_string();
                        self.status(
                            MavSeverity::MAV_SEVERITY_WARNING,
                            &format!("no parameter {id} (index {})", r.param_index),
                        );
                    }
                }
            }
            MavMessage::PARAM_SET(p) if self.for_us(p.target_system, p.target_component, false) => {
                let name = p.param_id.to_str().unwrap_or("").trim_end_matches('\0').to_string();
                self.param_set(&f, &name, Wire { value: p.param_value, ty: p.param_type });
            }
            MavMessage::COMMAND_LONG(c) if self.for_us(c.target_system, c.target_component, true) => {
                let broadcast = c.target_component == 0 || c.target_system == 0;
                self.command(&f, c.clone(), broadcast);
            }
            _ => {}
        }
    }

    fn observe_stamp(&mut self, stamp: f64, now: f64) {
        if self.aligner.clock.observe_stamp(stamp, now) {
            self.counters.autopilot_reboots += 1;
            self.aligner.reset();
            self.streams = vec![StreamState::Pending { tries: 0, next_s: 0 }; STREAMS.len()];
            self.gimbal_control = false;
            self.status(MavSeverity::MAV_SEVERITY_WARNING, "autopilot rebooted; re-requesting its streams");
            // reset() cleared the clock; keep this stamp.
            self.aligner.clock.observe_stamp(stamp, now);
        }
    }

    fn send_param(&mut self, i: usize) {
        let def = &params::PARAMS[i];
        let w = params::encode(&self.settings, def);
        self.send(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: w.value,
            param_count: params::PARAMS.len() as u16,
            param_index: i as u16,
            param_id: def.name.into(),
            param_type: w.ty,
        }));
    }

    fn param_set(&mut self, f: &Frame, name: &str, w: Wire) {
        let index = params::find(name).map(|(i, _)| i);
        if let Err(why) = self.trusted(f) {
            self.counters.params_refused += 1;
            self.status(MavSeverity::MAV_SEVERITY_WARNING, &format!("refused PARAM_SET {name}: {why}"));
            if let Some(i) = index {
                self.send_param(i);
            }
            return;
        }
        match params::set(&self.settings, name, w) {
            Ok((new, value)) => {
                let pipeline_changed = new.daemon.pipeline != self.settings.daemon.pipeline;
                self.settings = new;
                let (ap, mount, offsets) = align_params(&self.settings);
                self.aligner.set_params(ap, mount, offsets);
                if let Err(e) = self.store.record(name, value) {
                    self.status(MavSeverity::MAV_SEVERITY_WARNING, &format!("{name} set but not saved: {e}"));
                }
                tracing::info!("parameter {name} = {value} (PARAM_SET from system {})", f.header.system_id);
                self.actions.push(Action::Apply(Box::new(self.settings.clone())));
                if pipeline_changed && matches!(self.pipeline, PipelineState::Running(_)) {
                    match self.settings.daemon.pipeline {
                        PipelineKind::None => self.actions.push(Action::StopPipeline),
                        k => self.actions.push(Action::StartPipeline(k)),
                    }
                }
                self.send_param(index.expect("set succeeded, so it exists"));
            }
            Err(e) => {
                self.counters.params_refused += 1;
                self.status(MavSeverity::MAV_SEVERITY_WARNING, &format!("refused {e}"));
                if let SetError::Refused { .. } = e {
                    self.send_param(index.expect("refused, so it exists"));
                }
            }
        }
    }

    pub fn ack(&mut self, command: MavCmd, result: MavResult, to: (u8, u8)) {
        self.send(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command,
            result,
            progress: 0,
            result_param2: 0,
            target_system: to.0,
            target_component: to.1,
        }));
    }

    fn command(&mut self, f: &Frame, c: COMMAND_LONG_DATA, broadcast: bool) {
        let from = (f.header.system_id as u8, f.header.component_id);
        let id = c.command as u32;
        let ours = matches!(id, CMD_PIPELINE | CMD_SNAPSHOT) || c.command == MavCmd::MAV_CMD_REQUEST_MESSAGE;
        if broadcast && !ours {
            return; // not ours to answer: other components will.
        }
        if let Err(why) = self.trusted(f) {
            self.counters.commands_refused += 1;
            tracing::warn!("refused command {id} from {}/{}: {why}", from.0, from.1);
            self.ack(c.command, MavResult::MAV_RESULT_DENIED, from);
            return;
        }
        match id {
            CMD_PIPELINE => {
                let kind = match c.param1 as i32 {
                    0 => self.settings.daemon.pipeline,
                    1 => PipelineKind::Area,
                    2 => PipelineKind::Indoor,
                    _ => return self.ack(c.command, MavResult::MAV_RESULT_DENIED, from),
                };
                match (c.param2 as i32, kind) {
                    (1, PipelineKind::None) => {
                        self.status(
                            MavSeverity::MAV_SEVERITY_WARNING,
                            "no pipeline configured (LOC_PIPELINE = none)",
                        );
                        self.ack(c.command, MavResult::MAV_RESULT_DENIED, from);
                    }
                    (1, k) => {
                        if let Err(why) = self.can_start(k) {
                            self.status(
                                MavSeverity::MAV_SEVERITY_WARNING,
                                &format!("cannot start {k:?}: {why}"),
                            );
                            return self.ack(c.command, MavResult::MAV_RESULT_DENIED, from);
                        }
                        self.actions.push(Action::StartPipeline(k));
                        self.ack(c.command, MavResult::MAV_RESULT_ACCEPTED, from);
                    }
                    (0, _) => {
                        self.actions.push(Action::StopPipeline);
                        self.ack(c.command, MavResult::MAV_RESULT_ACCEPTED, from);
                    }
                    (2, _) if matches!(self.pipeline, PipelineState::Running(_)) => {
                        self.actions.push(Action::ResetPipeline);
                        self.ack(c.command, MavResult::MAV_RESULT_ACCEPTED, from);
                    }
                    (2, _) => self.ack(c.command, MavResult::MAV_RESULT_TEMPORARILY_REJECTED, from),
                    _ => self.ack(c.command, MavResult::MAV_RESULT_DENIED, from),
                }
            }
            CMD_SNAPSHOT => {
                self.ack(c.command, MavResult::MAV_RESULT_IN_PROGRESS, from);
                self.actions.push(Action::Snapshot { requester: from });
            }
            _ if c.command == MavCmd::MAV_CMD_REQUEST_MESSAGE => match c.param1 as u32 {
                0 => {
                    self.ack(c.command, MavResult::MAV_RESULT_ACCEPTED, from);
                    self.heartbeat();
                }
                22 if (c.param2 as usize) < params::PARAMS.len() => {
                    self.ack(c.command, MavResult::MAV_RESULT_ACCEPTED, from);
                    self.send_param(c.param2 as usize);
                }
                _ => self.ack(c.command, MavResult::MAV_RESULT_UNSUPPORTED, from),
            },
            _ => self.ack(c.command, MavResult::MAV_RESULT_UNSUPPORTED, from),
        }
    }

    /// Publishes what the pipeline found on one frame captured at local time `capture`
    /// (seconds on mavloc's monotonic clock, the clock its TIMESYNC replies carry, so PX4
    /// can map the stamps onto its own).
    ///
    /// The indoor estimate goes out as VISION_POSITION_ESTIMATE rather than ODOMETRY:
    /// the pipeline measures horizontal position only, and PX4's EKF2 fuses exactly that
    /// from VISION_POSITION_ESTIMATE (`EKF2_EV_CTRL` bit 0) with the covariance taken from
    /// the message; ODOMETRY would need a velocity and frame ids mavloc cannot vouch for.
    /// Area landmarks go out as DEBUG_VECT named `LMK` (north, east, down in metres,
    /// local NED of the autopilot), which QGroundControl's MAVLink inspector shows.
    pub fn publish(&mut self, report: &super::worker::Report, capture: f64, attitude: (f64, f64, f64)) {
        self.counters.frames_processed += 1;
        let usec = (capture.max(0.0) * 1e6) as u64;
        for p in &report.new_landmarks {
            self.send(MavMessage::DEBUG_VECT(DEBUG_VECT_DATA {
                time_usec: usec,
                x: p[0] as f32,
                y: p[1] as f32,
                z: p[2] as f32,
                name: "LMK".into(),
            }));
        }
        if let Some(e) = &report.position {
            self.send(vision_position_estimate(e, usec, attitude));
        }
        let ms = (capture.max(0.0) * 1e3) as u32;
        for &(name, value) in &report.counters {
            self.send(MavMessage::NAMED_VALUE_FLOAT(NAMED_VALUE_FLOAT_DATA {
                time_boot_ms: ms,
                value,
                name: name.into(),
            }));
        }
        for e in &report.events {
            self.status(MavSeverity::MAV_SEVERITY_INFO, e);
        }
    }

    /// The landing trigger fired. MAV_CMD_NAV_LAND rather than LANDING_TARGET: the trigger
    /// fires only once the vehicle is inside the zone and the particles agree (indoor seed
    /// sec. 4.7), so "land where you are" is the whole manoeuvre; LANDING_TARGET would
    /// need PX4's landing-target estimator fed with a bearing to a target, which the
    /// texton pipeline does not have (it knows where the vehicle is, not where a pad is).
    /// Sent only when landing is enabled (IND_LAND_EN) and the vehicle is armed and in
    /// the air; retried once a second until acknowledged.
    pub fn request_landing(&mut self, now: f64) {
        if !self.settings.indoor.landing_enabled {
            self.status(
                MavSeverity::MAV_SEVERITY_INFO,
                "landing trigger fired; landing is disabled (IND_LAND_EN 0)",
            );
            return;
        }
        let airborne = matches!(self.landed_state, Some(MavLandedState::MAV_LANDED_STATE_IN_AIR));
        if !self.autopilot_found || !self.armed || !airborne {
            self.status(
                MavSeverity::MAV_SEVERITY_WARNING,
                &format!(
                    "landing trigger fired, but the vehicle is not armed and in the air (armed {}, landed state {:?}); not landing",
                    self.armed, self.landed_state
                ),
            );
            return;
        }
        if self.landing.is_none() {
            self.status(MavSeverity::MAV_SEVERITY_NOTICE, "landing requested: sending MAV_CMD_NAV_LAND");
            self.landing = Some((0, now));
        }
    }

    /// Points the camera (with `gimbal.aim = "border"`): takes gimbal-manager control with
    /// MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, then sends MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
    /// with an earth-frame yaw, at most 5 times a second. The autopilot's gimbal manager
    /// (PX4 with MNT_MODE_IN=4, or the simulated vehicle) passes it to the gimbal device.
    pub fn aim_gimbal(&mut self, yaw: f64, pitch: f64, now: f64) {
        if self.settings.gimbal.aim != crate::settings::GimbalAim::Border
            || !self.autopilot_found
            || now - self.last_aim < 0.2 - 1e-6
        {
            return;
        }
        self.last_aim = now;
        let target = self.settings.mavlink.autopilot_system_id;
        let command = |command, p: [f32; 7]| {
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                param1: p[0],
                param2: p[1],
                param3: p[2],
                param4: p[3],
                param5: p[4],
                param6: p[5],
                param7: p[6],
                command,
                target_system: target,
                target_component: 1,
                confirmation: 0,
            })
        };
        if !self.gimbal_control {
            self.gimbal_control = true;
            // Primary control to us; secondary unchanged (-1); all gimbals (device id 0).
            let (sys, comp) = (self.system_id as f32, self.component_id as f32);
            self.send(command(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                [sys, comp, -1.0, -1.0, 0.0, 0.0, 0.0],
            ));
            self.status(
                MavSeverity::MAV_SEVERITY_INFO,
                "gimbal: taking manager control to keep the border in view",
            );
        }
        // Flags: GIMBAL_MANAGER_FLAGS_YAW_IN_EARTH_FRAME (64); rates NaN = angles only.
        let (p, y) = (pitch.to_degrees() as f32, yaw.to_degrees() as f32);
        self.send(command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [p, y, f32::NAN, f32::NAN, 64.0, 0.0, 0.0],
        ));
    }

    /// The autopilot says it is on the ground: a downward camera sees the floor up close,
    /// and a landed vehicle needs no position from vision.
    pub fn on_ground(&self) -> bool {
        matches!(self.landed_state, Some(MavLandedState::MAV_LANDED_STATE_ON_GROUND))
    }

    /// Whether a pipeline has what it needs to start.
    pub fn can_start(&self, k: PipelineKind) -> Result<(), String> {
        match k {
            PipelineKind::Indoor if self.settings.indoor.model.is_empty() => {
                Err("indoor.model is not set (train one with `mavloc indoor train`)".into())
            }
            PipelineKind::Indoor if !std::path::Path::new(&self.settings.indoor.model).exists() => {
                Err(format!("model {} does not exist", self.settings.indoor.model))
            }
            _ => Ok(()),
        }
    }
}

/// Variance reported for what the pipeline does not measure (z, attitude): large enough
/// that EKF2 would never lean on it, finite so nothing downstream divides by infinity.
const UNMEASURED_VARIANCE: f32 = 1.0e4;

/// VISION_POSITION_ESTIMATE for an indoor estimate. The covariance is the upper triangle
/// of the 6x6 (x, y, z, roll, pitch, yaw) matrix, row-major, as MAVLink defines it.
pub fn vision_position_estimate(
    e: &super::worker::PositionEstimate,
    usec: u64,
    attitude: (f64, f64, f64),
) -> MavMessage {
    let mut covariance = [0f32; 21];
    covariance[0] = e.cov[0][0] as f32;
    covariance[1] = e.cov[0][1] as f32;
    covariance[6] = e.cov[1][1] as f32;
    for i in [11, 15, 18, 20] {
        covariance[i] = UNMEASURED_VARIANCE;
    }
    MavMessage::VISION_POSITION_ESTIMATE(VISION_POSITION_ESTIMATE_DATA {
        usec,
        x: e.north as f32,
        y: e.east as f32,
        z: e.down as f32,
        roll: attitude.0 as f32,
        pitch: attitude.1 as f32,
        yaw: attitude.2 as f32,
        covariance,
        reset_counter: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::{MavHeader, MavlinkVersion};

    #[test]
    fn vision_position_covariance_is_the_upper_triangle() {
        let e = super::super::worker::PositionEstimate {
            autopilot_time: 0.0,
            north: 1.5,
            east: -2.0,
            down: -1.0,
            cov: [[0.04, 0.01], [0.01, 0.09]],
        };
        let MavMessage::VISION_POSITION_ESTIMATE(v) =
            vision_position_estimate(&e, 1_000_000, (0.0, 0.0, 0.3))
        else {
            unreachable!()
        };
        assert_eq!((v.x, v.y, v.usec), (1.5, -2.0, 1_000_000));
        // Upper-triangle indices of the diagonal: 0, 6, 11, 15, 18, 20.
        assert_eq!((v.covariance[0], v.covariance[1], v.covariance[6]), (0.04, 0.01, 0.09));
        assert!(v.covariance[11] >= 1e3 && v.covariance[20] >= 1e3);
        assert_eq!(v.covariance[2], 0.0);
    }

    fn frame(sys: u8, comp: u8, message: MavMessage) -> Frame {
        Frame {
            version: MavlinkVersion::V2,
            header: MavHeader { system_id: sys as u32, component_id: comp, sequence: 0 },
            message,
            auth: Auth::Unsigned,
        }
    }

    fn px4_heartbeat() -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_STANDBY,
            mavlink_version: 3,
        })
    }

    fn attitude(ms: u32) -> MavMessage {
        MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: ms, ..Default::default() })
    }

    fn interval_requests(c: &Core) -> usize {
        c.out
            .iter()
            .filter(|o| {
                matches!(&o.message, MavMessage::COMMAND_LONG(l) if l.command == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL)
            })
            .count()
    }

    fn core() -> Core {
        Core::new(Settings::default(), ParamStore::in_memory(), false)
    }

    #[test]
    fn streams_are_requested_one_at_a_time_and_again_after_a_reboot() {
        let mut c = core();
        c.tick(0.0);
        assert_eq!(interval_requests(&c), 0, "no autopilot, no requests");
        c.handle(frame(1, 1, px4_heartbeat()), 0.0);
        assert!(c.autopilot_found());
        let mut t = 0.0;
        // Acknowledge each request: all streams get requested exactly once.
        for _ in 0..STREAMS.len() {
            c.out.clear();
            c.tick(t);
            assert_eq!(interval_requests(&c), 1);
            let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                result: MavResult::MAV_RESULT_ACCEPTED,
                ..Default::default()
            });
            c.handle(frame(1, 1, ack), t);
            t += 0.1;
        }
        c.out.clear();
        c.tick(t + 2.0);
        assert_eq!(interval_requests(&c), 0, "all acknowledged");
        // The autopilot reboots: its clock jumps back; everything is requested again.
        c.handle(frame(1, 1, px4_heartbeat()), t);
        c.handle(frame(1, 1, attitude(600_000)), t);
        c.handle(frame(1, 1, attitude(1_000)), t + 0.1);
        assert_eq!(c.counters.autopilot_reboots, 1);
        c.out.clear();
        c.tick(t + 0.2);
        assert_eq!(interval_requests(&c), 1);
    }

    #[test]
    fn echoes_and_other_components_commands_are_ignored() {
        let mut c = core();
        let cmd = |target_component| {
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_DO_SET_MODE,
                target_system: 1,
                target_component,
                ..Default::default()
            })
        };
        // Our own message echoed back by PX4's forwarding.
        c.handle(frame(1, 191, px4_heartbeat()), 0.0);
        assert!(!c.autopilot_found());
        // A command for the autopilot, and a broadcast command mavloc does not implement.
        c.handle(frame(255, 190, cmd(1)), 0.0);
        c.handle(frame(255, 190, cmd(0)), 0.0);
        assert!(c.out.is_empty(), "{:?}", c.out);
        // The same command addressed to mavloc: UNSUPPORTED.
        c.handle(frame(255, 190, cmd(191)), 0.0);
        assert!(matches!(&c.out[0].message,
            MavMessage::COMMAND_ACK(a) if a.result == MavResult::MAV_RESULT_UNSUPPORTED && a.target_system == 255));
    }

    #[test]
    fn heartbeat_is_active_only_with_autopilot_clock_camera_and_pipeline() {
        let mut c = core();
        assert_eq!(c.mav_state(), MavState::MAV_STATE_STANDBY);
        c.pipeline = PipelineState::Running(PipelineKind::Area);
        c.handle(frame(1, 1, px4_heartbeat()), 0.0);
        c.handle(frame(1, 1, attitude(5_000)), 0.0);
        assert_eq!(c.mav_state(), MavState::MAV_STATE_STANDBY, "no frames yet");
        c.camera_live = true;
        assert_eq!(c.mav_state(), MavState::MAV_STATE_ACTIVE);
        c.pipeline = PipelineState::Failed(PipelineKind::Area);
        assert_eq!(c.mav_state(), MavState::MAV_STATE_CRITICAL);
    }

    #[test]
    fn long_status_texts_are_chunked() {
        let mut c = core();
        c.status(MavSeverity::MAV_SEVERITY_INFO, &"x".repeat(120));
        let chunks: Vec<_> = c
            .out
            .iter()
            .filter_map(|o| match &o.message {
                MavMessage::STATUSTEXT(s) => Some((s.id, s.chunk_seq)),
                _ => None,
            })
            .collect();
        assert_eq!(chunks.len(), 3);
        assert!(chunks.iter().all(|(id, _)| *id == chunks[0].0 && *id != 0));
        assert_eq!(chunks.iter().map(|c| c.1).collect::<Vec<_>>(), vec![0, 1, 2]);
    }
}

#[cfg(test)]
mod landing_tests {
    use super::*;
    use crate::link::params::ParamStore;
    use mavlink::{MavHeader, MavlinkVersion};

    fn from_autopilot(message: MavMessage) -> Frame {
        Frame {
            version: MavlinkVersion::V2,
            header: MavHeader { system_id: 1, component_id: 1, sequence: 0 },
            message,
            auth: Auth::Unsigned,
        }
    }

    fn flying_core(landing_enabled: bool) -> Core {
        let mut s = Settings::default();
        s.indoor.landing_enabled = landing_enabled;
        let mut c = Core::new(s, ParamStore::in_memory(), false);
        let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        });
        c.handle(from_autopilot(hb), 0.0);
        c.handle(
            from_autopilot(MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: MavLandedState::MAV_LANDED_STATE_IN_AIR,
            })),
            0.0,
        );
        c.out.clear();
        c
    }

    fn land_commands(c: &Core) -> usize {
        c.out
            .iter()
            .filter(|o| matches!(&o.message, MavMessage::COMMAND_LONG(l) if l.command == MavCmd::MAV_CMD_NAV_LAND))
            .count()
    }

    #[test]
    fn nav_land_is_retried_until_acknowledged() {
        let mut c = flying_core(true);
        c.request_landing(1.0);
        c.tick(1.0);
        c.tick(1.5);
        assert_eq!(land_commands(&c), 1, "once a second");
        c.tick(2.05);
        assert_eq!(land_commands(&c), 2);
        let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
            command: MavCmd::MAV_CMD_NAV_LAND,
            result: MavResult::MAV_RESULT_ACCEPTED,
            ..Default::default()
        });
        c.handle(from_autopilot(ack), 2.1);
        c.tick(5.0);
        assert_eq!(land_commands(&c), 2, "no more after the ACK");
    }

    #[test]
    fn no_landing_when_disabled_or_on_the_ground() {
        let mut c = flying_core(false);
        c.request_landing(1.0);
        c.tick(1.0);
        assert_eq!(land_commands(&c), 0);
        let mut c = flying_core(true);
        c.handle(
            from_autopilot(MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: MavLandedState::MAV_LANDED_STATE_ON_GROUND,
            })),
            0.5,
        );
        assert!(c.on_ground());
        c.request_landing(1.0);
        c.tick(1.0);
        assert_eq!(land_commands(&c), 0);
    }

    #[test]
    fn border_aiming_takes_control_once_then_streams_at_most_5_hz() {
        let mut c = flying_core(false);
        c.aim_gimbal(0.3, -0.5, 1.0);
        assert!(c.out.is_empty(), "gimbal.aim = mission: mavloc leaves the gimbal alone");
        c.settings.gimbal.aim = crate::settings::GimbalAim::Border;
        for i in 0..10 {
            c.aim_gimbal(0.3, -0.5, 1.0 + i as f64 * 0.1);
        }
        let count = |cmd| {
            c.out
                .iter()
                .filter(|o| matches!(&o.message, MavMessage::COMMAND_LONG(l) if l.command == cmd))
                .count()
        };
        assert_eq!(count(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE), 1);
        assert_eq!(count(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW), 5, "1 s at 5 Hz");
        let py = c
            .out
            .iter()
            .find_map(|o| match &o.message {
                MavMessage::COMMAND_LONG(l) if l.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                    Some(l.clone())
                }
                _ => None,
            })
            .unwrap();
        assert!(
            (py.param1 - (-0.5f32).to_degrees()).abs() < 1e-4
                && (py.param2 - 0.3f32.to_degrees()).abs() < 1e-4
        );
        assert_eq!(py.param5, 64.0, "earth-frame yaw");
    }
}
