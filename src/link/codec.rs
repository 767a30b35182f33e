//! MAVLink framing without I/O: bytes in, checked frames out; messages in, bytes out.
//!
//! The `mavlink` crate's readers skip what they cannot parse without telling anyone,
//! return only MAVLink 2 unless told otherwise, and check signatures with one policy for
//! every message. The daemon needs more: a count of every byte and frame it skipped (the
//! issue's "skipped and counted"), MAVLink 1 accepted in, and per-message knowledge of
//! whether a frame carried a valid signature, because commands and parameter sets need
//! one while telemetry may not. So the scanning is ours (sans-IO, fuzzed by property
//! tests); message definitions, CRC extras, payload (de)serialisation and the signature
//! hash stay the crate's.

use mavlink::dialects::common::MavMessage;
use mavlink::{MAVLinkV2MessageRaw, MavHeader, MavlinkVersion, Message};

use super::signing::{Signer, Verdict};

const STX_V1: u8 = 0xFE;
const STX_V2: u8 = 0xFD;
const IFLAG_SIGNED: u8 = 0x01;
const V1_OVERHEAD: usize = 8; // STX, 5 header bytes, 2 CRC
const V2_OVERHEAD: usize = 12; // STX, 9 header bytes, 2 CRC
const SIGNATURE_LEN: usize = 13;

/// How a frame was authenticated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Auth {
    /// No signature (MAVLink 1, or MAVLink 2 unsigned), or signed while mavloc has no key.
    Unsigned,
    /// A signature that verified against mavloc's key, with a fresh timestamp.
    Signed,
}

/// A checked, parsed frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub version: MavlinkVersion,
    pub header: MavHeader,
    pub message: MavMessage,
    pub auth: Auth,
    /// A COMMAND_LONG or COMMAND_INT whose command id the dialect does not define: the id.
    /// `message` then carries [`PLACEHOLDER_COMMAND`] in its place (the crate's typed
    /// enum cannot hold the id) and must not be acted on, only answered UNSUPPORTED.
    pub unknown_command: Option<u16>,
}

/// Stands in for a command id the dialect does not define (see [`Frame::unknown_command`]).
pub const PLACEHOLDER_COMMAND: u16 = 16; // MAV_CMD_NAV_WAYPOINT

/// COMMAND_INT (75) and COMMAND_LONG (76) both carry the command id at payload byte 28.
const COMMAND_ID_AT: usize = 28;

/// Parses a command whose id the dialect does not know: the id, and the message with
/// [`PLACEHOLDER_COMMAND`] in its place. `None` for anything else that fails to parse.
fn parse_unknown_command(version: MavlinkVersion, id: u32, payload: &[u8]) -> Option<(MavMessage, u16)> {
    if id != 75 && id != 76 {
        return None;
    }
    // MAVLink 2 drops trailing zero bytes; put them back so the id is there to read.
    let mut p = payload.to_vec();
    p.resize(p.len().max(COMMAND_ID_AT + 2), 0);
    let command = u16::from_le_bytes([p[COMMAND_ID_AT], p[COMMAND_ID_AT + 1]]);
    p[COMMAND_ID_AT..COMMAND_ID_AT + 2].copy_from_slice(&PLACEHOLDER_COMMAND.to_le_bytes());
    MavMessage::parse(version, id, &p).ok().map(|m| (m, command))
}

/// What the decoder skipped, by reason. Counted, never fatal.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SkipCounts {
    /// Bytes outside any frame (noise, other protocols).
    pub garbage_bytes: u64,
    /// Frames whose checksum did not match.
    pub bad_crc: u64,
    /// Frames with a message id the common dialect does not define.
    pub unknown_id: u64,
    /// Frames whose payload did not parse (e.g. an enum value out of range).
    pub unparseable: u64,
    /// Frames cut short: a datagram ended inside one.
    pub truncated: u64,
    /// MAVLink 2 frames with incompatibility flags mavloc does not understand.
    pub unsupported_flags: u64,
    /// Signed frames whose signature or timestamp did not verify.
    pub bad_signature: u64,
}

impl SkipCounts {
    /// Adds another decoder's counts (a link has one decoder per connection).
    pub fn add(&mut self, o: &SkipCounts) {
        self.garbage_bytes += o.garbage_bytes;
        self.bad_crc += o.bad_crc;
        self.unknown_id += o.unknown_id;
        self.unparseable += o.unparseable;
        self.truncated += o.truncated;
        self.unsupported_flags += o.unsupported_flags;
        self.bad_signature += o.bad_signature;
    }

