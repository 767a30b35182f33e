//! Logging: `tracing` with a filter from `RUST_LOG` or, when that is unset, from the
//! configuration's `daemon.log`. Plain lines without colour when stderr is not a terminal,
//! which is what journald stores under systemd.
//!
//! OpenCV 4.6 (Debian's) writes its own log lines (`[ WARN:0@0.444] global ...`) and its
//! image decoders theirs (libjpeg's "Premature end of JPEG file") straight to file
//! descriptor 2, and has no callback to take them. So [`capture_native_stderr`] puts a pipe
//! in place of fd 2: a thread reads it, turns those lines into `tracing` events (target
//! `opencv`, at their level) and passes every other line through unchanged to the real
//! stderr, which mavloc's own output (tracing, progress bars, error messages) writes to
//! directly. The descriptor table is process-wide by nature, hence the one global here.

use std::fs::File;
use std::io::{BufRead, IsTerminal, Write};
use std::os::fd::FromRawFd;
use std::sync::OnceLock;

use tracing_subscriber::EnvFilter;

/// The real stderr once fd 2 has been captured.
static REAL_STDERR: OnceLock<File> = OnceLock::new();

/// Where mavloc's own diagnostics go: the real stderr (not the capture pipe). Borrowed,
/// not duplicated: tracing asks for a writer on every event.
pub fn stderr() -> Box<dyn Write + Send> {
    match REAL_STDERR.get() {
        Some(f) => Box::new(f),
        None => Box::new(std::io::stderr()),
    }
}

/// Whether the real stderr is a terminal.
pub fn stderr_is_terminal() -> bool {
    match REAL_STDERR.get() {
        Some(f) => f.is_terminal(),
        None => std::io::stderr().is_terminal(),
    }
}

/// A progress bar target on the real stderr (hidden when it is not a terminal).
pub fn progress_target() -> indicatif::ProgressDrawTarget {
    match REAL_STDERR.get().and_then(|f| f.try_clone().ok()) {
        Some(f) if f.is_terminal() => match File::open("/dev/null") {
            Ok(input) => indicatif::ProgressDrawTarget::term(console::Term::read_write_pair(input, f), 20),
            Err(_) => indicatif::ProgressDrawTarget::hidden(),
        },
        Some(_) => indicatif::ProgressDrawTarget::hidden(),
        None => indicatif::ProgressDrawTarget::stderr(),
    }
}

/// Installs the global subscriber. `fallback` is the filter used when `RUST_LOG` is unset.
/// Calling it twice is harmless (the second call keeps the first subscriber).
pub fn init(fallback: &str) {
    let filter = match std::env::var("RUST_LOG") {
        Ok(v) if !v.trim().is_empty() => EnvFilter::try_new(&v).unwrap_or_else(|e| {
            let _ = writeln!(stderr(), "mavloc: ignoring RUST_LOG={v:?}: {e}");
            EnvFilter::new(fallback)
        }),
        _ => EnvFilter::try_new(fallback).unwrap_or_else(|_| EnvFilter::new("info")),
    };
    let terminal = stderr_is_terminal();
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(stderr).with_ansi(terminal);
    // journald adds its own timestamps; a terminal user wants them.
    let _ = if terminal { builder.try_init() } else { builder.without_time().try_init() };
}

/// Restores fd 2 and drains the pipe when dropped (at the end of `main`).
pub struct NativeCapture {
    saved: i32,
    drained: std::sync::mpsc::Receiver<()>,
}

/// Captures fd 2 (see the module's doc). `None` if the process cannot (no fds left): then
/// the native lines go to stderr as they are.
pub fn capture_native_stderr() -> Option<NativeCapture> {
    // SAFETY: plain descriptor calls on descriptors this function owns; fd 2 is replaced
    // atomically by dup2, so a concurrent writer sees either the old or the new file.
    unsafe {
        let saved = libc::fcntl(2, libc::F_DUPFD_CLOEXEC, 3);
        if saved < 0 {
            return None;
        }
        let mut fds = [0i32; 2];
        if libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) != 0 {
            libc::close(saved);
            return None;
        }
        if libc::dup2(fds[1], 2) < 0 {
            libc::close(fds[0]);
            libc::close(fds[1]);
            libc::close(saved);
            return None;
        }
        libc::close(fds[1]);
        let real = File::from_raw_fd(libc::fcntl(saved, libc::F_DUPFD_CLOEXEC, 3));
        let _ = REAL_STDERR.set(real);
        let read = File::from_raw_fd(fds[0]);
        let (tx, rx) = std::sync::mpsc::channel();
        let spawned = std::thread::Builder::new().name("native-stderr".into()).spawn(move || {
            let mut lines = std::io::BufReader::new(read);
            let mut buf = Vec::new();
            while matches!(lines.read_until(b'\n', &mut buf), Ok(n) if n > 0) {
                forward(&String::from_utf8_lossy(&buf));
                buf.clear();
            }
            let _ = tx.send(());
        });
        if spawned.is_err() {
            libc::dup2(saved, 2);
            libc::close(saved);
            return None;
        }
        Some(NativeCapture { saved, drained: rx })
    }
}

