//! `mavloc config check FILE` and `mavloc config show` (with the tuned-over-MAVLink layer).

use std::process::ExitCode;

use super::{load, Global};
use crate::cli::ConfigCommand;
use crate::link::params::Tuned;
use crate::settings;

pub fn run(command: ConfigCommand, global: Global) -> anyhow::Result<ExitCode> {
    match command {
        ConfigCommand::Check { file } => {
            let loaded = load(Some(file.clone()), global.overrides)?;
            // What `run` needs besides valid values (files it names): refused here too.
            let missing = settings::preflight(&loaded);
            if !missing.is_empty() {
                return Err(settings::SettingsError::Invalid(missing).into());
            }
            println!(
                "{}: valid ({} key{} set in the file or overridden)",
                file.display(),
                loaded.origins.len(),
                if loaded.origins.len() == 1 { "" } else { "s" }
            );
            Ok(ExitCode::SUCCESS)
        }
        ConfigCommand::Show => {
            let mut loaded = global.load()?;
            let (path, tuned) = super::params::tuned_layer(&mut loaded);
            print!("{}", settings::render_effective(&loaded));
            for t in tuned {
                if let Tuned::Pinned { name, key, value } = t {
                    println!("# {name} = {value} is tuned in {} but --set {key} wins", path.display());
                }
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}
