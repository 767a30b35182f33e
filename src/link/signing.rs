//! MAVLink 2 message signing (<https://mavlink.io/en/guide/message_signing.html>): the key
//! file, signing what mavloc sends, verifying what it receives with replay protection,
//! and a timestamp that never goes backwards across restarts.
//!
//! Replay protection outlives a restart: the spec keeps the last timestamp of each
//! (link, system, component) stream in memory only, so a frame captured shortly before a
//! restart would verify again after it (a new stream is accepted within a minute of our
//! clock). The state file therefore holds our own timestamp *and* every stream's last
//! one; it is saved every [`SAVE_INTERVAL_S`], at shutdown, and at once after a signed
//! frame that changes mavloc (a command or a parameter set), so even a crash right after
//! one cannot let it be replayed.
//!
//! The `mavlink` crate computes the SHA-256/48 signature; the policy (which messages need a
//! signature) lives in the daemon, so verification here answers per frame.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use mavlink::MAVLinkV2MessageRaw;

/// Signing timestamps count 10 µs units since 2015-01-01 00:00:00 UTC.
const EPOCH_2015_UNIX_S: u64 = 1_420_070_400;
/// A new stream more than a minute behind our clock is a replay (the spec's rule).
const NEW_STREAM_WINDOW: u64 = 60 * 100_000;
/// The signature's timestamp field is 48 bits: a larger value cannot be sent, and a
/// state file holding one was not written by a signer (mavloc once panicked adding to
/// `u64::MAX`, and kept panicking at every restart).
const TIMESTAMP_LIMIT: u64 = 1 << 48;
/// The timestamp is saved this often; after a crash mavloc restarts this far ahead of the
/// last saved value, so it cannot reuse a timestamp it had already sent.
pub const SAVE_INTERVAL_S: u64 = 10;

/// Verification result of one signed frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    Valid,
    Invalid,
}

/// The key and the timestamps of one link.
pub struct Signer {
    key: [u8; 32],
    link_id: u8,
    timestamp: u64,
    streams: Streams,
    state_file: Option<PathBuf>,
    /// Something to save since the last save.
    dirty: bool,
}

/// Message ids whose replay would change mavloc: saved at once when accepted.
const COMMANDING: [u32; 3] = [
    23, // PARAM_SET
    75, // COMMAND_INT
    76, // COMMAND_LONG
];

/// Each stream's last timestamp, by (link id, system id, component id).
type Streams = HashMap<(u8, u8, u8), u64>;

/// The state file: our timestamp on the first line, then one stream per line as
/// `link system component timestamp`. Unparseable stream lines are skipped (each is one
/// stream's memory, not a reason to refuse to start).
fn parse_state(text: &str) -> Option<(u64, Streams)> {
    let mut lines = text.lines();
    // Below half the 48-bit range (the year 2059), leaving room to count up from it.
    let ts = lines.next()?.trim().parse::<u64>().ok().filter(|t| *t < TIMESTAMP_LIMIT / 2)?;
    let mut streams = HashMap::new();
    for l in lines {
        let f: Vec<u64> = l.split_whitespace().filter_map(|v| v.parse().ok()).collect();
        if let [link, sys, comp, t] = f[..] {
            if t >= TIMESTAMP_LIMIT {
                continue;
            }
            if let (Ok(a), Ok(b), Ok(c)) = (u8::try_from(link), u8::try_from(sys), u8::try_from(comp)) {
                streams.insert((a, b, c), t);
            }
        }
    }
    Some((ts, streams))
}

/// The state file's text; one larger than any signer writes (a stream a line, a few
/// hundred in practice) reads as empty, which does not parse.
fn read_bounded(p: &Path) -> std::io::Result<String> {
    let bytes = mavloc_data::state::read_capped(p, 4 << 20)?.unwrap_or_default();
    String::from_utf8(bytes).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
}

fn now_units() -> u64 {
    let unix = SystemTime::now().duration_since(UNIX_EPOCH).unwrap_or_default();
    (unix.as_micros() as u64 / 10).saturating_sub(EPOCH_2015_UNIX_S * 100_000)
}

