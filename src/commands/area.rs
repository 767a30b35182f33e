//! `mavloc area`: the area pipeline over a dataset ([`crate::area::offline`]), with a
//! progress bar and a summary.

use std::process::ExitCode;

use super::{Global, Progress};
use crate::cli::AreaArgs;
use crate::settings::{self, Layers};

pub fn run(args: AreaArgs, global: Global) -> anyhow::Result<ExitCode> {
    // A dataset may carry the settings it needs (an imported photo survey does).
    let own = args.dataset.join(crate::data::SETTINGS_FILE);
    let mut layers = Layers::from_process(global.config_file(), global.overrides);
    layers.dataset = own.exists().then(|| own.clone());
    let loaded = settings::load(&layers)?;
    crate::logging::init(&loaded.settings.daemon.log);
    let own_origin = own.display().to_string();
    let from_dataset: Vec<&str> =
        loaded.origins.iter().filter(|(_, o)| **o == own_origin).map(|(k, _)| k.as_str()).collect();
    if !from_dataset.is_empty() {
        println!("settings from the dataset's {}: {}", own.display(), from_dataset.join(", "));
    }
    run_on_dataset(args, &loaded.settings)
}

/// The pipeline run with the settings in force, then its summary.
fn run_on_dataset(args: AreaArgs, settings: &settings::Settings) -> anyhow::Result<ExitCode> {
    use crate::area::offline::{run_stoppable, RunOptions};
    use crate::settings::AreaMethod;
    let method = match args.method.as_deref() {
        Some("ground-plane") => AreaMethod::GroundPlane,
        Some(_) => AreaMethod::Ukf,
        None => settings.area.method,
    };
    if crate::data::staged::nested(&args.dataset, &args.out) {
        anyhow::bail!(
            "--out {} and --dataset {} are the same folder or one is inside the other: results go elsewhere",
            args.out.display(),
            args.dataset.display()
        );
    }
    if !args.dataset.join(crate::data::dataset::TELEMETRY_FILE).exists() && holds_photos(&args.dataset) {
        anyhow::bail!(
            "{} holds photos but is not a dataset (no {}): make one with `mavloc import photos {} --out DATASET`",
            args.dataset.display(),
            crate::data::dataset::TELEMETRY_FILE,
            args.dataset.display()
        );
    }
    let opts = RunOptions {
        dataset: args.dataset,
        out: args.out,
        method,
        trace: args.trace,
        max_frames: args.frames,
        debug_masks: args.debug_masks,
    };
    let stop = super::stop_on_ctrl_c()?;
    let bar = Progress::new("area", "frames");
    let summary = run_stoppable(
        &opts,
        settings,
        |done, total| {
            bar.set(done, total);
        },
        &stop,
    )?;
    bar.finish();
    if summary.frames == 0 && !summary.complete {
        eprintln!(
            "mavloc area: stopped by Ctrl-C before any frame was used; {} left as it was",
            opts.out.display()
        );
        return Ok(ExitCode::from(super::STOPPED_BY_CTRL_C));
    }
    if summary.frames == 0 {
        // Exit non-zero: a run that looked at nothing has no result to stand for.
        anyhow::bail!(
            "no frame of {} could be used ({} skipped){}; {} left as it was",
            opts.dataset.display(),
            summary.skipped_frames,
            summary.first_skip_reason.as_deref().map(|r| format!("; the first: {r}")).unwrap_or_default(),
            opts.out.display()
        );
    }
    // Where they are: beside complete earlier results (`NAME.stopped`) after a Ctrl-C.
    println!(
        "{}: {} frames ({} skipped) in {:.1} s, {:.1} frames/s; {} landmarks, {} border line{} ({})",
        summary.written_to.display(),
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
            "per frame: read+segment {:.1} ms, band {:.1} ms, SIFT {:.1} ms, match+estimate {:.1} ms, purge+add {:.1} ms",
            summary.prepare_ms,
            summary.band_ms, summary.sift_ms, summary.match_estimate_ms, summary.purge_add_ms
        );
    }
    if let (Some(n), Some(t)) = (summary.aligned_photos, summary.tie_points) {
        println!(
            "photo alignment: {n} photos by {t} tie points over {} linked pairs of {} overlapping ({} dropped as false links); tie points reproject within {:.1} px as tagged -> {:.1} px aligned (median), photos corrected by {:.2} deg (median; alignment.csv)",
            summary.tie_pairs_linked.unwrap_or(0),
            summary.tie_pairs_matched.unwrap_or(0),
            summary.tie_pairs_dropped.unwrap_or(0),
            summary.align_median_before_px.unwrap_or(f64::NAN),
            summary.align_median_after_px.unwrap_or(f64::NAN),
            summary.align_correction_median_deg.unwrap_or(f64::NAN),
        );
    }
    if let (Some(b), Some(n)) = (summary.aligned_bearing_noise_deg, summary.aligned_min_observations) {
        if summary.unaligned_frames.is_empty() {
            println!("every photo aligned: the landmark filters ran with {b} deg of bearing noise and {n} sightings a landmark (area.aligned_*)");
        } else {
            println!(
                "photos aligned: the landmark filters ran with {b} deg of bearing noise and {n} sightings a landmark (area.aligned_*), without the {} photo(s) no tie point reached (frames {:?})",
                summary.unaligned_frames.len(),
                summary.unaligned_frames
            );
        }
    }
    if let Some(n) = summary.cross_line_tie_pairs {
        let m = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2} m"));
        println!(
            "tie points triangulated from each of two lines alone ({n} pairs) lie {} apart as tagged, {} aligned (median)",
            m(summary.cross_line_tie_median_m),
            m(summary.cross_line_tie_aligned_median_m)
        );
    }
    if let (Some(m), Some(p90)) = (summary.residual_median_px, summary.residual_p90_px) {
        println!("reprojection residuals of converged landmarks: median {m:.1} px, 90th percentile {p90:.1} px (per frame: residuals.csv)");
    }
    if let (Some(b), Some(a), Some(d)) = (
        summary.refined_median_before_px,
        summary.refined_median_after_px,
        summary.attitude_correction_median_deg,
    ) {
        let out = summary.refined_left_out.unwrap_or(0);
        println!("attitude refinement: sightings reproject within {b:.1} px -> {a:.1} px (median), frames corrected by {d:.2} deg (median; attitude.csv); {out} sightings left out as false matches");
    }
    if let Some(why) = &summary.refined_rejected {
        println!("attitude refinement not used: {why}; the landmarks are the filters'");
    }
    if let (Some(o), Some(sd)) = (summary.refined_gimbal_offset_deg, summary.refined_gimbal_offset_sd_deg) {
        println!(
            "static gimbal offset found with it: yaw {:+.3}, pitch {:+.3}, roll {:+.3} deg (SD {:.3}, {:.3}, {:.3} from the sightings; add to gimbal.*_offset_deg, or `mavloc calibrate gimbal`)",
            o[0], o[1], o[2], sd[0], sd[1], sd[2]
        );
    }
    if let (Some(lines), Some(n)) = (summary.flight_lines, summary.cross_line_pairs) {
        let m = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2} m"));
        // As tagged (when the photos were aligned), as the filters ran, after refinement.
        let mut stages = Vec::new();
        if summary.cross_line_tagged_median_m.is_some() {
            stages.push(format!("{} as tagged", m(summary.cross_line_tagged_median_m)));
            stages.push(format!("{} aligned", m(summary.cross_line_median_m)));
        } else {
            stages.push(m(summary.cross_line_median_m));
        }
        if let Some(v) = summary.cross_line_refined_median_m {
            stages.push(format!("{v:.2} m after refinement"));
        }
        println!(
            "{lines} flight lines; landmarks triangulated from each of two lines alone ({n} pairs) lie apart by {} (median)",
            stages.join(", ")
        );
    }
    for f in &summary.yaw_off_180_frames {
        println!("frame {f}: residuals say its recorded yaw is off by about 180 deg");
    }
    if !summary.complete {
        let frames = (summary.frames + summary.skipped_frames) as usize;
        return Ok(super::stopped_with_results("area", frames, &summary.written_to, &opts.out));
    }
    Ok(ExitCode::SUCCESS)
}

/// Whether a folder has JPEG photos directly in it (raw photos, not a dataset).
fn holds_photos(dir: &std::path::Path) -> bool {
    std::fs::read_dir(dir).into_iter().flatten().flatten().any(|e| {
        let ext = e.path().extension().map(|x| x.to_string_lossy().to_ascii_lowercase());
        matches!(ext.as_deref(), Some("jpg" | "jpeg"))
    })
}
