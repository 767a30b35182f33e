//! Why no autopilot is found yet. Once [`WAIT`] has passed with the link up and no
//! autopilot since mavloc started, the link's own evidence names the usual cause, the
//! first thing an integrator wiring a companion computer to PX4 needs to know:
//!
//! * frames from a system that is neither the autopilot's nor the ground station's: a
//!   vehicle whose `MAV_SYS_ID` is not `mavlink.autopilot_system_id`;
//! * frames whose signature does not check: another signing key than the autopilot's;
//! * unsigned frames dropped because signing is on and unsigned telemetry is refused;
//! * bytes with no MAVLink frame in them (or frames that fail their checks): a baud rate
//!   other than the autopilot's (PX4's `SER_TEL2_BAUD`), or a port that speaks something
//!   else;
//! * only the ground station, or only other components of the vehicle, or nothing at all:
//!   a port the autopilot sends no MAVLink on (PX4's `MAV_1_CONFIG`), a wiring fault, or a
//!   router with no endpoint here.
//!
//! Said once, and again only when the evidence changes (the baud rate fixed, say), so a
//! bench run with no autopilot at all logs it once; a link that goes down and up starts the
//! wait again but says nothing it said before unless the evidence has changed in between.
//! Nothing is said after the autopilot has been found: its loss has its own warning.

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
/// Rejected frames (bad CRC, bad signature) beyond one cut when the port opened.
const REJECTED_MIN: u64 = 3;
/// Senders listed in the message, at most.
const HEARD_MAX: usize = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Evidence {
    OtherSystems,
    BadSignatures,
    Unsigned,
    Junk,
    /// Nothing from the autopilot: silence, or only the ground station or the vehicle's
    /// other components.
    NoAutopilot,
}

/// The link's counters at the start of the wait.
#[derive(Clone, Copy, Debug, Default)]
struct Base {
    junk: u64,
    bad_frames: u64,
    bad_signatures: u64,
    unsigned: u64,
}

#[derive(Debug)]
pub struct Waiting {
    /// Waiting since; `None` once the autopilot has been found.
    since: Option<Mono>,
    base: Base,
    /// (system, component) of the frames accepted while waiting.
    heard: BTreeSet<(u8, u8)>,
    /// Unsigned frames dropped with signing on (the core's count, not the link's).
    unsigned: u64,
    said: Option<Evidence>,
    /// The short form of the evidence now, for systemd's status line and `status.json`.
    short: Option<&'static str>,
    /// Whether `short` is of the link as it is now: not while it is down, nor before the
    /// wait since it came up is over.
    current: bool,
}

impl Default for Waiting {
    fn default() -> Self {
        Waiting {
            since: Some(Mono::ZERO),
            base: Base::default(),
            heard: BTreeSet::new(),
            unsigned: 0,
            said: None,
            short: None,
            current: false,
        }
    }
}

impl Waiting {
    /// A frame accepted from `from` (system, component) while no autopilot is known.
    pub fn heard(&mut self, from: (u8, u8)) {
        if self.since.is_some() && self.heard.len() < HEARD_MAX {
            self.heard.insert(from);
        }
    }

    /// An unsigned frame dropped because signing is on.
    pub fn unsigned(&mut self) {
        self.unsigned += 1;
    }

    /// The autopilot is found: nothing more to say in this run.
    pub fn found(&mut self) {
        self.since = None;
        self.heard.clear();
    }