/// Reads a key file: 64 hexadecimal characters (surrounding whitespace allowed), the form
/// `mavproxy` and pymavlink users keep keys in. Refuses a file others can read.
pub fn load_key(path: &Path) -> Result<[u8; 32], String> {
    use std::os::unix::fs::MetadataExt;
    let meta = std::fs::metadata(path)
        .map_err(|e| format!("signing key {}: cannot read it: {e}", path.display()))?;
    if meta.mode() & 0o077 != 0 {
        return Err(format!(
            "signing key {}: mode {:o} lets other users read it; run `chmod 600 {}`",
            path.display(),
            meta.mode() & 0o777,
            path.display()
        ));
    }
    // SAFETY: geteuid has no preconditions and cannot fail.
    let euid = unsafe { libc::geteuid() };
    if meta.uid() != euid {
        return Err(format!(
            "signing key {}: owned by uid {}, but mavloc runs as uid {euid}; the key must be mavloc's own",
            path.display(),
            meta.uid()
        ));
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("signing key {}: cannot read it: {e}", path.display()))?;
    parse_key(text.trim()).map_err(|e| format!("signing key {}: {e}", path.display()))
}

/// Parses 64 hexadecimal characters into a key.
pub fn parse_key(hex: &str) -> Result<[u8; 32], String> {
    if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(format!("expected 64 hexadecimal characters (32 bytes), found {} characters", hex.len()));
    }
    let mut key = [0u8; 32];
    for (i, k) in key.iter_mut().enumerate() {
        *k = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).expect("checked hex");
    }
    Ok(key)
}

impl Signer {
    /// A signer whose outgoing timestamp starts after anything saved in `state_file`.
    /// A state file that does not parse is moved aside (named in a warning): starting
    /// matters more, and the spec's one-minute window still guards new streams.
    pub fn new(key: [u8; 32], link_id: u8, state_file: Option<PathBuf>) -> Signer {
        let (stored, streams) = match state_file.as_deref().map(|p| (p, read_bounded(p))) {
            Some((p, Ok(text))) => match parse_state(&text) {
                Some((t, streams)) => (t + SAVE_INTERVAL_S * 100_000, streams),
                None => {
                    let said = mavloc_data::state::set_aside(p, None, "signing state", "does not parse");
                    tracing::warn!("{said}; starting with no stream remembered");
                    (0, HashMap::new())
                }
            },
            // Bytes that are not text are as corrupt as text that does not parse.
            Some((p, Err(e))) if e.kind() == std::io::ErrorKind::InvalidData => {
                let said = mavloc_data::state::set_aside(p, None, "signing state", "not text");
                tracing::warn!("{said}; starting with no stream remembered");
                (0, HashMap::new())
            }
            Some((_, Err(e))) if e.kind() == std::io::ErrorKind::NotFound => (0, HashMap::new()),
            // Unreadable (permissions, a directory in its place): said, since saving will
            // fail too and replay protection then does not survive a restart.
            Some((p, Err(e))) => {
                tracing::warn!(
                    "signing: cannot read the saved state {} ({e}); starting from this computer's clock with no stream remembered",
                    p.display()
                );
                (0, HashMap::new())
            }
            None => (0, HashMap::new()),
        };
        let now = now_units();
        if stored > now + NEW_STREAM_WINDOW {
            // Either this computer's clock is behind (no real-time clock, before NTP: then
            // all is well) or the state was saved by a clock that ran ahead. In the second
            // case every peer's new stream is more than a minute behind ours, and MAVLink's
            // rule refuses it as a replay, until real time catches up with the file.
            tracing::warn!(
                "signing: the saved timestamp in {} is {:.0} s ahead of this computer's clock; peers \
                 whose clocks are right will be refused as replays if it is the saved time that is \
                 wrong (a clock that ran ahead): then stop mavloc and delete the file",
                state_file.as_deref().map(|p| p.display().to_string()).unwrap_or_default(),
                (stored - now) as f64 / 100_000.0
            );
        }
        let timestamp = stored.max(now);
        let mut s = Signer { key, link_id, timestamp, streams, state_file, dirty: true };
        s.save();
        s
    }

    /// The last timestamp used.
    pub fn timestamp(&self) -> u64 {
        self.timestamp
    }

