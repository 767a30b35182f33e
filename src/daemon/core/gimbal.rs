//! Pointing the camera (`gimbal.aim = "border"`), as a gimbal-manager client (MAVLink
//! gimbal protocol v2): take primary control with MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
//! then send MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW with an earth-frame yaw and a
//! horizon-stabilised pitch, at most 5 times a second; between sends only the newest aim
//! is kept.
//!
//! mavloc shares the gimbal: GIMBAL_MANAGER_STATUS names the primary controller, and
//! while another holds it (a ground station, the autopilot's own mission, RTL or landing)
//! mavloc sends nothing and takes control again only once it is let go. It lets go itself
//! (CONFIGURE -3) when it stops aiming (the mission's aim chosen) or shuts down, and when
//! the vehicle lands, after levelling the camera as PX4's navigator does for the
//! touchdown. Control is released when the autopilot reboots or vanishes, and taken again.

use std::time::Duration;

use mavlink::dialects::common::*;

use super::time::Mono;

pub const MIN_INTERVAL: Duration = Duration::from_millis(200);
/// ROLL_LOCK (4) | PITCH_LOCK (8) | YAW_LOCK (16) | YAW_IN_EARTH_FRAME (64): every axis
/// held in the earth frame. PX4 v1.16's gimbal manager takes an axis relative to the
/// vehicle unless its LOCK flag is set (with 80, no roll or pitch lock, it stopped
/// stabilising and the camera tilted with the airframe, measured on SIH); it honours only
/// YAW_LOCK for the yaw (issue #18: median pointing error 15.7 degrees with 64 alone),
/// while managers that follow the newer spec read YAW_IN_EARTH_FRAME. Both say the same.
const FLAGS: f32 = 92.0;
/// GIMBAL_MANAGER_FLAGS_NEUTRAL: the gimbal's neutral attitude (level), as PX4's navigator
/// sets it for the landing.
const NEUTRAL: f32 = 2.0;
/// CONFIGURE's "primary control": -3 lets go if we hold it, -1 leaves it as it is.
const LET_GO: f32 = -3.0;
const UNCHANGED: f32 = -1.0;

/// A CONFIGURE unanswered this long: the autopilot runs no gimbal manager (PX4's default
/// MNT_MODE_IN = -1 leaves the commands unanswered); asked again after [`RETRY_QUIET`].
pub const ACK_WAIT: Duration = Duration::from_secs(3);
pub const RETRY_QUIET: Duration = Duration::from_secs(10);
/// After a refused setpoint, the manager's status (PX4 streams it every 2 s unless asked
/// for more) says who took the gimbal; a manager that says nothing in this time is asked
/// for control again.
pub const RETAKE: Duration = Duration::from_secs(3);
/// Before the manager's first status: control is not taken from a controller that may
/// already hold the gimbal until a status had this long to arrive.
pub const FIRST_STATUS_WAIT: Duration = Duration::from_secs(3);
/// A status saying nobody holds the gimbal this soon after mavloc's CONFIGURE was
/// accepted is older than the acceptance.
const STATUS_GRACE: Duration = Duration::from_secs(3);

/// Whether mavloc points the gimbal now.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Aim {
    /// `gimbal.aim = "border"` with an autopilot present.
    On,
    /// Not aiming (the mission's aim chosen, no autopilot): let go.
    Off,
    /// The vehicle is landing: level the camera, as PX4 does for the touchdown, then let go.
    /// (PX4's RTL levels it and lets go at once when it starts; mavloc took it again for
    /// the return leg, and it touched down pointing where mavloc had aimed it.)
    Landing,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Control {
    Released,
    /// CONFIGURE sent at this time; setpoints wait for its acknowledgement.
    Requested(Mono),
    InControl,
    /// A setpoint was refused at this time: another controller took the gimbal. Nothing is
    /// sent until the manager's status says who, or [`RETAKE`] passes without one.
    Refused(Mono),
    /// The manager says this controller (system, component) holds the gimbal: nothing is
    /// sent until it lets go.
    Yielded((u8, u8)),
}

/// A setpoint is given this long to be reached before the gimbal's report is compared.
pub const SETTLE: Duration = Duration::from_millis(500);
/// The recent pointing error is over this long (the status's "last minute").
pub const RECENT: Duration = Duration::from_secs(60);
/// At most this many recent errors are kept (a minute at 100 Hz): an autopilot that
/// floods gimbal reports costs no more memory or sorting than that.
const RECENT_MAX: usize = 6000;
/// Resolution of the flight's error histogram, degrees (0..180).
const BIN_DEG: f64 = 0.01;

