//! A deterministic world for the core, modelled on quinn-proto's test `Pair`: the core,
//! a fake autopilot, a fake ground station and a clock that jumps from one event to the
//! next. Nothing sleeps: minutes of flight take milliseconds.

use std::collections::BTreeMap;
use std::time::Duration;

use mavlink::dialects::common::*;
use mavlink::{MavHeader, MavlinkVersion};

use super::*;

pub fn frame(sys: u8, comp: u8, message: MavMessage) -> Frame {
    Frame {
        version: MavlinkVersion::V2,
        header: MavHeader { system_id: sys as u32, component_id: comp, sequence: 0 },
        message,
        auth: Auth::Unsigned,
        unknown_command: None,
    }
}

/// How the fake autopilot answers stream requests.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StreamAnswer {
    Accept,
    Refuse,
    Ignore,
}

/// A PX4-like flight controller: heartbeat at 1 Hz with its boot clock, telemetry at
/// 10 Hz once streams are requested, TIMESYNC and command answers.
pub struct FakeAutopilot {
    pub booted: Mono,
    pub alive: bool,
    pub armed: bool,
    pub in_air: bool,
    /// Says its landed state (EXTENDED_SYS_STATE), as PX4 does; false: only armed or not.
    pub says_landed_state: bool,
    pub streams: StreamAnswer,
    pub land_answer: Option<MavResult>,
    /// Landing commands of either kind (NAV_LAND, NAV_LAND_LOCAL).
    pub land_commands: u32,
    pub precision_commands: u32,
    /// LANDING_TARGETs received: north, east.
    pub landing_targets: Vec<(f32, f32)>,
    /// With GPS (an origin from boot). Without, as PX4 v1.16 with EKF2_GPS_CTRL 0: a
    /// position only from vision, an origin only from SET_GPS_GLOBAL_ORIGIN, and
    /// pre-arm checks that pass 4.5 s after the origin while vision keeps coming.
    pub gps: bool,
    /// Where the vehicle truly is (north, east): vision farther than the gate is
    /// rejected, as EKF2's innovation gate does.
    pub truth: (f32, f32),
    pub vision: u32,
    pub vision_rejected: u32,
    pub last_vision: Option<(Mono, f32, f32)>,
    pub origin: Option<(Mono, i32, i32, i32)>,
    next_status: Mono,
    event_sequence: u16,
    pub gimbal_commands: Vec<(Mono, COMMAND_LONG_DATA)>,
    /// A gimbal manager (PX4 with MNT_MODE_IN=4): it answers CONFIGURE and PITCHYAW and
    /// says who holds the gimbal every 2 s. Without one (PX4's default), it answers none.
    pub gimbal_manager: bool,
    /// In the air and descending to land (RTL's or a land mode's last leg).
    pub landing: bool,
    /// The gimbal's primary controller, (0, 0) for none.
    pub gimbal_primary: (u8, u8),
    /// Its clock's rate against the wall clock: PX4 SITL's lockstep clock runs slower
    /// than the wall clock on a busy machine (1.2-2.5 % measured against v1.16 SIH).
    pub clock_rate: f64,
    next_gimbal_status: Mono,
    streaming: bool,
    next_heartbeat: Mono,
    next_telemetry: Mono,
}

impl FakeAutopilot {
    pub fn new(boot: Mono) -> FakeAutopilot {
        FakeAutopilot {
            booted: boot,
            alive: true,
            armed: false,
            in_air: false,
            says_landed_state: true,
            streams: StreamAnswer::Accept,
            land_answer: Some(MavResult::MAV_RESULT_ACCEPTED),
            land_commands: 0,
            precision_commands: 0,
            landing_targets: Vec::new(),
            gps: true,
            truth: (0.0, 0.0),
            vision: 0,
            vision_rejected: 0,
            last_vision: None,
            origin: None,
            next_status: boot,
            event_sequence: 0,
            gimbal_commands: Vec::new(),
            gimbal_manager: true,
            landing: false,
            gimbal_primary: (0, 0),
            clock_rate: 1.0,
            next_gimbal_status: boot,
            streaming: false,
            next_heartbeat: boot,
            next_telemetry: boot,
        }
    }

    pub fn reboot(&mut self, now: Mono) {
        // PX4 streams its default set again after a reboot, before anyone asks.
        *self = FakeAutopilot {
            streams: self.streams,
            streaming: self.streaming,
            gps: self.gps,
            truth: self.truth,
            ..FakeAutopilot::new(now)
        };
    }

