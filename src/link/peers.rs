//! Who a listening link (`udpin`, `tcpin`) talks to, decided without I/O.
//!
//! A listening socket hears anyone who can reach it. If the last datagram's sender
//! became the destination, as mavproxy's and the first mavloc's `udpin` did, one stray or
//! hostile packet would redirect every message and cut the autopilot off. So a sender
//! becomes a peer only by a frame that *vouches* for it ([`Trust::vouches`]): checked,
//! from the configured autopilot's or ground station's system id, and signed when signing
//! is on. Peers are kept while they keep vouching; a new one is added beside the others
//! (output goes to all, as mavlink-router fans out to its endpoints), never instead of
//! one, so no frame can take the autopilot's place. The table is bounded: when it is
//! full, newcomers wait until a peer falls silent.

use std::net::SocketAddr;
use std::time::Duration;

use tokio::time::Instant;

use super::codec::{Auth, Frame};

/// A peer that sends no vouching frame for this long is forgotten. PX4 and ground
/// stations send a heartbeat every second; ten missed ones mean it is gone.
pub const PEER_EXPIRY: Duration = Duration::from_secs(10);

/// At most this many peers at once (an autopilot, a few ground stations or routers).
pub const MAX_PEERS: usize = 8;

/// Which frames make their sender a peer.
#[derive(Clone, Debug)]
pub struct Trust {
    pub autopilot_system_id: u8,
    pub gcs_system_id: u8,
    /// Signing is on: a vouching frame must carry a valid signature...
    pub signing: bool,
    /// ...except the autopilot's, when unsigned telemetry is accepted (an autopilot that
    /// does not sign could otherwise never be answered).
    pub accept_unsigned_telemetry: bool,
}

impl Trust {
    /// Does this checked frame make its sender someone mavloc talks to?
    pub fn vouches(&self, f: &Frame) -> bool {
        let Ok(sys) = u8::try_from(f.header.system_id) else { return false };
        let autopilot = sys == self.autopilot_system_id;
        if !autopilot && sys != self.gcs_system_id {
            return false;
        }
        !self.signing || f.auth == Auth::Signed || (autopilot && self.accept_unsigned_telemetry)
    }
}

/// What [`Peers::heard`] made of a vouching frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Heard {
    Known,
    Added,
    /// The table is full: not added (counted by the caller).
    Full,
}

/// The peers of a listening link, by address.
#[derive(Debug, Default)]
pub struct Peers {
    entries: Vec<(SocketAddr, Instant)>,
}

impl Peers {
    /// A vouching frame came from `from` at `now`.
    pub fn heard(&mut self, from: SocketAddr, now: Instant) -> Heard {
        self.expire(now);
        if let Some(e) = self.entries.iter_mut().find(|(a, _)| *a == from) {
            e.1 = now;
            return Heard::Known;
        }
        if self.entries.len() >= MAX_PEERS {
            return Heard::Full;
        }
        self.entries.push((from, now));
        Heard::Added
    }

    /// Forgets peers silent for [`PEER_EXPIRY`]; returns them.
    pub fn expire(&mut self, now: Instant) -> Vec<SocketAddr> {
        let mut gone = Vec::new();
        self.entries.retain(|&(a, t)| {
            let keep = now.saturating_duration_since(t) < PEER_EXPIRY;
            if !keep {
                gone.push(a);
            }
            keep
        });
        gone
    }

    pub fn addresses(&self) -> impl Iterator<Item = SocketAddr> + '_ {
        self.entries.iter().map(|(a, _)| *a)
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{MavMessage, HEARTBEAT_DATA};
    use mavlink::{MavHeader, MavlinkVersion};

    fn frame(sys: u32, auth: Auth) -> Frame {
        Frame {
            version: MavlinkVersion::V2,
            header: MavHeader { system_id: sys, component_id: 1, sequence: 0 },
            message: MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
            auth,
            unknown_command: None,
        }
    }

    fn trust(signing: bool, unsigned_telemetry: bool) -> Trust {
        Trust {
            autopilot_system_id: 1,
            gcs_system_id: 255,
            signing,
            accept_unsigned_telemetry: unsigned_telemetry,
        }
    }

    #[test]
    fn only_the_autopilot_and_the_ground_station_vouch_and_signed_when_signing() {
        let open = trust(false, true);
        assert!(open.vouches(&frame(1, Auth::Unsigned)));
        assert!(open.vouches(&frame(255, Auth::Unsigned)));
        assert!(!open.vouches(&frame(42, Auth::Unsigned)), "a foreign system id is nobody");
        assert!(!open.vouches(&frame(1 + 256, Auth::Unsigned)), "an id over 255 is not 1");
        let strict = trust(true, false);
        assert!(!strict.vouches(&frame(1, Auth::Unsigned)));
        assert!(!strict.vouches(&frame(255, Auth::Unsigned)));
        assert!(strict.vouches(&frame(1, Auth::Signed)));
        assert!(strict.vouches(&frame(255, Auth::Signed)));
        assert!(!strict.vouches(&frame(42, Auth::Signed)));
        let telemetry = trust(true, true);
        assert!(telemetry.vouches(&frame(1, Auth::Unsigned)));
        assert!(!telemetry.vouches(&frame(255, Auth::Unsigned)), "a GCS must sign");
    }

    #[tokio::test(start_paused = true)]
    async fn a_newcomer_is_added_beside_the_others_and_silence_expires() {
        let a: SocketAddr = "127.0.0.1:14580".parse().unwrap();
        let b: SocketAddr = "127.0.0.1:14550".parse().unwrap();
        let mut p = Peers::default();
        let t0 = Instant::now();
        assert_eq!(p.heard(a, t0), Heard::Added);
        assert_eq!(p.heard(b, t0 + Duration::from_secs(5)), Heard::Added);
        assert_eq!(p.heard(a, t0 + Duration::from_secs(6)), Heard::Known);
        assert_eq!(p.addresses().collect::<Vec<_>>(), vec![a, b]);
        // b said nothing since t0 + 5 s.
        assert_eq!(p.expire(t0 + Duration::from_secs(15)), vec![b]);
        assert_eq!(p.addresses().collect::<Vec<_>>(), vec![a]);
    }

    #[tokio::test(start_paused = true)]
    async fn a_full_table_keeps_its_peers() {
        let mut p = Peers::default();
        let t0 = Instant::now();
        for i in 0..MAX_PEERS {
            let addr = SocketAddr::from(([127, 0, 0, 1], 20000 + i as u16));
            assert_eq!(p.heard(addr, t0), Heard::Added);
        }
        let late = SocketAddr::from(([127, 0, 0, 1], 30000));
        assert_eq!(p.heard(late, t0), Heard::Full);
        assert_eq!(p.len(), MAX_PEERS);
        assert!(!p.addresses().any(|a| a == late));
    }
}
