//! `mavloc eval area|indoor`: results against a dataset's ground truth, as the seeds
//! measure them, with plots.

use std::path::Path;
use std::process::ExitCode;

use crate::cli::EvalCommand;

pub fn run(command: EvalCommand) -> anyhow::Result<ExitCode> {
    match command {
        EvalCommand::Area { dataset, result, json } => area(&dataset, &result, json),
        EvalCommand::Indoor { dataset, result, json } => indoor(&dataset, &result, json),
    }
}

/// Refuses a result made from another dataset than `dataset` (its `summary.json` records
/// the dataset's telemetry CRC; results of an older mavloc have none and are measured):
/// the numbers would be meaningless and the plots written into the result would replace
/// its own.
fn same_dataset(dataset: &Path, result: &Path) -> anyhow::Result<()> {
    let theirs = std::fs::read_to_string(result.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v.get("dataset_crc32").and_then(|c| c.as_str()).map(String::from));
    let ours = crate::data::dataset::telemetry_crc32(dataset);
    if let (Some(theirs), Some(ours)) = (theirs, ours) {
        if theirs != ours {
            anyhow::bail!(
                "{} was made from another dataset than {} (or from an earlier version of it): their telemetry differs \
                 (CRC-32 {theirs} in its summary.json, {ours} now); give the dataset the run used",
                result.display(),
                dataset.display()
            );
        }
    }
    Ok(())
}