    /// PX4's pre-arm verdict: with GPS always; without, fresh vision and an origin
    /// given at least 4.5 s ago (measured on SITL: 4.23-4.46 s).
    pub fn prearm_ok(&self, now: Mono) -> bool {
        if self.gps {
            return true;
        }
        let vision =
            self.last_vision.is_some_and(|(t, _, _)| now.saturating_sub(t) < Duration::from_millis(500));
        let origin = self.origin.is_some_and(|(t, ..)| now.saturating_sub(t) >= Duration::from_millis(4500));
        vision && origin
    }

    /// A ground station asks to arm: PX4's answer, and its EVENT when refused.
    pub fn arm(&mut self, now: Mono) -> (MavResult, Option<MavMessage>) {
        if self.prearm_ok(now) {
            self.armed = true;
            return (MavResult::MAV_RESULT_ACCEPTED, None);
        }
        self.event_sequence += 1;
        let event = MavMessage::EVENT(EVENT_DATA {
            id: 0x0102_089d,
            event_time_boot_ms: self.boot_ms(now),
            sequence: self.event_sequence,
            destination_component: 0,
            destination_system: 0,
            log_levels: 0x62,
            arguments: [0; 40],
        });
        (MavResult::MAV_RESULT_TEMPORARILY_REJECTED, Some(event))
    }

    /// A vision position through EKF2_EVP_GATE: 5 SD of the reported variance (or
    /// EKF2_EVP_NOISE 0.1 m).
    fn vision_position(&mut self, now: Mono, x: f32, y: f32, var: f32) {
        self.vision += 1;
        let var = if var.is_finite() { var.max(0.01) } else { 0.01 };
        let d = ((x - self.truth.0).powi(2) + (y - self.truth.1).powi(2)).sqrt();
        if d > 5.0 * var.sqrt() {
            self.vision_rejected += 1;
        } else {
            self.last_vision = Some((now, x, y));
        }
    }

    fn boot_ms(&self, now: Mono) -> u32 {
        (self.boot_us(now) / 1000) as u32
    }

    /// Its own clock at `now`, microseconds since its boot.
    pub fn boot_us(&self, now: Mono) -> u64 {
        ((now.0 - self.booted.0) as f64 * self.clock_rate) as u64
    }

    /// Another controller (a ground station) takes the gimbal: the manager's status
    /// saying so, which PX4 sends at once.
    pub fn gimbal_taken_by(&mut self, who: (u8, u8), now: Mono) -> MavMessage {
        self.gimbal_primary = who;
        self.gimbal_status(now)
    }

    fn gimbal_status(&self, now: Mono) -> MavMessage {
        MavMessage::GIMBAL_MANAGER_STATUS(GIMBAL_MANAGER_STATUS_DATA {
            time_boot_ms: self.boot_ms(now),
            primary_control_sysid: self.gimbal_primary.0,
            primary_control_compid: self.gimbal_primary.1,
            ..Default::default()
        })
    }

    pub fn next_event(&self) -> Option<Mono> {
        self.alive.then(|| {
            let mut next = self.next_heartbeat.min(self.next_status);
            if self.gimbal_manager {
                next = next.min(self.next_gimbal_status);
            }
            if self.streaming {
                next.min(self.next_telemetry)
            } else {
                next
            }
        })
    }