#[derive(Debug)]
pub struct Gimbal {
    control: Control,
    /// The recent setpoints: when sent, and the direction each asks for (unit, NED).
    pub sent: std::collections::VecDeque<(Mono, [f64; 3])>,
    /// Pointing errors (degrees) of reports against settled setpoints over the last
    /// [`RECENT`] (at most [`RECENT_MAX`]), with their times, the newest last.
    pub errors: std::collections::VecDeque<(Mono, f64)>,
    /// Every airborne report's error since the start, in [`BIN_DEG`] bins: the flight's
    /// median in constant memory (PX4 reports the gimbal at up to 70 Hz).
    flight: Vec<u64>,
    /// (yaw, pitch) radians, newest aim not yet sent.
    pending: Option<(f64, f64)>,
    next: Mono,
    /// No CONFIGURE before this (after an unanswered or refused one, and until the
    /// manager's first status had time to come).
    retry_at: Option<Mono>,
    /// When a held-back CONFIGURE may go.
    wake: Option<Mono>,
    /// When mavloc's CONFIGURE was last accepted.
    configured_at: Option<Mono>,
    /// The manager has sent its status at least once: it says who holds the gimbal.
    status_seen: bool,
    /// Let go of the gimbal at the next send (mavloc stops aiming or shuts down).
    let_go: bool,
    /// The camera was levelled for a landing; letting go comes next.
    levelled: bool,
    /// `retry_at` is the wait for the manager's first status (which that status ends).
    first_wait: bool,
    refused_once: bool,
    unanswered_said: bool,
    /// A setpoint was accepted since control was last taken: the reports answer mavloc's
    /// setpoints, and a refusal now means another controller took the gimbal.
    in_use: bool,
    /// A setpoint was ever accepted.
    ever_accepted: bool,
}

impl Default for Gimbal {
    fn default() -> Self {
        Gimbal {
            control: Control::Released,
            sent: Default::default(),
            errors: Default::default(),
            flight: vec![0; (180.0 / BIN_DEG) as usize + 1],
            pending: None,
            next: Mono::ZERO,
            retry_at: None,
            wake: None,
            configured_at: None,
            status_seen: false,
            let_go: false,
            levelled: false,
            first_wait: false,
            refused_once: false,
            unanswered_said: false,
            in_use: false,
            ever_accepted: false,
        }
    }
}

/// Who a controller is, in words.
fn who(c: (u8, u8), autopilot: u8) -> String {
    match c {
        (s, 1) if s == autopilot => format!("the autopilot ({s}/1: its mission, RTL or landing)"),
        (s, 190) => format!("a ground station ({s}/190)"),
        (s, k) => format!("system {s} component {k}"),
    }
}

impl Gimbal {
    pub fn control(&self) -> Control {
        self.control
    }

    pub fn aim(&mut self, yaw: f64, pitch: f64) {
        self.pending = Some((yaw, pitch));
    }

    /// A gimbal report (optical axis, NED, unit) at `now`: its angle to the newest
    /// setpoint sent at least [`SETTLE`] before is kept for [`RECENT`] and, when the
    /// vehicle is `airborne`, counted in the flight's median (on the ground an autopilot
    /// holds the camera in its landing range whatever it is told: PX4's MNT_LND_P_*).
    /// Only while mavloc's setpoints are taken: another controller's pointing, or an
    /// autopilot that answers nothing, is not mavloc's error.
    pub fn on_report(&mut self, now: Mono, axis: [f64; 3], airborne: bool) {
        if self.control != Control::InControl || !self.in_use {
            return;
        }
        let Some(&(_, want)) = self.sent.iter().rev().find(|(t, _)| *t + SETTLE <= now) else { return };
        let dot: f64 = (0..3).map(|i| axis[i] * want[i]).sum();
        let error = dot.clamp(-1.0, 1.0).acos().to_degrees();
        tracing::trace!("gimbal report {axis:.3?} against setpoint {want:.3?}: {error:.2} deg");
        self.errors.push_back((now, error));
        while self.errors.front().is_some_and(|(t, _)| *t + RECENT < now) || self.errors.len() > RECENT_MAX {
            self.errors.pop_front();
        }
        if airborne {
            let last = self.flight.len() - 1;
            self.flight[((error / BIN_DEG).round() as usize).min(last)] += 1;
        }
    }

    /// Median pointing error over the last [`RECENT`], degrees.
    pub fn median_error_deg(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.errors.iter().map(|e| e.1).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }

