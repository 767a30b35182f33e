//! `mavloc run`: the daemon ([`crate::daemon::run`]) on a tokio runtime, until SIGTERM or
//! SIGINT (SIGHUP is ignored). Exit codes: 0 after a clean stop; 78 (EX_CONFIG) when the configuration cannot
//! run (bad file or key, unusable state directory: a restart would fail the same way, so
//! the unit lists it in `RestartPreventExitStatus=`); 1 for anything else.

use std::io::Write;
use std::process::ExitCode;

use super::Global;
use crate::cli::RunArgs;

pub fn run(args: RunArgs, global: Global) -> anyhow::Result<ExitCode> {
    let mut global = global;
    if let Some(address) = args.mavlink {
        global.overrides.push(format!("mavlink.connection={address}"));
    }
    // Every problem at once, files the settings name included, as `config check` reports.
    let layers = crate::settings::Layers::from_process(global.config_file(), global.overrides.clone());
    let loaded = match crate::settings::check(&layers, &crate::commands::FILE_CHECKS) {
        Ok(l) => l,
        Err(e) => {
            let _ = writeln!(crate::logging::stderr(), "mavloc: {e:#}");
            return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
        }
    };
    crate::logging::init(&loaded.settings.daemon.log);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .thread_name("mavloc-io")
        .build()?;
    let result = runtime.block_on(async {
        use tokio::signal::unix::{signal, SignalKind};
        let mut term = signal(SignalKind::terminate())?;
        let mut int = signal(SignalKind::interrupt())?;
        // SIGHUP (the SSH session of someone trying mavloc on the drone ends) killed the
        // daemon uncleanly, the vehicle's position source with it: it is said and ignored,
        // as there is no configuration to reload in place.
        let mut hup = signal(SignalKind::hangup())?;
        let shutdown = async move {
            loop {
                tokio::select! {
                    _ = term.recv() => break tracing::info!("SIGTERM: shutting down"),
                    _ = int.recv() => break tracing::info!("SIGINT: shutting down"),
                    _ = hup.recv() => tracing::warn!(
                        "SIGHUP ignored: mavloc keeps running (a changed configuration takes a restart)"
                    ),
                }
            }
        };
        let pinned = crate::link::params::pinned_keys(&loaded.origins);
        crate::daemon::run(loaded.settings, pinned, shutdown).await
    });
    if let Err(e) = &result {
        if e.downcast_ref::<crate::daemon::Unusable>().is_some() {
            tracing::error!("{e:#}");
            let _ = writeln!(crate::logging::stderr(), "mavloc: {e:#}");
            return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
        }
    }
    result?;
    // The link task may still hold a socket read; do not wait for it.
    runtime.shutdown_timeout(std::time::Duration::from_millis(200));
    Ok(ExitCode::SUCCESS)
}
