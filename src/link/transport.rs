//! The link task: opens the configured transport, keeps it open (reconnecting with
//! backoff), turns bytes into checked frames and outgoing messages into bytes.
//!
//! No peer can make it wait. Each stream connection (serial, TCP) has its own reader and
//! writer task; the writer takes bytes from a bounded queue, and the link only ever
//! *offers* to that queue: a peer that stops reading loses messages (counted), and one
//! whose write does not complete within [`WRITE_STALL`] is disconnected. UDP sends never
//! wait either (a full socket buffer drops the datagram, counted). So heartbeats keep
//! going to everyone else whatever one peer does.
//!
//! Listening links (`udpin`, `tcpin`) talk only to peers a checked frame vouched for
//! ([`super::peers`]): no datagram or client can take the autopilot's place. `tcpin`
//! takes up to [`MAX_PEERS`] clients at once and drops one that sends no vouching frame
//! for [`PEER_EXPIRY`].
//!
//! It logs one line per state change, never one per retry or per datagram. While the
//! link is down, outgoing messages are dropped and counted: MAVLink is a stream of
//! current state, and a queue of stale heartbeats helps nobody.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use mavlink::dialects::common::MavMessage;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::{broadcast, mpsc};
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::codec::{Decoder, Encoder, Frame, SkipCounts};
use super::peers::{Heard, Peers, Trust, MAX_PEERS, PEER_EXPIRY};

/// Frames dropped for their signature are said at most this often.
const SIGNATURE_LINE_EVERY: Duration = Duration::from_secs(60);

/// Lines about `tcpin` clients connecting and leaving, per 10 s.
const CLIENT_LINES: u32 = 20;

/// The budget of [`CLIENT_LINES`]: the lines beyond it are counted and summed up in the
/// first line of the next period.
#[derive(Default)]
struct ClientLines {
    period: Option<Instant>,
    said: u32,
    unsaid: u64,
}

impl ClientLines {
    fn say(&mut self, line: String) {
        let now = Instant::now();
        if self.period.is_none_or(|p| now.saturating_duration_since(p) >= Duration::from_secs(10)) {
            self.period = Some(now);
            self.said = 0;
            if self.unsaid > 0 {
                tracing::info!(
                    "{} more lines about tcp clients connecting and leaving were not logged",
                    self.unsaid
                );
                self.unsaid = 0;
            }
        }
        if self.said < CLIENT_LINES {
            self.said += 1;
            tracing::info!("{line}");
        } else {
            self.unsaid += 1;
        }
    }
}
use super::address::host_port;
use super::signing::{Signer, SAVE_INTERVAL_S};
use super::LinkAddress;

/// A message for the link to send.
#[derive(Clone, Debug)]
pub struct Outgoing {
    pub system_id: u8,
    pub component_id: u8,
    pub message: MavMessage,
    /// A COMMAND_ACK's command id when the dialect does not define it (see
    /// [`super::codec::Frame::unknown_command`]).
    pub unknown_command: Option<u16>,
}

/// What the link tells the daemon.
#[derive(Debug)]
pub enum LinkEvent {
    /// A checked frame and when the reader took it off the wire, so queueing delay
    /// cannot bend time alignment or TIMESYNC.
    Frame { rx: Instant, frame: Box<Frame> },
    /// The transport is open (for listening links: bound, talking to vouched peers).
    Up(String),
    /// The transport closed or failed; the link is retrying.
    Down(String),
}

/// Counters shared with the daemon (for logs, `status.json` and NAMED_VALUE_FLOAT).
#[derive(Default)]
pub struct LinkStats {
    pub skipped: Mutex<SkipCounts>,
    pub frames_in: AtomicU64,
    pub frames_out: AtomicU64,
    /// Outgoing messages dropped: link down, no peer yet, or a peer's queue full.
    pub dropped_out: AtomicU64,
    /// Peers disconnected because they stopped reading (write stalled) or fell silent.
    pub peers_dropped: AtomicU64,
    /// Would-be peers turned away because the table was full.
    pub peers_refused: AtomicU64,
}

/// The daemon's side of a running link.
pub struct LinkHandle {
    pub outgoing: mpsc::Sender<Outgoing>,
    pub events: mpsc::Receiver<LinkEvent>,
    pub stats: Arc<LinkStats>,
    pub task: JoinHandle<()>,
}

/// Starts the link task. It runs until `shutdown` fires, then saves the signing state
/// and returns.
pub fn spawn(
    address: LinkAddress,
    trust: Trust,
    signer: Option<Signer>,
    shutdown: broadcast::Receiver<()>,
) -> LinkHandle {
    spawn_with_expiry(address, trust, signer, shutdown, PEER_EXPIRY)
}

/// [`spawn`] with another peer expiry (tests use a short one on real sockets).
fn spawn_with_expiry(
    address: LinkAddress,
    trust: Trust,
    signer: Option<Signer>,
    shutdown: broadcast::Receiver<()>,
    expiry: Duration,
) -> LinkHandle {
    let (out_tx, out_rx) = mpsc::channel(256);
    let (ev_tx, ev_rx) = mpsc::channel(1024);
    let stats = Arc::new(LinkStats::default());
    let link = Link {
        address,
        trust,
        decoder: Decoder::new(),
        encoder: Encoder::new(),
        signer,
        stats: stats.clone(),
        events: ev_tx,
        expiry,
    };
    let task = tokio::spawn(link.run(out_rx, shutdown));
    LinkHandle { outgoing: out_tx, events: ev_rx, stats, task }
}

