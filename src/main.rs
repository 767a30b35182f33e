//! The `mavloc` binary: parse the command line, load the configuration, dispatch.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use mavloc::cli::{Cli, Command, ConfigCommand};
use mavloc::settings::{self, Layers, Loaded};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("mavloc: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// The configuration file to use: the one given, else the system one if it exists.
fn config_file(given: Option<PathBuf>) -> Option<PathBuf> {
    given.or_else(|| {
        Path::new(settings::SYSTEM_CONFIG)
            .exists()
            .then(|| PathBuf::from(settings::SYSTEM_CONFIG))
    })
}

fn load(file: Option<PathBuf>, overrides: Vec<String>) -> anyhow::Result<Loaded> {
    Ok(settings::load(&Layers::from_process(file, overrides))?)
}

/// Tells the user plainly that a command is not built yet, and which issue builds it.
fn not_yet(what: &str, issue: u32) -> anyhow::Result<ExitCode> {
    eprintln!("mavloc {what}: not implemented yet (tracked as issue #{issue}); nothing was done.");
    Ok(ExitCode::from(2))
}

fn dispatch(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Config {
            command: ConfigCommand::Check { file },
        } => {
            let loaded = load(Some(file.clone()), cli.overrides)?;
            println!(
                "{}: valid ({} key{} set in the file or overridden)",
                file.display(),
                loaded.origins.len(),
                if loaded.origins.len() == 1 { "" } else { "s" }
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Config {
            command: ConfigCommand::Show,
        } => {
            let loaded = load(config_file(cli.config), cli.overrides)?;
            print!("{}", settings::render_effective(&loaded));
            Ok(ExitCode::SUCCESS)
        }
        Command::Demo(args) => {
            let loaded = load(config_file(cli.config), cli.overrides)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            let report = mavloc::demo::run(&loaded.settings, args.seed)?;
            print!("{report}");
            Ok(if report.passed() {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            })
        }
        Command::Run(args) => {
            let mut overrides = cli.overrides;
            if let Some(address) = args.mavlink {
                overrides.push(format!("mavlink.connection={address}"));
            }
            let loaded = load(config_file(cli.config), overrides)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            tracing::info!(connection = %loaded.settings.mavlink.connection, "configuration valid");
            not_yet("run (the daemon)", 6)
        }
        Command::Sim { .. } => not_yet("sim", 3),
        Command::Area(_) => not_yet("area", 4),
        Command::Indoor { .. } => not_yet("indoor", 5),
        Command::Eval { .. } => not_yet("eval", 4),
    }
}
