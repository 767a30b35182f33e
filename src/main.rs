//! The `mavloc` binary: parse the command line and dispatch to [`mavloc::commands`]; an
//! error is printed and exits 1.

use std::io::Write;
use std::process::ExitCode;

use clap::Parser;
use mavloc::cli::{Cli, Command};
use mavloc::commands::{self, Global};

fn main() -> ExitCode {
    let cli = Cli::parse();
    if !matches!(cli.command, Command::Run(_)) {
        // `mavloc eval ... | head`: a reader that leaves ends the command quietly, as
        // it does any Unix tool, instead of a panic in println!. Not for the daemon: its
        // log reader going away must not stop it (its log writes ignore the error).
        // SAFETY: restoring a signal's default disposition, before any thread starts.
        unsafe { libc::signal(libc::SIGPIPE, libc::SIG_DFL) };
    }
    // OpenCV's and the image decoders' own lines go through `tracing` (logging.rs); the
    // guard restores stderr and drains what is left when main returns.
    let native = mavloc::logging::capture_native_stderr();
    let code = match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            // A closed stderr is no reason to panic on the way out.
            let _ = writeln!(mavloc::logging::stderr(), "mavloc: {e:#}");
            ExitCode::FAILURE
        }
    };
    if code == ExitCode::from(commands::STOPPED_BY_CTRL_C) {
        // Stopped by Ctrl-C, its files in place: the stderr lines drained, then ended by
        // the signal, so a shell script running mavloc stops as well.
        drop(native);
        commands::die_by_sigint();
    }
    code
}

fn dispatch(cli: Cli) -> anyhow::Result<ExitCode> {
    let global = Global { config: cli.config, overrides: cli.overrides };
    match cli.command {
        Command::Run(args) => commands::run::run(args, global),
        Command::Demo(args) => commands::demo::run(args, global),
        Command::Sim { command } => commands::sim::run(command),
        Command::Area(args) => commands::area::run(args, global),
        Command::Indoor { command } => commands::indoor::run(command, global),
        Command::Eval { command } => commands::eval::run(command),
        Command::Config { command } => commands::config::run(command, global),
        Command::Params { command } => commands::params::run(command, global),
        Command::Import { command } => commands::import::run(command),
        Command::Calibrate { command } => commands::calibrate::run(command, global),
    }
}