    /// Saves the timestamps (write, then rename) if anything moved since the last save.
    pub fn save(&mut self) {
        if !self.dirty {
            return;
        }
        if let Some(p) = &self.state_file {
            use std::fmt::Write;
            let mut text = format!("{}\n", self.timestamp);
            let mut streams: Vec<_> = self.streams.iter().collect();
            streams.sort();
            for ((link, sys, comp), t) in streams {
                let _ = writeln!(text, "{link} {sys} {comp} {t}");
            }
            match mavloc_data::write_atomic(p, text.as_bytes()) {
                Ok(()) => self.dirty = false,
                Err(e) => tracing::warn!("cannot save the signing state to {}: {e}", p.display()),
            }
        } else {
            self.dirty = false;
        }
    }

    /// Signs a frame serialised with the signed flag set.
    pub fn sign(&mut self, raw: &mut MAVLinkV2MessageRaw) {
        self.timestamp = (self.timestamp + 1).max(now_units());
        self.dirty = true;
        *raw.signature_link_id_mut() = self.link_id;
        raw.signature_timestamp_bytes_mut().copy_from_slice(&self.timestamp.to_le_bytes()[..6]);
        let mut sig = [0u8; 6];
        raw.calculate_signature(&self.key, &mut sig);
        raw.signature_value_mut().copy_from_slice(&sig);
    }

    /// Verifies a whole signed MAVLink 2 frame (STX to the end of the signature).
    pub fn verify(&mut self, frame: &[u8]) -> Verdict {
        let mut raw = MAVLinkV2MessageRaw::new();
        if frame.len() > raw.as_slice().len() {
            return Verdict::Invalid;
        }
        raw.as_mut_slice()[..frame.len()].copy_from_slice(frame);
        let mut sig = [0u8; 6];
        raw.calculate_signature(&self.key, &mut sig);
        if sig != raw.signature_value() {
            return Verdict::Invalid;
        }
        let ts = raw.signature_timestamp();
        let stream = (raw.signature_link_id(), raw.system_id() as u8, raw.component_id());
        self.timestamp = self.timestamp.max(now_units());
        match self.streams.get(&stream) {
            Some(&last) if ts <= last => return Verdict::Invalid,
            None if ts + NEW_STREAM_WINDOW < self.timestamp => return Verdict::Invalid,
            _ => {}
        }
        self.streams.insert(stream, ts);
        self.dirty = true;
        if COMMANDING.contains(&raw.message_id()) {
            self.save();
        }
        Verdict::Valid
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::codec::{Auth, Decoder, Encoder};
    use mavlink::dialects::common::{MavMessage, PARAM_REQUEST_LIST_DATA};

    fn msg() -> MavMessage {
        MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA { target_system: 1, target_component: 191 })
    }

    #[test]
    fn signed_frames_verify_and_replays_and_wrong_keys_do_not() {
        let key = [7u8; 32];
        let mut tx = Signer::new(key, 0, None);
        let mut rx = Signer::new(key, 1, None);
        let mut wrong = Signer::new([8u8; 32], 1, None);
        let mut e = Encoder::new();
        let frame = e.encode(255, 190, &msg(), Some(&mut tx));
        let mut d = Decoder::new();
        d.push(&frame);
        assert_eq!(d.next_frame(Some(&mut rx)).unwrap().auth, Auth::Signed);
        // The same bytes again are a replay.
        d.push(&frame);
        assert!(d.next_frame(Some(&mut rx)).is_none());
        assert_eq!(d.skipped.bad_signature, 1);
        let frame2 = e.encode(255, 190, &msg(), Some(&mut tx));
        d.push(&frame2);
        assert!(d.next_frame(Some(&mut wrong)).is_none());
        assert_eq!(d.skipped.bad_signature, 2);
        // Unsigned frames pass as unsigned; policy is the daemon's.
        d.push(&e.encode(255, 190, &msg(), None));
        assert_eq!(d.next_frame(Some(&mut rx)).unwrap().auth, Auth::Unsigned);
    }

