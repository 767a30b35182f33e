//! `mavloc params list` and `mavloc params reset [NAME]`: the values tuned over MAVLink
//! (QGroundControl's parameter editor), kept in `params.json` in the state directory.
//! They are a layer of the configuration: defaults < file < environment < tuned < `--set`.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;

use super::Global;
use crate::cli::ParamsCommand;
use crate::link::params::{apply_tuned, find, pinned_keys, read_tuned, Tuned, Unreadable};
use crate::settings::Loaded;

fn params_file(loaded: &Loaded) -> PathBuf {
    crate::daemon::state_dir(&loaded.settings).join("params.json")
}

fn read(path: &std::path::Path) -> anyhow::Result<BTreeMap<String, f64>> {
    match read_tuned(path) {
        Ok(m) => Ok(m.unwrap_or_default()),
        Err(Unreadable::Corrupt(why)) => {
            anyhow::bail!(
                "{}: not a parameter file ({why}); mavloc moves it aside at its next start",
                path.display()
            )
        }
        Err(Unreadable::Io(e)) => anyhow::bail!("{}: {e}", path.display()),
    }
}

/// Applies the tuned layer to `loaded` (settings and origins), as `mavloc run` would.
pub fn tuned_layer(loaded: &mut Loaded) -> (PathBuf, Vec<Tuned>) {
    let path = params_file(loaded);
    let Ok(tuned) = read(&path) else { return (path, Vec::new()) };
    let pinned = pinned_keys(&loaded.origins);
    let result = apply_tuned(&mut loaded.settings, &tuned, &pinned);
    for t in &result {
        if let Tuned::Applied { key, .. } = t {
            loaded.origins.insert(key.to_string(), format!("tuned over MAVLink ({})", path.display()));
        }
    }
    (path, result)
}

pub fn run(command: ParamsCommand, global: Global) -> anyhow::Result<ExitCode> {
    if let ParamsCommand::Doc = command {
        // Needs no configuration: it describes the parameters, not this machine's values.
        print!("{}", crate::link::metadata::markdown_table());
        return Ok(ExitCode::SUCCESS);
    }
    let loaded = global.load()?;
    let path = params_file(&loaded);
    match command {
        ParamsCommand::List => {
            let tuned = read(&path)?;
            if tuned.is_empty() {
                println!("no values tuned over MAVLink ({} holds none)", path.display());
                return Ok(ExitCode::SUCCESS);
            }
            let pinned = pinned_keys(&loaded.origins);
            let mut settings = loaded.settings.clone();
            println!("{:<16} {:<28} {:>12}  in force", "parameter", "configuration key", "tuned");
            for t in apply_tuned(&mut settings, &tuned, &pinned) {
                match t {
                    Tuned::Applied { name, key, value } => println!("{name:<16} {key:<28} {value:>12}  yes"),
                    Tuned::Pinned { name, key, value } => {
                        println!("{name:<16} {key:<28} {value:>12}  no: --set {key} wins")
                    }
                    Tuned::Dropped { name, why } => println!("{name:<16} {:<28} {:>12}  no: {why}", "", ""),
                }
            }
            println!("(from {})", path.display());
            Ok(ExitCode::SUCCESS)
        }
        ParamsCommand::Reset { name } => {
            let mut tuned = read(&path)?;
            let removed: Vec<String> = match &name {
                Some(n) => {
                    let n = n.to_uppercase();
                    if find(&n).is_none() && !tuned.contains_key(&n) {
                        anyhow::bail!(
                            "{n} is not a mavloc parameter (`mavloc params list` shows the tuned ones)"
                        );
                    }
                    tuned.remove(&n).map(|_| n).into_iter().collect()
                }
                None => std::mem::take(&mut tuned).into_keys().collect(),
            };
            if removed.is_empty() {
                println!("nothing to reset: {} holds no such tuned value", path.display());
                return Ok(ExitCode::SUCCESS);
            }
            let json = serde_json::to_string_pretty(&tuned)?;
            mavloc_data::write_atomic(&path, json.as_bytes())
                .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
            println!(
                "reset {} (the configuration's value applies from mavloc's next start)",
                removed.join(", ")
            );
            println!(
                "a running mavloc keeps its values and saves them again at the next parameter set: restart it now (systemctl restart mavloc)"
            );
            Ok(ExitCode::SUCCESS)
        }
        ParamsCommand::Doc => unreachable!("answered above"),
    }
}
