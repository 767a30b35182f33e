//! `mavloc import photos`: geotagged drone photos to a dataset ([`crate::import`]).

use std::process::ExitCode;

use crate::cli::ImportCommand;

pub fn run(command: ImportCommand) -> anyhow::Result<ExitCode> {
    match command {
        ImportCommand::Photos { dir, out, calibration } => {
            let r = crate::import::import_photos(&dir, &out, calibration.as_deref())
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
            Ok(ExitCode::SUCCESS)
        }
    }
}