    /// What it sends on its own at `now`.
    fn poll(&mut self, now: Mono) -> Vec<MavMessage> {
        let mut out = Vec::new();
        if !self.alive {
            return out;
        }
        if self.next_heartbeat <= now {
            self.next_heartbeat = now + Duration::from_secs(1);
            let mut base_mode = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
            if self.armed {
                base_mode |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
            }
            out.push(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
                base_mode,
                system_status: MavState::MAV_STATE_STANDBY,
                mavlink_version: 3,
            }));
            if self.says_landed_state {
                out.push(MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                    vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                    landed_state: if self.in_air && self.landing {
                        MavLandedState::MAV_LANDED_STATE_LANDING
                    } else if self.in_air {
                        MavLandedState::MAV_LANDED_STATE_IN_AIR
                    } else {
                        MavLandedState::MAV_LANDED_STATE_ON_GROUND
                    },
                }));
            }
        }
        if self.gimbal_manager && self.next_gimbal_status <= now {
            self.next_gimbal_status = now + Duration::from_secs(2);
            out.push(self.gimbal_status(now));
        }
        if self.next_status <= now {
            self.next_status = now + Duration::from_secs(1);
            let bit = MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK;
            out.push(MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                // As PX4: the health bit alone.
                onboard_control_sensors_health: if self.prearm_ok(now) {
                    bit
                } else {
                    MavSysStatusSensor::empty()
                },
                ..Default::default()
            }));
        }
        if self.streaming && self.next_telemetry <= now {
            self.next_telemetry = now + Duration::from_millis(100);
            let ms = self.boot_ms(now);
            out.push(MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: ms, ..Default::default() }));
            out.push(MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: ms,
                z: -10.0,
                ..Default::default()
            }));
        }
        out
    }

    /// Its answers to what mavloc sent.
    fn receive(&mut self, now: Mono, m: &MavMessage) -> Vec<MavMessage> {
        if !self.alive {
            return Vec::new();
        }
        let ack = |command, result| {
            MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                command,
                result,
                target_system: 1,
                target_component: 191,
                ..Default::default()
            })
        };
        match m {
            MavMessage::COMMAND_LONG(c) if c.target_system == 1 => match c.command {
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => match self.streams {
                    StreamAnswer::Accept => {
                        self.streaming = true;
                        vec![ack(c.command, MavResult::MAV_RESULT_ACCEPTED)]
                    }
                    StreamAnswer::Refuse => vec![ack(c.command, MavResult::MAV_RESULT_DENIED)],
                    StreamAnswer::Ignore => vec![],
                },
                MavCmd::MAV_CMD_NAV_LAND | MavCmd::MAV_CMD_NAV_LAND_LOCAL => {
                    self.land_commands += 1;
                    self.precision_commands += (c.command == MavCmd::MAV_CMD_NAV_LAND_LOCAL) as u32;
                    self.land_answer.map(|r| vec![ack(c.command, r)]).unwrap_or_default()
                }
                // What mavloc (1/191) sends, as PX4's gimbal manager takes it: anyone may
                // take control; setpoints only from the primary controller.
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE | MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                    self.gimbal_commands.push((now, c.clone()));
                    if !self.gimbal_manager {
                        return vec![];
                    }
                    let mavloc = (1, 191);
                    let result = if c.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE {
                        if c.param1 >= 0.0 {
                            self.gimbal_primary = (c.param1 as u8, c.param2 as u8);
                        } else if c.param1 == -3.0 && self.gimbal_primary == mavloc {
                            self.gimbal_primary = (0, 0);
                        }
                        MavResult::MAV_RESULT_ACCEPTED
                    } else if self.gimbal_primary == mavloc {
                        MavResult::MAV_RESULT_ACCEPTED
                    } else {
                        MavResult::MAV_RESULT_DENIED
                    };
                    vec![ack(c.command, result)]
                }
                _ => vec![],
            },
            MavMessage::LANDING_TARGET(l) => {
                self.landing_targets.push((l.x, l.y));
                vec![]
            }
            MavMessage::VISION_POSITION_ESTIMATE(v) => {
                self.vision_position(now, v.x, v.y, v.covariance[0]);
                vec![]
            }
            // A position when x, y and z are numbers (PX4 reads NaN as "velocity only").
            MavMessage::ODOMETRY(o) if o.x.is_finite() && o.y.is_finite() && o.z.is_finite() => {
                self.vision_position(now, o.x, o.y, o.pose_covariance[0]);
                vec![]
            }
            #[allow(deprecated)]
            MavMessage::SET_GPS_GLOBAL_ORIGIN(o) if !self.gps && o.target_system == 1 => {
                self.origin = Some((now, o.latitude, o.longitude, o.altitude));
                #[allow(deprecated)]
                let echo = MavMessage::GPS_GLOBAL_ORIGIN(GPS_GLOBAL_ORIGIN_DATA {
                    latitude: o.latitude,
                    longitude: o.longitude,
                    altitude: o.altitude,
                    time_usec: 0,
                });
                vec![echo]
            }
            MavMessage::TIMESYNC(t) if t.tc1 == 0 => vec![MavMessage::TIMESYNC(TIMESYNC_DATA {
                tc1: self.boot_us(now) as i64 * 1000,
                ts1: t.ts1,
                target_system: 1,
                target_component: 191,
            })],
            _ => vec![],
        }
    }
}

/// The simulated world. Every output is logged with its time.
pub struct Sim {
    pub core: Core,
    pub now: Mono,
    pub ap: FakeAutopilot,
    pub latency: Duration,
    /// Drops the n-th message from the core to the ground station when it returns true.
    pub gcs_loss: fn(u64) -> bool,
    gcs_sent: u64,
    inbound: BTreeMap<(Mono, u64), Frame>,
    seq: u64,
    pub sent: Vec<(Mono, MavMessage)>,
    pub to_gcs: Vec<(Mono, MavMessage)>,
    pub actions: Vec<(Mono, Action)>,
    /// How the shell answers start requests.
    pub start_result: Result<(), String>,
    /// Whether the shell's saves of the tuned parameters fail (a full disk).
    pub disk_full: bool,
    /// The link's counters as the shell hands them in (an open link that counted nothing).
    pub link: ShellStats,
    pub steps: u64,
}