    pub fn total_frames(&self) -> u64 {
        self.bad_crc
            + self.unknown_id
            + self.unparseable
            + self.truncated
            + self.unsupported_flags
            + self.bad_signature
    }
}

/// Finds frames in a byte stream. Feed bytes with [`Decoder::push`], take frames with
/// [`Decoder::next_frame`]; for datagram transports take them with
/// [`Decoder::next_in_datagram`], so a truncated frame cannot swallow the next datagram.
#[derive(Default)]
pub struct Decoder {
    buf: Vec<u8>,
    pos: usize,
    pub skipped: SkipCounts,
}

enum Scan {
    /// Need more bytes.
    More,
    /// Drop this many bytes (counted already) and rescan.
    Skip(usize),
    /// A frame of this many bytes.
    Frame(Box<Frame>, usize),
}

impl Decoder {
    pub fn new() -> Decoder {
        Decoder::default()
    }

    pub fn push(&mut self, bytes: &[u8]) {
        // Compact lazily so a long stream does not grow the buffer.
        if self.pos > 0 && self.pos >= self.buf.len() / 2 {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// The next frame of a datagram whose bytes have all been pushed: a start marker
    /// whose frame would run past the end is a truncated or false frame, skipped so the
    /// frames after it are still found. Returns `None` once the datagram is used up, and
    /// leaves the decoder empty for the next one.
    pub fn next_in_datagram(&mut self, signer: Option<&mut Signer>) -> Option<Frame> {
        let f = self.next_inner(signer, true);
        if f.is_none() {
            self.buf.clear();
            self.pos = 0;
        }
        f
    }

    /// Forgets a partial frame (after a reconnection).
    pub fn reset(&mut self) {
        self.buf.clear();
        self.pos = 0;
    }

    /// The next valid frame, or `None` when more bytes are needed.
    pub fn next_frame(&mut self, signer: Option<&mut Signer>) -> Option<Frame> {
        self.next_inner(signer, false)
    }

    fn next_inner(&mut self, signer: Option<&mut Signer>, at_end: bool) -> Option<Frame> {
        let mut signer = signer;
        loop {
            // Skip to the next start marker.
            let rest = &self.buf[self.pos..];
            let start = rest.iter().position(|&b| b == STX_V1 || b == STX_V2);
            match start {
                None => {
                    self.skipped.garbage_bytes += rest.len() as u64;
                    self.pos = self.buf.len();
                    return None;
                }
                Some(i) => {
                    self.skipped.garbage_bytes += i as u64;
                    self.pos += i;
                }
            }
            match self.scan(signer.as_deref_mut()) {
                Scan::More if at_end => {
                    self.skipped.truncated += 1;
                    self.pos += 1;
                }
                Scan::More => return None,
                Scan::Skip(n) => self.pos += n,
                Scan::Frame(f, n) => {
                    self.pos += n;
                    return Some(*f);
                }
            }
        }
    }

    fn scan(&mut self, signer: Option<&mut Signer>) -> Scan {
        let b = &self.buf[self.pos..];
        if b.len() < 2 {
            return Scan::More;
        }
        let len = b[1] as usize;
        if b[0] == STX_V1 {
            let n = V1_OVERHEAD + len;
            if b.len() < n {
                return Scan::More;
            }
            let id = b[5] as u32;
            let Some(extra) = extra_crc(id) else {
                self.skipped.unknown_id += 1;
                // An unknown id cannot be checked; skipping the marker alone keeps a
                // valid frame inside a false one reachable.
                return Scan::Skip(1);
            };
            let crc = u16::from_le_bytes([b[n - 2], b[n - 1]]);
            if mavlink::calculate_crc(&b[1..n - 2], extra) != crc {
                self.skipped.bad_crc += 1;
                return Scan::Skip(1);
            }
            let header = MavHeader { system_id: b[3] as u32, component_id: b[4], sequence: b[2] };
            let payload = &b[6..6 + len];
            let parsed = MavMessage::parse(MavlinkVersion::V1, id, payload).map(|m| (m, None)).or_else(|e| {
                parse_unknown_command(MavlinkVersion::V1, id, payload).map(|(m, c)| (m, Some(c))).ok_or(e)
            });
            return match parsed {
                Ok((message, unknown_command)) => Scan::Frame(
                    Box::new(Frame {
                        version: MavlinkVersion::V1,
                        header,
                        message,
                        auth: Auth::Unsigned,
                        unknown_command,
                    }),
                    n,
                ),
                Err(_) => {
                    self.skipped.unparseable += 1;
                    Scan::Skip(n)
                }
            };
        }
        // MAVLink 2.
        if b.len() < 3 {
            return Scan::More;
        }
        let iflags = b[2];
        let signed = iflags & IFLAG_SIGNED != 0;
        let n = V2_OVERHEAD + len + if signed { SIGNATURE_LEN } else { 0 };
        if b.len() < V2_OVERHEAD + len {
            return Scan::More;
        }
        let id = u32::from_le_bytes([b[7], b[8], b[9], 0]);
        let body_end = V2_OVERHEAD + len; // end of the CRC
        let Some(extra) = extra_crc(id) else {
            self.skipped.unknown_id += 1;
            return Scan::Skip(1);
        };
        let crc = u16::from_le_bytes([b[body_end - 2], b[body_end - 1]]);
        if mavlink::calculate_crc(&b[1..body_end - 2], extra) != crc {
            self.skipped.bad_crc += 1;
            return Scan::Skip(1);
        }
        if iflags & !IFLAG_SIGNED != 0 {
            self.skipped.unsupported_flags += 1;
            return Scan::Skip(body_end);
        }
        if b.len() < n {
            return Scan::More;
        }
        let auth = if signed {
            match signer {
                None => Auth::Unsigned,
                Some(s) => match s.verify(&b[..n]) {
                    Verdict::Valid => Auth::Signed,
                    Verdict::Invalid => {
                        self.skipped.bad_signature += 1;
                        return Scan::Skip(n);
                    }
                },
            }
        } else {
            Auth::Unsigned
        };
        let header = MavHeader { system_id: b[5] as u32, component_id: b[6], sequence: b[4] };
        let payload = &b[10..10 + len];
        let parsed = MavMessage::parse(MavlinkVersion::V2, id, payload).map(|m| (m, None)).or_else(|e| {
            parse_unknown_command(MavlinkVersion::V2, id, payload).map(|(m, c)| (m, Some(c))).ok_or(e)
        });
        match parsed {
            Ok((message, unknown_command)) => Scan::Frame(
                Box::new(Frame { version: MavlinkVersion::V2, header, message, auth, unknown_command }),
                n,
            ),
            Err(_) => {
                self.skipped.unparseable += 1;
                Scan::Skip(n)
            }
        }
    }
}

/// The CRC extra of a message id, `None` when the dialect does not define the id.
fn extra_crc(id: u32) -> Option<u8> {
    MavMessage::default_message_from_id(id).map(|_| MavMessage::extra_crc(id))
}

/// Serialises mavloc's outgoing messages: MAVLink 2, with a running sequence number, signed
/// when a signer is set.
pub struct Encoder {
    sequence: u8,
}

impl Default for Encoder {
    fn default() -> Self {
        Encoder::new()
    }
}

impl Encoder {
    pub fn new() -> Encoder {
        Encoder { sequence: 0 }
    }

    pub fn encode(
        &mut self,
        system_id: u8,
        component_id: u8,
        message: &MavMessage,
        signer: Option<&mut Signer>,
    ) -> Vec<u8> {
        self.encode_with_command(system_id, component_id, message, None, signer)
    }

    /// As [`Encoder::encode`]; `command`: for a COMMAND_ACK of an id the dialect does not
    /// define, that id, written over the placeholder the typed message carries.
    pub fn encode_with_command(
        &mut self,
        system_id: u8,
        component_id: u8,
        message: &MavMessage,
        command: Option<u16>,
        signer: Option<&mut Signer>,
    ) -> Vec<u8> {
        let header = MavHeader { system_id: system_id as u32, component_id, sequence: self.sequence };
        self.sequence = self.sequence.wrapping_add(1);
        let mut raw = MAVLinkV2MessageRaw::new();
        if signer.is_some() {
            raw.serialize_message_for_signing(header, message);
        } else {
            raw.serialize_message(header, message);
        }
        if let (Some(id), MavMessage::COMMAND_ACK(_)) = (command, message) {
            // COMMAND_ACK's payload starts with the command id (u16) then the result; a
            // result is never 0 here (ACCEPTED is 0 but unknown ids are UNSUPPORTED), so
            // MAVLink 2's trailing-zero truncation cannot have cut the id.
            let b = raw.as_mut_slice();
            let len = b[1] as usize;
            b[10..12].copy_from_slice(&id.to_le_bytes());
            let crc = mavlink::calculate_crc(&b[1..10 + len], MavMessage::extra_crc(77));
            b[10 + len..12 + len].copy_from_slice(&crc.to_le_bytes());
        }
        if let Some(s) = signer {
            s.sign(&mut raw);
        }
        raw.raw_bytes().to_vec()
    }
}

/// MAVLink 1 encoding, for tests that speak as an old peer.
pub fn encode_v1(header: MavHeader, message: &MavMessage) -> Vec<u8> {
    let mut raw = mavlink::MAVLinkV1MessageRaw::new();
    raw.serialize_message(header, message);
    raw.raw_bytes().to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{
        MavAutopilot, MavModeFlag, MavState, MavType, HEARTBEAT_DATA, PARAM_VALUE_DATA,
    };
    use proptest::prelude::*;

    fn heartbeat(mode: u32) -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: mode,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    fn param(i: u16) -> MavMessage {
        MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: i as f32 * 0.5,
            param_count: 100,
            param_index: i,
            param_id: "AREA_BAND_PX".into(),
            param_type: mavlink::dialects::common::MavParamType::MAV_PARAM_TYPE_REAL32,
        })
    }

