//! `mavloc sim ...`: the simulated world (render datasets, plans, orthophotos, a
//! simulated vehicle). With the demo and the sim camera, the only users of the simulator
//! crate (`tests/layers.rs`).

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::anyhow;

use super::Progress;
use crate::cli::{RenderArgs, SimCommand};

pub fn run(command: SimCommand) -> anyhow::Result<ExitCode> {
    match command {
        SimCommand::Render(args) => render(args),
        SimCommand::Plan { scenario, out } => plan(&scenario, out),
        SimCommand::Vehicle { scenario, mavlink, system_id, duration, start, truth_log } => {
            let scenario = mavloc_sim::Scenario::load(&scenario).map_err(anyhow::Error::msg)?;
            let opts = mavloc_sim::vehicle::VehicleOptions {
                address: mavlink,
                system_id,
                duration_s: duration,
                start_s: start,
                truth_log,
            };
            eprintln!("simulated vehicle: {} over {}", scenario.name, opts.address);
            let landed = mavloc_sim::vehicle::run(&scenario, &opts).map_err(anyhow::Error::msg)?;
            if let Some(p) = landed {
                println!("landed at north {:.3} east {:.3} m", p.x, p.y);
            }
            Ok(ExitCode::SUCCESS)
        }
        SimCommand::Orthophoto { scenario, out, half_extent_m, metres_per_px } => {
            if !(metres_per_px > 0.0 && half_extent_m > 0.0 && half_extent_m / metres_per_px <= 8000.0) {
                anyhow::bail!(
                    "--half-extent-m and --metres-per-px must be positive, at most 16000 px a side"
                );
            }
            writable_image(&out)?;
            let scenario = mavloc_sim::Scenario::load(&scenario).map_err(|e| anyhow!(e))?;
            let world = mavloc_sim::World::build(&scenario).map_err(|e| anyhow!(e))?;
            let (w, h, rgb) = world.orthophoto(half_extent_m, metres_per_px);
            image_write(&out, w, h, &rgb)?;
            println!(
                "{}: {w}x{h} px at {metres_per_px} m/px, centred on the origin, north up",
                out.display()
            );
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `mavloc sim render`: a dataset from a scenario, with a progress bar.
fn render(args: Box<RenderArgs>) -> anyhow::Result<ExitCode> {
    use mavloc_sim::{render_dataset_until, RenderOptions, Scenario};
    let scenario = Scenario::load(&args.scenario).map_err(|e| anyhow!(e))?;
    let mut noise = scenario.noise.clone();
    if args.no_noise {
        noise = mavloc_sim::scenario::NoiseSpec::none();
    }
    if let Some(sd) = args.gimbal_sd_deg {
        noise.gimbal_yaw_sd_deg = sd;
        noise.gimbal_pitch_sd_deg = sd;
    }
    if let Some(v) = args.position_sd_m {
        noise.position_sd_m = v;
    }
    if let Some(v) = args.gimbal_offset_deg {
        noise.gimbal_offset_deg = v;
    }
    if let Some(d) = args.gimbal_drift_deg {
        noise.gimbal_drift_sd_deg = d;
    }
    if let Some(tau) = args.gimbal_drift_tau_s {
        noise.gimbal_drift_tau_s = tau;
    }
    if let Some(lag) = args.gimbal_lag_s {
        noise.gimbal_lag_s = lag;
    }
    if let Some(rate) = args.drop_rate {
        noise.drop_rate = rate;
    }
    if args.blur_px.is_some_and(|b| b == 0 || b % 2 == 0) {
        anyhow::bail!("--blur-px must be an odd number of pixels (1 = no blur)");
    }
    let appearance =
        (args.brightness.is_some() || args.contrast.is_some() || args.blur_px.is_some()).then(|| {
            crate::data::dataset::Appearance {
                brightness: args.brightness.unwrap_or(0.0),
                contrast: args.contrast.unwrap_or(1.0),
                blur_px: args.blur_px.unwrap_or(1),
            }
        });
    let opts = RenderOptions {
        views: args.views,
        appearance,
        frames: args.frames,
        size: args.width.zip(args.height),
        seed: args.seed,
        noise: Some(noise),
        force: args.force,
        frames_from: args.frames_from.clone(),
    };
    let stop = super::stop_on_ctrl_c()?;
    let bar = Progress::new(&format!("rendering {}", scenario.name), "frames");
    let start = std::time::Instant::now();
    let progress = |done: usize, total: usize| bar.set(done as u64, total as u64);
    let summary = match render_dataset_until(&scenario, &opts, &args.out, progress, &stop) {
        Ok(s) => s,
        Err(e) if super::stopped(&stop) => {
            bar.finish();
            return Ok(super::stopped_with_nothing_written(&args.out, &e));
        }
        Err(e) => return Err(anyhow!(e)),
    };
    bar.finish();
    println!(
        "{}: {} frames ({} dropped) of {} in {:.1} s",
        summary.dir.display(),
        summary.frames,
        summary.dropped,
        scenario.name,
        start.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// `mavloc sim plan`: the scenario's mission as a QGroundControl plan.
fn plan(scenario: &str, out: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    let scenario = mavloc_sim::Scenario::load(scenario).map_err(|e| anyhow!(e))?;
    let world = mavloc_sim::World::build(&scenario).map_err(|e| anyhow!(e))?;
    let mission = mavloc_sim::Mission::plan(&world).map_err(|e| anyhow!(e))?;
    let text = serde_json::to_string_pretty(&mission.qgc_plan(&world.frame))? + "\n";
    match out {
        Some(path) => {
            std::fs::write(&path, text).map_err(|e| anyhow!("cannot write {}: {e}", path.display()))?;
            println!("{}: {} waypoints", path.display(), mission.waypoints.len());
        }
        None => print!("{text}"),
    }
    Ok(ExitCode::SUCCESS)
}

/// Writes an RGB image (format from the extension) through OpenCV.
fn image_write(path: &Path, w: usize, h: usize, rgb: &[u8]) -> anyhow::Result<()> {
    use opencv::prelude::*;
    let bgr = crate::imaging::bgr_from_rgb(rgb, h as u32)?;
    anyhow::ensure!(bgr.cols() as usize == w, "image width mismatch");
    let written = opencv::imgcodecs::imwrite(path, &bgr, &opencv::core::Vector::new())
        .map_err(|e| anyhow!("cannot write {}: {}", path.display(), e.message))?;
    if !written {
        anyhow::bail!("cannot write {}", path.display());
    }
    Ok(())
}

/// An image file `imwrite` can write at `path`, checked before the work that makes it.
fn writable_image(path: &Path) -> anyhow::Result<()> {
    super::writable_file(path, "image")?;
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    if !matches!(ext.as_str(), "png" | "jpg" | "jpeg" | "tif" | "tiff" | "bmp") {
        anyhow::bail!("--out {}: name the image .png, .jpg, .tif or .bmp", path.display());
    }
    Ok(())
}
