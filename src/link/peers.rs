//! Who a listening link (`udpin`, `tcpin`) talks to, decided without I/O.
//!
//! A listening socket hears anyone who can reach it. If the last datagram's sender
//! became the destination, as mavproxy's and the first mavloc's `udpin` did, one stray or
//! hostile packet would redirect every message and cut the autopilot off. So a sender
//! becomes a peer only by a frame that *vouches* for it ([`Trust::vouches`]): checked,
//! from the configured autopilot's or ground station's system id, and signed when signing
//! is on. Peers are kept while they keep vouching; a new one is added beside the others
//! (output goes to all, as mavlink-router fans out to its endpoints), never instead of
//! one, so no frame can take the autopilot's place. The table is bounded, and so is each
//! identity's share of it (frames claiming the autopilot's id from many ports cannot lock
//! the ground station out); when a share is full, newcomers wait until a peer falls
//! silent, except a peer that had itself fallen silent and comes back from its address
//! (an autopilot after a reboot), which takes its place back from a newcomer.

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
    /// A peer that had fallen silent came back to an identity's full share: it took the
    /// place of the newest peer that came while it was away (named here).
    Returned(SocketAddr),
    /// The table, or the identity's share of it, is full: not added (counted by the caller).
    Full,
}

/// Each identity (the system id a peer vouched with: the autopilot's or the ground
/// station's) may hold at most this many peers: frames claiming one identity from many
/// ports (unsigned, a spoofer can claim the autopilot's) cannot fill the table and lock
/// the other out.
pub const MAX_PEERS_PER_IDENTITY: usize = MAX_PEERS / 2;

/// A peer that fell silent is remembered this long: coming back from the same address
/// (an autopilot after its reboot), it finds its place even if newcomers of its identity
/// filled the share meanwhile.
pub const REMEMBER_DEPARTED: Duration = Duration::from_secs(300);

#[derive(Clone, Copy, Debug)]
struct Entry {
    addr: SocketAddr,
    identity: u8,
    heard: Instant,
    added: Instant,
}

/// The peers of a listening link, by address.
#[derive(Debug, Default)]
pub struct Peers {
    entries: Vec<Entry>,
    /// Peers that fell silent or gave way: (address, identity, when).
    departed: Vec<(SocketAddr, u8, Instant)>,
}

impl Peers {
    /// A frame vouching for `identity` (its system id) came from `from` at `now`.
    pub fn heard(&mut self, from: SocketAddr, identity: u8, now: Instant) -> Heard {
        self.expire(now);
        if let Some(e) = self.entries.iter_mut().find(|e| e.addr == from) {
            e.heard = now;
            return Heard::Known;
        }
        let share = self.entries.iter().filter(|e| e.identity == identity).count();
        let entry = Entry { addr: from, identity, heard: now, added: now };
        if share < MAX_PEERS_PER_IDENTITY && self.entries.len() < MAX_PEERS {
            self.entries.push(entry);
            self.departed.retain(|d| d.0 != from);
            return Heard::Added;
        }
        // A departed peer of this identity takes back a place from a newcomer that came
        // while it was away; a stranger cannot, and nor can anyone displace a peer that
        // was there before it left.
        let Some(&(_, _, gone)) = self.departed.iter().find(|d| d.0 == from && d.1 == identity) else {
            return Heard::Full;
        };
        let newest = self
            .entries
            .iter()
            .enumerate()
            .filter(|(_, e)| e.identity == identity && e.added > gone)
            .max_by_key(|(_, e)| e.added)
            .map(|(i, _)| i);
        let Some(i) = newest else { return Heard::Full };
        let out = self.entries.remove(i);
        self.depart(out.addr, out.identity, now);
        self.entries.push(entry);
        self.departed.retain(|d| d.0 != from);
        Heard::Returned(out.addr)
    }

    fn depart(&mut self, addr: SocketAddr, identity: u8, now: Instant) {
        self.departed.retain(|d| d.0 != addr && now.saturating_duration_since(d.2) < REMEMBER_DEPARTED);
        // Bounded: the oldest memory goes first.
        if self.departed.len() >= 4 * MAX_PEERS {
            self.departed.remove(0);
        }
        self.departed.push((addr, identity, now));
    }

    /// Forgets peers silent for [`PEER_EXPIRY`]; returns them.
    pub fn expire(&mut self, now: Instant) -> Vec<SocketAddr> {
        let (gone, kept): (Vec<Entry>, Vec<Entry>) =
            self.entries.iter().partition(|e| now.saturating_duration_since(e.heard) >= PEER_EXPIRY);
        self.entries = kept;
        for e in &gone {
            self.depart(e.addr, e.identity, e.heard + PEER_EXPIRY);
        }
        gone.into_iter().map(|e| e.addr).collect()
    }