    fn drain(d: &mut Decoder) -> Vec<Frame> {
        std::iter::from_fn(|| d.next_frame(None)).collect()
    }

    #[test]
    fn v1_and_v2_frames_decode_with_their_headers() {
        let mut e = Encoder::new();
        let v2 = e.encode(7, 191, &heartbeat(1), None);
        let v1 = encode_v1(MavHeader { system_id: 1, component_id: 1, sequence: 9 }, &heartbeat(2));
        let mut d = Decoder::new();
        d.push(&v2);
        d.push(&v1);
        let f = drain(&mut d);
        assert_eq!(f.len(), 2);
        assert_eq!(f[0].version, MavlinkVersion::V2);
        assert_eq!((f[0].header.system_id, f[0].header.component_id), (7, 191));
        assert_eq!(f[0].message, heartbeat(1));
        assert_eq!(f[1].version, MavlinkVersion::V1);
        assert_eq!(f[1].header.sequence, 9);
        assert_eq!(f[1].message, heartbeat(2));
        assert_eq!(d.skipped, SkipCounts::default());
    }

    #[test]
    fn a_corrupted_frame_is_counted_and_its_neighbours_survive() {
        let mut e = Encoder::new();
        let mut bad = e.encode(1, 1, &param(3), None);
        bad[12] ^= 0x55;
        let mut d = Decoder::new();
        d.push(&e.encode(1, 1, &param(1), None));
        d.push(&bad);
        d.push(&e.encode(1, 1, &param(2), None));
        let f = drain(&mut d);
        assert_eq!(f.iter().map(|f| f.message.clone()).collect::<Vec<_>>(), vec![param(1), param(2)]);
        assert_eq!(d.skipped.bad_crc, 1);
    }