    /// Median pointing error over every airborne report so far, degrees (to
    /// [`BIN_DEG`]).
    pub fn flight_median_error_deg(&self) -> Option<f64> {
        let total: u64 = self.flight.iter().sum();
        if total == 0 {
            return None;
        }
        let mut seen = 0;
        for (i, n) in self.flight.iter().enumerate() {
            seen += n;
            if 2 * seen > total {
                return Some(i as f64 * BIN_DEG);
            }
        }
        None
    }

    /// The autopilot rebooted or vanished: whatever control mavloc had is gone.
    pub fn release(&mut self) {
        self.control = Control::Released;
        self.pending = None;
        self.sent.clear();
        self.in_use = false;
        self.let_go = false;
        self.status_seen = false;
        self.retry_at = None;
    }

    /// Lets go of the gimbal at the next send, if mavloc holds or asked for it (the
    /// daemon shuts down): a manager keeps a departed primary controller otherwise, and
    /// refuses everyone else's setpoints.
    pub fn let_go(&mut self) {
        if matches!(self.control, Control::InControl | Control::Requested(_)) {
            self.let_go = true;
        }
    }

    pub fn deadline(&self) -> Option<Mono> {
        let timer = match self.control {
            Control::Requested(at) => Some(at + ACK_WAIT),
            Control::Refused(at) => Some(at + RETAKE),
            _ => None,
        };
        let send = match (self.let_go, self.pending, self.control) {
            (true, _, _) => Some(Mono::ZERO),
            (_, Some(_), Control::InControl) => Some(self.next),
            // A CONFIGURE held back until `retry_at` (a past time here would wake the
            // loop for nothing while control may not be taken).
            (_, Some(_), Control::Released) => self.wake,
            _ => None,
        };
        super::time::earliest([timer, send])
    }

    /// Expires a CONFIGURE the manager did not answer, and a refusal no status explained.
    /// Returns a line to report: the first unanswered CONFIGURE.
    pub fn on_timeout(&mut self, now: Mono) -> Option<String> {
        match self.control {
            Control::Requested(at) if now >= at + ACK_WAIT => {
                self.control = Control::Released;
                self.retry_at = Some(now + RETRY_QUIET);
                self.sent.clear();
                (!std::mem::replace(&mut self.unanswered_said, true)).then(|| {
                    format!(
                        "the autopilot did not answer MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE in {} s: is it a gimbal manager (PX4: MNT_MODE_IN=4)? mavloc asks again every {} s",
                        ACK_WAIT.as_secs(),
                        RETRY_QUIET.as_secs()
                    )
                })
            }
            Control::Refused(at) if now >= at + RETAKE => {
                self.control = Control::Released;
                None
            }
            _ => None,
        }
    }

    /// A let-go is waiting to be sent (the daemon sends it before anything else).
    pub fn letting_go(&self) -> bool {
        self.let_go
    }

    /// The next command: letting go (after levelling the camera for a landing), taking
    /// control, or the newest aim. `me` is mavloc's (system, component).
    pub fn poll_transmit(&mut self, now: Mono, target: u8, me: (u8, u8), aim: Aim) -> Option<MavMessage> {
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
        let holding = matches!(self.control, Control::InControl | Control::Requested(_));
        if self.let_go || (aim != Aim::On && holding) {
            if aim == Aim::Landing && self.control == Control::InControl && !self.levelled {
                self.levelled = true;
                self.pending = None;
                self.sent.clear();
                return Some(command(
                    MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
                    [f32::NAN, f32::NAN, f32::NAN, f32::NAN, NEUTRAL, 0.0, 0.0],
                ));
            }
            self.levelled = false;
            self.let_go = false;
            self.control = Control::Released;
            self.pending = None;
            self.sent.clear();
            self.in_use = false;
            return Some(command(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                [LET_GO, LET_GO, UNCHANGED, UNCHANGED, 0.0, 0.0, 0.0],
            ));
        }
        if aim != Aim::On {
            self.pending = None;
            return None;
        }
        let (yaw, pitch) = self.pending?;
        self.wake = None;
        match self.control {
            Control::Released => {
                // Before the manager's first status, give it time to say whether someone
                // holds the gimbal already (a ground station at mavloc's start).
                if !self.status_seen && self.retry_at.is_none() {
                    self.retry_at = Some(now + FIRST_STATUS_WAIT);
                    self.first_wait = true;
                }
                if let Some(t) = self.retry_at.filter(|t| now < *t) {
                    self.wake = Some(t);
                    return None;
                }
                self.control = Control::Requested(now);
                // Primary control to us; secondary unchanged (-1); all gimbals (device id 0).
                Some(command(
                    MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                    [me.0 as f32, me.1 as f32, UNCHANGED, UNCHANGED, 0.0, 0.0, 0.0],
                ))
            }
            Control::InControl if now >= self.next => {
                self.pending = None;
                self.next = now + MIN_INTERVAL;
                let (cp, sp) = (pitch.cos(), pitch.sin());
                self.sent.push_back((now, [cp * yaw.cos(), cp * yaw.sin(), -sp]));
                while self.sent.len() > 16 {
                    self.sent.pop_front();
                }
                // Rates NaN: angles only.
                Some(command(
                    MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
                    [pitch.to_degrees() as f32, yaw.to_degrees() as f32, f32::NAN, f32::NAN, FLAGS, 0.0, 0.0],
                ))
            }
            _ => None,
        }
    }

