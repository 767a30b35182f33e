//! `mavloc demo`: the end-to-end demonstration ([`crate::demo`]) and its report.

use std::process::ExitCode;

use super::Global;
use crate::cli::DemoArgs;

/// Runs the demo; it starts the vehicle and the daemon as child processes of the current
/// executable, which must therefore be the `mavloc` binary.
pub fn run(args: DemoArgs, global: Global) -> anyhow::Result<ExitCode> {
    let loaded = global.load()?;
    crate::logging::init(&loaded.settings.daemon.log);
    let opts = crate::demo::DemoOptions {
        bin: std::env::current_exe()?,
        out: args.out,
        coast_s: args.coast_s,
        indoor_s: args.indoor_s,
        views: args.views,
    };
    let report = crate::demo::run(&opts, |stage| eprintln!("mavloc demo: {stage}"))?;
    print!("{report}");
    Ok(if report.passed() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
