//! Logging: `tracing` with a filter from `RUST_LOG` or, when that is unset, from the
//! configuration's `daemon.log`. Plain lines without colour when stderr is not a terminal,
//! which is what journald stores under systemd.

use std::io::IsTerminal;
use std::io::Write;

use tracing_subscriber::EnvFilter;

/// Installs the global subscriber. `fallback` is the filter used when `RUST_LOG` is unset.
/// Calling it twice is harmless (the second call keeps the first subscriber).
pub fn init(fallback: &str) {
    let filter = match std::env::var("RUST_LOG") {
        Ok(v) if !v.trim().is_empty() => EnvFilter::try_new(&v).unwrap_or_else(|e| {
            let _ = writeln!(std::io::stderr(), "mavloc: ignoring RUST_LOG={v:?}: {e}");
            EnvFilter::new(fallback)
        }),
        _ => EnvFilter::try_new(fallback).unwrap_or_else(|_| EnvFilter::new("info")),
    };
    let terminal = std::io::stderr().is_terminal();
    let builder =
        tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(terminal);
    // journald adds its own timestamps; a terminal user wants them.
    let _ = if terminal { builder.try_init() } else { builder.without_time().try_init() };
}