    pub fn addresses(&self) -> impl Iterator<Item = SocketAddr> + '_ {
        self.entries.iter().map(|e| e.addr)
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
        assert_eq!(p.heard(a, 1, t0), Heard::Added);
        assert_eq!(p.heard(b, 255, t0 + Duration::from_secs(5)), Heard::Added);
        assert_eq!(p.heard(a, 1, t0 + Duration::from_secs(6)), Heard::Known);
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
            assert_eq!(p.heard(addr, if i % 2 == 0 { 1 } else { 255 }, t0), Heard::Added);
        }
        let late = SocketAddr::from(([127, 0, 0, 1], 30000));
        assert_eq!(p.heard(late, 1, t0), Heard::Full);
        assert_eq!(p.heard(late, 255, t0), Heard::Full);
        assert_eq!(p.len(), MAX_PEERS);
        assert!(!p.addresses().any(|a| a == late));
    }

    fn port(n: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], n))
    }

    /// The audit's attack: frames claiming the autopilot's system id from seven ports.
    /// They fill only the autopilot's share, so a ground station arriving later is added.
    #[tokio::test(start_paused = true)]
    async fn claims_of_one_identity_fill_only_its_share() {
        let mut p = Peers::default();
        let t0 = Instant::now();
        let autopilot = port(14580);
        assert_eq!(p.heard(autopilot, 1, t0), Heard::Added);
        let spoofed: Vec<Heard> = (0..7).map(|i| p.heard(port(40000 + i), 1, t0)).collect();
        assert_eq!(spoofed.iter().filter(|h| **h == Heard::Added).count(), MAX_PEERS_PER_IDENTITY - 1);
        assert_eq!(p.heard(port(14550), 255, t0 + Duration::from_secs(1)), Heard::Added, "the GCS");
    }

    /// The autopilot falls silent (a reboot) while spoofers hold the rest of its share and
    /// one more takes its place: back from its address, it displaces that newcomer, which
    /// cannot displace it in turn, and nor can a peer that was there before it left.
    #[tokio::test(start_paused = true)]
    async fn an_autopilot_back_from_a_reboot_takes_its_place_back_from_a_newcomer() {
        let mut p = Peers::default();
        let t0 = Instant::now();
        let autopilot = port(14580);
        assert_eq!(p.heard(autopilot, 1, t0), Heard::Added);
        for i in 0..3 {
            assert_eq!(p.heard(port(40000 + i), 1, t0), Heard::Added);
        }
        // The spoofers keep talking; the autopilot reboots and says nothing for 15 s.
        let mut now = t0;
        for _ in 0..15 {
            now += Duration::from_secs(1);
            for i in 0..3 {
                p.heard(port(40000 + i), 1, now);
            }
        }
        assert!(!p.addresses().any(|a| a == autopilot), "silent, forgotten");
        let usurper = port(40100);
        assert_eq!(p.heard(usurper, 1, now), Heard::Added);
        now += Duration::from_secs(5);
        assert_eq!(p.heard(autopilot, 1, now), Heard::Returned(usurper));
        assert!(p.addresses().any(|a| a == autopilot));
        assert_eq!(p.heard(usurper, 1, now + Duration::from_secs(1)), Heard::Full, "no ping-pong");
        // A spoofer that was a peer before, silent and back, does not displace it either.
        for _ in 0..12 {
            now += Duration::from_secs(1);
            p.heard(autopilot, 1, now);
            p.heard(port(40000), 1, now);
            p.heard(port(40001), 1, now);
        }
        assert_eq!(p.heard(port(40002), 1, now), Heard::Added, "its place was free");
        for _ in 0..12 {
            now += Duration::from_secs(1);
            p.heard(autopilot, 1, now);
            p.heard(port(40000), 1, now);
            p.heard(port(40001), 1, now);
        }
        // 40002 went silent; 40003 came meanwhile. 40002 back displaces 40003, never the
        // autopilot, which came before 40002 left.
        assert_eq!(p.heard(port(40003), 1, now), Heard::Added);
        assert_eq!(p.heard(port(40002), 1, now), Heard::Returned(port(40003)));
        assert_eq!(p.heard(port(40003), 1, now), Heard::Full, "no ping-pong");
        assert!(p.addresses().any(|a| a == autopilot));
    }
}