const BACKOFF_MIN: Duration = Duration::from_millis(250);
const BACKOFF_MAX: Duration = Duration::from_secs(5);
/// A write that has not completed in this long means the peer stopped reading.
pub const WRITE_STALL: Duration = Duration::from_secs(2);
/// Frames waiting for one stream peer's writer; beyond it they are dropped.
const PEER_QUEUE: usize = 128;

trait Stream: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Stream for T {}

/// What a stream connection's tasks tell the link.
enum Wire {
    Bytes(u64, Vec<u8>),
    /// Closed, and why; `stalled`: the peer stopped reading.
    Closed {
        id: u64,
        reason: String,
        stalled: bool,
    },
}

/// One stream connection: its decoder, its writer's queue, its two tasks.
struct Conn {
    what: String,
    decoder: Decoder,
    queue: mpsc::Sender<Arc<[u8]>>,
    /// Last vouching frame (listening links send only to vouched clients).
    vouched: Option<Instant>,
    opened: Instant,
    tasks: [JoinHandle<()>; 2],
}

impl Drop for Conn {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// `serial`: the stream is a serial device, whose end of file and I/O errors are the
/// device going away, not a peer closing.
fn start_conn(
    id: u64,
    what: String,
    stream: Box<dyn Stream>,
    serial: bool,
    wire: mpsc::Sender<Wire>,
) -> Conn {
    let (mut rd, mut wr) = tokio::io::split(stream);
    let (queue, mut rx) = mpsc::channel::<Arc<[u8]>>(PEER_QUEUE);
    let w = wire.clone();
    let failed = move |e: &std::io::Error| if serial { serial_io_error(e) } else { stream_io_error(e) };
    let ended = if serial { SERIAL_GONE } else { PEER_CLOSED };
    let reader = tokio::spawn(async move {
        let mut buf = vec![0u8; 16384];
        let reason = loop {
            match rd.read(&mut buf).await {
                Ok(0) => break ended.to_string(),
                Ok(n) => {
                    if w.send(Wire::Bytes(id, buf[..n].to_vec())).await.is_err() {
                        return;
                    }
                }
                Err(e) => break failed(&e),
            }
        };
        let _ = w.send(Wire::Closed { id, reason, stalled: false }).await;
    });
    let writer = tokio::spawn(async move {
        while let Some(bytes) = rx.recv().await {
            let (reason, stalled) = match tokio::time::timeout(WRITE_STALL, wr.write_all(&bytes)).await {
                Ok(Ok(())) => continue,
                Ok(Err(e)) => (failed(&e), false),
                Err(_) => (format!("stopped reading (a write waited {WRITE_STALL:?})"), true),
            };
            let _ = wire.send(Wire::Closed { id, reason, stalled }).await;
            return;
        }
    });
    Conn {
        what,
        decoder: Decoder::new(),
        queue,
        vouched: None,
        opened: Instant::now(),
        tasks: [reader, writer],
    }
}

/// A network peer's end of file, or the errors of [`stream_io_error`].
const PEER_CLOSED: &str = "closed by the peer";

/// How a network stream's read or write failed. A peer that closes with mavloc's bytes
/// still unread in its socket (a router killed or restarted: it has never read the last
/// ones) makes the kernel send a reset instead of an end of file, so mavloc sees
/// ECONNRESET or EPIPE, not a read of 0: both are the peer closing, said as such.
fn stream_io_error(e: &std::io::Error) -> String {
    use std::io::ErrorKind::*;
    match e.kind() {
        ConnectionReset | ConnectionAborted | BrokenPipe => format!("{PEER_CLOSED} ({e})"),
        _ => e.to_string(),
    }
}

/// A serial device that is not there when it is opened.
const NO_DEVICE: &str =
    "no such device (unplugged? a USB port is best named by its /dev/serial/by-id/ link, which follows it)";
/// A serial device's end of file, or the errors of [`serial_io_error`].
const SERIAL_GONE: &str = "the device went away (unplugged?)";

/// How a serial device's read or write failed: EIO, ENODEV and ENXIO, as a USB adapter
/// pulled out or a pseudo-terminal closed gives them, are the device going away.
fn serial_io_error(e: &std::io::Error) -> String {
    match e.raw_os_error() {
        Some(libc::EIO | libc::ENODEV | libc::ENXIO) => SERIAL_GONE.to_string(),
        _ => e.to_string(),
    }
}

/// A link-local address's zone that names no interface of this machine: the resolver
/// says only "Name or service not known", as if the address were a host name.
fn missing_zone(address: &LinkAddress) -> Option<std::io::Error> {
    let host = match address {
        LinkAddress::Serial { .. } => return None,
        LinkAddress::UdpIn { host, .. }
        | LinkAddress::UdpOut { host, .. }
        | LinkAddress::TcpIn { host, .. }
        | LinkAddress::TcpOut { host, .. } => host,
    };
    let (_, zone) = host.split_once('%')?;
    // Without /sys (not Linux, or not mounted) the resolver is left to judge.
    if !std::path::Path::new("/sys/class/net").is_dir() {
        return None;
    }
    let known = if zone.bytes().all(|b| b.is_ascii_digit()) {
        std::fs::read_dir("/sys/class/net")
            .ok()?
            .flatten()
            .any(|d| std::fs::read_to_string(d.path().join("ifindex")).is_ok_and(|i| i.trim() == zone))
    } else {
        std::path::Path::new("/sys/class/net").join(zone).exists()
    };
    (!known).then(|| {
        std::io::Error::other(format!(
            "no network interface `{zone}` on this machine (the zone of {host}; `ip link` lists them)"
        ))
    })
}

/// A serial device that would not open, with what usually stands behind it: the bare errno
/// text ("Permission denied", "Device or resource busy") leaves the user guessing, and the
/// causes are few and well known.
fn serial_open_error(e: tokio_serial::Error) -> std::io::Error {
    use std::io::ErrorKind as Io;
    use tokio_serial::ErrorKind as K;
    let hint = match e.kind {
        // serialport reports a lock held by another opener (its flock, or TIOCEXCL's EBUSY)
        // as "no device".
        K::NoDevice if e.description.contains("lock") || e.description.contains("busy") => {
            "in use by another program (a second mavloc, mavlink-router or ModemManager?)"
        }
        // ENODEV and ENXIO come as "unknown", named only by their text.
        K::NoDevice | K::Io(Io::NotFound) => NO_DEVICE,
        K::Unknown if e.description.starts_with("No such device") => NO_DEVICE,
        K::Io(Io::PermissionDenied) => {
            "permission denied (the user needs the dialout group, which the systemd service has; a serial login \
             console on the port, as Raspberry Pi OS can enable, keeps it for the tty group: turn the console off)"
        }
        _ => return std::io::Error::other(e.description),
    };
    std::io::Error::other(format!("{}: {hint}", e.description))
}

/// An open transport.
enum Endpoint {
    /// `udpin` (peers learnt from vouching frames) or `udpout` (one fixed peer).
    Udp { socket: UdpSocket, fixed: Option<SocketAddr>, peers: Peers },
    /// Serial or `tcpout`: one connection; the link is down when it closes.
    Single,
    /// `tcpin`: clients come and go; the link is up while the listener is.
    Listener(TcpListener),
}

struct Link {
    address: LinkAddress,
    trust: Trust,
    /// For datagrams (one per datagram, so a frame cut short ends with it).
    decoder: Decoder,
    encoder: Encoder,
    signer: Option<Signer>,
    stats: Arc<LinkStats>,
    events: mpsc::Sender<LinkEvent>,
    /// A `tcpin` client with no vouching frame for this long is dropped.
    expiry: Duration,
}

/// Why serving an endpoint ended.
enum End {
    Down(String),
    Shutdown,
}

impl Link {
    async fn open(&self) -> std::io::Result<(Endpoint, Option<Box<dyn Stream>>, String)> {
        if let Some(e) = missing_zone(&self.address) {
            return Err(e);
        }
        match &self.address {
            LinkAddress::UdpIn { host, port } => {
                let socket = UdpSocket::bind((host.as_str(), *port)).await?;
                let e = Endpoint::Udp { socket, fixed: None, peers: Peers::default() };
                Ok((e, None, format!("listening on udp {}", host_port(host, *port))))
            }
            LinkAddress::UdpOut { host, port } => {
                let peer = tokio::net::lookup_host((host.as_str(), *port))
                    .await?
                    .next()
                    .ok_or_else(|| std::io::Error::other(format!("{host} resolves to no address")))?;
                let local: SocketAddr =
                    if peer.is_ipv4() { "0.0.0.0:0".parse().unwrap() } else { "[::]:0".parse().unwrap() };
                let socket = UdpSocket::bind(local).await?;
                let e = Endpoint::Udp { socket, fixed: Some(peer), peers: Peers::default() };
                Ok((e, None, format!("sending to udp {peer}")))
            }
            LinkAddress::TcpOut { host, port } => {
                let s = TcpStream::connect((host.as_str(), *port)).await.map_err(|e| {
                    if e.kind() == std::io::ErrorKind::ConnectionRefused {
                        // mavlink-router's TCP server not started yet, or on another port.
                        std::io::Error::other(format!(
                            "{e}: nothing listens there (is mavlink-router running, with its TCP server on port {port}?)"
                        ))
                    } else {
                        e
                    }
                })?;
                tune(&s)?;
                Ok((
                    Endpoint::Single,
                    Some(Box::new(s)),
                    format!("connected to tcp {}", host_port(host, *port)),
                ))
            }
            LinkAddress::TcpIn { host, port } => {
                let l = TcpListener::bind((host.as_str(), *port)).await?;
                Ok((Endpoint::Listener(l), None, format!("listening on tcp {}", host_port(host, *port))))
            }
            LinkAddress::Serial { device, baud } => {
                use tokio_serial::SerialPortBuilderExt;
                let s = tokio_serial::new(device, *baud).open_native_async().map_err(serial_open_error)?;
                Ok((Endpoint::Single, Some(Box::new(s)), format!("serial {device} at {baud} baud")))
            }
        }
    }