impl Sim {
    pub fn new(settings: Settings) -> Sim {
        Sim {
            core: Core::new(settings, BTreeMap::new(), false, Some(Duration::from_secs(10))),
            now: Mono::ZERO,
            ap: FakeAutopilot { alive: false, ..FakeAutopilot::new(Mono::ZERO) },
            latency: Duration::from_millis(2),
            gcs_loss: |_| false,
            gcs_sent: 0,
            inbound: BTreeMap::new(),
            seq: 0,
            sent: Vec::new(),
            to_gcs: Vec::new(),
            actions: Vec::new(),
            start_result: Ok(()),
            disk_full: false,
            link: ShellStats { link_up: true, ..ShellStats::default() },
            steps: 0,
        }
    }

    /// Queues a frame to arrive at the core after the link latency.
    pub fn deliver(&mut self, f: Frame) {
        self.seq += 1;
        self.inbound.insert((self.now + self.latency, self.seq), f);
    }

    pub fn gcs_sends(&mut self, m: MavMessage) {
        self.deliver(frame(255, 190, m));
    }

    pub fn input(&mut self, i: Input) {
        self.core.handle(i);
        self.flush();
    }

    fn flush(&mut self) {
        while let Some(a) = self.core.poll_action() {
            self.actions.push((self.now, a.clone()));
            let done = |token| Input::Done { now: self.now, token, result: Ok(()) };
            match a {
                Action::Worker(WorkerRequest::Start { token, .. }) => {
                    let result = self.start_result.clone();
                    self.core.handle(Input::Done { now: self.now, token, result });
                }
                Action::SaveParams { token, .. } if self.disk_full => self.core.handle(Input::Done {
                    now: self.now,
                    token,
                    result: Err("No space left on device (os error 28)".into()),
                }),
                Action::Snapshot { token } | Action::SaveParams { token, .. } => {
                    self.core.handle(done(token))
                }
                Action::Report => {
                    self.core.handle(Input::Stats { now: self.now, stats: self.link });
                }
                _ => {}
            }
        }
        while let Some(o) = self.core.poll_transmit(self.now) {
            let m = o.message;
            self.sent.push((self.now, m.clone()));
            for r in self.ap.receive(self.now, &m) {
                self.deliver(frame(1, 1, r));
            }
            self.gcs_sent += 1;
            if !(self.gcs_loss)(self.gcs_sent) {
                self.to_gcs.push((self.now + self.latency, m));
            }
        }
    }

    /// One step: deliver what has arrived, expire timers, drain outputs, let the
    /// autopilot speak, then jump to the next event.
    /// One step that does not jump past `horizon`.
    fn step_until(&mut self, horizon: Mono) {
        self.steps += 1;
        while let Some(entry) = self.inbound.first_entry() {
            if entry.key().0 > self.now {
                break;
            }
            let ((rx, _), f) = entry.remove_entry();
            self.core.handle(Input::Mav { rx, frame: f });
        }
        if self.core.poll_timeout().is_some_and(|t| t <= self.now) {
            self.core.handle_timeout(self.now);
        }
        self.flush();
        for m in self.ap.poll(self.now) {
            self.deliver(frame(1, 1, m));
        }
        let next = time::earliest([
            self.core.poll_timeout(),
            self.inbound.keys().next().map(|k| k.0),
            self.ap.next_event(),
        ]);
        if let Some(n) = next {
            // A deadline at or before now has just been handled: move on by at least 1 µs.
            self.now = n.max(Mono(self.now.0 + 1)).min(horizon.max(self.now));
        }
    }

    pub fn run_until(&mut self, t: Mono) {
        let limit = self.steps + 1_000_000;
        while self.now < t {
            self.step_until(t);
            assert!(self.steps < limit, "no progress");
        }
    }

    pub fn run_for(&mut self, d: Duration) {
        let t = self.now + d;
        self.run_until(t);
    }

    /// Messages the core sent within [from, to).
    pub fn sent_between(&self, from: Mono, to: Mono) -> impl Iterator<Item = &MavMessage> {
        self.sent.iter().filter(move |(t, _)| *t >= from && *t < to).map(|(_, m)| m)
    }

    pub fn statustexts(&self) -> Vec<String> {
        self.sent
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::STATUSTEXT(s) => {
                    Some(String::from_utf8_lossy(&s.text[..]).trim_end_matches('\0').to_string())
                }
                _ => None,
            })
            .collect()
    }
}

pub fn is_command(m: &MavMessage, cmd: MavCmd) -> bool {
    matches!(m, MavMessage::COMMAND_LONG(c) if c.command == cmd)
}
