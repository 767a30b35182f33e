//! A read-only MAVLink FTP server (<https://mavlink.io/en/services/ftp.html>) for the
//! files mavloc publishes: its component metadata (`link::metadata`), which a ground
//! station fetches after COMPONENT_METADATA names it, and the area pipeline's current
//! result set under `/mavloc/results/area/` (the map after its adjustment at landing
//! included), replaced as a whole when the pipeline publishes a new one: a download
//! already open goes on reading the set it opened. No I/O: requests in, replies out,
//! a burst read paced by the clock like the parameter list (PX4 forwards a ground
//! station's traffic and drops what comes in a heap).
//!
//! Payload (251 bytes): seq u16, session u8, opcode u8, size u8, req_opcode u8,
//! burst_complete u8, padding u8, offset u32, data[239]; little-endian. A reply carries
//! the request's seq + 1 and the request's opcode in `req_opcode`; a repeated request
//! (same seq from the same peer: our reply was lost) gets the same reply again.

use std::collections::BTreeMap;
use std::time::Duration;

use super::time::Mono;

pub const PAYLOAD: usize = 251;
const DATA: usize = 239;
const HEADER: usize = 12;

// Opcodes.
const TERMINATE_SESSION: u8 = 1;
const RESET_SESSIONS: u8 = 2;
const LIST_DIRECTORY: u8 = 3;
const OPEN_FILE_RO: u8 = 4;
const READ_FILE: u8 = 5;
const CALC_FILE_CRC32: u8 = 14;
const BURST_READ_FILE: u8 = 15;
const ACK: u8 = 128;
const NAK: u8 = 129;
/// Create, write, remove, mkdir, rmdir, open for writing, truncate, rename.
const WRITES: std::ops::RangeInclusive<u8> = 6..=13;

// NAK reasons.
const INVALID_SESSION: u8 = 4;
const NO_SESSIONS_AVAILABLE: u8 = 5;
const EOF: u8 = 6;
const UNKNOWN_COMMAND: u8 = 7;
const FILE_PROTECTED: u8 = 9;
const FILE_NOT_FOUND: u8 = 10;

/// Open files at once (a ground station needs one; a second tolerates a stale one).
const SESSIONS: usize = 4;
/// Between two packets of a burst.
pub const BURST_INTERVAL: Duration = Duration::from_millis(4);

/// One FTP message: the peer it goes to and its payload.
pub type Packet = ((u8, u8), [u8; PAYLOAD]);

#[derive(Clone, Copy, Debug, PartialEq)]
struct Header {
    seq: u16,
    session: u8,
    opcode: u8,
    size: u8,
    req_opcode: u8,
    burst_complete: u8,
    offset: u32,
}

fn parse(p: &[u8; PAYLOAD]) -> (Header, &[u8]) {
    let h = Header {
        seq: u16::from_le_bytes([p[0], p[1]]),
        session: p[2],
        opcode: p[3],
        size: p[4],
        req_opcode: p[5],
        burst_complete: p[6],
        offset: u32::from_le_bytes([p[8], p[9], p[10], p[11]]),
    };
    let n = (h.size as usize).min(DATA);
    (h, &p[HEADER..HEADER + n])
}

fn build(h: Header, data: &[u8]) -> [u8; PAYLOAD] {
    let mut p = [0u8; PAYLOAD];
    p[0..2].copy_from_slice(&h.seq.to_le_bytes());
    p[2] = h.session;
    p[3] = h.opcode;
    p[4] = data.len() as u8;
    p[5] = h.req_opcode;
    p[6] = h.burst_complete;
    p[8..12].copy_from_slice(&h.offset.to_le_bytes());
    p[HEADER..HEADER + data.len()].copy_from_slice(data);
    p
}

#[derive(Clone, Debug)]
struct Session {
    peer: (u8, u8),
    /// The file as it was when opened.
    data: std::sync::Arc<Vec<u8>>,
}

#[derive(Clone, Debug)]
struct Burst {
    session: u8,
    peer: (u8, u8),
    offset: usize,
    chunk: usize,
    seq: u16,
}

#[derive(Debug)]
pub struct FtpServer {
    files: BTreeMap<String, std::sync::Arc<Vec<u8>>>,
    sessions: [Option<Session>; SESSIONS],
    burst: Option<Burst>,
    next_burst: Mono,
    /// The last request and reply of each peer: a repeat of the request gets the reply again.
    last: BTreeMap<(u8, u8), ([u8; PAYLOAD], [u8; PAYLOAD])>,
}