    async fn run(mut self, mut outgoing: mpsc::Receiver<Outgoing>, mut shutdown: broadcast::Receiver<()>) {
        let mut backoff = BACKOFF_MIN;
        let mut last_error: Option<String> = None;
        'outer: loop {
            let opened = tokio::select! {
                r = self.open() => r,
                _ = shutdown.recv() => break 'outer,
            };
            let (endpoint, stream, what) = match opened {
                Ok(c) => c,
                Err(e) => {
                    let msg = format!("{}: {e}", self.address);
                    if last_error.as_deref() != Some(&msg) {
                        tracing::warn!("link down: {msg}; retrying with backoff up to {BACKOFF_MAX:?}");
                        let _ = self.events.send(LinkEvent::Down(msg.clone())).await;
                        last_error = Some(msg);
                    }
                    // Drop what the daemon wants to send meanwhile, and keep waiting.
                    let sleep = tokio::time::sleep(backoff);
                    tokio::pin!(sleep);
                    loop {
                        tokio::select! {
                            _ = &mut sleep => break,
                            o = outgoing.recv() => match o {
                                Some(_) => { self.stats.dropped_out.fetch_add(1, Relaxed); }
                                None => break 'outer,
                            },
                            _ = shutdown.recv() => break 'outer,
                        }
                    }
                    backoff = (backoff * 2).min(BACKOFF_MAX);
                    continue;
                }
            };
            if last_error.take().is_some() || backoff > BACKOFF_MIN {
                tracing::info!("link up again: {what}");
            } else {
                tracing::info!("link up: {what}");
            }
            backoff = BACKOFF_MIN;
            if self.events.send(LinkEvent::Up(what.clone())).await.is_err() {
                break;
            }
            match self.serve(endpoint, stream, what, &mut outgoing, &mut shutdown).await {
                End::Shutdown => break 'outer,
                End::Down(reason) => {
                    tracing::warn!("link down: {reason}; reconnecting");
                    if self.events.send(LinkEvent::Down(reason.clone())).await.is_err() {
                        break;
                    }
                    last_error = Some(reason);
                    tokio::time::sleep(BACKOFF_MIN).await;
                }
            }
        }
        if let Some(s) = self.signer.as_mut() {
            s.save();
        }
    }

