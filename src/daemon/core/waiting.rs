//! Why no autopilot is found yet. Once [`WAIT`] has passed with the link up and no
//! autopilot since mavloc started, the link's own evidence names the usual cause, the
//! first thing an integrator wiring a companion computer to PX4 needs to know:
//!
//! * bytes with no MAVLink frame in them: a baud rate other than the autopilot's (PX4's
//!   `SER_TEL2_BAUD`), or a port that speaks something else;
//! * frames, but only from other systems or components: a vehicle whose `MAV_SYS_ID` is
//!   not `mavlink.autopilot_system_id`, or a ground station alone;
//! * frames, none accepted: with signing on, unsigned telemetry;
//! * silence: a port the autopilot sends no MAVLink on (PX4's `MAV_1_CONFIG`), a wiring
//!   fault, or a router with no endpoint here.
//!
//! Said once, and again only when the evidence changes (the baud rate fixed, say), so a
//! bench run with no autopilot at all logs it once. Nothing is said after the autopilot has
//! been found: its loss has its own warning.

use std::collections::BTreeSet;
use std::time::Duration;

use super::time::Mono;
use super::ShellStats;
use crate::settings::LinkAddress;

/// How long mavloc waits for the autopilot before it says why none came. PX4 sends its
/// heartbeat at 1 Hz from boot, and a link comes up in well under a second.
pub const WAIT: Duration = Duration::from_secs(10);
/// Bytes that are not MAVLink beyond what one frame cut when the port opened leaves.
const JUNK_MIN: u64 = 64;
/// Senders listed in the message, at most.
const HEARD_MAX: usize = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Evidence {
    Silence,
    Junk,
    Unaccepted,
    OthersOnly,
}

#[derive(Debug)]
pub struct Waiting {
    /// Waiting since; `None` once the autopilot has been found.
    since: Option<Mono>,
    /// The link's frames in and bytes skipped when the wait began.
    base: (u64, u64),
    /// (system, component) of the frames accepted while waiting.
    heard: BTreeSet<(u8, u8)>,
    said: Option<Evidence>,
}

impl Default for Waiting {
    fn default() -> Self {
        Waiting { since: Some(Mono::ZERO), base: (0, 0), heard: BTreeSet::new(), said: None }
    }
}

impl Waiting {
    /// A frame accepted from `from` (system, component) while no autopilot is known.
    pub fn heard(&mut self, from: (u8, u8)) {
        if self.since.is_some() && self.heard.len() < HEARD_MAX {
            self.heard.insert(from);
        }
    }

    /// The autopilot is found: nothing more to say in this run.
    pub fn found(&mut self) {
        self.since = None;
        self.heard.clear();
    }