    /// Why no autopilot, in short, while it is still missing and the link has been up for
    /// the wait.
    pub fn note(&self) -> Option<&'static str> {
        self.since.and(self.short).filter(|_| self.current)
    }

    /// The shell's counters, once a second: what to say now, if anything, as a log line
    /// and a short STATUSTEXT. `gcs` is the ground station's system id.
    pub fn on_stats(
        &mut self,
        now: Mono,
        s: &ShellStats,
        connection: &str,
        autopilot: u8,
        gcs: u8,
    ) -> Option<(String, &'static str)> {
        let since = self.since?;
        if !s.link_up {
            // The link's own warning says why it is down; the wait starts when it is up.
            self.since = Some(now);
            self.base = Base {
                junk: s.link_garbage_bytes,
                bad_frames: s.link_bad_frames,
                bad_signatures: s.link_bad_signatures,
                unsigned: self.unsigned,
            };
            self.heard.clear();
            self.current = false;
            return None;
        }
        if now.0.saturating_sub(since.0) < WAIT.as_micros() as u64 {
            return None;
        }
        let junk = s.link_garbage_bytes.saturating_sub(self.base.junk);
        let bad_signatures = s.link_bad_signatures.saturating_sub(self.base.bad_signatures);
        let bad_frames =
            s.link_bad_frames.saturating_sub(self.base.bad_frames).saturating_sub(bad_signatures);
        let unsigned = self.unsigned - self.base.unsigned;
        let strangers: Vec<&(u8, u8)> =
            self.heard.iter().filter(|(sys, _)| *sys != autopilot && *sys != gcs).collect();
        let evidence = if !strangers.is_empty() {
            Evidence::OtherSystems
        } else if bad_signatures >= REJECTED_MIN {
            Evidence::BadSignatures
        } else if unsigned >= REJECTED_MIN {
            Evidence::Unsigned
        } else if junk >= JUNK_MIN || bad_frames >= REJECTED_MIN {
            Evidence::Junk
        } else {
            Evidence::NoAutopilot
        };
        let waited = WAIT.as_secs();
        let list = |senders: &[&(u8, u8)]| -> String {
            senders.iter().map(|(s, c)| format!("{s}/{c}")).collect::<Vec<_>>().join(", ")
        };
        let link = LinkAddress::parse(connection).ok();
        let serial = match &link {
            Some(LinkAddress::Serial { device, baud }) => Some((device.as_str(), *baud)),
            _ => None,
        };
        let said = match evidence {
            Evidence::OtherSystems => (
                format!(
                    "no autopilot after {waited} s: frames from {} (system/component), which is neither the autopilot \
                     (system {autopilot}) nor the ground station (system {gcs}): is mavlink.autopilot_system_id the \
                     vehicle's MAV_SYS_ID?",
                    list(&strangers)
                ),
                "no autopilot: another system id heard",
            ),
            Evidence::BadSignatures => (
                format!(
                    "no autopilot after {waited} s: {bad_signatures} frames whose signature does not check: is \
                     mavlink.signing_key the autopilot's key?"
                ),
                "no autopilot: signatures do not check",
            ),
            Evidence::Unsigned => (
                format!(
                    "no autopilot after {waited} s: {unsigned} unsigned frames dropped, since signing is on and \
                     mavlink.accept_unsigned_telemetry is false: sign the autopilot's link too, or accept its \
                     unsigned telemetry"
                ),
                "no autopilot: its frames are unsigned",
            ),
            Evidence::Junk => {
                let what = if bad_frames > 0 {
                    format!("{junk} bytes and {bad_frames} frames that fail their checks (CRC, length or message id)")
                } else {
                    format!("{junk} bytes")
                };
                match serial {
                    Some((device, baud)) => (
                        format!(
                            "no autopilot after {waited} s: {what} on {device} but no MAVLink frame that checks: \
                             does the autopilot send at {baud} baud (PX4: SER_TEL2_BAUD for TELEM2), and MAVLink \
                             on that port (MAV_1_CONFIG)?"
                        ),
                        "no autopilot: bytes, no frame (baud rate?)",
                    ),
                    None => (
                        format!("no autopilot after {waited} s: {what} on {connection} but no MAVLink frame that checks"),
                        "no autopilot: bytes, no MAVLink frame",
                    ),
                }
            }
            Evidence::NoAutopilot => {
                let heard: Vec<&(u8, u8)> = self.heard.iter().collect();
                let what = if heard.is_empty() {
                    "nothing heard".to_string()
                } else {
                    format!("only {} (system/component) heard, nothing from the autopilot ({autopilot}/1)", list(&heard))
                };
                match (serial, &link) {
                    (Some((device, baud)), _) => (
                        format!(
                            "no autopilot after {waited} s: {what} on {device}: is the autopilot's MAVLink on that \
                             port (PX4: MAV_1_CONFIG = TELEM 2, MAV_1_MODE = Onboard, SER_TEL2_BAUD = {baud}), and \
                             its TX wired to this port's RX?"
                        ),
                        "no autopilot: nothing from it heard",
                    ),
                    (None, Some(LinkAddress::UdpIn { host, port })) => (
                        format!(
                            "no autopilot after {waited} s: {what} on udp {}: is the autopilot or \
                             mavlink-router sending there (PX4 SITL's onboard link: 14540)?",
                            crate::settings::address::host_port(host, *port)
                        ),
                        "no autopilot: nothing from it heard",
                    ),
                    _ => (format!("no autopilot after {waited} s: {what} on {connection}"), "no autopilot: nothing from it heard"),
                }
            }
        };
        // Worked out each second (a few strings): the status line follows the evidence,
        // the log says it only when it changes.
        self.short = Some(said.1);
        self.current = true;
        if self.said == Some(evidence) {
            return None;
        }
        self.said = Some(evidence);
        Some(said)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn up(junk: u64) -> ShellStats {
        ShellStats { link_garbage_bytes: junk, link_up: true, ..Default::default() }
    }

    fn at(s: u64) -> Mono {
        Mono::from_millis(s * 1000)
    }

    const SERIAL: &str = "serial:/dev/ttyAMA0:921600";
    const UDP: &str = "udpin:127.0.0.1:14540";

    /// Once a second for `from..to` s with the same counters: what was said, with when.
    fn said(w: &mut Waiting, from: u64, to: u64, s: &ShellStats, link: &str) -> Vec<(u64, String)> {
        (from..to).filter_map(|t| w.on_stats(at(t), s, link, 1, 255).map(|(log, _)| (t, log))).collect()
    }

    #[test]
    fn nothing_is_said_before_the_wait_nor_twice_for_the_same_evidence() {
        let mut w = Waiting::default();
        let silence = said(&mut w, 1, 130, &up(0), SERIAL);
        assert_eq!(silence.len(), 1, "{silence:?}");
        let (t, log) = &silence[0];
        assert_eq!(*t, 10);
        assert!(
            log.contains("nothing heard on /dev/ttyAMA0") && log.contains("SER_TEL2_BAUD = 921600"),
            "{log}"
        );
        // The evidence changes: said again, with what it now points at, once.
        let noise = said(&mut w, 130, 260, &up(5000), SERIAL);
        assert_eq!(noise.len(), 1, "{noise:?}");
        assert!(
            noise[0].1.contains("5000 bytes on /dev/ttyAMA0") && noise[0].1.contains("921600 baud"),
            "{noise:?}"
        );
        // Every short text fits one STATUSTEXT.
        let mut w = Waiting::default();
        let (_, short) = w.on_stats(at(10), &up(0), SERIAL, 1, 255).unwrap();
        assert!(short.len() <= 50, "{short}");
    }

    #[test]
    fn a_down_link_restarts_the_wait_and_a_found_autopilot_ends_it() {
        let mut w = Waiting::default();
        let down = ShellStats { link_up: false, link_garbage_bytes: 900, ..Default::default() };
        assert_eq!(w.on_stats(at(20), &down, SERIAL, 1, 255), None);
        // Up at 20 s with 900 bytes counted before: not junk, and not before 30 s.
        let after = said(&mut w, 21, 60, &up(950), SERIAL);
        assert_eq!(after.len(), 1, "{after:?}");
        assert!(after[0].0 == 30 && after[0].1.contains("nothing heard"), "{after:?}");
        // Down and up again with the same silence: not said again, and the status line
        // carries no diagnosis while the link is down or before the wait is over again.
        assert_eq!(w.note(), Some("no autopilot: nothing from it heard"));
        assert_eq!(w.on_stats(at(60), &down, SERIAL, 1, 255), None);
        assert_eq!(w.note(), None, "an unplugged device is not a missing autopilot");
        assert!(said(&mut w, 61, 70, &up(950), SERIAL).is_empty());
        assert_eq!(w.note(), None, "not before the wait since the link came up");
        assert!(said(&mut w, 70, 120, &up(950), SERIAL).is_empty());
        assert_eq!(w.note(), Some("no autopilot: nothing from it heard"));
        w.found();
        assert_eq!(w.note(), None, "found: no longer missing");
        assert!(said(&mut w, 120, 200, &up(90_000), SERIAL).is_empty());
    }

    #[test]
    fn another_system_is_named_with_the_system_id_setting_and_a_ground_station_alone_is_not() {
        let mut w = Waiting::default();
        w.heard((255, 190));
        let (log, _) = w.on_stats(at(10), &up(0), UDP, 1, 255).unwrap();
        assert!(log.contains("only 255/190") && log.contains("nothing from the autopilot (1/1)"), "{log}");
        assert!(!log.contains("MAV_SYS_ID"), "a ground station alone says nothing of the system id: {log}");
        // The vehicle's other components (a gimbal) do not make it another system either.
        w.heard((1, 154));
        assert_eq!(w.on_stats(at(11), &up(0), UDP, 1, 255), None);
        w.heard((2, 1));
        let (log, _) = w.on_stats(at(12), &up(0), UDP, 1, 255).unwrap();
        assert!(log.contains("frames from 2/1") && log.contains("MAV_SYS_ID"), "{log}");
    }

    #[test]
    fn rejected_frames_are_named_by_why() {
        let mut w = Waiting::default();
        let signed_wrong =
            ShellStats { link_up: true, link_bad_frames: 40, link_bad_signatures: 40, ..Default::default() };
        let (log, _) = w.on_stats(at(10), &signed_wrong, UDP, 1, 255).unwrap();
        assert!(
            log.contains("40 frames whose signature does not check") && log.contains("signing_key"),
            "{log}"
        );
        let mut w = Waiting::default();
        for _ in 0..40 {
            w.unsigned();
        }
        let (log, _) = w.on_stats(at(10), &up(0), UDP, 1, 255).unwrap();
        assert!(log.contains("40 unsigned frames dropped"), "{log}");
        let mut w = Waiting::default();
        let bad_crc = ShellStats { link_up: true, link_bad_frames: 12, ..Default::default() };
        let (log, _) = w.on_stats(at(10), &bad_crc, SERIAL, 1, 255).unwrap();
        assert!(
            log.contains("12 frames that fail their checks (CRC, length or message id)")
                && log.contains("921600 baud"),
            "{log}"
        );
        // Silence over udp names its port.
        let mut w = Waiting::default();
        let (log, _) = w.on_stats(at(10), &up(0), UDP, 1, 255).unwrap();
        assert!(log.contains("nothing heard on udp 127.0.0.1:14540"), "{log}");
    }
}