    /// Serves one open endpoint until it fails or shutdown.
    async fn serve(
        &mut self,
        mut endpoint: Endpoint,
        stream: Option<Box<dyn Stream>>,
        what: String,
        outgoing: &mut mpsc::Receiver<Outgoing>,
        shutdown: &mut broadcast::Receiver<()>,
    ) -> End {
        let (wire_tx, mut wire_rx) = mpsc::channel::<Wire>(64);
        let mut conns: HashMap<u64, Conn> = HashMap::new();
        let mut next_id = 0u64;
        if let Some(s) = stream {
            let serial = matches!(self.address, LinkAddress::Serial { .. });
            conns.insert(next_id, start_conn(next_id, what.clone(), s, serial, wire_tx.clone()));
            next_id += 1;
        }
        let listening = matches!(endpoint, Endpoint::Listener(_) | Endpoint::Udp { fixed: None, .. });
        let mut buf = vec![0u8; 65536];
        let mut housekeeping = tokio::time::interval((self.expiry / 10).min(Duration::from_secs(1)));
        let mut save_tick = tokio::time::interval(Duration::from_secs(SAVE_INTERVAL_S));
        // Client comings and goings are logged, but a client reconnecting in a loop would
        // fill the disk: at most CLIENT_LINES lines per 10 s, the rest summed up.
        let mut client_lines = ClientLines::default();
        // Frames dropped for their signature, and when that was last said: a wrong key or
        // a clock a minute off otherwise shows only as a counter in status.json.
        let mut signatures_said = (0u64, None::<Instant>);
        loop {
            tokio::select! {
                r = recv_datagram(&endpoint, &mut buf) => match r {
                    Ok((n, from)) => {
                        if !self.datagram(&mut endpoint, &buf[..n], from).await { return End::Shutdown; }
                    }
                    Err(e) => return End::Down(format!("{}: {e}", self.address)),
                },
                a = accept(&endpoint) => match a {
                    Ok((s, peer)) => {
                        if conns.len() >= MAX_PEERS {
                            // A full table of clients that never vouched (connections held
                            // open and silent) would lock every ground station out: the
                            // longest-open of them gives way. No grace: an attacker who
                            // reconnects faster than a grace would keep every place young,
                            // while a ground station that sends its heartbeat on connecting
                            // is the newest and goes last.
                            let idle = conns
                                .iter()
                                .filter(|(_, c)| c.vouched.is_none())
                                .min_by_key(|(_, c)| c.opened)
                                .map(|(&id, _)| id);
                            match idle.and_then(|id| conns.remove(&id)) {
                                Some(c) => {
                                    self.stats.peers_dropped.fetch_add(1, Relaxed);
                                    client_lines.say(format!("{}: no frame from the autopilot or ground station yet, and the clients are full; disconnected for tcp client {peer}", c.what));
                                }
                                None => {
                                    // Closing at once tells the client, and costs nothing.
                                    self.stats.peers_refused.fetch_add(1, Relaxed);
                                    drop(s);
                                    continue;
                                }
                            }
                        }
                        if let Err(e) = tune(&s) {
                            tracing::info!("tcp client {peer}: {e}; not accepted");
                            continue;
                        }
                        client_lines.say(format!("tcp client {peer} connected"));
                        conns.insert(next_id, start_conn(next_id, format!("tcp client {peer}"), Box::new(s), false, wire_tx.clone()));
                        next_id += 1;
                    }
                    Err(e) => return End::Down(format!("{}: {e}", self.address)),
                },
                w = wire_rx.recv() => match w {
                    Some(Wire::Bytes(id, bytes)) => {
                        if !self.stream_bytes(&mut conns, id, &bytes).await { return End::Shutdown; }
                    }
                    Some(Wire::Closed { id, reason, stalled }) => {
                        if let Some(c) = conns.remove(&id) {
                            if stalled {
                                self.stats.peers_dropped.fetch_add(1, Relaxed);
                            }
                            if !listening {
                                return End::Down(format!("{}: {reason}", self.address));
                            }
                            client_lines.say(format!("{}: {reason}; disconnected", c.what));
                        }
                    }
                    None => return End::Down(format!("{}: connection tasks ended", self.address)),
                },
                o = outgoing.recv() => match o {
                    Some(o) => self.send(&endpoint, &conns, &o, listening),
                    None => return End::Shutdown,
                },
                _ = housekeeping.tick() => {
                    let now = Instant::now();
                    let bad = self.stats.skipped.lock().expect("stats lock").bad_signature;
                    if bad > signatures_said.0
                        && signatures_said.1.is_none_or(|t| now.saturating_duration_since(t) >= SIGNATURE_LINE_EVERY)
                    {
                        tracing::warn!(
                            "{} frames dropped for a wrong signature or a replayed or stale timestamp ({bad} in all): \
                             check the peers' key, and their clocks (a new stream more than a minute behind \
                             mavloc's signing time is a replay by MAVLink's rule)",
                            bad - signatures_said.0
                        );
                        signatures_said = (bad, Some(now));
                    }
                    if let Endpoint::Udp { peers, fixed: None, .. } = &mut endpoint {
                        for gone in peers.expire(now) {
                            tracing::info!("udp peer {gone} silent for {PEER_EXPIRY:?}; no longer sent to");
                        }
                    }
                    if matches!(endpoint, Endpoint::Listener(_)) {
                        let idle: Vec<u64> = conns
                            .iter()
                            .filter(|(_, c)| now.saturating_duration_since(c.vouched.unwrap_or(c.opened)) >= self.expiry)
                            .map(|(&id, _)| id)
                            .collect();
                        for id in idle {
                            if let Some(c) = conns.remove(&id) {
                                self.stats.peers_dropped.fetch_add(1, Relaxed);
                                client_lines.say(format!("{}: no frame from the autopilot or ground station for {:?}; disconnected", c.what, self.expiry));
                            }
                        }
                    }
                },
                _ = save_tick.tick() => if let Some(s) = self.signer.as_mut() { s.save() },
                _ = shutdown.recv() => return End::Shutdown,
            }
        }
    }