    #[test]
    fn a_datagram_cut_short_counts_as_truncated() {
        let mut e = Encoder::new();
        let whole = e.encode(1, 1, &param(1), None);
        let mut d = Decoder::new();
        d.push(&whole[..whole.len() - 4]);
        assert!(d.next_in_datagram(None).is_none());
        assert!(d.skipped.truncated >= 1);
        d.push(&whole);
        assert_eq!(drain(&mut d).len(), 1);
        // A false start marker before a valid frame at the end of a datagram.
        let mut dgram = vec![STX_V2, 200];
        dgram.extend_from_slice(&whole);
        d.push(&dgram);
        assert!(d.next_frame(None).is_none(), "a stream waits for more bytes");
        assert_eq!(d.next_in_datagram(None).unwrap().message, param(1));
    }

    #[test]
    fn unknown_ids_are_counted() {
        // A MAVLink 2 frame with message id 0xABCDEF, which the common dialect lacks.
        let frame = [STX_V2, 1, 0, 0, 0, 1, 1, 0xEF, 0xCD, 0xAB, 42, 0, 0];
        let mut d = Decoder::new();
        d.push(&frame);
        d.push(&Encoder::new().encode(1, 1, &heartbeat(5), None));
        let f = drain(&mut d);
        assert_eq!(f.len(), 1);
        assert_eq!(d.skipped.unknown_id, 1);
    }

