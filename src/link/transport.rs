//! The link task: opens the configured transport, keeps it open (reconnecting with
//! backoff), turns bytes into checked frames and outgoing messages into bytes.
//!
//! It logs one line per state change, never one per retry. While the link is down,
//! outgoing messages are dropped and counted: MAVLink is a stream of current state, and
//! a queue of stale heartbeats helps nobody.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use mavlink::dialects::common::MavMessage;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::{broadcast, mpsc};

use super::codec::{Decoder, Encoder, Frame, SkipCounts};
use super::signing::{Signer, SAVE_INTERVAL_S};
use super::LinkAddress;

/// A message for the link to send.
#[derive(Clone, Debug)]
pub struct Outgoing {
    pub system_id: u8,
    pub component_id: u8,
    pub message: MavMessage,
}

/// What the link tells the daemon.
#[derive(Debug)]
pub enum LinkEvent {
    /// A checked frame and when the reader took it off the wire, so queueing delay
    /// cannot bend time alignment or TIMESYNC.
    Frame { rx: tokio::time::Instant, frame: Box<Frame> },
    /// The transport is open (for `udpin`: bound; answers go to whoever spoke last).
    Up(String),
    /// The transport closed or failed; the link is retrying.
    Down(String),
}

/// Counters shared with the daemon (for logs and NAMED_VALUE_FLOAT).
#[derive(Default)]
pub struct LinkStats {
    pub skipped: Mutex<SkipCounts>,
    pub frames_in: std::sync::atomic::AtomicU64,
    pub frames_out: std::sync::atomic::AtomicU64,
    /// Outgoing messages dropped because the link was down or had no peer yet.
    pub dropped_out: std::sync::atomic::AtomicU64,
}

/// The daemon's side of a running link.
pub struct LinkHandle {
    pub outgoing: mpsc::Sender<Outgoing>,
    pub events: mpsc::Receiver<LinkEvent>,
    pub stats: Arc<LinkStats>,
    pub task: tokio::task::JoinHandle<()>,
}

/// Starts the link task. It runs until `shutdown` fires, then saves the signing
/// timestamp and returns.
pub fn spawn(address: LinkAddress, signer: Option<Signer>, shutdown: broadcast::Receiver<()>) -> LinkHandle {
    let (out_tx, out_rx) = mpsc::channel(256);
    let (ev_tx, ev_rx) = mpsc::channel(1024);
    let stats = Arc::new(LinkStats::default());
    let task = tokio::spawn(run(address, signer, out_rx, ev_tx, stats.clone(), shutdown));
    LinkHandle { outgoing: out_tx, events: ev_rx, stats, task }
}

const BACKOFF_MIN: Duration = Duration::from_millis(250);
const BACKOFF_MAX: Duration = Duration::from_secs(5);

trait Stream: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Stream for T {}

enum Conn {
    Udp { socket: UdpSocket, peer: Option<SocketAddr>, follow_sender: bool },
    Stream(Box<dyn Stream>),
}

struct Session {
    decoder: Decoder,
    encoder: Encoder,
    signer: Option<Signer>,
    stats: Arc<LinkStats>,
    events: mpsc::Sender<LinkEvent>,
}

impl Session {
    /// Forwards decoded frames; false when the daemon has gone. `datagram`: the bytes
    /// pushed are a whole datagram, so a frame cut short ends there.
    async fn drain(&mut self, datagram: bool) -> bool {
        loop {
            let signer = self.signer.as_mut();
            let f = if datagram {
                self.decoder.next_in_datagram(signer)
            } else {
                self.decoder.next_frame(signer)
            };
            let Some(f) = f else { break };
            let rx = tokio::time::Instant::now();
            self.stats.frames_in.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if self.events.send(LinkEvent::Frame { rx, frame: Box::new(f) }).await.is_err() {
                return false;
            }
        }
        *self.stats.skipped.lock().expect("stats lock") = self.decoder.skipped;
        true
    }

    fn encode(&mut self, o: &Outgoing) -> Vec<u8> {
        self.encoder.encode(o.system_id, o.component_id, &o.message, self.signer.as_mut())
    }
}

async fn open(address: &LinkAddress, listener: &mut Option<TcpListener>) -> std::io::Result<(Conn, String)> {
    match address {
        LinkAddress::UdpIn { host, port } => {
            let socket = UdpSocket::bind((host.as_str(), *port)).await?;
            Ok((
                Conn::Udp { socket, peer: None, follow_sender: true },
                format!("listening on udp {host}:{port}"),
            ))
        }
        LinkAddress::UdpOut { host, port } => {
            let peer = tokio::net::lookup_host((host.as_str(), *port))
                .await?
                .next()
                .ok_or_else(|| std::io::Error::other(format!("{host} resolves to no address")))?;
            let local: SocketAddr =
                if peer.is_ipv4() { "0.0.0.0:0".parse().unwrap() } else { "[::]:0".parse().unwrap() };
            let socket = UdpSocket::bind(local).await?;
            Ok((
                Conn::Udp { socket, peer: Some(peer), follow_sender: false },
                format!("sending to udp {peer}"),
            ))
        }
        LinkAddress::TcpOut { host, port } => {
            let s = TcpStream::connect((host.as_str(), *port)).await?;
            s.set_nodelay(true)?;
            Ok((Conn::Stream(Box::new(s)), format!("connected to tcp {host}:{port}")))
        }
        LinkAddress::TcpIn { host, port } => {
            if listener.is_none() {
                *listener = Some(TcpListener::bind((host.as_str(), *port)).await?);
            }
            let (s, peer) = listener.as_ref().expect("bound").accept().await?;
            s.set_nodelay(true)?;
            Ok((Conn::Stream(Box::new(s)), format!("tcp client {peer} on {host}:{port}")))
        }
        LinkAddress::Serial { device, baud } => {
            use tokio_serial::SerialPortBuilderExt;
            let s = tokio_serial::new(device, *baud).open_native_async().map_err(std::io::Error::other)?;
            Ok((Conn::Stream(Box::new(s)), format!("serial {device} at {baud} baud")))
        }
    }
}