    /// The shell's counters, once a second: what to say now, if anything, as a log line
    /// and a short STATUSTEXT.
    pub fn on_stats(
        &mut self,
        now: Mono,
        s: &ShellStats,
        connection: &str,
        autopilot: u8,
        signing: bool,
    ) -> Option<(String, &'static str)> {
        let since = self.since?;
        let junk = s.link_garbage_bytes;
        if !s.link_up {
            // The link's own warning says why it is down; the wait starts when it is up.
            self.since = Some(now);
            self.base = (s.link_in, junk);
            self.heard.clear();
            return None;
        }
        if now.0.saturating_sub(since.0) < WAIT.as_micros() as u64 {
            return None;
        }
        let frames = s.link_in.saturating_sub(self.base.0);
        let junk = junk.saturating_sub(self.base.1);
        let evidence = if !self.heard.is_empty() {
            Evidence::OthersOnly
        } else if frames > 0 && signing {
            Evidence::Unaccepted
        } else if junk >= JUNK_MIN {
            Evidence::Junk
        } else {
            Evidence::Silence
        };
        if self.said == Some(evidence) {
            return None;
        }
        self.said = Some(evidence);
        let waited = WAIT.as_secs();
        let link = LinkAddress::parse(connection).ok();
        let serial = match &link {
            Some(LinkAddress::Serial { device, baud }) => Some((device.as_str(), *baud)),
            _ => None,
        };
        let said = match evidence {
            Evidence::OthersOnly => {
                let who: Vec<String> = self.heard.iter().map(|(s, c)| format!("{s}/{c}")).collect();
                (
                    format!(
                        "no autopilot after {waited} s: frames from {} (system/component) but no heartbeat from the autopilot, \
                         system {autopilot} component 1: is mavlink.autopilot_system_id the vehicle's MAV_SYS_ID?",
                        who.join(", ")
                    ),
                    "no autopilot: other system ids only",
                )
            }
            Evidence::Unaccepted => (
                format!(
                    "no autopilot after {waited} s: {frames} frames arrived but none was signed, and signing is on: \
                     sign the autopilot's link too, or set mavlink.accept_unsigned_telemetry"
                ),
                "no autopilot: its frames are unsigned",
            ),
            Evidence::Junk => match serial {
                Some((device, baud)) => (
                    format!(
                        "no autopilot after {waited} s: {junk} bytes on {device} but no MAVLink frame in them: \
                         does the autopilot send at {baud} baud (PX4: SER_TEL2_BAUD for TELEM2), and MAVLink \
                         on that port (MAV_1_CONFIG)?"
                    ),
                    "no autopilot: bytes, no frame (baud rate?)",
                ),
                None => (
                    format!("no autopilot after {waited} s: {junk} bytes on {connection} but no MAVLink frame in them"),
                    "no autopilot: bytes, no MAVLink frame",
                ),
            },
            Evidence::Silence => match (serial, &link) {
                (Some((device, baud)), _) => (
                    format!(
                        "no autopilot after {waited} s: nothing heard on {device}: is the autopilot's MAVLink on \
                         that port (PX4: MAV_1_CONFIG = TELEM 2, MAV_1_MODE = Onboard, SER_TEL2_BAUD = {baud}), \
                         and its TX wired to this port's RX?"
                    ),
                    "no autopilot: nothing heard",
                ),
                (None, Some(LinkAddress::UdpIn { host, port })) => (
                    format!(
                        "no autopilot after {waited} s: nothing heard on udp {host}:{port}: is the autopilot or \
                         mavlink-router sending there (PX4 SITL's onboard link: 14540)?"
                    ),
                    "no autopilot: nothing heard",
                ),
                _ => (
                    format!("no autopilot after {waited} s: nothing heard on {connection}"),
                    "no autopilot: nothing heard",
                ),
            },
        };
        Some(said)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn up(link_in: u64, junk: u64) -> ShellStats {
        ShellStats { link_in, link_garbage_bytes: junk, link_up: true, ..Default::default() }
    }

    fn at(s: u64) -> Mono {
        Mono::from_millis(s * 1000)
    }

    const SERIAL: &str = "serial:/dev/ttyAMA0:921600";

    #[test]
    fn nothing_is_said_before_the_wait_nor_twice_for_the_same_evidence() {
        let mut w = Waiting::default();
        assert_eq!(w.on_stats(at(9), &up(0, 0), SERIAL, 1, false), None);
        let (log, short) = w.on_stats(at(10), &up(0, 0), SERIAL, 1, false).expect("said at 10 s");
        assert!(
            log.contains("nothing heard on /dev/ttyAMA0") && log.contains("SER_TEL2_BAUD = 921600"),
            "{log}"
        );
        assert!(short.len() <= 50, "{short}");
        assert_eq!(w.on_stats(at(60), &up(0, 10), SERIAL, 1, false), None, "the same silence, said once");
        // The evidence changes: said again, with what it now points at.
        let (log, _) = w.on_stats(at(61), &up(0, 5000), SERIAL, 1, false).expect("bytes now");
        assert!(log.contains("5000 bytes on /dev/ttyAMA0") && log.contains("921600 baud"), "{log}");
    }

    #[test]
    fn a_down_link_restarts_the_wait_and_a_found_autopilot_ends_it() {
        let mut w = Waiting::default();
        let down = ShellStats { link_up: false, link_garbage_bytes: 900, ..Default::default() };
        assert_eq!(w.on_stats(at(20), &down, SERIAL, 1, false), None);
        // Up at 20 s with 900 bytes counted before: not junk, and not before 30 s.
        assert_eq!(w.on_stats(at(29), &up(0, 900), SERIAL, 1, false), None);
        let (log, _) = w.on_stats(at(30), &up(0, 950), SERIAL, 1, false).unwrap();
        assert!(log.contains("nothing heard"), "{log}");
        w.found();
        assert_eq!(w.on_stats(at(100), &up(0, 90_000), SERIAL, 1, false), None);
    }

    #[test]
    fn frames_from_others_only_name_them_and_the_system_id_setting() {
        let mut w = Waiting::default();
        w.heard((255, 190));
        w.heard((2, 1));
        let (log, _) = w.on_stats(at(10), &up(40, 0), "udpin:127.0.0.1:14540", 1, false).unwrap();
        assert!(log.contains("frames from 2/1, 255/190") && log.contains("MAV_SYS_ID"), "{log}");
    }

    #[test]
    fn unsigned_frames_with_signing_on_are_named() {
        let mut w = Waiting::default();
        let (log, _) = w.on_stats(at(10), &up(40, 0), SERIAL, 1, true).unwrap();
        assert!(log.contains("40 frames arrived but none was signed"), "{log}");
        // Without signing, frames that were not heard cannot be; silence over udp names its port.
        let mut w = Waiting::default();
        let (log, _) = w.on_stats(at(10), &up(0, 0), "udpin:127.0.0.1:14540", 1, false).unwrap();
        assert!(log.contains("udp 127.0.0.1:14540") && log.contains("14540"), "{log}");
    }
}
