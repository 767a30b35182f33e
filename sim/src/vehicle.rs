//! The simulated vehicle (`mavloc sim vehicle`): a MAVLink autopilot that talks to a
//! companion computer the way PX4 does, flying a scenario's mission, with a gimbal device
//! (gimbal protocol v2) on board. It is the embedded default for running mavloc with no
//! PX4 installed, and it uses the `mavlink` crate's own framing, independent of mavloc's.
//!
//! What it does, and what it leaves out:
//! - HEARTBEAT as a PX4 quadrotor (AUTO.MISSION, then AUTO.LAND; armed while flying);
//!   ATTITUDE, LOCAL_POSITION_NED, GLOBAL_POSITION_INT, HOME_POSITION (home = the local
//!   origin), EXTENDED_SYS_STATE, SYSTEM_TIME at PX4-like default rates, each changeable
//!   with MAV_CMD_SET_MESSAGE_INTERVAL (ACKed; -1 stops a stream, 0 restores the
//!   default) or sent once on MAV_CMD_REQUEST_MESSAGE; TIMESYNC answered.
//! - It starts armed and in the air at the mission's start and flies the mission at its
//!   speed (no take-off: the pipelines have nothing to see on the ground). After
//!   `duration_s` of mission, or on MAV_CMD_NAV_LAND (ACKed), it descends vertically and
//!   reports LANDING, then ON_GROUND, and disarms.
//! - As gimbal manager (like PX4 with MNT_MODE_IN=4) it accepts
//!   MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE (one primary controller; -3 lets go) and
//!   MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW from that controller, passed to the gimbal (the
//!   pitch relative to the airframe without PITCH_LOCK, as PX4 v1.16), and says who
//!   holds the gimbal in GIMBAL_MANAGER_STATUS (every 2 s, and when it changes hands).
//! - The gimbal (component 154, MAV_COMP_ID_GIMBAL) points the camera at the mission's
//!   border targets and reports GIMBAL_DEVICE_ATTITUDE_STATUS with YAW_IN_EARTH_FRAME, or,
//!   when GIMBAL_DEVICE_SET_ATTITUDE arrives, holds the commanded attitude for as long as
//!   setpoints keep coming (a gimbal manager streams them), returning to the mission's
//!   pointing 2 s after the last. Indoor missions have the camera fixed to the body: no
//!   gimbal is reported.
//! - Telemetry is the true state, like PX4 SIH whose estimate sits close to the truth;
//!   the scenario's gimbal lag is applied (the gimbal attitude reported is the one
//!   `gimbal_lag_s` earlier). The scenario's random noise is applied by mavloc's sim
//!   camera instead (see `mavloc::camera::sim`), since a picture rendered from a noisy
//!   report would carry the same noise and cancel it.
//! - The true state is logged to a CSV (`truth_log`) for evaluation.

use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use mavlink::dialects::common::*;
use mavlink::{MavHeader, MavlinkVersion};
use mavloc_geometry::{LocalFrame, Vec3};
use nalgebra::UnitQuaternion;

use mavloc_data::dataset::GimbalFrame;
use mavloc_data::truth::{self, TruthRow};

use crate::mission::Mission;
use crate::scenario::Scenario;
use crate::state::State;
use crate::world::World;

pub const GIMBAL_COMPONENT: u8 = 154;
/// The gimbal's clock runs this far ahead of the autopilot's (it was powered up first): a
/// receiver that took its stamps for the autopilot's would pair every frame with the
/// wrong gimbal attitude, or with none.
pub const GIMBAL_BOOTED_EARLIER_S: f64 = 2.5;
/// A commanded gimbal attitude is held this long after the last setpoint.
const SETPOINT_HOLD_S: f64 = 2.0;
/// Descent speeds as PX4's defaults: MPC_Z_VEL_MAX_DN high up, MPC_LAND_SPEED below
/// MPC_LAND_ALT2.
const DESCENT_FAST_M_S: f64 = 1.5;
const DESCENT_M_S: f64 = 0.7;
const SLOW_BELOW_M: f64 = 5.0;
/// A precision landing's horizontal approach speed (PX4's precland flies at cruise speed,
/// slowing near the target; one figure is enough here).
const APPROACH_M_S: f64 = 1.0;
/// PX4's PLD_BTOUT: a target older than this is lost.
const TARGET_TIMEOUT_S: f64 = 5.0;
/// PX4's take-off climb rate (MPC_TKO_SPEED).
const CLIMB_M_S: f64 = 1.5;
/// PX4 v1.16 without GPS (measured on SITL): pre-arm passes about 4.5 s after the origin,
/// while vision keeps coming; vision older than this is lost.
const PREARM_AFTER_ORIGIN_S: f64 = 4.5;
const VISION_TIMEOUT_S: f64 = 0.5;
/// PX4's "Arming denied: Resolve system health failures first" event id.
pub const EVENT_ARM_DENIED: u32 = 0x0102_089d;

/// How to run the vehicle.
#[derive(Clone, Debug)]
pub struct VehicleOptions {
    /// `udpout:HOST:PORT` (send to mavloc, PX4's onboard link) or `udpin:HOST:PORT`.
    pub address: String,
    pub system_id: u8,
    /// Land after this much mission time, then exit once on the ground.
    pub duration_s: Option<f64>,
    /// Start this far into the mission, seconds.
    pub start_s: f64,
    /// Append the true state here at 10 Hz.
    pub truth_log: Option<PathBuf>,
}

/// Flight phase.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Phase {
    /// Without GPS: disarmed on the ground at the mission's start until armed.
    Standing,
    /// Armed, climbing to the mission's first point (since when).
    TakingOff(f64),
    Mission,
    Landing,
    Landed,
}