    /// The manager's status (GIMBAL_MANAGER_STATUS): who holds the gimbal. Returns a line
    /// to report when another controller takes it from mavloc, or lets it go.
    pub fn on_manager_status(
        &mut self,
        now: Mono,
        primary: (u8, u8),
        me: (u8, u8),
        autopilot: u8,
    ) -> Option<String> {
        self.status_seen = true;
        if std::mem::replace(&mut self.first_wait, false) {
            // The first status came: no need to wait out the rest of its time (only that
            // wait: one after a refusal or an unanswered request stands).
            self.retry_at = None;
        }
        match (primary.0 != 0).then_some(primary) {
            Some(p) if p == me => {
                // Ours: the manager took our CONFIGURE even if its answer was lost. (A
                // status from before a refusal does not undo the refusal.)
                if matches!(self.control, Control::Yielded(_) | Control::Requested(_)) {
                    self.control = Control::InControl;
                    self.configured_at = Some(now);
                }
                None
            }
            Some(p) => {
                if self.control == Control::Yielded(p) {
                    return None;
                }
                self.control = Control::Yielded(p);
                self.pending = None;
                self.sent.clear();
                self.in_use = false;
                Some(format!(
                    "gimbal held by {}: mavloc stops pointing it until it is let go",
                    who(p, autopilot)
                ))
            }
            None => match self.control {
                Control::Yielded(p) => {
                    self.control = Control::Released;
                    self.retry_at = None;
                    Some(format!("gimbal let go by {}: mavloc points it again", who(p, autopilot)))
                }
                Control::InControl if self.configured_at.is_some_and(|t| now >= t + STATUS_GRACE) => {
                    // Released by someone else's CONFIGURE: ask again.
                    self.control = Control::Released;
                    self.in_use = false;
                    self.sent.clear();
                    None
                }
                _ => None,
            },
        }
    }