    #[test]
    fn the_timestamp_survives_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("signing-timestamp");
        // A stored timestamp far in the future (a clock that was ahead) must still win.
        let future = now_units() + 1_000_000_000;
        std::fs::write(&file, format!("{future}\n")).unwrap();
        let s = Signer::new([1; 32], 0, Some(file.clone()));
        assert!(s.timestamp() > future);
        let saved: u64 = std::fs::read_to_string(&file).unwrap().trim().parse().unwrap();
        assert_eq!(saved, s.timestamp());
    }

    #[test]
    fn a_frame_accepted_before_a_restart_is_a_replay_after_it() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("signing-timestamp");
        let key = [5u8; 32];
        let mut gcs = Signer::new(key, 2, None);
        let set = MavMessage::PARAM_SET(mavlink::dialects::common::PARAM_SET_DATA {
            target_system: 1,
            target_component: 191,
            param_id: "IND_LAND_EN".into(),
            param_value: 1.0,
            param_type: mavlink::dialects::common::MavParamType::MAV_PARAM_TYPE_REAL32,
        });
        let captured = Encoder::new().encode(255, 190, &set, Some(&mut gcs));
        let verify = |s: &mut Signer| {
            let mut d = Decoder::new();
            d.push(&captured);
            d.next_frame(Some(s)).map(|f| f.auth)
        };
        {
            let mut before = Signer::new(key, 0, Some(file.clone()));
            assert_eq!(verify(&mut before), Some(Auth::Signed));
            // No save() and no drop here: a crash right after the command.
            std::mem::forget(before);
        }
        let mut after = Signer::new(key, 0, Some(file.clone()));
        assert_eq!(verify(&mut after), None, "the captured frame replayed after a restart");
        // The stream itself goes on.
        let next = Encoder::new().encode(255, 190, &set, Some(&mut gcs));
        let mut d = Decoder::new();
        d.push(&next);
        assert_eq!(d.next_frame(Some(&mut after)).map(|f| f.auth), Some(Auth::Signed));
    }

    #[test]
    fn a_corrupt_state_file_is_moved_aside_and_signing_starts() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("signing-timestamp");
        std::fs::write(&file, "not a number\n").unwrap();
        let s = Signer::new([1; 32], 0, Some(file.clone()));
        // One without end is not read to its end (a link to /dev/zero ran mavloc out of
        // memory): it reads as empty, which does not parse, so it goes aside as this one.
        let zero = dir.path().join("zero");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        assert_eq!(read_bounded(&zero).unwrap(), "");
        assert!(s.timestamp() > 0);
        let aside: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("signing-timestamp.corrupt-"))
            .collect();
        assert_eq!(aside.len(), 1);
        assert!(file.exists(), "a fresh state file is written");
        // Bytes that are not UTF-8 go aside the same way (they were dropped without a word).
        std::fs::write(&file, [0xff, 0xfe, 0x00, 0x80]).unwrap();
        let s = Signer::new([1; 32], 0, Some(file.clone()));
        assert!(s.timestamp() > 0);
        let aside = std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| {
                e.as_ref().unwrap().file_name().to_string_lossy().starts_with("signing-timestamp.corrupt-")
            })
            .count();
        assert_eq!(aside, 2, "the binary file is kept aside for a person to look at");
    }

    /// A saved timestamp past half the signature's 48 bits (2059) is no signer's: the
    /// file is moved aside and signing starts from the clock (u64::MAX once made every
    /// start panic); a stream's value beyond 48 bits is forgotten.
    #[test]
    fn a_timestamp_beyond_48_bits_is_a_corrupt_state_file() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("signing-timestamp");
        for first in [u64::MAX.to_string(), (1u64 << 48).to_string(), ((1u64 << 48) - 1000).to_string()] {
            std::fs::write(&file, format!("{first}\n0 1 1 {}\n", u64::MAX)).unwrap();
            let s = Signer::new([1; 32], 0, Some(file.clone()));
            assert!(s.timestamp() < now_units() + 100_000, "{first}: started from the clock");
        }
        let aside = std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| {
                e.as_ref().unwrap().file_name().to_string_lossy().starts_with("signing-timestamp.corrupt-")
            })
            .count();
        assert!(aside >= 1, "moved aside");
        let (_, streams) = parse_state(&format!("5\n0 1 1 {}\n0 2 1 7\n", 1u64 << 48)).unwrap();
        assert_eq!(streams.len(), 1, "the stream beyond 48 bits is forgotten: {streams:?}");
    }

    #[test]
    fn key_files_are_checked() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("key");
        std::fs::write(&p, format!("{}\n", "ab".repeat(32))).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o644)).unwrap();
        assert!(load_key(&p).unwrap_err().contains("chmod 600"));
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert_eq!(load_key(&p).unwrap(), [0xab; 32]);
        std::fs::write(&p, "short").unwrap();
        assert!(load_key(&p).unwrap_err().contains("64 hexadecimal"));
    }
}