/// `mavloc eval area`: the seed's table for a result folder.
fn area(dataset: &Path, result: &Path, json: bool) -> anyhow::Result<ExitCode> {
    use anyhow::Context;
    let ds = crate::data::Dataset::open(dataset).map_err(|e| anyhow::anyhow!(e))?;
    same_dataset(dataset, result)?;
    if ds.ground_truth.is_empty() {
        anyhow::bail!("{} has no ground truth (ground_truth.csv)", dataset.display());
    }
    let lpath = result.join("landmarks.csv");
    let text = std::fs::read_to_string(&lpath).with_context(|| format!("cannot read {}", lpath.display()))?;
    let landmarks = crate::output::parse_landmarks_csv(&text, &lpath.display().to_string())
        .map_err(|e| anyhow::anyhow!(e))?;
    let border = std::fs::read_to_string(result.join("border.csv"))
        .map(|t| crate::data::results::parse_border_csv(&t))
        .unwrap_or_default();
    let summary = std::fs::read_to_string(result.join("summary.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<crate::area::offline::RunSummary>(&t).ok());
    let fps = summary.as_ref().map_or(f64::NAN, |s| s.frames_per_s);
    let offsets = summary.as_ref().and_then(|s| s.gimbal_offsets_deg);
    let mut e = crate::area::eval::evaluate(&landmarks, &ds.ground_truth, &border, fps);
    // A rendered dataset carries its scenario, so its ground is known everywhere, and its
    // `true` poses are the truth.
    if let Some(surface) = crate::simulated::surface::true_surface(dataset).map_err(anyhow::Error::msg)? {
        e = e.with_surface(&landmarks, surface);
        let alignment = result.join("alignment.csv");
        match offsets {
            Some(o) if alignment.is_file() => {
                let (attitudes, positions) = aligned_attitudes(&ds, &alignment, o)?;
                e = e.with_aligned_attitudes(&attitudes, &positions);
            }
            None if alignment.is_file() => {
                eprintln!("mavloc eval area: alignment.csv is there, but summary.json is missing or does not say the gimbal offsets the run added (results of an older mavloc): the aligned attitudes are not set against the true ones")
            }
            _ => {}
        }
        let trace = result.join("trace.csv");
        match summary.and_then(|s| s.downscale) {
            Some(downscale) if trace.is_file() => {
                let (rays, pixel_rad) = true_rays(&ds, &trace, downscale)?;
                e = e.with_true_rays(&landmarks, &rays, pixel_rad);
            }
            // Results of a run before its summary said its scale: the pixels cannot be placed.
            None if trace.is_file() => {
                eprintln!("mavloc eval area: trace.csv is there, but summary.json does not say the frames' scale (area.downscale; results of an older mavloc): no error against the true poses")
            }
            _ => {}
        }
    }
    let title = format!("{} vs {}", result.display(), dataset.display());
    let plots = [result.join("histogram.png"), result.join("views.png")];
    let points: Vec<_> = landmarks.iter().map(|l| l.position).collect();
    let drawn = crate::output::plot::distance_histogram(&plots[0], &e.distances, &title).and_then(|_| {
        crate::output::plot::landmark_views(&plots[1], &points, &ds.ground_truth, &border, &title)
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

/// Pairs of rotations (true, aligned) and of positions (true, tagged).
type AlignedPoses = (
    Vec<(crate::geometry::Rot3, crate::geometry::Rot3)>,
    Vec<(crate::geometry::Vec3, crate::geometry::Vec3)>,
);

/// Each aligned photo's true attitude and its aligned one: the tagged pose with the run's
/// gimbal offsets (`offsets_deg`), turned by its correction (`area::align::Correction`);
/// and its true and tagged positions.
fn aligned_attitudes(
    ds: &crate::data::Dataset,
    alignment: &Path,
    offsets_deg: [f64; 3],
) -> anyhow::Result<AlignedPoses> {
    let rows = mavloc_data::table::read::<crate::area::offline::AlignmentRow>(alignment)?;
    let records: std::collections::HashMap<u64, _> = ds.records.iter().map(|r| (r.frame, r)).collect();
    let (mut pairs, mut positions) = (Vec::new(), Vec::new());
    for row in rows {
        let Some(r) = records.get(&row.frame) else {
            anyhow::bail!("{}: frame {} is not in the dataset", alignment.display(), row.frame);
        };
        let turn = crate::geometry::Vec3::new(row.about_north_deg, row.about_east_deg, row.about_down_deg)
            .map(f64::to_radians);
        let tagged = ds.camera_pose(&r.measured, offsets_deg);
        let aligned = crate::area::refine::corrected(&tagged, &turn);
        let truth = ds.camera_pose(&r.truth, [0.0; 3]);
        // A photo no tie point reached keeps its tags (the run leaves it out too); its
        // position still counts for the GPS's turn.
        if row.tie_sightings > 0 {
            pairs.push((truth.attitude, aligned.attitude));
        }
        positions.push((truth.position, tagged.position));
    }
    Ok((pairs, positions))
}

/// Each landmark's accepted sightings in `trace.csv` cast from the dataset's true poses
/// (`downscale`: the scale of the trace's pixels), by landmark id, and a pixel's angle.
fn true_rays(
    ds: &crate::data::Dataset,
    trace: &Path,
    downscale: u32,
) -> anyhow::Result<(std::collections::HashMap<u64, Vec<crate::area::rays::Ray>>, f64)> {
    let k = ds.camera.intrinsics().downscaled(downscale);
    let poses: std::collections::HashMap<u64, crate::geometry::CameraPose> =
        ds.records.iter().map(|r| (r.frame, ds.camera_pose(&r.truth, [0.0; 3]))).collect();
    let mut rays: std::collections::HashMap<u64, Vec<crate::area::rays::Ray>> = Default::default();
    for (frame, landmark, px, accepted) in
        crate::area::offline::read_trace_sightings(trace).map_err(anyhow::Error::msg)?
    {
        if let (true, Some(pose)) = (accepted, poses.get(&frame)) {
            let dir = pose.direction(&k, px);
            rays.entry(landmark).or_default().push(crate::area::rays::Ray { origin: pose.position, dir });
        }
    }
    Ok((rays, 1.0 / k.fx))
}

/// `mavloc eval indoor`: errors against ground truth, and the plot.
fn indoor(dataset: &Path, result: &Path, json: bool) -> anyhow::Result<ExitCode> {
    same_dataset(dataset, result)?;
    let (e, rows) = crate::indoor::eval::evaluate(dataset, result).map_err(|e| anyhow::anyhow!(e))?;
    let plot = result.join("trajectory.png");
    let title = format!("{} vs {}", result.display(), dataset.display());
    let drawn = crate::indoor::eval::plot(&plot, &rows, &title);
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
        println!("largest after 2 s      {:.3} m", e.max_err_after_2s_m);
        println!("largest error          {:.3} m", e.max_err_m);
        println!(
            "position fixes         {} of {} frames, the first after {:.2} s: RMS {:.3} m, largest {:.3} m",
            e.fix_frames, e.frames, e.first_fix_s, e.rmse_fix_m, e.max_err_fix_m
        );
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