/// The vehicle's logic, free of sockets: messages in, messages out, time given.
pub struct Vehicle {
    pub mission: Mission,
    origin: LocalFrame,
    world: World,
    has_gimbal: bool,
    lag_s: f64,
    pub phase: Phase,
    /// Mission time offset and where the descent started.
    start_s: f64,
    /// The state the descent started from, and when.
    descent: Option<(State, f64)>,
    /// A precision landing's target (north, east), flown to before the descent.
    descent_target: Option<(f64, f64)>,
    /// The newest LANDING_TARGET (local NED, position valid): when, north, east.
    landing_target: Option<(f64, f64, f64)>,
    /// Current true state.
    pub state: State,
    rates: Vec<Stream>,
    setpoint: Option<(f64, UnitQuaternion<f64>)>,
    /// Who controls the gimbal through the manager (system, component).
    manager: Option<(u8, u8)>,
    system_id: u8,
    pub out: Vec<(u8, MavMessage)>,
    /// False: as PX4 with EKF2_GPS_CTRL 0 (see [`Vehicle::without_gps`]).
    gps: bool,
    /// Vehicle time the mission's clock started (after the take-off without GPS).
    mission_t0: f64,
    /// Where home is (local NED): the origin with GPS; set at arming without.
    home: Vec3,
    pub vision_accepted: u64,
    /// Vision estimates farther from the truth than EKF2's gate (5 SD) would take.
    pub vision_rejected: u64,
    last_vision: Option<f64>,
    origin_at: Option<f64>,
    event_sequence: u16,
}

#[derive(Clone, Copy, Debug)]
struct Stream {
    id: u32,
    default_hz: f64,
    hz: f64,
    next: f64,
}

const DEFAULT_RATES: &[(u32, f64)] = &[
    (0, 1.0),    // HEARTBEAT
    (30, 50.0),  // ATTITUDE
    (32, 30.0),  // LOCAL_POSITION_NED
    (33, 10.0),  // GLOBAL_POSITION_INT
    (242, 0.5),  // HOME_POSITION
    (245, 2.0),  // EXTENDED_SYS_STATE
    (1, 1.0),    // SYS_STATUS
    (2, 1.0),    // SYSTEM_TIME
    (285, 20.0), // GIMBAL_DEVICE_ATTITUDE_STATUS
    (281, 0.5),  // GIMBAL_MANAGER_STATUS (PX4's onboard default)
    (115, 0.0),  // HIL_STATE_QUATERNION: the ground truth, off until asked for (as PX4 SITL)
];

fn px4_mode(main: u32, sub: u32) -> u32 {
    (main << 16) | (sub << 24)
}

impl Vehicle {
    pub fn new(scenario: &Scenario, system_id: u8, start_s: f64) -> Result<Vehicle, String> {
        let world = World::build(scenario)?;
        let mission = Mission::plan(&world)?;
        let origin = LocalFrame::new(scenario.origin);
        let state = mission.state(start_s);
        let has_gimbal = mission.gimbal_frame == GimbalFrame::Earth;
        let rates = DEFAULT_RATES
            .iter()
            .filter(|(id, _)| has_gimbal || (*id != 285 && *id != 281))
            .map(|&(id, hz)| Stream { id, default_hz: hz, hz, next: 0.0 })
            .collect();
        Ok(Vehicle {
            mission,
            origin,
            world,
            has_gimbal,
            lag_s: scenario.noise.gimbal_lag_s,
            phase: Phase::Mission,
            start_s,
            descent: None,
            descent_target: None,
            landing_target: None,
            state,
            rates,
            setpoint: None,
            manager: None,
            system_id,
            out: Vec::new(),
            gps: true,
            mission_t0: 0.0,
            home: Vec3::zeros(),
            vision_accepted: 0,
            vision_rejected: 0,
            last_vision: None,
            origin_at: None,
            event_sequence: 0,
        })
    }

    /// As PX4 v1.16 with EKF2_GPS_CTRL 0 (measured on SITL, `../shared/data/px4-sitl`):
    /// standing disarmed on the ground at the mission's start, it arms only with vision
    /// estimates coming (VISION_POSITION_ESTIMATE within EKF2's gate of its truth) and an
    /// origin given 4.5 s before (SET_GPS_GLOBAL_ORIGIN, echoed as GPS_GLOBAL_ORIGIN);
    /// a refusal is a COMMAND_ACK TEMPORARILY_REJECTED and an EVENT, no STATUSTEXT. Armed,
    /// it sets home where it stands, climbs to the mission's start and flies it.
    pub fn without_gps(mut self) -> Vehicle {
        self.gps = false;
        self.phase = Phase::Standing;
        self.state = self.true_state(0.0);
        self
    }

    /// PX4's pre-arm verdict at `t`.
    pub fn prearm_ok(&self, t: f64) -> bool {
        self.gps
            || (self.last_vision.is_some_and(|v| t - v <= VISION_TIMEOUT_S)
                && self.origin_at.is_some_and(|o| t - o >= PREARM_AFTER_ORIGIN_S))
    }

    fn send(&mut self, component: u8, m: MavMessage) {
        self.out.push((component, m));
    }

