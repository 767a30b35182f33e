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
            // MAVLOC_CONFIG is a standing default (a shell profile, a unit's environment):
            // the file named on the command line wins over it; two files named on the
            // command line are refused.
            let from_env = global.config.as_ref().is_some_and(|c| {
                std::env::var_os("MAVLOC_CONFIG").is_some_and(|e| std::path::Path::new(&e) == c.as_path())
            });
            let file = match (file, &global.config) {
                (Some(f), Some(c)) if !from_env && !same_file(&f, c) => anyhow::bail!(
                    "two files to check: {} (the argument) and {} (--config); give one",
                    f.display(),
                    c.display()
                ),
                (Some(f), _) => f,
                (None, _) => match global.config_file() {
                    Some(f) => f,
                    None => {
                        use std::io::Write;
                        let _ = writeln!(
                            crate::logging::stderr(),
                            "mavloc: no configuration file: give one (`mavloc config check FILE`) or install {}",
                            settings::SYSTEM_CONFIG
                        );
                        // What `config check` promises for a configuration `run` cannot use.
                        return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
                    }
                },
            };
            let layers = settings::Layers::from_process(Some(file.clone()), global.overrides);
            let loaded = match settings::check(&layers, &crate::commands::FILE_CHECKS) {
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
