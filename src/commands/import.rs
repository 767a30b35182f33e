//! `mavloc import photos`: geotagged drone photos to a dataset ([`crate::import`]).

use std::process::ExitCode;

use crate::cli::ImportCommand;

pub fn run(command: ImportCommand) -> anyhow::Result<ExitCode> {
    match command {
        ImportCommand::Photos { dir, out, calibration, force } => {
            let r = crate::import::import_photos(&dir, &out, calibration.as_deref(), force)
                .map_err(anyhow::Error::msg)?;
            println!(
                "{}: {} photos imported, {} skipped; fx {:.1} px from the {}",
                out.display(),
                r.imported.len(),
                r.skipped.len(),
                r.fx_px,
                r.intrinsics_from
            );
            for (name, why) in &r.skipped {
                println!("  skipped {name}: {why}");
            }
            if let Some(note) = &r.kept_settings {
                println!("{note}");
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}
