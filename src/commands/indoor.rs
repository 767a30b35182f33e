//! `mavloc indoor train|run|landings|map-eval`: the indoor pipeline offline
//! ([`crate::indoor::offline`]) and its simulated evaluations ([`crate::simulated`]).

use std::process::ExitCode;

use anyhow::anyhow;

use super::{Global, Progress};
use crate::cli::IndoorCommand;
use crate::indoor::offline;

pub fn run(command: IndoorCommand, global: Global) -> anyhow::Result<ExitCode> {
    let loaded = global.load()?;
    crate::logging::init(&loaded.settings.daemon.log);
    let settings = &loaded.settings;
    match command {
        IndoorCommand::Train(a) => {
            let labelling = match (&a.orthomap, a.map_metres_per_px) {
                (Some(map), Some(scale)) => offline::Labelling::Homography(
                    crate::indoor::labelling::OrthoMap::load(map, scale, a.map_origin, a.min_inliers)
                        .map_err(|e| anyhow!(e))?,
                ),
                _ => offline::Labelling::Telemetry,
            };
            let opts = offline::TrainOptions { dataset: a.dataset, out: a.out, labelling, seed: a.seed };
            let bar = Progress::new("histograms", "images");
            let r = offline::train(&opts, &settings.indoor, |done, total| {
                bar.set(done as u64, total as u64);
            })
            .map_err(|e| anyhow!(e))?;
            bar.finish();
            println!(
                "{}: {} images ({} rejected) in {:.1} s ({:.1} s of full-sampling histograms, {:.0} images/s)",
                opts.out.display(),
                r.images,
                r.rejected,
                r.seconds,
                r.histogram_seconds,
                (r.images + r.rejected) as f64 / r.histogram_seconds.max(1e-9)
            );
            let ranks: Vec<String> = r.loo_rms_m.iter().map(|v| format!("{v:.2}")).collect();
            println!("leave-one-out RMS error per neighbour rank, m: {}", ranks.join(", "));
            let fit: Vec<String> = r
                .inlier_sd_m
                .iter()
                .zip(&r.inlier_fraction)
                .map(|(sd, p)| format!("{:.0} % within SD {sd:.2}", p * 100.0))
                .collect();
            println!("per rank, right neighbours: {}", fit.join(", "));
            println!("process noise: {}", r.process_source);
            Ok(ExitCode::SUCCESS)
        }
        IndoorCommand::Run(a) => {
            let opts = offline::RunOptions {
                dataset: a.dataset,
                model: a.model,
                out: a.out,
                max_frames: a.frames,
                no_velocity: a.no_velocity,
                camera_velocity: a.camera_velocity,
                seed: a.seed,
            };
            let stop = super::stop_on_ctrl_c()?;
            let bar = Progress::new("indoor", "frames");
            let progress = |done: usize, total: usize| bar.set(done as u64, total as u64);
            let s =
                offline::run_stoppable(&opts, &settings.indoor, progress, &stop).map_err(|e| anyhow!(e))?;
            bar.finish();
            if !s.complete && s.frames == 0 {
                return Ok(super::stopped_with_nothing_written(
                    &opts.out,
                    "stopped by Ctrl-C before any frame was used",
                ));
            }
            if s.frames == 0 {
                anyhow::bail!(
                    "no frame of {} could be used ({} skipped; the log names each and why)",
                    opts.dataset.display(),
                    s.skipped_frames
                );
            }
            println!(
                "{}: {} frames ({} skipped), {:.0} frames/s whole frames: read+decode {:.2} ms, prepare {:.2} ms, localise {:.2} ms per frame; motion model {}, derotation {}",
                s.written_to.display(),
                s.frames,
                s.skipped_frames,
                s.frames_per_s,
                s.read_ms,
                s.prepare_ms,
                s.localize_ms,
                s.motion_model,
                if s.derotate { "on" } else { "off" }
            );
            if let (Some(n), rms) = (s.camera_velocity_frames, s.camera_velocity_rms_m_s) {
                println!(
                    "camera velocity on {n} frame pairs, {} per axis against the true velocity",
                    rms.map_or("no pair".into(), |r| format!("{r:.3} m/s RMS"))
                );
            }
            if !s.complete {
                let frames = s.frames + s.skipped_frames;
                return Ok(super::stopped_with_results("indoor run", frames, &s.written_to, &opts.out));
            }
            Ok(ExitCode::SUCCESS)
        }
        IndoorCommand::Landings(a) => {
            use crate::simulated::approach::{run, ApproachOptions};
            let model = crate::indoor::model::Model::load(&a.model).map_err(|e| anyhow!(e))?;
            let opts =
                ApproachOptions { trials: a.trials, seed: a.seed, max_s: a.max_s, ..Default::default() };
            let bar = Progress::new("approaches", "trials");
            let rows = run(&model, &settings.indoor, &opts, |done, total| {
                bar.set(done as u64, total as u64);
            })
            .map_err(|e| anyhow!(e))?;
            bar.finish();
            std::fs::create_dir_all(&a.out)?;
            let path = a.out.join("landings.csv");
            crate::output::write_atomic(&path, crate::data::results::landings_csv(&rows).as_bytes())?;
            let inside = rows.iter().filter(|r| r.fired && r.inside).count();
            let outside = rows.iter().filter(|r| r.fired && !r.inside).count();
            println!(
                "{}: {inside} of {} landings inside the zone, {outside} outside, {} not triggered within {} s",
                path.display(),
                rows.len(),
                rows.len() - inside - outside,
                a.max_s
            );
            Ok(ExitCode::SUCCESS)
        }
        IndoorCommand::MapEval(a) => {
            super::writable_file(&a.out, "heat map")?;
            let bar = Progress::new("rendering views", "views");
            let e = crate::simulated::mapeval::evaluate(
                &a.map,
                a.metres_per_px,
                a.views,
                a.sigma_m,
                &settings.indoor,
                a.seed,
                &|done, total| bar.set(done as u64, total as u64),
            )
            .map_err(|e| anyhow!(e))?;
            bar.finish();
            let title = format!("{}: L(D) = {:.4} over {} views", a.map.display(), e.global_loss, e.views);
            let drawn = crate::indoor::mapeval::heatmap(&a.out, &e, 0.25, &title);
            if a.json {
                let heatmap = drawn.is_ok().then_some(&a.out);
                println!(
                    "{}",
                    serde_json::json!({"global_loss": e.global_loss, "views": e.views, "heatmap": heatmap})
                );
            } else {
                println!("global loss L(D) = {:.4} over {} views (lower is better)", e.global_loss, e.views);
                if drawn.is_ok() {
                    println!("heat map: {}", a.out.display());
                }
            }
            // The loss is printed; the run still failed at what it was asked for.
            drawn.map_err(|why| anyhow!("heat map not written to {}: {why}", a.out.display()))?;
            Ok(ExitCode::SUCCESS)
        }
    }
}