    /// The true state at vehicle time `t` (seconds since boot).
    fn true_state(&self, t: f64) -> State {
        let start = self.mission.state(self.start_s);
        let ground = |p: &Vec3| self.world.surface_height(p.x, p.y);
        match self.phase {
            Phase::Standing => {
                let p = Vec3::new(start.position.x, start.position.y, ground(&start.position));
                return State { t, position: p, velocity: Vec3::zeros(), ..start };
            }
            Phase::TakingOff(since) => {
                let z0 = ground(&start.position);
                let z = (z0 - CLIMB_M_S * (t - since)).max(start.position.z);
                let v = if z > start.position.z { -CLIMB_M_S } else { 0.0 };
                let p = Vec3::new(start.position.x, start.position.y, z);
                return State { t, position: p, velocity: Vec3::new(0.0, 0.0, v), ..start };
            }
            _ => {}
        }
        let Some((from, since)) = self.descent else {
            return self.mission.state(self.start_s + (t - self.mission_t0).max(0.0));
        };
        let mut p = from.position;
        let mut since = since;
        // A precision landing first flies over the target at its height, then descends.
        if let Some((n, e)) = self.descent_target {
            let d = ((n - p.x).powi(2) + (e - p.y).powi(2)).sqrt();
            let approach_s = d / APPROACH_M_S;
            if t - since < approach_s {
                let f = ((t - since) / approach_s).max(0.0);
                let v = Vec3::new(n - p.x, e - p.y, 0.0) / approach_s;
                return State {
                    t,
                    position: Vec3::new(p.x + f * (n - p.x), p.y + f * (e - p.y), p.z),
                    velocity: v,
                    attitude: [0.0, 0.0, from.attitude[2]],
                    gimbal: from.gimbal,
                };
            }
            p = Vec3::new(n, e, p.z);
            since += approach_s;
        }
        let ground = self.world.surface_height(p.x, p.y);
        // Fast down to SLOW_BELOW_M above the ground, then slowly.
        let dt = (t - since).max(0.0);
        let fast_m = (ground - SLOW_BELOW_M - p.z).max(0.0);
        let fast_s = fast_m / DESCENT_FAST_M_S;
        let z = if dt < fast_s {
            p.z + DESCENT_FAST_M_S * dt
        } else {
            (p.z + fast_m + DESCENT_M_S * (dt - fast_s)).min(ground)
        };
        let descending = z < ground;
        State {
            t,
            position: Vec3::new(p.x, p.y, z),
            velocity: Vec3::new(0.0, 0.0, if descending { DESCENT_M_S } else { 0.0 }),
            attitude: [0.0, 0.0, from.attitude[2]],
            gimbal: from.gimbal,
        }
    }

    /// Starts the descent at time `t` (idempotent).
    pub fn land(&mut self, t: f64) {
        if self.phase == Phase::Mission {
            self.descent = Some((self.true_state(t), t));
            self.phase = Phase::Landing;
        }
    }

    fn armed(&self) -> bool {
        !matches!(self.phase, Phase::Landed | Phase::Standing)
    }

    /// Advances to time `t`: phase changes and due streams.
    pub fn step(&mut self, t: f64) {
        if let Phase::TakingOff(_) = self.phase {
            if self.true_state(t).velocity.z == 0.0 {
                self.phase = Phase::Mission;
                self.mission_t0 = t;
            }
        }
        self.state = self.true_state(t);
        if let Phase::Landing = self.phase {
            // Still: on the ground (the approach of a precision landing moves level).
            if self.state.velocity == Vec3::zeros() {
                self.phase = Phase::Landed;
            }
        }
        for i in 0..self.rates.len() {
            let s = self.rates[i];
            if s.hz > 0.0 && t >= s.next {
                self.rates[i].next = t + 1.0 / s.hz;
                self.emit(s.id, t);
            }
        }
    }

    fn gimbal_attitude(&self, t: f64) -> UnitQuaternion<f64> {
        if let Some((at, q)) = self.setpoint {
            if t - at < SETPOINT_HOLD_S {
                return q;
            }
        }
        let lagged = if self.lag_s > 0.0 && self.phase == Phase::Mission {
            self.mission.state(self.start_s + t - self.lag_s).gimbal
        } else {
            self.state.gimbal
        };
        let r = mavloc_geometry::GimbalChain::YawPitchRoll.rotation(lagged);
        UnitQuaternion::from_rotation_matrix(&r)
    }