    proptest! {
        /// Valid frames survive any garbage around them, split at any points: the decoder
        /// returns each of them (a frame can only be lost if garbage forms a frame that
        /// overlaps it with a valid CRC, which random bytes essentially never do).
        #[test]
        fn frames_survive_garbage_and_arbitrary_splits(
            garbage in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..40), 6),
            cuts in proptest::collection::vec(1usize..64, 1..30),
        ) {
            let mut e = Encoder::new();
            let mut stream = Vec::new();
            let mut sent = Vec::new();
            for (i, g) in garbage.iter().enumerate() {
                // Garbage ending in a start marker must not hide the next frame.
                stream.extend_from_slice(g);
                let m = if i % 2 == 0 { param(i as u16) } else { heartbeat(i as u32) };
                stream.extend(e.encode(1, 1, &m, None));
                sent.push(m);
            }
            let mut d = Decoder::new();
            let mut got = Vec::new();
            let mut at = 0;
            for c in cuts.iter().cycle() {
                if at >= stream.len() { break; }
                let end = (at + c).min(stream.len());
                d.push(&stream[at..end]);
                at = end;
                got.extend(drain(&mut d).into_iter().map(|f| f.message));
            }
            // A stream goes on: later traffic resolves a false marker near the end.
            d.push(&[0u8; 300]);
            got.extend(drain(&mut d).into_iter().map(|f| f.message));
            // Garbage that happens to form a frame with a valid CRC (1 in 65536 per false
            // marker; proptest finds such cases) is a frame: it may cover a real one. The
            // property is about every other case.
            prop_assume!(got.iter().all(|g| sent.contains(g)));
            // Every sent message arrives, in order.
            let mut it = got.iter();
            for m in &sent {
                prop_assert!(it.any(|g| g == m), "lost {:?}", m);
            }
        }

        /// Random bytes never panic the decoder.
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2000)) {
            let mut d = Decoder::new();
            for chunk in bytes.chunks(97) {
                d.push(chunk);
                drain(&mut d);
            }
            for chunk in bytes.chunks(61) {
                d.push(chunk);
                while d.next_in_datagram(None).is_some() {}
            }
        }

        /// In datagram mode every valid frame is found whatever garbage precedes it.
        #[test]
        fn datagrams_keep_their_frames(
            garbage in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..40), 6),
        ) {
            let mut e = Encoder::new();
            let mut d = Decoder::new();
            for (i, g) in garbage.iter().enumerate() {
                let m = param(i as u16);
                let mut dgram = g.clone();
                dgram.extend(e.encode(1, 1, &m, None));
                d.push(&dgram);
                let got: Vec<_> = std::iter::from_fn(|| d.next_in_datagram(None)).map(|f| f.message).collect();
                // As above: a false frame with a valid CRC may cover the real one.
                prop_assume!(got.iter().all(|g| *g == m));
                prop_assert!(got.contains(&m));
            }
        }
    }

    #[test]
    fn a_command_with_an_id_the_dialect_lacks_is_decoded_and_its_ack_carries_the_id() {
        use mavlink::dialects::common::{MavCmd, COMMAND_LONG_DATA};
        let placeholder = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            param1: 1.0,
            target_system: 1,
            target_component: 191,
            ..Default::default()
        });
        // The same frame as a peer would send with command id 42424.
        let mut b = Encoder::new().encode(255, 190, &placeholder, None);
        let len = b[1] as usize;
        b[10 + 28..10 + 30].copy_from_slice(&42424u16.to_le_bytes());
        let crc = mavlink::calculate_crc(&b[1..10 + len], MavMessage::extra_crc(76));
        b[10 + len..12 + len].copy_from_slice(&crc.to_le_bytes());
        let mut d = Decoder::new();
        d.push(&b);
        let f = d.next_frame(None).expect("decoded, not skipped");
        assert_eq!(f.unknown_command, Some(42424));
        assert_eq!(d.skipped.unparseable, 0);
        // A known id decodes as itself.
        d.push(&Encoder::new().encode(255, 190, &placeholder, None));
        assert_eq!(d.next_frame(None).unwrap().unknown_command, None);
        // The ACK goes out with 42424 in its command field and a valid checksum.
        let ack = MavMessage::COMMAND_ACK(mavlink::dialects::common::COMMAND_ACK_DATA {
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            result: mavlink::dialects::common::MavResult::MAV_RESULT_UNSUPPORTED,
            ..Default::default()
        });
        let out = Encoder::new().encode_with_command(1, 191, &ack, Some(42424), None);
        assert_eq!(u16::from_le_bytes([out[10], out[11]]), 42424);
        let n = out.len();
        let crc = mavlink::calculate_crc(&out[1..n - 2], MavMessage::extra_crc(77));
        assert_eq!(u16::from_le_bytes([out[n - 2], out[n - 1]]), crc);
    }
}
