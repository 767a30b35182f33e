//! `mavloc demo`: the end-to-end demonstration ([`crate::demo`]) and its report.

use std::process::ExitCode;

use super::Global;
use crate::cli::DemoArgs;

/// Exit code of a demo that ran to completion and printed its report, but missed its
/// accuracy bar (FAIL); errors exit 1, so a script can tell the two apart.
pub const EXIT_FAIL: u8 = 2;

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
    let report = crate::demo::run(&opts, |stage| {
        let _ = writeln!(crate::logging::stderr(), "mavloc demo: {stage}");
    })?;
    print!("{report}");
    Ok(if report.passed() { ExitCode::SUCCESS } else { ExitCode::from(EXIT_FAIL) })
}
