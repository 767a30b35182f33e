//! `mavloc config check FILE` and `mavloc config show`.

use std::process::ExitCode;

use super::{load, Global};
use crate::cli::ConfigCommand;
use crate::settings;

pub fn run(command: ConfigCommand, global: Global) -> anyhow::Result<ExitCode> {
    match command {
        ConfigCommand::Check { file } => {
            let loaded = load(Some(file.clone()), global.overrides)?;
            println!(
                "{}: valid ({} key{} set in the file or overridden)",
                file.display(),
                loaded.origins.len(),
                if loaded.origins.len() == 1 { "" } else { "s" }
            );
            Ok(ExitCode::SUCCESS)
        }
        ConfigCommand::Show => {
            let loaded = global.load()?;
            print!("{}", settings::render_effective(&loaded));
            Ok(ExitCode::SUCCESS)
        }
    }
}