    /// The manager's answer to CONFIGURE or PITCHYAW. Returns a line to report: the first
    /// refusal of a manager that never took a setpoint (likely no gimbal manager), and
    /// each time a manager that took setpoints starts refusing them without saying who
    /// holds the gimbal instead; while it keeps refusing, nothing more.
    pub fn on_ack(&mut self, now: Mono, command: MavCmd, result: MavResult) -> Option<String> {
        let accepted = matches!(result, MavResult::MAV_RESULT_ACCEPTED | MavResult::MAV_RESULT_IN_PROGRESS);
        match (command, accepted, self.control) {
            (MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, true, Control::Requested(_)) => {
                self.control = Control::InControl;
                self.configured_at = Some(now);
                self.unanswered_said = false;
                None
            }
            (MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, true, Control::InControl) => {
                self.in_use = true;
                self.ever_accepted = true;
                None
            }
            (MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, false, Control::Requested(_)) => {
                self.control = Control::Released;
                self.retry_at = Some(now + RETAKE);
                let first = !std::mem::replace(&mut self.refused_once, true);
                (first && !self.ever_accepted).then(|| {
                    format!("autopilot refused {command:?}: {result:?}; is it a gimbal manager (PX4: MNT_MODE_IN=4)?")
                })
            }
            (MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, false, Control::InControl) => {
                // The refused setpoints are not where the gimbal was told to go: another
                // controller points it, and comparing its reports with them would count
                // its choice as mavloc's pointing error.
                self.control = Control::Refused(now);
                self.sent.clear();
                let first = !std::mem::replace(&mut self.refused_once, true);
                if std::mem::replace(&mut self.in_use, false) {
                    // A manager that reports its status names the new holder itself.
                    (!self.status_seen).then(|| {
                        format!(
                            "the gimbal manager refused mavloc's setpoint ({result:?}): another controller took the gimbal \
                             (PX4's navigator does for RTL and landing); mavloc asks again in {} s",
                            RETAKE.as_secs()
                        )
                    })
                } else if first && !self.ever_accepted {
                    Some(format!(
                        "autopilot refused {command:?}: {result:?}; is it a gimbal manager (PX4: MNT_MODE_IN=4)?"
                    ))
                } else {
                    None
                }
            }
            // Late answers (to a CONFIGURE that let go, to setpoints sent before control
            // changed hands) change nothing.
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ME: (u8, u8) = (1, 191);
    const QGC: (u8, u8) = (255, 190);
    const CONFIGURE: MavCmd = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE;
    const PITCHYAW: MavCmd = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW;
    const OK: MavResult = MavResult::MAV_RESULT_ACCEPTED;
    const DENIED: MavResult = MavResult::MAV_RESULT_DENIED;

    fn command(m: &MavMessage) -> (MavCmd, [f32; 2], f32) {
        match m {
            MavMessage::COMMAND_LONG(c) => (c.command, [c.param1, c.param2], c.param5),
            other => panic!("{other:?}"),
        }
    }

    fn ms(t: u64) -> Mono {
        Mono::from_millis(t)
    }

    /// Everything sent at `now` while aiming and free to take control.
    fn send(g: &mut Gimbal, now: Mono) -> Vec<(MavCmd, [f32; 2], f32)> {
        std::iter::from_fn(|| g.poll_transmit(now, 1, ME, Aim::On)).map(|m| command(&m)).collect()
    }

    /// A gimbal in mavloc's control at `now`, its first setpoint accepted (the manager's
    /// status seen, saying nobody held it).
    fn in_control(now: Mono) -> Gimbal {
        let mut g = Gimbal::default();
        assert!(g.on_manager_status(now, (0, 0), ME, 1).is_none());
        g.aim(0.0, -1.0);
        assert_eq!(send(&mut g, now)[0].0, CONFIGURE);
        g.on_ack(now, CONFIGURE, OK);
        g.aim(0.0, -1.0);
        assert_eq!(send(&mut g, now)[0].0, PITCHYAW);
        g.on_ack(now, PITCHYAW, OK);
        g
    }

    #[test]
    fn takes_control_once_then_at_most_5_hz_with_the_newest_aim() {
        let mut g = Gimbal::default();
        g.on_manager_status(ms(900), (0, 0), ME, 1);
        let mut sent = Vec::new();
        for i in 0..10u64 {
            let now = ms(1000 + i * 100);
            g.aim(0.3 + i as f64 * 0.01, -0.5);
            sent.extend(send(&mut g, now).into_iter().map(|c| (now, c)));
            if i == 0 {
                assert_eq!(sent.len(), 1, "setpoints wait for the CONFIGURE's answer");
                g.on_ack(now, CONFIGURE, OK);
            }
        }
        assert_eq!(sent[0].1 .0, CONFIGURE);
        let setpoints: Vec<_> = sent.iter().filter(|s| s.1 .0 == PITCHYAW).collect();
        assert_eq!(setpoints.len(), 5, "1 s at 5 Hz");
        for w in setpoints.windows(2) {
            assert!(w[1].0.saturating_sub(w[0].0) >= MIN_INTERVAL);
        }
        let (_, [p, y], flags) = setpoints[1].1;
        assert!((p - (-0.5f32).to_degrees()).abs() < 1e-4);
        assert!((y - 0.33f32.to_degrees()).abs() < 1e-3, "the aim of its own time, {y}");
        // Every axis locked to the earth: PX4 takes an unlocked pitch or roll relative to
        // the airframe and stops stabilising it.
        assert_eq!(flags, 92.0, "ROLL_LOCK | PITCH_LOCK | YAW_LOCK | YAW_IN_EARTH_FRAME");
        // A newer aim waits for the next slot.
        g.aim(0.5, -0.5);
        assert!(send(&mut g, ms(2000)).is_empty());
        assert_eq!(g.deadline(), Some(ms(2100)));
        assert_eq!(send(&mut g, ms(2100)).len(), 1);
    }

    /// Reports are compared with the setpoint in force, once the manager took one; once
    /// it refuses setpoints (another controller points the gimbal), or while it answers
    /// nothing, its pointing is not counted as mavloc's error.
    #[test]
    fn pointing_errors_count_only_setpoints_the_autopilot_took() {
        let axis = |pitch: f64| [pitch.cos(), 0.0, -pitch.sin()];
        // Control asked for and never answered: nothing counted.
        let mut g = Gimbal::default();
        g.on_manager_status(Mono::ZERO, (0, 0), ME, 1);
        g.aim(0.0, -1.0);
        send(&mut g, Mono::ZERO);
        g.on_report(ms(900), axis(0.0), true);
        assert!(g.errors.is_empty());
        let mut g = in_control(Mono::ZERO);
        // Before the setpoint has settled nothing is compared; after, the report is on it.
        g.on_report(ms(400), axis(0.0), true);
        assert!(g.errors.is_empty());
        g.on_report(ms(900), axis(-1.0), true);
        assert!(g.median_error_deg().unwrap() < 1e-6);
        // Refused: another controller levels the camera.
        g.aim(0.0, -1.0);
        send(&mut g, ms(1100));
        g.on_ack(ms(1100), PITCHYAW, DENIED);
        for t in [2000, 2500, 3000] {
            g.on_report(ms(t), axis(0.0), true);
        }
        assert_eq!(g.errors.len(), 1, "{:?}", g.errors);
        // A wrong pointing under a setpoint in force does count (57 degrees off).
        let mut g = in_control(ms(3100));
        g.on_report(ms(4000), axis(0.0), true);
        assert_eq!(g.errors.len(), 1);
        assert!((g.errors[0].1 - 57.3).abs() < 0.1, "{:?}", g.errors);
    }

    /// The recent median is over the last minute whatever the report rate (PX4 sends up
    /// to 70 a second); the flight's counts airborne reports only, all of them.
    #[test]
    fn the_recent_median_is_a_minute_and_the_flights_is_airborne() {
        let mut g = in_control(Mono::ZERO);
        let off = |deg: f64| {
            let p = -1.0 - deg.to_radians();
            [p.cos(), 0.0, -p.sin()]
        };
        // 82 s airborne at 50 Hz: the first 42 s 3 degrees off, then 40 s 1 degree off.
        for i in 0..4100u64 {
            let deg = if i < 2100 { 3.0 } else { 1.0 };
            g.on_report(ms(1000 + i * 20), off(deg), true);
        }
        // Then 10 s on the ground, levelled by the autopilot (57 degrees off).
        for i in 0..500u64 {
            g.on_report(ms(83_000 + i * 20), off(57.3), false);
        }
        let flight = g.flight_median_error_deg().unwrap();
        assert!((flight - 3.0).abs() < 0.02, "flight median {flight}");
        // The last minute (33-93 s): 10 s at 3 degrees, 40 s at 1, 10 s on the ground.
        let recent = g.median_error_deg().unwrap();
        assert!((recent - 1.0).abs() < 0.02, "recent median {recent}");
        assert!(g.errors.len() <= 3001, "a minute of reports: {}", g.errors.len());
        // A flood is capped: 10 s at 1 kHz keeps the newest RECENT_MAX.
        for i in 0..10_000u64 {
            g.on_report(ms(93_000) + Duration::from_micros(i * 1000), off(2.0), true);
        }
        assert_eq!(g.errors.len(), RECENT_MAX);
        assert!(g.errors.iter().all(|e| (e.1 - 2.0).abs() < 1e-9));
    }

    /// A refused CONFIGURE is said once (the manager hint) and asked again after
    /// [`RETAKE`], not at the next aim.
    #[test]
    fn a_refusal_is_reported_once_and_control_is_asked_again_later() {
        let mut g = Gimbal::default();
        g.on_manager_status(Mono::ZERO, (0, 0), ME, 1);
        g.aim(0.0, -1.0);
        send(&mut g, Mono::ZERO);
        let said = g.on_ack(Mono::ZERO, CONFIGURE, DENIED).expect("said");
        assert!(said.contains("MNT_MODE_IN=4"), "{said}");
        assert_eq!(g.control(), Control::Released);
        assert!(send(&mut g, ms(1000)).is_empty(), "not again at once");
        assert_eq!(send(&mut g, ms(3000))[0].0, CONFIGURE);
        assert!(g.on_ack(ms(3000), CONFIGURE, DENIED).is_none(), "said once");
    }

    /// QGroundControl takes the gimbal while mavloc points it (audit, session 37: mavloc
    /// took it back within 0.3 s, every time). mavloc's next setpoint is refused, the
    /// manager's status names the holder: mavloc sends nothing, not even a CONFIGURE,
    /// until the holder lets go; then it takes control again.
    #[test]
    fn another_controller_holding_the_gimbal_is_left_alone_until_it_lets_go() {
        let mut g = in_control(Mono::ZERO);
        g.aim(0.1, -1.0);
        send(&mut g, ms(1000));
        assert!(g.on_ack(ms(1000), PITCHYAW, DENIED).is_none(), "the status names the holder");
        let said = g.on_manager_status(ms(1500), QGC, ME, 1).expect("the holder is named");
        assert!(said.contains("ground station (255/190)"), "{said}");
        assert_eq!(g.control(), Control::Yielded(QGC));
        for t in (1600..60_000).step_by(100) {
            g.aim(0.1, -1.0);
            g.on_timeout(ms(t));
            assert!(send(&mut g, ms(t)).is_empty(), "nothing sent at {t} ms");
            if t % 2000 == 0 {
                assert!(g.on_manager_status(ms(t), QGC, ME, 1).is_none(), "said once");
            }
        }
        let said = g.on_manager_status(ms(60_000), (0, 0), ME, 1).expect("the release is said");
        assert!(said.contains("let go"), "{said}");
        g.aim(0.1, -1.0);
        assert_eq!(send(&mut g, ms(60_100))[0].0, CONFIGURE);
        // The autopilot itself (RTL) is named as such.
        let mut g = in_control(Mono::ZERO);
        let said = g.on_manager_status(ms(500), (1, 1), ME, 1).unwrap();
        assert!(said.contains("the autopilot"), "{said}");
    }

    /// At start, a ground station may hold the gimbal already: no CONFIGURE until the
    /// manager's first status had time to say so, and none at all when it names a holder.
    #[test]
    fn control_is_not_taken_before_the_manager_could_say_who_holds_it() {
        let mut g = Gimbal::default();
        g.aim(0.0, -1.0);
        assert!(send(&mut g, Mono::ZERO).is_empty());
        assert_eq!(g.deadline(), Some(Mono::ZERO + FIRST_STATUS_WAIT));
        assert!(g.on_manager_status(ms(1000), QGC, ME, 1).is_some());
        g.aim(0.0, -1.0);
        assert!(send(&mut g, ms(5000)).is_empty(), "held by the ground station");
        // A manager that sends no status: control is asked after the wait.
        let mut g = Gimbal::default();
        g.aim(0.0, -1.0);
        assert!(send(&mut g, ms(2900)).is_empty());
        assert!(send(&mut g, ms(2900) + FIRST_STATUS_WAIT).iter().any(|c| c.0 == CONFIGURE));
    }

    /// A manager that refuses setpoints and sends no status (so cannot say who holds the
    /// gimbal) is told of once per time it happens, and asked for control after
    /// [`RETAKE`], not at 5 Hz.
    #[test]
    fn a_refusal_without_a_status_is_said_and_control_asked_after_a_while() {
        let mut g = Gimbal::default();
        g.aim(0.0, -1.0);
        assert!(send(&mut g, Mono::ZERO).is_empty());
        let t0 = Mono::ZERO + FIRST_STATUS_WAIT;
        assert_eq!(send(&mut g, t0)[0].0, CONFIGURE);
        g.on_ack(t0, CONFIGURE, OK);
        g.aim(0.0, -1.0);
        send(&mut g, t0);
        g.on_ack(t0, PITCHYAW, OK);
        g.aim(0.0, -1.0);
        send(&mut g, t0 + MIN_INTERVAL);
        let said = g.on_ack(t0 + MIN_INTERVAL, PITCHYAW, DENIED).expect("said");
        assert!(said.contains("another controller took the gimbal"), "{said}");
        g.aim(0.0, -1.0);
        assert!(send(&mut g, t0 + Duration::from_secs(2)).is_empty());
        g.on_timeout(t0 + MIN_INTERVAL + RETAKE);
        assert_eq!(send(&mut g, t0 + MIN_INTERVAL + RETAKE)[0].0, CONFIGURE);
    }

    /// PX4 with no gimbal manager (MNT_MODE_IN = -1, its default) answers nothing: one
    /// warning naming the parameter, no setpoints into the void, a CONFIGURE every 10 s.
    #[test]
    fn an_unanswered_configure_is_said_once_and_retried_quietly() {
        let mut g = Gimbal::default();
        g.on_manager_status(Mono::ZERO, (0, 0), ME, 1);
        let mut configures = 0;
        let mut said = Vec::new();
        for t in (0..30_000).step_by(100) {
            g.aim(0.0, -1.0);
            if let Some(line) = g.on_timeout(ms(t)) {
                said.push(line);
            }
            for c in send(&mut g, ms(t)) {
                assert_eq!(c.0, CONFIGURE, "no setpoint before control");
                configures += 1;
            }
        }
        assert_eq!(said.len(), 1, "{said:?}");
        assert!(said[0].contains("MNT_MODE_IN=4"), "{}", said[0]);
        assert_eq!(configures, 3, "at 0, 13 and 26 s");
    }

    /// The vehicle lands (PX4's RTL levelled the camera when it began, and mavloc took the
    /// gimbal again for the return leg): the camera is levelled, as PX4 does for the
    /// touchdown, then let go; nothing more is sent while landing.
    #[test]
    fn a_landing_levels_the_camera_then_lets_go() {
        let mut g = in_control(Mono::ZERO);
        g.aim(0.1, -1.0);
        let level = g.poll_transmit(ms(300), 1, ME, Aim::Landing).unwrap();
        let MavMessage::COMMAND_LONG(c) = &level else { panic!("{level:?}") };
        assert_eq!((c.command, c.param5), (PITCHYAW, 2.0), "GIMBAL_MANAGER_FLAGS_NEUTRAL");
        assert!(c.param1.is_nan() && c.param2.is_nan(), "no angles: the gimbal's neutral");
        let let_go = command(&g.poll_transmit(ms(300), 1, ME, Aim::Landing).unwrap());
        assert_eq!((let_go.0, let_go.1), (CONFIGURE, [-3.0, -3.0]));
        for t in (400..10_000).step_by(100) {
            g.aim(0.1, -1.0);
            g.on_timeout(ms(t));
            assert!(g.poll_transmit(ms(t), 1, ME, Aim::Landing).is_none());
        }
    }

    /// The manager's answer to mavloc's CONFIGURE is lost, but its status names mavloc:
    /// mavloc is in control and points the gimbal, with no false hint of a missing manager.
    #[test]
    fn a_status_naming_mavloc_stands_for_a_lost_answer() {
        let mut g = Gimbal::default();
        g.on_manager_status(Mono::ZERO, (0, 0), ME, 1);
        g.aim(0.0, -1.0);
        assert_eq!(send(&mut g, Mono::ZERO)[0].0, CONFIGURE);
        assert!(g.on_manager_status(ms(500), ME, ME, 1).is_none());
        assert_eq!(g.control(), Control::InControl);
        g.aim(0.0, -1.0);
        assert_eq!(send(&mut g, ms(600))[0].0, PITCHYAW);
        assert_eq!(g.on_timeout(ms(5000)), None);
    }

    /// A manager that refuses CONFIGURE and streams its status is asked again after
    /// [`RETAKE`], not at each status (only the wait for the first status ends with it).
    #[test]
    fn a_refused_configure_is_not_asked_again_at_each_status() {
        let mut g = Gimbal::default();
        g.on_manager_status(Mono::ZERO, (0, 0), ME, 1);
        let mut configures = 0;
        for t in (0..2900).step_by(100) {
            g.aim(0.0, -1.0);
            if t % 500 == 0 {
                g.on_manager_status(ms(t), (0, 0), ME, 1);
            }
            for c in send(&mut g, ms(t)) {
                configures += 1;
                g.on_ack(ms(t), c.0, DENIED);
            }
        }
        assert_eq!(configures, 1);
    }

    /// mavloc lets go of the gimbal when it stops aiming (GMB_AIM set back to the mission,
    /// the vehicle landing: the autopilot levels the camera for the touchdown) or shuts down: a manager keeps a departed primary and refuses everyone else.
    #[test]
    fn control_is_let_go_when_aiming_stops_or_the_daemon_does() {
        let let_go = |m: Option<MavMessage>| match m {
            Some(MavMessage::COMMAND_LONG(c)) => {
                c.command == CONFIGURE && c.param1 == -3.0 && c.param2 == -3.0
            }
            _ => false,
        };
        let mut g = in_control(Mono::ZERO);
        assert!(let_go(g.poll_transmit(ms(300), 1, ME, Aim::Off)));
        assert_eq!(g.control(), Control::Released);
        assert!(g.poll_transmit(ms(400), 1, ME, Aim::Off).is_none(), "once");
        let mut g = in_control(Mono::ZERO);
        g.let_go();
        assert_eq!(g.deadline(), Some(Mono::ZERO));
        assert!(let_go(g.poll_transmit(ms(300), 1, ME, Aim::On)));
        // Not held: nothing to let go.
        let mut g = Gimbal::default();
        g.let_go();
        assert!(g.poll_transmit(ms(300), 1, ME, Aim::Off).is_none());
    }
}