impl Drop for NativeCapture {
    fn drop(&mut self) {
        // SAFETY: `saved` is ours; putting it back on fd 2 closes the pipe's last write end
        // (unless a child process still holds it, hence the bounded wait).
        unsafe {
            libc::dup2(self.saved, 2);
            libc::close(self.saved);
        }
        let _ = self.drained.recv_timeout(std::time::Duration::from_millis(500));
    }
}

/// How a native line is passed on.
#[derive(Debug, PartialEq)]
enum Native<'a> {
    /// An OpenCV log line: its level and message.
    OpenCv(tracing::Level, &'a str),
    /// A decoder's message (libjpeg, libpng): a warning.
    Decoder(&'a str),
    /// Anything else: written to the real stderr unchanged.
    Other,
}

/// Sorts a line written to fd 2.
fn classify(line: &str) -> Native<'_> {
    let l = line.trim_end();
    // OpenCV: `[ WARN:0@0.444] global /path/file.cpp (902) open message`.
    if let Some(rest) = l.strip_prefix('[') {
        if let Some((head, msg)) = rest.split_once(']') {
            let level = match head.trim_start().split(':').next().unwrap_or("") {
                "FATAL" | "ERROR" => Some(tracing::Level::ERROR),
                "WARN" => Some(tracing::Level::WARN),
                "INFO" => Some(tracing::Level::INFO),
                "DEBUG" => Some(tracing::Level::DEBUG),
                "VERBOSE" => Some(tracing::Level::TRACE),
                _ => None,
            };
            if let Some(level) = level {
                let msg = msg.trim();
                return Native::OpenCv(level, msg.strip_prefix("global ").unwrap_or(msg));
            }
            // FFmpeg, OpenCV's video decoder: `[mov,mp4,m4a @ 0x7fcc...] moov atom not found`.
            if head.contains(" @ 0x") {
                return Native::Decoder(l);
            }
        }
    }
    const DECODERS: [&str; 6] = [
        "Premature end of JPEG",
        "Corrupt JPEG",
        "Invalid JPEG",
        "Not a JPEG",
        "libpng warning",
        "libpng error",
    ];
    if DECODERS.iter().any(|d| l.starts_with(d)) {
        return Native::Decoder(l);
    }
    Native::Other
}

fn forward(line: &str) {
    // Before a subscriber exists (or in a command that never sets one) nothing would be
    // shown: pass the line through rather than lose it.
    let subscribed = tracing::dispatcher::has_been_set();
    match classify(line) {
        Native::OpenCv(level, msg) if subscribed => match level {
            tracing::Level::ERROR => tracing::error!(target: "opencv", "{msg}"),
            tracing::Level::WARN => tracing::warn!(target: "opencv", "{msg}"),
            tracing::Level::INFO => tracing::info!(target: "opencv", "{msg}"),
            tracing::Level::DEBUG => tracing::debug!(target: "opencv", "{msg}"),
            _ => tracing::trace!(target: "opencv", "{msg}"),
        },
        Native::Decoder(msg) if subscribed => tracing::warn!(target: "opencv", "image decoder: {msg}"),
        _ => {
            let _ = stderr().write_all(line.as_bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opencv_and_decoder_lines_are_told_from_others() {
        assert_eq!(
            classify("[ WARN:0@0.444] global cap_v4l.cpp (902) open VIDEOIO(V4L2:/dev/video9): can't open camera by index\n"),
            Native::OpenCv(
                tracing::Level::WARN,
                "cap_v4l.cpp (902) open VIDEOIO(V4L2:/dev/video9): can't open camera by index"
            )
        );
        assert_eq!(
            classify("[ERROR:0@1.2] global x.cpp (1) f oops"),
            Native::OpenCv(tracing::Level::ERROR, "x.cpp (1) f oops")
        );
        assert_eq!(classify("Premature end of JPEG file\n"), Native::Decoder("Premature end of JPEG file"));
        assert_eq!(
            classify("[mov,mp4,m4a @ 0x7fcca0001480] moov atom not found\n"),
            Native::Decoder("[mov,mp4,m4a @ 0x7fcca0001480] moov atom not found")
        );
        assert_eq!(classify("mavloc: cannot read x\n"), Native::Other);
        assert_eq!(classify("[section] not a log line"), Native::Other);
    }
}