impl FtpServer {
    pub fn new(files: BTreeMap<String, Vec<u8>>) -> FtpServer {
        FtpServer {
            files: files.into_iter().map(|(p, f)| (p, std::sync::Arc::new(f))).collect(),
            sessions: Default::default(),
            burst: None,
            next_burst: Mono::ZERO,
            last: BTreeMap::new(),
        }
    }

    /// Replaces every file under the folder `dir` (`/mavloc/results/area`) by `files`
    /// (names inside it). Open sessions keep the files they opened.
    pub fn publish(&mut self, dir: &str, files: Vec<(String, Vec<u8>)>) {
        let prefix = format!("{dir}/");
        self.files.retain(|p, _| !p.starts_with(&prefix));
        for (name, bytes) in files {
            self.files.insert(format!("{prefix}{name}"), std::sync::Arc::new(bytes));
        }
    }

    /// A request from `peer`; the immediate reply, if any (a burst's packets come from
    /// [`FtpServer::poll`]).
    pub fn on_request(
        &mut self,
        now: Mono,
        peer: (u8, u8),
        payload: &[u8; PAYLOAD],
    ) -> Option<[u8; PAYLOAD]> {
        let (h, data) = parse(payload);
        if h.opcode == ACK || h.opcode == NAK {
            return None; // a reply, not a request: not ours to answer
        }
        if let Some((request, reply)) = self.last.get(&peer) {
            if request == payload {
                return Some(*reply);
            }
        }
        let reply = self.answer(now, peer, h, data)?;
        if self.last.len() > 16 {
            self.last.clear(); // bounded: many peers only lose the repeat cache
        }
        self.last.insert(peer, (*payload, reply));
        Some(reply)
    }

    fn answer(&mut self, now: Mono, peer: (u8, u8), h: Header, data: &[u8]) -> Option<[u8; PAYLOAD]> {
        let ack = |data: &[u8], session: u8, offset: u32| {
            build(
                Header {
                    seq: h.seq.wrapping_add(1),
                    session,
                    opcode: ACK,
                    size: 0,
                    req_opcode: h.opcode,
                    burst_complete: 0,
                    offset,
                },
                data,
            )
        };
        let nak = |why: u8| {
            build(
                Header {
                    seq: h.seq.wrapping_add(1),
                    session: h.session,
                    opcode: NAK,
                    size: 0,
                    req_opcode: h.opcode,
                    burst_complete: 0,
                    offset: 0,
                },
                &[why],
            )
        };
        let path = || {
            let end = data.iter().position(|&b| b == 0).unwrap_or(data.len());
            String::from_utf8_lossy(&data[..end]).trim_end_matches('/').to_string()
        };
        Some(match h.opcode {
            TERMINATE_SESSION => match self.session(h.session, peer) {
                Some(_) => {
                    self.sessions[h.session as usize] = None;
                    if self.burst.as_ref().is_some_and(|b| b.session == h.session) {
                        self.burst = None;
                    }
                    ack(&[], h.session, 0)
                }
                None => nak(INVALID_SESSION),
            },
            RESET_SESSIONS => {
                self.sessions = Default::default();
                self.burst = None;
                ack(&[], 0, 0)
            }
            OPEN_FILE_RO => {
                let path = path();
                let Some(data) = self.files.get(&path).cloned() else {
                    return Some(nak(FILE_NOT_FOUND));
                };
                let len = data.len();
                // A peer reopening gets its old session back rather than exhausting them.
                let free = self
                    .sessions
                    .iter()
                    .position(|s| s.as_ref().is_some_and(|s| s.peer == peer))
                    .or_else(|| self.sessions.iter().position(Option::is_none));
                match free {
                    Some(i) => {
                        self.sessions[i] = Some(Session { peer, data });
                        ack(&(len as u32).to_le_bytes(), i as u8, 0)
                    }
                    None => nak(NO_SESSIONS_AVAILABLE),
                }
            }
            READ_FILE => {
                let Some(file) = self.session(h.session, peer).map(|s| &s.data) else {
                    return Some(nak(INVALID_SESSION));
                };
                let at = h.offset as usize;
                if at >= file.len() {
                    return Some(nak(EOF));
                }
                let n = (h.size as usize).clamp(1, DATA).min(file.len() - at);
                ack(&file[at..at + n], h.session, h.offset)
            }
            BURST_READ_FILE => {
                let Some(file) = self.session(h.session, peer).map(|s| &s.data) else {
                    return Some(nak(INVALID_SESSION));
                };
                if h.offset as usize >= file.len() {
                    return Some(nak(EOF));
                }
                self.burst = Some(Burst {
                    session: h.session,
                    peer,
                    offset: h.offset as usize,
                    chunk: if h.size == 0 { DATA } else { (h.size as usize).min(DATA) },
                    seq: h.seq.wrapping_add(1),
                });
                self.next_burst = now;
                return None;
            }
            CALC_FILE_CRC32 => match self.files.get(&path()) {
                Some(f) => ack(&crate::link::metadata::crc32(f).to_le_bytes(), h.session, 0),
                None => nak(FILE_NOT_FOUND),
            },
            LIST_DIRECTORY => {
                let dir = path();
                let prefix = format!("{dir}/");
                // Entries directly below `dir`: files, and folders on the way to files.
                let mut entries: Vec<String> = Vec::new();
                for (p, bytes) in &self.files {
                    let Some(rest) = p.strip_prefix(&prefix) else { continue };
                    let entry = match rest.split_once('/') {
                        Some((folder, _)) => format!("D{folder}"),
                        None => format!("F{rest}\t{}", bytes.len()),
                    };
                    if !entries.contains(&entry) {
                        entries.push(entry);
                    }
                }
                let first = h.offset as usize;
                if entries.is_empty() && first == 0 {
                    return Some(nak(FILE_NOT_FOUND));
                }
                if first >= entries.len() {
                    return Some(nak(EOF));
                }
                let mut out = Vec::new();
                for e in &entries[first..] {
                    if out.len() + e.len() + 1 > DATA {
                        break;
                    }
                    out.extend_from_slice(e.as_bytes());
                    out.push(0);
                }
                ack(&out, h.session, h.offset)
            }
            op if WRITES.contains(&op) => nak(FILE_PROTECTED),
            _ => nak(UNKNOWN_COMMAND),
        })
    }

