//! `mavloc import photos`: geotagged drone photos to a dataset ([`crate::import`]).

use std::process::ExitCode;

use crate::cli::ImportCommand;

pub fn run(command: ImportCommand) -> anyhow::Result<ExitCode> {
    match command {
        ImportCommand::Photos { dir, out, calibration, force, mount_deg, ground_alt_m, altitude_datum } => {
            // Skipped photos and the image-up check speak through the log.
            crate::logging::init("info");
            let stop = super::stop_on_ctrl_c()?;
            let opts = crate::import::ImportOptions {
                calibration,
                replace: force,
                mount_deg,
                ground_alt_m,
                altitude_datum,
                stop: Some(stop.clone()),
            };
            let r = match crate::import::import_photos(&dir, &out, &opts) {
                Ok(r) => r,
                Err(e) if super::stopped(&stop) => return Ok(super::stopped_with_nothing_written(&out, &e)),
                Err(e) => return Err(anyhow::Error::msg(e)),
            };
            println!(
                "{}: {} photos imported, {} skipped; fx {:.1} px from the {}",
                out.display(),
                r.imported.len(),
                r.skipped.len(),
                r.fx_px,
                r.intrinsics_from
            );
            if let Some(o) = &r.origin {
                println!("take-off at {:.2} m above sea level: {}", o.alt_m, r.altitudes);
            }
            for (name, why) in &r.skipped {
                println!("  skipped {name}: {why}");
            }
            if let Some(m) = r.overlap_median_m {
                println!(
                    "overlapping photos agree on the ground within {m:.1} m (median over consecutive pairs)"
                );
            }
            for name in &r.turned {
                println!("  {name}: its image is turned half a turn from its tags (seen from its overlap); yaw corrected by 180 deg");
            }
            if let Some(note) = &r.kept_settings {
                println!("{note}");
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}