    /// Decodes one datagram; on `udpin`, a vouching frame makes its sender a peer.
    /// False when the daemon has gone.
    async fn datagram(&mut self, endpoint: &mut Endpoint, bytes: &[u8], from: SocketAddr) -> bool {
        self.decoder.push(bytes);
        while let Some(f) = self.decoder.next_in_datagram(self.signer.as_mut()) {
            let rx = Instant::now();
            if let Endpoint::Udp { peers, fixed: None, .. } = endpoint {
                if self.trust.vouches(&f) {
                    // `vouches` took only an 8-bit system id.
                    match peers.heard(from, f.header.system_id as u8, rx) {
                        Heard::Added => tracing::info!(
                            "udp peer {from} (system {}) added; {} peer(s)",
                            f.header.system_id,
                            peers.len()
                        ),
                        Heard::Returned(out) => tracing::warn!(
                            "udp peer {from} (system {}) is back and takes its place from {out}, which \
                             came while it was silent; {} peer(s)",
                            f.header.system_id,
                            peers.len()
                        ),
                        Heard::Full => {
                            self.stats.peers_refused.fetch_add(1, Relaxed);
                        }
                        Heard::Known => {}
                    }
                }
            }
            if !self.forward(rx, f).await {
                return false;
            }
        }
        let counts = std::mem::take(&mut self.decoder.skipped);
        self.stats.skipped.lock().expect("stats lock").add(&counts);
        true
    }

    /// Decodes bytes from a stream connection. False when the daemon has gone.
    async fn stream_bytes(&mut self, conns: &mut HashMap<u64, Conn>, id: u64, bytes: &[u8]) -> bool {
        let Some(c) = conns.get_mut(&id) else { return true };
        c.decoder.push(bytes);
        let mut frames = Vec::new();
        while let Some(f) = c.decoder.next_frame(self.signer.as_mut()) {
            if self.trust.vouches(&f) {
                c.vouched = Some(Instant::now());
            }
            frames.push(f);
        }
        let counts = std::mem::take(&mut c.decoder.skipped);
        self.stats.skipped.lock().expect("stats lock").add(&counts);
        for f in frames {
            if !self.forward(Instant::now(), f).await {
                return false;
            }
        }
        true
    }

    async fn forward(&mut self, rx: Instant, f: Frame) -> bool {
        self.stats.frames_in.fetch_add(1, Relaxed);
        self.events.send(LinkEvent::Frame { rx, frame: Box::new(f) }).await.is_ok()
    }