    fn session(&self, id: u8, peer: (u8, u8)) -> Option<&Session> {
        self.sessions.get(id as usize)?.as_ref().filter(|s| s.peer == peer)
    }

    /// The next packet of a burst read, when pacing allows.
    pub fn poll(&mut self, now: Mono) -> Option<Packet> {
        let b = self.burst.as_mut()?;
        if now < self.next_burst {
            return None;
        }
        let file = self.sessions.get(b.session as usize).and_then(|s| s.as_ref()).map(|s| &s.data);
        let Some(file) = file else {
            self.burst = None;
            return None;
        };
        let n = b.chunk.min(file.len() - b.offset);
        let end = b.offset + n >= file.len();
        let packet = build(
            Header {
                seq: b.seq,
                session: b.session,
                opcode: ACK,
                size: 0,
                req_opcode: BURST_READ_FILE,
                burst_complete: end as u8,
                offset: b.offset as u32,
            },
            &file[b.offset..b.offset + n],
        );
        let peer = b.peer;
        b.seq = b.seq.wrapping_add(1);
        b.offset += n;
        if end {
            self.burst = None;
        }
        self.next_burst = now + BURST_INTERVAL;
        Some((peer, packet))
    }

    pub fn deadline(&self) -> Option<Mono> {
        self.burst.as_ref().map(|_| self.next_burst)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PEER: (u8, u8) = (255, 190);

    fn server() -> FtpServer {
        let big: Vec<u8> = (0..1000u32).map(|i| (i * 7 % 251) as u8).collect();
        FtpServer::new(BTreeMap::from([
            ("/mavloc/general.json".to_string(), b"{\"version\":1}".to_vec()),
            ("/mavloc/big.bin".to_string(), big),
        ]))
    }

    fn req(seq: u16, session: u8, opcode: u8, size: u8, offset: u32, data: &[u8]) -> [u8; PAYLOAD] {
        let mut p =
            build(Header { seq, session, opcode, size: 0, req_opcode: 0, burst_complete: 0, offset }, data);
        p[4] = if data.is_empty() { size } else { data.len() as u8 };
        p
    }

    fn open(s: &mut FtpServer, path: &str) -> (u8, u32) {
        open_seq(s, path, 1)
    }

    fn open_seq(s: &mut FtpServer, path: &str, seq: u16) -> (u8, u32) {
        let r = s.on_request(Mono::ZERO, PEER, &req(seq, 0, OPEN_FILE_RO, 0, 0, path.as_bytes())).unwrap();
        let (h, d) = parse(&r);
        assert_eq!((h.opcode, h.req_opcode, h.seq), (ACK, OPEN_FILE_RO, seq + 1), "{h:?} {d:?}");
        (h.session, u32::from_le_bytes(d.try_into().unwrap()))
    }

    #[test]
    fn a_file_read_piece_by_piece_is_the_file() {
        let mut s = server();
        let (session, len) = open(&mut s, "/mavloc/big.bin");
        assert_eq!(len, 1000);
        let mut got = Vec::new();
        let mut seq = 10;
        loop {
            let r = s
                .on_request(Mono::ZERO, PEER, &req(seq, session, READ_FILE, 239, got.len() as u32, &[]))
                .unwrap();
            seq += 1;
            let (h, d) = parse(&r);
            if h.opcode == NAK {
                assert_eq!(d, [EOF]);
                break;
            }
            assert_eq!(h.offset as usize, got.len());
            got.extend_from_slice(d);
        }
        assert_eq!(got, *s.files["/mavloc/big.bin"]);
    }

    #[test]
    fn a_burst_is_paced_complete_and_marked_at_its_end() {
        let mut s = server();
        let (session, _) = open(&mut s, "/mavloc/big.bin");
        assert!(s.on_request(Mono::ZERO, PEER, &req(5, session, BURST_READ_FILE, 200, 0, &[])).is_none());
        let mut now = Mono::ZERO;
        let mut got = Vec::new();
        let mut seqs = Vec::new();
        while let Some(due) = s.deadline() {
            assert!(due >= now);
            now = due;
            if let Some((peer, p)) = s.poll(now) {
                assert_eq!(peer, PEER);
                let (h, d) = parse(&p);
                assert_eq!((h.opcode, h.req_opcode, h.offset as usize), (ACK, BURST_READ_FILE, got.len()));
                got.extend_from_slice(d);
                seqs.push(h.seq);
                assert_eq!(h.burst_complete == 1, got.len() == 1000);
                assert!(s.poll(now).is_none(), "one packet per interval");
            }
        }
        assert_eq!(got, *s.files["/mavloc/big.bin"]);
        assert_eq!(seqs, (6..6 + seqs.len() as u16).collect::<Vec<_>>());
        assert_eq!(seqs.len(), 5, "200-byte packets");
    }

    #[test]
    fn unknown_files_writes_foreign_sessions_and_garbage_are_refused_in_words() {
        let mut s = server();
        let nak_of = |r: [u8; PAYLOAD]| {
            let (h, d) = parse(&r);
            assert_eq!(h.opcode, NAK);
            d[0]
        };
        let r = s.on_request(Mono::ZERO, PEER, &req(1, 0, OPEN_FILE_RO, 0, 0, b"/etc/passwd")).unwrap();
        assert_eq!(nak_of(r), FILE_NOT_FOUND);
        let r = s.on_request(Mono::ZERO, PEER, &req(2, 0, 7, 0, 0, b"x")).unwrap();
        assert_eq!(nak_of(r), FILE_PROTECTED);
        let r = s.on_request(Mono::ZERO, PEER, &req(3, 0, 99, 0, 0, &[])).unwrap();
        assert_eq!(nak_of(r), UNKNOWN_COMMAND);
        let (session, _) = open(&mut s, "/mavloc/general.json");
        // Another peer cannot read or close this session.
        let r = s.on_request(Mono::ZERO, (1, 1), &req(1, session, READ_FILE, 10, 0, &[])).unwrap();
        assert_eq!(nak_of(r), INVALID_SESSION);
        // A size byte beyond the data field is clamped, not trusted.
        let mut bad = req(9, session, READ_FILE, 255, 0, &[]);
        bad[4] = 255;
        let r = s.on_request(Mono::ZERO, PEER, &bad).unwrap();
        assert_eq!(parse(&r).0.opcode, ACK);
    }

    #[test]
    fn a_repeated_request_gets_the_same_reply_and_sessions_are_reused() {
        let mut s = server();
        let (a, _) = open(&mut s, "/mavloc/general.json");
        let first = s.on_request(Mono::ZERO, PEER, &req(7, a, READ_FILE, 5, 0, &[])).unwrap();
        let again = s.on_request(Mono::ZERO, PEER, &req(7, a, READ_FILE, 5, 0, &[])).unwrap();
        assert_eq!(first, again);
        for seq in 100..110 {
            let (b, _) = open_seq(&mut s, "/mavloc/big.bin", seq);
            assert_eq!(b, a, "one peer reopening keeps one session");
        }
        let r = s.on_request(Mono::ZERO, PEER, &req(20, 0, LIST_DIRECTORY, 0, 0, b"/mavloc")).unwrap();
        let (h, d) = parse(&r);
        assert_eq!(h.opcode, ACK);
        let listing = String::from_utf8_lossy(d);
        assert!(listing.contains("Fbig.bin\t1000") && listing.contains("Fgeneral.json"), "{listing}");
        let r =
            s.on_request(Mono::ZERO, PEER, &req(21, 0, CALC_FILE_CRC32, 0, 0, b"/mavloc/big.bin")).unwrap();
        let (_, d) = parse(&r);
        assert_eq!(
            u32::from_le_bytes(d.try_into().unwrap()),
            crate::link::metadata::crc32(s.files["/mavloc/big.bin"].as_slice())
        );
    }

    /// Lists a folder: its entries, NUL-separated. (`seq` differs from call to call: a
    /// repeated one is answered from the last reply.)
    fn list(s: &mut FtpServer, seq: u16, dir: &str) -> Vec<String> {
        let r = s.on_request(Mono::ZERO, PEER, &req(seq, 0, LIST_DIRECTORY, 0, 0, dir.as_bytes())).unwrap();
        let (h, d) = parse(&r);
        if h.opcode == NAK {
            return Vec::new();
        }
        String::from_utf8_lossy(d).split('\0').filter(|e| !e.is_empty()).map(String::from).collect()
    }

    /// Reads a whole open file with READ_FILE.
    fn read_all(s: &mut FtpServer, session: u8, first_seq: u16) -> Vec<u8> {
        let mut got = Vec::new();
        for seq in first_seq.. {
            let r = s
                .on_request(Mono::ZERO, PEER, &req(seq, session, READ_FILE, 239, got.len() as u32, &[]))
                .unwrap();
            let (h, d) = parse(&r);
            if h.opcode == NAK {
                break;
            }
            got.extend_from_slice(d);
        }
        got
    }

    /// A published result set replaces the folder's files as a whole; a download opened
    /// before reads the set it opened to its end, one opened after the new set; the
    /// metadata beside it stays.
    #[test]
    fn a_published_set_replaces_the_folder_and_open_downloads_keep_theirs() {
        let mut s = server();
        let dir = "/mavloc/results/area";
        assert!(list(&mut s, 40, dir).is_empty(), "nothing published yet");
        let first: Vec<u8> = b"id,north\n".iter().copied().cycle().take(700).collect();
        s.publish(dir, vec![("landmarks.csv".into(), first.clone()), ("old.kml".into(), b"<kml/>".to_vec())]);
        assert_eq!(list(&mut s, 41, dir), ["Flandmarks.csv\t700", "Fold.kml\t6"]);
        let (session, len) = open(&mut s, "/mavloc/results/area/landmarks.csv");
        assert_eq!(len, 700);
        s.publish(dir, vec![("landmarks.csv".into(), b"id,north\n1,2\n".to_vec())]);
        assert_eq!(list(&mut s, 42, dir), ["Flandmarks.csv\t13"], "the old set's files are gone");
        assert_eq!(read_all(&mut s, session, 100), first, "the open download reads the set it opened");
        let (session, len) = open_seq(&mut s, "/mavloc/results/area/landmarks.csv", 60);
        assert_eq!((len, read_all(&mut s, session, 200)), (13, b"id,north\n1,2\n".to_vec()));
        assert_eq!(list(&mut s, 43, "/mavloc").len(), 3, "general.json, big.bin and the results folder");
    }
}