async fn run(
    address: LinkAddress,
    signer: Option<Signer>,
    mut outgoing: mpsc::Receiver<Outgoing>,
    events: mpsc::Sender<LinkEvent>,
    stats: Arc<LinkStats>,
    mut shutdown: broadcast::Receiver<()>,
) {
    use std::sync::atomic::Ordering::Relaxed;
    let mut session =
        Session { decoder: Decoder::new(), encoder: Encoder::new(), signer, stats: stats.clone(), events };
    let mut backoff = BACKOFF_MIN;
    let mut listener = None;
    let mut last_error: Option<String> = None;
    let mut save_tick = tokio::time::interval(Duration::from_secs(SAVE_INTERVAL_S));
    'outer: loop {
        let opened = tokio::select! {
            r = open(&address, &mut listener) => r,
            _ = shutdown.recv() => break 'outer,
        };
        let (mut conn, what) = match opened {
            Ok(c) => c,
            Err(e) => {
                let msg = format!("{address}: {e}");
                if last_error.as_deref() != Some(&msg) {
                    tracing::warn!("link down: {msg}; retrying with backoff up to {BACKOFF_MAX:?}");
                    let _ = session.events.send(LinkEvent::Down(msg.clone())).await;
                    last_error = Some(msg);
                }
                // Drop what the daemon wants to send meanwhile, and keep waiting.
                let sleep = tokio::time::sleep(backoff);
                tokio::pin!(sleep);
                loop {
                    tokio::select! {
                        _ = &mut sleep => break,
                        o = outgoing.recv() => match o {
                            Some(_) => { stats.dropped_out.fetch_add(1, Relaxed); }
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
        if session.events.send(LinkEvent::Up(what)).await.is_err() {
            break;
        }
        session.decoder.reset();
        let mut buf = vec![0u8; 65536];
        let reason: String = loop {
            match &mut conn {
                Conn::Udp { socket, peer, follow_sender } => tokio::select! {
                    r = socket.recv_from(&mut buf) => match r {
                        Ok((n, from)) => {
                            if *follow_sender {
                                *peer = Some(from);
                            }
                            session.decoder.push(&buf[..n]);
                            if !session.drain(true).await { break 'outer; }
                        }
                        // ICMP "port unreachable" from a peer that went away surfaces
                        // here on Linux; the socket itself is fine.
                        Err(e) if e.kind() == std::io::ErrorKind::ConnectionRefused => {}
                        Err(e) => break format!("{address}: {e}"),
                    },
                    o = outgoing.recv() => match o {
                        Some(o) => match peer {
                            Some(p) => {
                                let bytes = session.encode(&o);
                                match socket.send_to(&bytes, *p).await {
                                    Ok(_) => { stats.frames_out.fetch_add(1, Relaxed); }
                                    Err(_) => { stats.dropped_out.fetch_add(1, Relaxed); }
                                }
                            }
                            None => { stats.dropped_out.fetch_add(1, Relaxed); }
                        },
                        None => break 'outer,
                    },
                    _ = save_tick.tick() => if let Some(s) = session.signer.as_mut() { s.save() },
                    _ = shutdown.recv() => break 'outer,
                },
                Conn::Stream(s) => tokio::select! {
                    r = s.read(&mut buf) => match r {
                        Ok(0) => break format!("{address}: closed by the peer"),
                        Ok(n) => {
                            session.decoder.push(&buf[..n]);
                            if !session.drain(false).await { break 'outer; }
                        }
                        Err(e) => break format!("{address}: {e}"),
                    },
                    o = outgoing.recv() => match o {
                        Some(o) => {
                            let bytes = session.encode(&o);
                            if let Err(e) = s.write_all(&bytes).await {
                                stats.dropped_out.fetch_add(1, Relaxed);
                                break format!("{address}: {e}");
                            }
                            stats.frames_out.fetch_add(1, Relaxed);
                        }
                        None => break 'outer,
                    },
                    _ = save_tick.tick() => if let Some(s) = session.signer.as_mut() { s.save() },
                    _ = shutdown.recv() => break 'outer,
                },
            }
        };
        tracing::warn!("link down: {reason}; reconnecting");
        if session.events.send(LinkEvent::Down(reason.clone())).await.is_err() {
            break;
        }
        last_error = Some(reason);
        tokio::time::sleep(BACKOFF_MIN).await;
    }
    if let Some(s) = session.signer.as_mut() {
        s.save();
    }
}