    /// Encodes once, offers to every peer; never waits.
    fn send(&mut self, endpoint: &Endpoint, conns: &HashMap<u64, Conn>, o: &Outgoing, listening: bool) {
        let bytes = self.encoder.encode_with_command(
            o.system_id,
            o.component_id,
            &o.message,
            o.unknown_command,
            self.signer.as_mut(),
        );
        let mut sent = false;
        match endpoint {
            Endpoint::Udp { socket, fixed, peers } => {
                // The fixed peer (`udpout`), else the vouched ones (`udpin`).
                let learnt = peers.addresses().filter(|_| fixed.is_none());
                for p in fixed.iter().copied().chain(learnt) {
                    match socket.try_send_to(&bytes, p) {
                        Ok(_) => sent = true,
                        Err(_) => {
                            self.stats.dropped_out.fetch_add(1, Relaxed);
                        }
                    }
                }
            }
            Endpoint::Single | Endpoint::Listener(_) => {
                let shared: Arc<[u8]> = bytes.into();
                for c in conns.values().filter(|c| !listening || c.vouched.is_some()) {
                    match c.queue.try_send(shared.clone()) {
                        Ok(()) => sent = true,
                        Err(_) => {
                            self.stats.dropped_out.fetch_add(1, Relaxed);
                        }
                    }
                }
            }
        }
        if sent {
            self.stats.frames_out.fetch_add(1, Relaxed);
        } else if listening && !matches!(endpoint, Endpoint::Udp { fixed: Some(_), .. }) {
            // Nobody to send to yet (no vouched peer): dropped, counted.
            self.stats.dropped_out.fetch_add(1, Relaxed);
        }
    }
}

/// No Nagle delay (telemetry is small and late is useless), and a small send buffer: a
/// peer that stops reading is noticed within seconds, not after megabytes of kernel
/// buffer, and nothing it was sent is minutes old.
fn tune(s: &TcpStream) -> std::io::Result<()> {
    s.set_nodelay(true)?;
    socket2::SockRef::from(s).set_send_buffer_size(TCP_SEND_BUFFER)
}

/// Bytes the kernel may hold for one TCP peer: about a second of a busy link.
const TCP_SEND_BUFFER: usize = 32 * 1024;

async fn recv_datagram(endpoint: &Endpoint, buf: &mut [u8]) -> std::io::Result<(usize, SocketAddr)> {
    match endpoint {
        Endpoint::Udp { socket, .. } => loop {
            match socket.recv_from(buf).await {
                // ICMP "port unreachable" from a peer that went away surfaces here on
                // Linux; the socket itself is fine.
                Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => continue,
                r => return r,
            }
        },
        _ => std::future::pending().await,
    }
}

async fn accept(endpoint: &Endpoint) -> std::io::Result<(TcpStream, SocketAddr)> {
    match endpoint {
        Endpoint::Listener(l) => l.accept().await,
        _ => std::future::pending().await,
    }
}

#[cfg(test)]
mod tests {
    //! The link on real loopback sockets: who gets mavloc's output, and that no peer
    //! can make it wait.
    use super::*;

    use crate::link::codec::Encoder;
    use mavlink::dialects::common::HEARTBEAT_DATA;

    #[test]
    fn a_serial_device_that_will_not_open_is_named_with_its_usual_cause() {
        use tokio_serial::{Error, ErrorKind};
        let said = |kind, what: &str| super::serial_open_error(Error::new(kind, what)).to_string();
        let locked = said(ErrorKind::NoDevice, "Unable to acquire exclusive lock on serial port");
        assert!(
            locked.starts_with("Unable to acquire") && locked.contains("in use by another program"),
            "{locked}"
        );
        assert!(said(ErrorKind::NoDevice, "Device or resource busy").contains("in use by another program"));
        let gone = said(ErrorKind::Io(std::io::ErrorKind::NotFound), "No such file or directory");
        assert!(gone.contains("unplugged?") && gone.contains("/dev/serial/by-id/"), "{gone}");
        let denied = said(ErrorKind::Io(std::io::ErrorKind::PermissionDenied), "Permission denied");
        assert!(denied.contains("dialout group") && denied.contains("login console"), "{denied}");
        assert!(said(ErrorKind::Unknown, "No such device or address").contains("unplugged?"));
        for errno in [libc::EIO, libc::ENODEV, libc::ENXIO] {
            assert_eq!(super::serial_io_error(&std::io::Error::from_raw_os_error(errno)), super::SERIAL_GONE);
        }
        let other = std::io::Error::from_raw_os_error(libc::EAGAIN);
        assert_eq!(super::serial_io_error(&other), other.to_string());
        assert_eq!(said(ErrorKind::InvalidInput, "bad baud rate"), "bad baud rate");
    }

    #[test]
    fn a_network_peer_that_resets_the_connection_is_said_to_have_closed_it() {
        for errno in [libc::ECONNRESET, libc::EPIPE, libc::ECONNABORTED] {
            let e = std::io::Error::from_raw_os_error(errno);
            let said = super::stream_io_error(&e);
            assert!(said.starts_with(super::PEER_CLOSED) && said.contains(&e.to_string()), "{said}");
        }
        let other = std::io::Error::from_raw_os_error(libc::ETIMEDOUT);
        assert_eq!(super::stream_io_error(&other), other.to_string());
    }

    fn trust(signing: bool) -> Trust {
        Trust { autopilot_system_id: 1, gcs_system_id: 255, signing, accept_unsigned_telemetry: false }
    }

