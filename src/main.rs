//! The `mavloc` binary: parse the command line, load the configuration, dispatch.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use mavloc::cli::{
    AreaArgs, Cli, Command, ConfigCommand, EvalCommand, ImportCommand, IndoorCommand, RenderArgs, SimCommand,
};
use mavloc::settings::{self, Layers, Loaded};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("mavloc: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// The configuration file to use: the one given, else the system one if it exists.
fn config_file(given: Option<PathBuf>) -> Option<PathBuf> {
    given.or_else(|| {
        Path::new(settings::SYSTEM_CONFIG).exists().then(|| PathBuf::from(settings::SYSTEM_CONFIG))
    })
}

fn load(file: Option<PathBuf>, overrides: Vec<String>) -> anyhow::Result<Loaded> {
    Ok(settings::load(&Layers::from_process(file, overrides))?)
}

/// Tells the user plainly that a command is not built yet, and which issue builds it.
fn dispatch(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Config { command: ConfigCommand::Check { file } } => {
            let loaded = load(Some(file.clone()), cli.overrides)?;
            println!(
                "{}: valid ({} key{} set in the file or overridden)",
                file.display(),
                loaded.origins.len(),
                if loaded.origins.len() == 1 { "" } else { "s" }
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Config { command: ConfigCommand::Show } => {
            let loaded = load(config_file(cli.config), cli.overrides)?;
            print!("{}", settings::render_effective(&loaded));
            Ok(ExitCode::SUCCESS)
        }
        Command::Demo(args) => {
            let loaded = load(config_file(cli.config), cli.overrides)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            let opts = mavloc::demo::DemoOptions {
                bin: std::env::current_exe()?,
                out: args.out,
                coast_s: args.coast_s,
                indoor_s: args.indoor_s,
                views: args.views,
            };
            let report = mavloc::demo::run(&opts, |stage| eprintln!("mavloc demo: {stage}"))?;
            print!("{report}");
            Ok(if report.passed() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
        }
        Command::Run(args) => {
            let mut overrides = cli.overrides;
            if let Some(address) = args.mavlink {
                overrides.push(format!("mavlink.connection={address}"));
            }
            let loaded = load(config_file(cli.config), overrides)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .enable_all()
                .thread_name("mavloc-io")
                .build()?;
            runtime.block_on(async {
                use tokio::signal::unix::{signal, SignalKind};
                let mut term = signal(SignalKind::terminate())?;
                let mut int = signal(SignalKind::interrupt())?;
                let shutdown = async move {
                    tokio::select! {
                        _ = term.recv() => tracing::info!("SIGTERM: shutting down"),
                        _ = int.recv() => tracing::info!("SIGINT: shutting down"),
                    }
                };
                mavloc::daemon::run(loaded.settings, shutdown).await
            })?;
            // The link task may still hold a socket read; do not wait for it.
            runtime.shutdown_timeout(std::time::Duration::from_millis(200));
            Ok(ExitCode::SUCCESS)
        }
        Command::Sim { command: SimCommand::Render(args) } => sim_render(args),
        Command::Sim { command: SimCommand::Plan { scenario, out } } => sim_plan(&scenario, out),
        Command::Sim {
            command: SimCommand::Vehicle { scenario, mavlink, system_id, duration, start, truth_log },
        } => {
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
        Command::Sim { command: SimCommand::Orthophoto { scenario, out, half_extent_m, metres_per_px } } => {
            use anyhow::anyhow;
            if !(metres_per_px > 0.0 && half_extent_m > 0.0 && half_extent_m / metres_per_px <= 8000.0) {
                anyhow::bail!(
                    "--half-extent-m and --metres-per-px must be positive, at most 16000 px a side"
                );
            }
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
        Command::Area(args) => {
            // A dataset may carry the settings it needs (an imported photo survey does).
            let own = args.dataset.join(mavloc::data::SETTINGS_FILE);
            let mut layers = Layers::from_process(config_file(cli.config), cli.overrides);
            layers.dataset = own.exists().then(|| own.clone());
            let loaded = settings::load(&layers)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            let own_origin = own.display().to_string();
            let from_dataset: Vec<&str> =
                loaded.origins.iter().filter(|(_, o)| **o == own_origin).map(|(k, _)| k.as_str()).collect();
            if !from_dataset.is_empty() {
                println!("settings from the dataset's {}: {}", own.display(), from_dataset.join(", "));
            }
            area_run(args, &loaded.settings)
        }
        Command::Indoor { command } => {
            let loaded = load(config_file(cli.config), cli.overrides)?;
            mavloc::logging::init(&loaded.settings.daemon.log);
            indoor(command, &loaded.settings)
        }
        Command::Import { command: ImportCommand::Photos { dir, out, calibration } } => {
            let r = mavloc::import::import_photos(&dir, &out, calibration.as_deref())
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
        Command::Eval { command: EvalCommand::Area { dataset, result, json } } => {
            eval_area(&dataset, &result, json)
        }
        Command::Eval { command: EvalCommand::Indoor { dataset, result, json } } => {
            eval_indoor(&dataset, &result, json)
        }
    }
}

/// `mavloc sim render`: a dataset from a scenario, with a progress bar.
fn sim_render(args: Box<RenderArgs>) -> anyhow::Result<ExitCode> {
    use anyhow::anyhow;
    use mavloc_sim::{render_dataset, RenderOptions, Scenario};
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
            mavloc::data::dataset::Appearance {
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
    };
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames, {per_sec}, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(format!("rendering {}", scenario.name));
    let start = std::time::Instant::now();
    let summary = render_dataset(&scenario, &opts, &args.out, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .map_err(|e| anyhow!(e))?;
    bar.finish_and_clear();
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
fn sim_plan(scenario: &str, out: Option<PathBuf>) -> anyhow::Result<ExitCode> {
    use anyhow::anyhow;
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

/// `mavloc area`: the area pipeline over a dataset, with a progress bar and a summary.
fn area_run(args: AreaArgs, settings: &mavloc::settings::Settings) -> anyhow::Result<ExitCode> {
    use mavloc::area::offline::{run, RunOptions};
    use mavloc::settings::AreaMethod;
    let method = match args.method.as_deref() {
        Some("ground-plane") => AreaMethod::GroundPlane,
        Some(_) => AreaMethod::Ukf,
        None => settings.area.method,
    };
    let opts = RunOptions {
        dataset: args.dataset,
        out: args.out,
        method,
        trace: args.trace,
        max_frames: args.frames,
        debug_masks: args.debug_masks,
    };
    let bar = progress_bar("area");
    let summary = run(&opts, settings, |done, total| {
        bar.set_length(total);
        bar.set_position(done);
    })?;
    bar.finish_and_clear();
    println!(
        "{}: {} frames ({} skipped) in {:.1} s, {:.1} frames/s; {} landmarks, {} border line{} ({})",
        opts.out.display(),
        summary.frames,
        summary.skipped_frames,
        summary.elapsed_s,
        summary.frames_per_s,
        summary.landmarks,
        summary.border_lines,
        if summary.border_lines == 1 { "" } else { "s" },
        summary.method
    );
    if summary.method == "ukf" {
        println!(
            "per frame: band {:.1} ms, SIFT {:.1} ms, match+estimate {:.1} ms, purge+add {:.1} ms",
            summary.band_ms, summary.sift_ms, summary.match_estimate_ms, summary.purge_add_ms
        );
    }
    if let (Some(m), Some(p90)) = (summary.residual_median_px, summary.residual_p90_px) {
        println!("reprojection residuals of converged landmarks: median {m:.1} px, 90th percentile {p90:.1} px (per frame: residuals.csv)");
    }
    for f in &summary.yaw_off_180_frames {
        println!("frame {f}: residuals say its recorded yaw is off by about 180 deg");
    }
    Ok(ExitCode::SUCCESS)
}

fn progress_bar(what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames, {per_sec}, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

/// `mavloc eval area`: the seed's table for a result folder.
fn eval_area(dataset: &Path, result: &Path, json: bool) -> anyhow::Result<ExitCode> {
    use anyhow::Context;
    let ds = mavloc::data::Dataset::open(dataset).map_err(|e| anyhow::anyhow!(e))?;
    if ds.ground_truth.is_empty() {
        anyhow::bail!("{} has no ground truth (ground_truth.csv)", dataset.display());
    }
    let lpath = result.join("landmarks.csv");
    let text = std::fs::read_to_string(&lpath).with_context(|| format!("cannot read {}", lpath.display()))?;
    let landmarks = mavloc::output::parse_landmarks_csv(&text, &lpath.display().to_string())
        .map_err(|e| anyhow::anyhow!(e))?;
    let border = std::fs::read_to_string(result.join("border.csv"))
        .map(|t| mavloc::data::results::parse_border_csv(&t))
        .unwrap_or_default();
    let fps = std::fs::read_to_string(result.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<mavloc::area::offline::RunSummary>(&t).ok())
        .map_or(f64::NAN, |s| s.frames_per_s);
    let e = mavloc::area::eval::evaluate(&landmarks, &ds.ground_truth, &border, fps);
    let title = format!("{} vs {}", result.display(), dataset.display());
    let plots = [result.join("histogram.png"), result.join("views.png")];
    let points: Vec<_> = landmarks.iter().map(|l| l.position).collect();
    let drawn = mavloc::output::plot::distance_histogram(&plots[0], &e.distances, &title).and_then(|_| {
        mavloc::output::plot::landmark_views(&plots[1], &points, &ds.ground_truth, &border, &title)
    });
    if let Err(why) = &drawn {
        eprintln!("mavloc eval area: plots not written: {why}");
    }
    if json {
        println!("{}", serde_json::to_string(&e)?);
    } else {
        print!("{e}");
        if drawn.is_ok() {
            println!("plots: {}, {}", plots[0].display(), plots[1].display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `mavloc indoor ...`.
fn indoor(command: IndoorCommand, settings: &mavloc::settings::Settings) -> anyhow::Result<ExitCode> {
    use anyhow::anyhow;
    use mavloc::indoor::offline;
    match command {
        IndoorCommand::Train(a) => {
            let labelling = match (&a.orthomap, a.map_metres_per_px) {
                (Some(map), Some(scale)) => offline::Labelling::Homography(
                    mavloc::indoor::labelling::OrthoMap::load(map, scale, a.map_origin, a.min_inliers)
                        .map_err(|e| anyhow!(e))?,
                ),
                _ => offline::Labelling::Telemetry,
            };
            let opts = offline::TrainOptions { dataset: a.dataset, out: a.out, labelling, seed: a.seed };
            let bar = progress_bar("histograms");
            let r = offline::train(&opts, &settings.indoor, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })
            .map_err(|e| anyhow!(e))?;
            bar.finish_and_clear();
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
                seed: a.seed,
            };
            let bar = progress_bar("indoor");
            let s = offline::run(&opts, &settings.indoor, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })
            .map_err(|e| anyhow!(e))?;
            bar.finish_and_clear();
            println!(
                "{}: {} frames ({} skipped), localiser {:.0} frames/s ({:.2} ms), reading+preparing {:.1} ms per frame; motion model {}, derotation {}",
                opts.out.display(),
                s.frames,
                s.skipped_frames,
                s.frames_per_s,
                s.localize_ms,
                s.prepare_ms,
                s.motion_model,
                if s.derotate { "on" } else { "off" }
            );
            Ok(ExitCode::SUCCESS)
        }
        IndoorCommand::Landings(a) => {
            use mavloc::simulated::approach::{run, ApproachOptions};
            let model = mavloc::indoor::model::Model::load(&a.model).map_err(|e| anyhow!(e))?;
            let opts =
                ApproachOptions { trials: a.trials, seed: a.seed, max_s: a.max_s, ..Default::default() };
            let bar = progress_bar("approaches");
            let rows = run(&model, &settings.indoor, &opts, |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            })
            .map_err(|e| anyhow!(e))?;
            bar.finish_and_clear();
            std::fs::create_dir_all(&a.out)?;
            let path = a.out.join("landings.csv");
            mavloc::output::write_atomic(&path, mavloc::data::results::landings_csv(&rows).as_bytes())?;
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
            let e = mavloc::simulated::mapeval::evaluate(
                &a.map,
                a.metres_per_px,
                a.views,
                a.sigma_m,
                &settings.indoor,
                a.seed,
            )
            .map_err(|e| anyhow!(e))?;
            let title = format!("{}: L(D) = {:.4} over {} views", a.map.display(), e.global_loss, e.views);
            let drawn = mavloc::indoor::mapeval::heatmap(&a.out, &e, 0.25, &title);
            if let Err(why) = &drawn {
                eprintln!("mavloc indoor map-eval: heat map not written: {why}");
            }
            if a.json {
                println!(
                    "{}",
                    serde_json::json!({"global_loss": e.global_loss, "views": e.views, "heatmap": a.out})
                );
            } else {
                println!("global loss L(D) = {:.4} over {} views (lower is better)", e.global_loss, e.views);
                if drawn.is_ok() {
                    println!("heat map: {}", a.out.display());
                }
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `mavloc eval indoor`: errors against ground truth, and the plot.
fn eval_indoor(dataset: &Path, result: &Path, json: bool) -> anyhow::Result<ExitCode> {
    let (e, rows) = mavloc::indoor::eval::evaluate(dataset, result).map_err(|e| anyhow::anyhow!(e))?;
    let plot = result.join("trajectory.png");
    let title = format!("{} vs {}", result.display(), dataset.display());
    let drawn = mavloc::indoor::eval::plot(&plot, &rows, &title);
    if let Err(why) = &drawn {
        eprintln!("mavloc eval indoor: plot not written: {why}");
    }
    if json {
        println!("{}", serde_json::to_string(&e)?);
    } else {
        println!("frames                 {}", e.frames);
        println!("mean |error| x, y      {:.3} m, {:.3} m", e.mean_err_x_m, e.mean_err_y_m);
        println!("RMS error              {:.3} m (x {:.3} m, y {:.3} m)", e.rmse_m, e.rmse_x_m, e.rmse_y_m);
        println!("RMS error after 2 s    {:.3} m", e.rmse_after_2s_m);
        println!("largest error          {:.3} m", e.max_err_m);
        println!(
            "lag                    {} frames (RMS {:.3} m when shifted)",
            e.lag_frames, e.rmse_at_lag_m
        );
        println!("localiser              {:.0} frames/s", e.frames_per_s);
        if e.landing_tries > 0 {
            println!("landings in zone       {} of {}", e.landings_in_zone, e.landing_tries);
        }
        if drawn.is_ok() {
            println!("plot: {}", plot.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Writes an RGB image (format from the extension) through OpenCV.
fn image_write(path: &Path, w: usize, h: usize, rgb: &[u8]) -> anyhow::Result<()> {
    use opencv::prelude::*;
    let m = opencv::core::Mat::from_slice(rgb)?.reshape(3, h as i32)?.try_clone()?;
    let mut bgr = opencv::core::Mat::default();
    opencv::imgproc::cvt_color(&m, &mut bgr, opencv::imgproc::COLOR_RGB2BGR, 0)?;
    anyhow::ensure!(bgr.cols() as usize == w, "image width mismatch");
    if !opencv::imgcodecs::imwrite(path, &bgr, &opencv::core::Vector::new())? {
        anyhow::bail!("cannot write {}", path.display());
    }
    Ok(())
}
