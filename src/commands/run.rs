//! `mavloc run`: the daemon ([`crate::daemon::run`]) on a tokio runtime, until SIGTERM or
//! SIGINT.

use std::process::ExitCode;

use super::Global;
use crate::cli::RunArgs;

pub fn run(args: RunArgs, global: Global) -> anyhow::Result<ExitCode> {
    let mut global = global;
    if let Some(address) = args.mavlink {
        global.overrides.push(format!("mavlink.connection={address}"));
    }
    let loaded = global.load()?;
    crate::logging::init(&loaded.settings.daemon.log);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .thread_name("mavloc-io")
        .build()?;
    runtime.block_on(async {
        use tokio::signal::unix::{signal, SignalKind};
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        let shutdown = async move {
            tokio::select! {
                _ = term.recv() => tracing::info!("SIGTERM: shutting down"),
                _ = int.recv() => tracing::info!("SIGINT: shutting down"),
            }
        };
        crate::daemon::run(loaded.settings, shutdown).await
    })?;
    // The link task may still hold a socket read; do not wait for it.
    runtime.shutdown_timeout(std::time::Duration::from_millis(200));
    Ok(ExitCode::SUCCESS)
}