    /// Sends one message of stream `id` now.
    fn emit(&mut self, id: u32, t: f64) {
        let ms = (t * 1000.0) as u32;
        let s = self.state;
        let geo = self.origin.to_geodetic(&s.position);
        let home = self.origin.origin;
        let m = match id {
            0 => {
                let (sub, status) = match self.phase {
                    Phase::Standing => (3, MavState::MAV_STATE_STANDBY), // PX4 boots in Hold
                    Phase::TakingOff(_) => (2, MavState::MAV_STATE_ACTIVE),
                    Phase::Mission => (4, MavState::MAV_STATE_ACTIVE),
                    Phase::Landing => (6, MavState::MAV_STATE_ACTIVE),
                    Phase::Landed => (3, MavState::MAV_STATE_STANDBY), // AUTO.LOITER
                };
                let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED;
                if self.armed() {
                    base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
                }
                if self.has_gimbal {
                    // A gimbal device sends its own heartbeat.
                    self.send(
                        GIMBAL_COMPONENT,
                        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                            custom_mode: 0,
                            mavtype: MavType::MAV_TYPE_GIMBAL,
                            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                            base_mode: MavModeFlag::empty(),
                            system_status: MavState::MAV_STATE_ACTIVE,
                            mavlink_version: 3,
                        }),
                    );
                }
                MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    custom_mode: px4_mode(4, sub),
                    mavtype: MavType::MAV_TYPE_QUADROTOR,
                    autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
                    base_mode: base,
                    system_status: status,
                    mavlink_version: 3,
                })
            }
            30 => MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms: ms,
                roll: s.attitude[0] as f32,
                pitch: s.attitude[1] as f32,
                yaw: s.attitude[2] as f32,
                rollspeed: 0.0,
                pitchspeed: 0.0,
                yawspeed: 0.0,
            }),
            32 => MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: ms,
                x: s.position.x as f32,
                y: s.position.y as f32,
                z: s.position.z as f32,
                vx: s.velocity.x as f32,
                vy: s.velocity.y as f32,
                vz: s.velocity.z as f32,
            }),
            33 => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms: ms,
                lat: (geo.lat_deg * 1e7).round() as i32,
                lon: (geo.lon_deg * 1e7).round() as i32,
                alt: (geo.alt_m * 1e3).round() as i32,
                relative_alt: ((geo.alt_m - home.alt_m) * 1e3).round() as i32,
                vx: (s.velocity.x * 100.0) as i16,
                vy: (s.velocity.y * 100.0) as i16,
                vz: (s.velocity.z * 100.0) as i16,
                hdg: (s.attitude[2].to_degrees().rem_euclid(360.0) * 100.0) as u16,
            }),
            // The ground truth, as PX4 SITL sends SIH's: time_usec 0. This vehicle's
            // telemetry is its truth too, so a camera rendering from either sees the same.
            115 => {
                let q =
                    nalgebra::UnitQuaternion::from_euler_angles(s.attitude[0], s.attitude[1], s.attitude[2]);
                MavMessage::HIL_STATE_QUATERNION(HIL_STATE_QUATERNION_DATA {
                    time_usec: 0,
                    attitude_quaternion: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
                    lat: (geo.lat_deg * 1e7).round() as i32,
                    lon: (geo.lon_deg * 1e7).round() as i32,
                    alt: (geo.alt_m * 1e3).round() as i32,
                    vx: (s.velocity.x * 100.0) as i16,
                    vy: (s.velocity.y * 100.0) as i16,
                    vz: (s.velocity.z * 100.0) as i16,
                    ..Default::default()
                })
            }
            242 if !self.gps && self.origin_at.is_none() => return, // no origin, no home
            242 => {
                let h = self.origin.to_geodetic(&self.home);
                MavMessage::HOME_POSITION(HOME_POSITION_DATA {
                    latitude: (h.lat_deg * 1e7).round() as i32,
                    longitude: (h.lon_deg * 1e7).round() as i32,
                    altitude: (h.alt_m * 1e3).round() as i32,
                    x: self.home.x as f32,
                    y: self.home.y as f32,
                    z: self.home.z as f32,
                    q: [1.0, 0.0, 0.0, 0.0],
                    approach_x: 0.0,
                    approach_y: 0.0,
                    approach_z: 0.0,
                    ..Default::default()
                })
            }
            1 => {
                // PX4 sets only the pre-arm health bit (measured on v1.16 SITL).
                let health = if self.prearm_ok(t) {
                    MavSysStatusSensor::MAV_SYS_STATUS_PREARM_CHECK
                } else {
                    MavSysStatusSensor::empty()
                };
                MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                    onboard_control_sensors_health: health,
                    ..Default::default()
                })
            }
            245 => MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: match self.phase {
                    Phase::Standing => MavLandedState::MAV_LANDED_STATE_ON_GROUND,
                    Phase::TakingOff(_) => MavLandedState::MAV_LANDED_STATE_TAKEOFF,
                    Phase::Mission => MavLandedState::MAV_LANDED_STATE_IN_AIR,
                    Phase::Landing => MavLandedState::MAV_LANDED_STATE_LANDING,
                    Phase::Landed => MavLandedState::MAV_LANDED_STATE_ON_GROUND,
                },
            }),
            2 => MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
                time_unix_usec: std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_micros() as u64)
                    .unwrap_or(0),
                time_boot_ms: ms,
            }),
            281 if self.has_gimbal => {
                let (sys, comp) = self.manager.unwrap_or((0, 0));
                MavMessage::GIMBAL_MANAGER_STATUS(GIMBAL_MANAGER_STATUS_DATA {
                    time_boot_ms: ms,
                    gimbal_device_id: GIMBAL_COMPONENT,
                    primary_control_sysid: sys,
                    primary_control_compid: comp,
                    ..Default::default()
                })
            }
            285 => {
                let q = self.gimbal_attitude(t);
                let flags = GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME
                    | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_ROLL_LOCK
                    | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_PITCH_LOCK
                    | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_ACCEPTS_YAW_IN_EARTH_FRAME;
                let yaw = s.attitude[2];
                let gimbal_yaw = self.state.gimbal.yaw;
                let m = MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
                    // The device's own boot clock, as a MAVLink gimbal's (PX4 forwards
                    // its reports unchanged).
                    time_boot_ms: ((t + GIMBAL_BOOTED_EARLIER_S) * 1000.0) as u32,
                    q: [q.w as f32, q.i as f32, q.j as f32, q.k as f32],
                    angular_velocity_x: f32::NAN,
                    angular_velocity_y: f32::NAN,
                    angular_velocity_z: f32::NAN,
                    flags,
                    delta_yaw: (gimbal_yaw - yaw) as f32,
                    delta_yaw_velocity: f32::NAN,
                    gimbal_device_id: 0,
                    ..Default::default()
                });
                self.send(GIMBAL_COMPONENT, m);
                return;
            }
            _ => return,
        };
        self.send(1, m);
    }

    fn ack(&mut self, command: MavCmd, result: MavResult, to: (u8, u8)) {
        self.send(
            1,
            MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                command,
                result,
                target_system: to.0,
                target_component: to.1,
                ..Default::default()
            }),
        );
    }

    /// A vision position (VISION_POSITION_ESTIMATE or ODOMETRY) through EKF2's innovation
    /// gate: EKF2_EVP_GATE (5) SD of the reported variance, floored at EKF2_EVP_NOISE (0.1
    /// m) as PX4 v1.16 does (ev_pos_control.cpp), which also stands in for a variance not
    /// given.
    fn vision_position(&mut self, t: f64, x: f32, y: f32, covariance: [f32; 2]) {
        let var = covariance.map(|c| if c.is_finite() { (c as f64).max(0.01) } else { 0.01 });
        let (dx, dy) = (x as f64 - self.state.position.x, y as f64 - self.state.position.y);
        if dx * dx / var[0] + dy * dy / var[1] > 25.0 {
            self.vision_rejected += 1;
        } else {
            self.vision_accepted += 1;
            self.last_vision = Some(t);
        }
    }

    /// Handles one message at vehicle time `t`.
    pub fn handle(&mut self, from: (u8, u8), m: &MavMessage, t: f64) {
        match m {
            MavMessage::COMMAND_LONG(c)
                if (c.target_system == self.system_id || c.target_system == 0)
                    && (c.target_component == 1 || c.target_component == 0) =>
            {
                let result = match c.command {
                    MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                        let id = c.param1 as u32;
                        match self.rates.iter_mut().find(|s| s.id == id) {
                            Some(s) => {
                                s.hz = match c.param2 {
                                    x if x < 0.0 => 0.0,
                                    0.0 => s.default_hz,
                                    us => 1e6 / us as f64,
                                };
                                s.next = t;
                                MavResult::MAV_RESULT_ACCEPTED
                            }
                            None => MavResult::MAV_RESULT_DENIED,
                        }
                    }
                    MavCmd::MAV_CMD_REQUEST_MESSAGE => {
                        let id = c.param1 as u32;
                        if DEFAULT_RATES.iter().any(|(i, _)| *i == id) {
                            self.emit(id, t);
                            MavResult::MAV_RESULT_ACCEPTED
                        } else {
                            MavResult::MAV_RESULT_DENIED
                        }
                    }
                    // The autopilot as gimbal manager (as PX4 is): one controller at a
                    // time; its pitch/yaw setpoints go to the gimbal device.
                    MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE if self.has_gimbal => {
                        let primary = (c.param1, c.param2);
                        if primary.0 >= 0.0 && primary.1 >= 0.0 {
                            self.manager = Some((primary.0 as u8, primary.1 as u8));
                        } else if primary.0 == -3.0 && self.manager == Some(from) {
                            // -3: the primary controller lets go.
                            self.manager = None;
                            self.setpoint = None;
                        }
                        // PX4 says who holds the gimbal when it changes hands.
                        self.emit(281, t);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW if self.has_gimbal => {
                        if self.manager.is_some_and(|m| m != from) {
                            MavResult::MAV_RESULT_DENIED
                        } else if (c.param5 as u32) & 2 != 0 {
                            // GIMBAL_MANAGER_FLAGS_NEUTRAL: level, facing forward.
                            let r = mavloc_geometry::GimbalChain::YawPitchRoll.rotation(
                                mavloc_geometry::GimbalAngles {
                                    yaw: self.state.attitude[2],
                                    pitch: 0.0,
                                    roll: 0.0,
                                },
                            );
                            self.setpoint = Some((t, UnitQuaternion::from_rotation_matrix(&r)));
                            MavResult::MAV_RESULT_ACCEPTED
                        } else if !(c.param1.is_finite() && c.param2.is_finite()) {
                            MavResult::MAV_RESULT_UNSUPPORTED // rate control is not simulated
                        } else {
                            let (pitch, yaw) =
                                ((c.param1 as f64).to_radians(), (c.param2 as f64).to_radians());
                            // As PX4 v1.16's gimbal manager (measured on SITL): the yaw is
                            // earth-fixed only with GIMBAL_MANAGER_FLAGS_YAW_LOCK (16);
                            // YAW_IN_EARTH_FRAME (64) alone is ignored, the yaw then
                            // taken relative to the vehicle.
                            let flags = c.param5 as u32;
                            let earth = flags & 16 != 0;
                            let yaw = if earth { yaw } else { yaw + self.state.attitude[2] };
                            // Nor is the pitch held to the horizon without PITCH_LOCK (8):
                            // PX4 stops stabilising it and the camera tilts with the
                            // airframe (measured on SIH: flags 80 against 92).
                            let pitch = if flags & 8 != 0 { pitch } else { pitch + self.state.attitude[1] };
                            let r = mavloc_geometry::GimbalChain::YawPitchRoll
                                .rotation(mavloc_geometry::GimbalAngles { yaw, pitch, roll: 0.0 });
                            self.setpoint = Some((t, UnitQuaternion::from_rotation_matrix(&r)));
                            MavResult::MAV_RESULT_ACCEPTED
                        }
                    }
                    MavCmd::MAV_CMD_COMPONENT_ARM_DISARM if c.param1 == 1.0 => match self.phase {
                        Phase::Standing if self.prearm_ok(t) => {
                            self.home = self.state.position;
                            self.phase = Phase::TakingOff(t);
                            self.emit(242, t); // PX4 sets home at arming
                            MavResult::MAV_RESULT_ACCEPTED
                        }
                        Phase::Standing => {
                            self.event_sequence = self.event_sequence.wrapping_add(1);
                            let event = MavMessage::EVENT(EVENT_DATA {
                                id: EVENT_ARM_DENIED,
                                event_time_boot_ms: (t * 1000.0) as u32,
                                sequence: self.event_sequence,
                                destination_component: 0,
                                destination_system: 0,
                                log_levels: 0x62,
                                arguments: [0; 40],
                            });
                            self.send(1, event);
                            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
                        }
                        _ => MavResult::MAV_RESULT_ACCEPTED, // armed already
                    },
                    MavCmd::MAV_CMD_NAV_LAND => {
                        self.land(t);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    // PX4 v1.16 takes command 23 as NAV_PRECLAND: over the newest
                    // LANDING_TARGET, then down; with no recent target it lands in place
                    // (PX4 would search first).
                    MavCmd::MAV_CMD_NAV_LAND_LOCAL => {
                        if self.phase == Phase::Mission {
                            self.descent_target = self
                                .landing_target
                                .filter(|(at, _, _)| t - at <= TARGET_TIMEOUT_S)
                                .map(|(_, n, e)| (n, e));
                        }
                        self.land(t);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    _ => MavResult::MAV_RESULT_UNSUPPORTED,
                };
                self.ack(c.command, result, from);
            }
            MavMessage::GIMBAL_DEVICE_SET_ATTITUDE(g)
                if g.target_system == self.system_id
                    && g.target_component == GIMBAL_COMPONENT
                    && g.q.iter().all(|c| c.is_finite()) =>
            {
                let q = nalgebra::Quaternion::new(g.q[0] as f64, g.q[1] as f64, g.q[2] as f64, g.q[3] as f64);
                if q.norm() > 0.5 {
                    let q = UnitQuaternion::from_quaternion(q);
                    // Yaw in the vehicle frame: turn it into earth frame.
                    let q = if g.flags.contains(GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME) {
                        q
                    } else {
                        UnitQuaternion::from_axis_angle(&Vec3::z_axis(), self.state.attitude[2]) * q
                    };
                    self.setpoint = Some((t, q));
                }
            }
            MavMessage::LANDING_TARGET(l)
                if l.position_valid == MavBool::MAV_BOOL_TRUE
                    && l.frame == MavFrame::MAV_FRAME_LOCAL_NED
                    && l.x.is_finite()
                    && l.y.is_finite() =>
            {
                self.landing_target = Some((t, l.x as f64, l.y as f64));
            }
            MavMessage::VISION_POSITION_ESTIMATE(v) if !self.gps => {
                self.vision_position(t, v.x, v.y, [v.covariance[0], v.covariance[6]]);
            }
            // PX4 takes a position from ODOMETRY when x, y and z are numbers (and reads a
            // NaN one as "velocity only").
            MavMessage::ODOMETRY(o) if !self.gps && o.x.is_finite() && o.y.is_finite() && o.z.is_finite() => {
                self.vision_position(t, o.x, o.y, [o.pose_covariance[0], o.pose_covariance[6]]);
            }
            #[allow(deprecated)]
            MavMessage::SET_GPS_GLOBAL_ORIGIN(o) if !self.gps && o.target_system == self.system_id => {
                self.origin_at = Some(t);
                #[allow(deprecated)]
                let echo = MavMessage::GPS_GLOBAL_ORIGIN(GPS_GLOBAL_ORIGIN_DATA {
                    latitude: o.latitude,
                    longitude: o.longitude,
                    altitude: o.altitude,
                    time_usec: 0,
                });
                self.send(1, echo);
            }
            MavMessage::TIMESYNC(ts) if ts.tc1 == 0 => {
                self.send(
                    1,
                    MavMessage::TIMESYNC(TIMESYNC_DATA {
                        tc1: (t * 1e9) as i64,
                        ts1: ts.ts1,
                        target_system: from.0,
                        target_component: from.1,
                    }),
                );
            }
            _ => {}
        }
    }
}

/// Runs the vehicle over UDP until it has landed after `duration_s`, or forever.
/// `on_landed(position)` is told where it touched down.
pub fn run(scenario: &Scenario, opts: &VehicleOptions) -> Result<Option<Vec3>, String> {
    let mut v = Vehicle::new(scenario, opts.system_id, opts.start_s)?;
    let (socket, mut peer): (UdpSocket, Option<SocketAddr>) = {
        let (mode, rest) = opts.address.split_once(':').ok_or_else(|| {
            format!("address {}: expected udpout:HOST:PORT or udpin:HOST:PORT", opts.address)
        })?;
        let addr: SocketAddr =
            rest.parse().map_err(|e| format!("address {}: {rest} is not HOST:PORT ({e})", opts.address))?;
        match mode {
            "udpout" => {
                let local = if addr.ip().is_loopback() { "127.0.0.1:0" } else { "0.0.0.0:0" };
                (UdpSocket::bind(local).map_err(|e| format!("cannot open a UDP socket: {e}"))?, Some(addr))
            }
            "udpin" => (UdpSocket::bind(addr).map_err(|e| format!("cannot listen on {addr}: {e}"))?, None),
            other => return Err(format!("address {}: {other} is not udpout or udpin", opts.address)),
        }
    };
    socket.set_read_timeout(Some(Duration::from_millis(2))).map_err(|e| e.to_string())?;
    let mut truth = match &opts.truth_log {
        Some(p) => Some(truth::create(p).map_err(|e| format!("{}: {e}", p.display()))?),
        None => None,
    };
    let started = Instant::now();
    let mut seq: u8 = 0;
    let mut next_truth = 0.0;
    let mut landed_at: Option<f64> = None;
    let mut buf = [0u8; 2048];
    loop {
        let t = started.elapsed().as_secs_f64();
        match socket.recv_from(&mut buf) {
            Ok((n, from)) => {
                if opts.address.starts_with("udpin") {
                    peer = Some(from);
                }
                let mut reader = mavlink::MavlinkReader::new(&buf[..n]);
                while let Ok((h, m)) = reader.read_any_message::<MavMessage>() {
                    v.handle((h.system_id as u8, h.component_id), &m, t);
                }
            }
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {} // nobody listening yet
            Err(e) => return Err(format!("UDP receive: {e}")),
        }
        if let Some(d) = opts.duration_s {
            if t >= d {
                v.land(t);
            }
        }
        v.step(t);
        if let Some(f) = truth.as_mut() {
            if t >= next_truth {
                next_truth = t + 0.1;
                let s = v.state;
                let _ = f.push(&TruthRow {
                    t,
                    north: s.position.x,
                    east: s.position.y,
                    down: s.position.z,
                    roll: s.attitude[0],
                    pitch: s.attitude[1],
                    yaw: s.attitude[2],
                    phase: format!("{:?}", v.phase),
                });
            }
        }
        for (component, m) in std::mem::take(&mut v.out) {
            let Some(to) = peer else { continue };
            let header =
                MavHeader { system_id: opts.system_id as u32, component_id: component, sequence: seq };
            seq = seq.wrapping_add(1);
            let mut out = Vec::with_capacity(280);
            if mavlink::write_versioned_msg(&mut out, MavlinkVersion::V2, header, &m).is_ok() {
                let _ = socket.send_to(&out, to);
            }
        }
        if v.phase == Phase::Landed {
            let at = *landed_at.get_or_insert(t);
            // Keep reporting ON_GROUND for a moment, then exit when the flight was timed.
            if opts.duration_s.is_some() && t - at > 1.5 {
                return Ok(Some(v.state.position));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vehicle(name: &str) -> Vehicle {
        Vehicle::new(&Scenario::load(name).unwrap(), 1, 0.0).unwrap()
    }

    #[test]
    fn streams_follow_set_message_interval_and_are_acked() {
        let mut v = vehicle("coastline");
        v.handle(
            (255, 190),
            &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                param1: 30.0,
                param2: 100_000.0, // 10 Hz
                target_system: 1,
                target_component: 1,
                ..Default::default()
            }),
            0.0,
        );
        assert!(
            matches!(&v.out[0].1, MavMessage::COMMAND_ACK(a) if a.result == MavResult::MAV_RESULT_ACCEPTED)
        );
        v.out.clear();
        let mut attitude = 0;
        for i in 0..100 {
            v.step(i as f64 * 0.01);
            attitude += v.out.drain(..).filter(|(_, m)| matches!(m, MavMessage::ATTITUDE(_))).count();
        }
        assert_eq!(attitude, 10, "10 Hz over one second");
    }

    #[test]
    fn a_precision_landing_flies_over_the_landing_target_then_descends() {
        let mut v = vehicle("indoor-floor");
        v.step(1.0);
        let before = v.state.position;
        let target = (before.x + 2.0, before.y - 1.0);
        v.handle(
            (1, 191),
            &MavMessage::LANDING_TARGET(LANDING_TARGET_DATA {
                frame: MavFrame::MAV_FRAME_LOCAL_NED,
                x: target.0 as f32,
                y: target.1 as f32,
                position_valid: MavBool::MAV_BOOL_TRUE,
                ..Default::default()
            }),
            1.0,
        );
        v.handle(
            (1, 191),
            &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_NAV_LAND_LOCAL,
                target_system: 1,
                target_component: 1,
                ..Default::default()
            }),
            1.0,
        );
        assert!(v.out.iter().any(|(_, m)| matches!(m, MavMessage::COMMAND_ACK(a)
            if a.command == MavCmd::MAV_CMD_NAV_LAND_LOCAL && a.result == MavResult::MAV_RESULT_ACCEPTED)));
        v.step(2.0);
        assert_eq!(v.phase, Phase::Landing, "flying over the target is not landed");
        assert!((v.state.position.z - before.z).abs() < 1e-9, "level while approaching");
        for i in 0..200 {
            v.step(2.0 + i as f64 * 0.05);
        }
        assert_eq!(v.phase, Phase::Landed);
        let off = ((v.state.position.x - target.0).powi(2) + (v.state.position.y - target.1).powi(2)).sqrt();
        assert!(off < 1e-6, "touched down {off} m from the target");
    }

    #[test]
    fn without_gps_it_arms_only_with_vision_within_the_gate_and_an_origin_and_sets_home_there() {
        let mut v = vehicle("indoor-floor").without_gps();
        v.step(0.0);
        let p = v.state.position;
        let arm = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: 1.0,
            command: MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        });
        let vpe = |dx: f32| {
            let mut covariance = [0.0f32; 21];
            covariance[0] = 0.0025;
            covariance[6] = 0.0025;
            MavMessage::VISION_POSITION_ESTIMATE(VISION_POSITION_ESTIMATE_DATA {
                x: p.x as f32 + dx,
                y: p.y as f32,
                covariance,
                ..Default::default()
            })
        };
        let acks = |v: &Vehicle| -> Vec<MavResult> {
            v.out
                .iter()
                .filter_map(|(_, m)| match m {
                    MavMessage::COMMAND_ACK(a) if a.command == MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                        Some(a.result)
                    }
                    _ => None,
                })
                .collect()
        };
        // Far from the truth (0.6 m, the gate is 5 x 0.1 m): rejected, no position.
        v.handle((1, 191), &vpe(0.6), 1.0);
        assert_eq!((v.vision_accepted, v.vision_rejected), (0, 1));
        #[allow(deprecated)]
        let origin = MavMessage::SET_GPS_GLOBAL_ORIGIN(SET_GPS_GLOBAL_ORIGIN_DATA {
            target_system: 1,
            ..Default::default()
        });
        v.handle((1, 191), &origin, 1.0);
        assert!(v.out.iter().any(|(_, m)| matches!(m, MavMessage::GPS_GLOBAL_ORIGIN(_))), "echoed");
        v.handle((255, 190), &arm, 6.0);
        assert_eq!(acks(&v), [MavResult::MAV_RESULT_TEMPORARILY_REJECTED], "no vision");
        assert!(v.out.iter().any(|(_, m)| matches!(m, MavMessage::EVENT(e) if e.id == EVENT_ARM_DENIED)));
        v.out.clear();
        v.handle((1, 191), &vpe(0.02), 6.0);
        assert_eq!(v.vision_accepted, 1);
        v.handle((255, 190), &arm, 6.1);
        assert_eq!(acks(&v), [MavResult::MAV_RESULT_ACCEPTED]);
        assert!(
            v.out.iter().any(|(_, m)| matches!(m, MavMessage::HOME_POSITION(h)
            if (h.x as f64 - p.x).abs() < 1e-3 && (h.y as f64 - p.y).abs() < 1e-3)),
            "home where it stood"
        );
        v.step(6.2);
        assert!(matches!(v.phase, Phase::TakingOff(_)));
        assert!(v.state.position.z < p.z, "climbing");
    }

    #[test]
    fn nav_land_descends_and_reports_on_ground() {
        let mut v = vehicle("indoor-floor");
        v.step(1.0);
        let before = v.state.position;
        v.handle(
            (1, 191),
            &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_NAV_LAND,
                target_system: 1,
                target_component: 1,
                ..Default::default()
            }),
            1.0,
        );
        assert!(matches!(v.phase, Phase::Landing));
        for i in 0..100 {
            v.step(1.0 + i as f64 * 0.05);
        }
        assert_eq!(v.phase, Phase::Landed);
        assert!((v.state.position.xy() - before.xy()).norm() < 1e-9, "vertical descent");
        v.out.clear();
        v.step(10.0);
        v.emit(245, 10.0);
        assert!(v.out.iter().any(|(_, m)| matches!(m, MavMessage::EXTENDED_SYS_STATE(e)
            if e.landed_state == MavLandedState::MAV_LANDED_STATE_ON_GROUND)));
    }

    #[test]
    fn the_gimbal_reports_the_mission_pointing_in_earth_frame_and_obeys_setpoints() {
        let mut v = vehicle("coastline");
        v.step(5.0);
        v.out.clear();
        v.emit(285, 5.0);
        let (comp, m) = &v.out[0];
        assert_eq!(*comp, GIMBAL_COMPONENT);
        let MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(g) = m else { panic!() };
        assert!(g.flags.contains(GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME));
        let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            g.q[0] as f64,
            g.q[1] as f64,
            g.q[2] as f64,
            g.q[3] as f64,
        ));
        let a = mavloc_geometry::GimbalChain::YawPitchRoll.angles(&q.to_rotation_matrix());
        assert!((a.pitch - v.state.gimbal.pitch).abs() < 1e-5 && (a.yaw - v.state.gimbal.yaw).abs() < 1e-5);
        // A setpoint (straight down) is followed, then released.
        let down = UnitQuaternion::from_euler_angles(0.0, -std::f64::consts::FRAC_PI_2, 0.0);
        v.handle(
            (1, 191),
            &MavMessage::GIMBAL_DEVICE_SET_ATTITUDE(GIMBAL_DEVICE_SET_ATTITUDE_DATA {
                q: [down.w as f32, down.i as f32, down.j as f32, down.k as f32],
                flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME,
                target_system: 1,
                target_component: GIMBAL_COMPONENT,
                ..Default::default()
            }),
            5.0,
        );
        assert!(v.gimbal_attitude(5.5).angle_to(&down) < 1e-6);
        assert!(v.gimbal_attitude(8.0).angle_to(&down) > 0.01, "released after the hold");
    }

    /// A command to the autopilot (1/1) with its first five parameters.
    fn cmd(command: MavCmd, p: [f32; 5]) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command,
            param1: p[0],
            param2: p[1],
            param3: p[2],
            param4: p[3],
            param5: p[4],
            target_system: 1,
            target_component: 1,
            ..Default::default()
        })
    }

    #[test]
    fn the_gimbal_manager_takes_one_controller_and_its_pitch_yaw() {
        let mut v = vehicle("coastline");
        let mavloc = (1, 191);
        v.handle(
            mavloc,
            &cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, [1.0, 191.0, -1.0, -1.0, 0.0]),
            1.0,
        );
        v.handle(
            mavloc,
            &cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, [-30.0, 45.0, f32::NAN, f32::NAN, 16.0]),
            1.0,
        );
        v.handle(
            (255, 190),
            &cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, [-90.0, 0.0, f32::NAN, f32::NAN, 64.0]),
            1.1,
        );
        let results: Vec<MavResult> = v
            .out
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::COMMAND_ACK(a) => Some(a.result),
                _ => None,
            })
            .collect();
        assert_eq!(
            results,
            [MavResult::MAV_RESULT_ACCEPTED, MavResult::MAV_RESULT_ACCEPTED, MavResult::MAV_RESULT_DENIED]
        );
        let a =
            mavloc_geometry::GimbalChain::YawPitchRoll.angles(&v.gimbal_attitude(1.5).to_rotation_matrix());
        assert!(
            (a.pitch.to_degrees() + 30.0).abs() < 1e-4 && (a.yaw.to_degrees() - 45.0).abs() < 1e-4,
            "{a:?}"
        );
        // As PX4 v1.16: YAW_IN_EARTH_FRAME alone is ignored; the yaw is the vehicle's + 45.
        v.handle(
            mavloc,
            &cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, [-30.0, 45.0, f32::NAN, f32::NAN, 64.0]),
            1.2,
        );
        let a =
            mavloc_geometry::GimbalChain::YawPitchRoll.angles(&v.gimbal_attitude(1.5).to_rotation_matrix());
        let want = (45.0 + v.state.attitude[2].to_degrees()).rem_euclid(360.0);
        let got = a.yaw.to_degrees().rem_euclid(360.0);
        assert!((got - want).abs() < 1e-3 || (got - want).abs() > 359.999, "{got} vs {want}");
        assert!(v.state.attitude[2].to_degrees().abs() > 1.0, "the test needs a vehicle not facing north");
    }

    /// As PX4 v1.16 (measured on SIH): a pitch without PITCH_LOCK is relative to the
    /// airframe, which tilts the camera with it; with the lock, to the horizon. The
    /// manager says who holds the gimbal when it changes hands, and a primary controller
    /// that lets go (-3) leaves it to nobody.
    #[test]
    fn the_gimbal_manager_locks_pitch_only_when_asked_and_says_who_holds_it() {
        let mut v = vehicle("coastline");
        v.state.attitude[1] = 5f64.to_radians();
        let mavloc = (1, 191);
        let configure =
            |p1: f32, p2: f32| cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, [p1, p2, -1.0, -1.0, 0.0]);
        let primary = |v: &Vehicle| {
            v.out.iter().rev().find_map(|(comp, m)| match m {
                MavMessage::GIMBAL_MANAGER_STATUS(s) if *comp == 1 => {
                    Some((s.primary_control_sysid, s.primary_control_compid))
                }
                _ => None,
            })
        };
        v.handle(mavloc, &configure(1.0, 191.0), 1.0);
        assert_eq!(primary(&v), Some(mavloc));
        let pitch_after = |v: &mut Vehicle, flags: f32| {
            v.handle(
                mavloc,
                &cmd(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, [-30.0, 45.0, f32::NAN, f32::NAN, flags]),
                1.0,
            );
            let r = v.gimbal_attitude(1.2).to_rotation_matrix();
            mavloc_geometry::GimbalChain::YawPitchRoll.angles(&r).pitch.to_degrees()
        };
        assert!((pitch_after(&mut v, 80.0) - (-25.0)).abs() < 1e-3, "tilted with the airframe");
        assert!((pitch_after(&mut v, 92.0) - (-30.0)).abs() < 1e-3, "held to the horizon");
        // Only the holder lets go.
        v.handle((255, 190), &configure(-3.0, -3.0), 1.5);
        assert_eq!(primary(&v), Some(mavloc));
        v.handle(mavloc, &configure(-3.0, -3.0), 1.6);
        assert_eq!(primary(&v), Some((0, 0)));
    }
}
