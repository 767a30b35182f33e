//! `mavloc config check FILE` and `mavloc config show` (with the tuned-over-MAVLink layer).

use std::process::ExitCode;

use super::Global;
use crate::cli::ConfigCommand;
use crate::link::params::Tuned;
use crate::settings;

pub fn run(command: ConfigCommand, global: Global) -> anyhow::Result<ExitCode> {
    match command {
        ConfigCommand::Check { file } => {
            // FILE, else --config (or MAVLOC_CONFIG), else the system file: one file, named.
            let file = match (file, &global.config) {
                (Some(f), Some(c)) if !same_file(&f, c) => anyhow::bail!(
                    "two files to check: {} (the argument) and {} (--config or MAVLOC_CONFIG); give one",
                    f.display(),
                    c.display()
                ),
                (Some(f), _) => f,
                (None, _) => global.config_file().ok_or_else(|| {
                    anyhow::anyhow!(
                        "no configuration file: give one (`mavloc config check FILE`) or install {}",
                        settings::SYSTEM_CONFIG
                    )
                })?,
            };
            let layers = settings::Layers::from_process(Some(file.clone()), global.overrides);
            let loaded = match settings::check(&layers) {
                Ok(l) => l,
                Err(e) => {
                    use std::io::Write;
                    let _ = writeln!(crate::logging::stderr(), "mavloc: {e}");
                    // The code `run` exits with on the same configuration.
                    return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
                }
            };
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

/// Whether two paths name the same file (either may not exist).
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    a == b || matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y)
}