    fn heartbeat(sys: u8, signer: Option<&mut Signer>) -> Vec<u8> {
        Encoder::new().encode(sys, 1, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()), signer)
    }

    fn out() -> Outgoing {
        Outgoing {
            system_id: 1,
            component_id: 191,
            message: MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
            unknown_command: None,
        }
    }

    fn free_port() -> u16 {
        std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
    }

    /// Waits for `n` frames from the link (skipping Up/Down).
    async fn frames(h: &mut LinkHandle, n: usize) {
        let mut got = 0;
        while got < n {
            match tokio::time::timeout(Duration::from_secs(5), h.events.recv()).await {
                Ok(Some(LinkEvent::Frame { .. })) => got += 1,
                Ok(Some(_)) => {}
                other => panic!("link ended or timed out: {other:?}"),
            }
        }
    }

    async fn up(h: &mut LinkHandle) {
        match tokio::time::timeout(Duration::from_secs(5), h.events.recv()).await {
            Ok(Some(LinkEvent::Up(_))) => {}
            other => panic!("expected the link up: {other:?}"),
        }
    }

    /// Sends one heartbeat through the link and says who received it within 300 ms.
    async fn who_hears(h: &LinkHandle, sockets: &[&UdpSocket]) -> Vec<bool> {
        h.outgoing.send(out()).await.unwrap();
        let mut heard = Vec::new();
        for s in sockets {
            let mut buf = [0u8; 512];
            let r = tokio::time::timeout(Duration::from_millis(300), s.recv(&mut buf)).await;
            heard.push(matches!(r, Ok(Ok(n)) if n > 0));
        }
        heard
    }

    #[tokio::test]
    async fn a_zone_that_names_no_interface_is_reported_as_such() {
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::UdpOut { host: "fe80::1%nosuch0".into(), port: 14550 };
        let mut h = spawn(addr, trust(false), None, rx);
        match tokio::time::timeout(Duration::from_secs(5), h.events.recv()).await {
            Ok(Some(LinkEvent::Down(m))) => assert!(m.contains("no network interface `nosuch0`"), "{m}"),
            other => panic!("expected the link down: {other:?}"),
        }
        // Loopback exists by name and by index (1) wherever /sys is mounted.
        if std::path::Path::new("/sys/class/net/lo").exists() {
            for host in ["fe80::1%lo", "fe80::1%1"] {
                let a = LinkAddress::UdpOut { host: host.into(), port: 14550 };
                assert!(missing_zone(&a).is_none(), "{host}");
            }
        }
    }

    #[tokio::test]
    async fn udpin_output_is_not_hijacked_by_garbage_empty_or_foreign_datagrams() {
        let port = free_port();
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::UdpIn { host: "127.0.0.1".into(), port };
        let mut h = spawn(addr, trust(false), None, rx);
        up(&mut h).await;
        let autopilot = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let attacker = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        autopilot.connect(("127.0.0.1", port)).await.unwrap();
        attacker.connect(("127.0.0.1", port)).await.unwrap();
        autopilot.send(&heartbeat(1, None)).await.unwrap();
        frames(&mut h, 1).await;
        assert_eq!(who_hears(&h, &[&autopilot, &attacker]).await, vec![true, false]);
        // The old rule (answer whoever spoke last) would send everything to the attacker.
        attacker.send(&[]).await.unwrap();
        attacker.send(b"\xfd\x09garbage that is not mavlink").await.unwrap();
        attacker.send(&heartbeat(42, None)).await.unwrap();
        frames(&mut h, 1).await; // the foreign heartbeat is a valid frame: the daemon sees it
        assert_eq!(who_hears(&h, &[&autopilot, &attacker]).await, vec![true, false]);
        assert!(h.stats.skipped.lock().unwrap().garbage_bytes > 0);
    }

    #[tokio::test]
    async fn with_signing_only_signed_frames_make_a_peer() {
        let key = [9u8; 32];
        let port = free_port();
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::UdpIn { host: "127.0.0.1".into(), port };
        let mut h = spawn(addr, trust(true), Some(Signer::new(key, 0, None)), rx);
        up(&mut h).await;
        let spoofer = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let gcs = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        spoofer.connect(("127.0.0.1", port)).await.unwrap();
        gcs.connect(("127.0.0.1", port)).await.unwrap();
        // An unsigned frame claiming to be the autopilot makes nobody a peer.
        spoofer.send(&heartbeat(1, None)).await.unwrap();
        frames(&mut h, 1).await;
        assert_eq!(who_hears(&h, &[&spoofer, &gcs]).await, vec![false, false]);
        let mut their = Signer::new(key, 3, None);
        gcs.send(&heartbeat(255, Some(&mut their))).await.unwrap();
        frames(&mut h, 1).await;
        assert_eq!(who_hears(&h, &[&spoofer, &gcs]).await, vec![false, true]);
    }

    /// Reads frames from a TCP client until one arrives or `limit` passes.
    async fn hears_tcp(s: &mut TcpStream, limit: Duration) -> bool {
        let mut buf = [0u8; 4096];
        matches!(tokio::time::timeout(limit, s.read(&mut buf)).await, Ok(Ok(n)) if n > 0)
    }

    #[tokio::test]
    async fn a_tcp_client_that_stops_reading_is_dropped_and_the_others_keep_hearing() {
        let port = free_port();
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::TcpIn { host: "127.0.0.1".into(), port };
        let mut h = spawn(addr, trust(false), None, rx);
        up(&mut h).await;
        // The stuck client: a tiny receive buffer it never reads.
        let sock = tokio::net::TcpSocket::new_v4().unwrap();
        sock.set_recv_buffer_size(4096).unwrap();
        let mut stuck = sock.connect(SocketAddr::from(([127, 0, 0, 1], port))).await.unwrap();
        let mut good = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        stuck.write_all(&heartbeat(255, None)).await.unwrap();
        good.write_all(&heartbeat(1, None)).await.unwrap();
        frames(&mut h, 2).await;
        // Far more than both sockets' buffers hold: the link must never wait on `stuck`.
        let big = MavMessage::STATUSTEXT(mavlink::dialects::common::STATUSTEXT_DATA {
            text: [b'x'; 50].into(),
            ..Default::default()
        });
        let reader = tokio::spawn(async move {
            let mut total = 0usize;
            let mut buf = vec![0u8; 65536];
            // Until the link has been quiet for a second: it sends nothing once the burst is out.
            while let Ok(Ok(n)) = tokio::time::timeout(Duration::from_secs(1), good.read(&mut buf)).await {
                if n == 0 {
                    break;
                }
                total += n;
            }
            total
        });
        for _ in 0..20_000 {
            let m = Outgoing { system_id: 1, component_id: 191, message: big.clone(), unknown_command: None };
            // The daemon's own rule: offer, never wait.
            if h.outgoing.try_send(m).is_err() {
                tokio::task::yield_now().await;
            }
        }
        let deadline = Instant::now() + Duration::from_secs(8);
        while h.stats.peers_dropped.load(Relaxed) == 0 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert_eq!(h.stats.peers_dropped.load(Relaxed), 1, "the stuck client is disconnected");
        let received = reader.await.unwrap();
        assert!(received > 500_000, "the reading client kept hearing: {received} bytes");
        // The stuck client finds its connection closed once it reads again.
        let mut buf = vec![0u8; 1 << 20];
        let mut closed = false;
        while let Ok(Ok(n)) = tokio::time::timeout(Duration::from_secs(2), stuck.read(&mut buf)).await {
            if n == 0 {
                closed = true;
                break;
            }
        }
        assert!(closed, "the stuck client was closed");
    }

    #[tokio::test]
    async fn tcpin_serves_several_clients_and_drops_a_silent_one() {
        let port = free_port();
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::TcpIn { host: "127.0.0.1".into(), port };
        let expiry = Duration::from_millis(1000);
        let mut h = spawn_with_expiry(addr, trust(false), None, rx, expiry);
        up(&mut h).await;
        let mut a = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let mut b = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let mut silent = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        a.write_all(&heartbeat(1, None)).await.unwrap();
        b.write_all(&heartbeat(255, None)).await.unwrap();
        frames(&mut h, 2).await;
        h.outgoing.send(out()).await.unwrap();
        assert!(hears_tcp(&mut a, Duration::from_secs(1)).await);
        assert!(hears_tcp(&mut b, Duration::from_secs(1)).await);
        // The silent client hears nothing and, after PEER_EXPIRY, is closed. The others
        // keep their place by vouching (a heartbeat a second, like PX4 and QGC).
        for _ in 0..15 {
            a.write_all(&heartbeat(1, None)).await.unwrap();
            b.write_all(&heartbeat(255, None)).await.unwrap();
            tokio::time::sleep(expiry / 8).await;
        }
        let mut buf = [0u8; 64];
        let r = tokio::time::timeout(Duration::from_secs(1), silent.read(&mut buf)).await;
        assert!(matches!(r, Ok(Ok(0))), "the silent client was closed: {r:?}");
        assert_eq!(h.stats.peers_dropped.load(Relaxed), 1);
        // Drain what a and b were sent, then check they still hear.
        while hears_tcp(&mut a, Duration::from_millis(50)).await {}
        while hears_tcp(&mut b, Duration::from_millis(50)).await {}
        h.outgoing.send(out()).await.unwrap();
        assert!(hears_tcp(&mut a, Duration::from_secs(1)).await);
        assert!(hears_tcp(&mut b, Duration::from_secs(1)).await);
    }

    /// The audit's attack on `tcpin`: connections held open and silent take every other
    /// place. A ground station connecting later is served, the longest-silent of them
    /// giving way, and a client that vouched never does.
    #[tokio::test]
    async fn silent_connections_give_way_to_a_new_client_when_the_places_are_full() {
        let port = free_port();
        let (_stop, rx) = broadcast::channel(1);
        let addr = LinkAddress::TcpIn { host: "127.0.0.1".into(), port };
        let mut h = spawn_with_expiry(addr, trust(false), None, rx, Duration::from_secs(30));
        up(&mut h).await;
        let mut autopilot = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        autopilot.write_all(&heartbeat(1, None)).await.unwrap();
        frames(&mut h, 1).await;
        let mut silent = Vec::new();
        for _ in 1..MAX_PEERS {
            silent.push(TcpStream::connect(("127.0.0.1", port)).await.unwrap());
        }
        let mut gcs = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        gcs.write_all(&heartbeat(255, None)).await.unwrap();
        frames(&mut h, 1).await;
        h.outgoing.send(out()).await.unwrap();
        assert!(hears_tcp(&mut gcs, Duration::from_secs(1)).await, "the ground station is served");
        assert!(hears_tcp(&mut autopilot, Duration::from_secs(1)).await, "the autopilot keeps its place");
        assert_eq!(h.stats.peers_dropped.load(Relaxed), 1, "one silent connection gave way");
        assert_eq!(h.stats.peers_refused.load(Relaxed), 0);
        let mut closed = 0;
        for s in &mut silent {
            let mut buf = [0u8; 64];
            if matches!(tokio::time::timeout(Duration::from_millis(200), s.read(&mut buf)).await, Ok(Ok(0))) {
                closed += 1;
            }
        }
        assert_eq!(closed, 1);
    }
}
