//! `mavloc calibrate gimbal`: the gimbal's static offset from a flight (area seed sec.
//! 6.11). The area pipeline runs over the dataset with the configured offsets; then one
//! yaw/pitch/roll offset shared by every frame is estimated together with the landmarks
//! from all their sightings (`area::refine::calibrate`), the positions held at the
//! recorded ones. With a surveyed marker (its position and its pixel in each frame), the
//! marker is held fixed and anchors the estimate, as in the seed's table 6.8.

use std::collections::BTreeMap;
use std::process::ExitCode;

use anyhow::{anyhow, bail, Context};

use super::{Global, Progress};
use crate::cli::{CalibrateCommand, CalibrateGimbalArgs};
use crate::geometry::{Pixel, Vec3};

pub fn run(command: CalibrateCommand, global: Global) -> anyhow::Result<ExitCode> {
    match command {
        CalibrateCommand::Gimbal(a) => gimbal(a, global),
    }
}

/// The marker's pixels: `frame,u,v` per line (a header line is allowed).
fn marker_pixels(path: &std::path::Path) -> anyhow::Result<Vec<(u64, f64, f64)>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut out = Vec::new();
    for (i, line) in mavloc_data::table::strip_bom(&text).lines().enumerate() {
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if line.trim().is_empty() || (i == 0 && fields[0].parse::<u64>().is_err()) {
            continue;
        }
        let parsed = (|| {
            Some((fields.first()?.parse().ok()?, fields.get(1)?.parse().ok()?, fields.get(2)?.parse().ok()?))
        })();
        match parsed {
            Some(v) => out.push(v),
            None => bail!("{} line {}: expected `frame,u,v`, got `{line}`", path.display(), i + 1),
        }
    }
    Ok(out)
}

/// Groups of contiguous frames for the jackknife.
const JACKKNIFE_GROUPS: usize = 6;

fn gimbal(a: CalibrateGimbalArgs, global: Global) -> anyhow::Result<ExitCode> {
    use crate::area::offline::{run_observed, RunOptions};
    let own = a.dataset.join(crate::data::SETTINGS_FILE);
    let mut layers = crate::settings::Layers::from_process(global.config_file(), global.overrides);
    layers.dataset = own.exists().then(|| own.clone());
    let mut settings = crate::settings::load(&layers)?.settings;
    crate::logging::init(&settings.daemon.log);
    // The filters' landmarks, not ones already bent by per-frame attitude corrections.
    settings.area.attitude_prior_deg = 0.0;
    // and on the recorded poses: aligning each photo first would absorb the offset.
    settings.area.align_prior_deg = 0.0;
    // Without --out the run's files go to a temporary folder, removed however this ends.
    let temp = match &a.out {
        Some(_) => None,
        None => Some(tempfile::tempdir().context("cannot create a temporary folder")?),
    };
    let out =
        a.out.clone().or_else(|| temp.as_ref().map(|t| t.path().to_path_buf())).expect("one of the two");
    let opts = RunOptions {
        dataset: a.dataset.clone(),
        out,
        method: crate::settings::AreaMethod::Ukf,
        trace: false,
        max_frames: None,
        debug_masks: false,
    };
    let bar = Progress::new("area", "frames");
    let (summary, obs) = run_observed(&opts, &settings, |d, t| bar.set(d, t), true, None)?;
    bar.finish();
    drop(temp);
    let k = obs.k.ok_or_else(|| anyhow!("no frame of {} could be used", a.dataset.display()))?;
    let ds = crate::data::Dataset::open(&a.dataset).map_err(|e| anyhow!(e))?;
    let records: BTreeMap<u64, crate::data::dataset::PoseRecord> =
        ds.records.iter().map(|r| (r.frame, r.measured)).collect();
    let base = settings.gimbal.offsets_deg();
    let pose = |f: u64, d: &Vec3| ds.camera_pose(&records[&f], [base[0] + d.x, base[1] + d.y, base[2] + d.z]);
    let mut sightings = obs.sightings.clone();
    let mut fixed = Vec::new();
    if let (Some(m), Some(path)) = (a.marker, &a.marker_pixels) {
        const MARKER: u64 = u64::MAX;
        let scale = obs.downscale.max(1) as f64;
        let full = ds.camera.intrinsics();
        let pixels = marker_pixels(path)?;
        if pixels.is_empty() {
            bail!("{}: no marker pixel (`frame,u,v` per line)", path.display());
        }
        for (f, u, v) in pixels {
            if !records.contains_key(&f) {
                bail!("{}: frame {f} is not in the dataset", path.display());
            }
            if !full.contains(Pixel::new(u, v)) {
                bail!(
                    "{}: frame {f}: the marker at ({u}, {v}) is not on the {}x{} image",
                    path.display(),
                    full.width,
                    full.height
                );
            }
            sightings.push((f, MARKER, Pixel::new((u + 0.5) / scale - 0.5, (v + 0.5) / scale - 0.5)));
        }
        fixed.push((MARKER, Vec3::new(m[0], m[1], m[2])));
    }
    if obs.landmarks.is_empty() && fixed.is_empty() {
        bail!(
            "no landmark converged over {} frames, so there is nothing to calibrate against",
            summary.frames
        );
    }
    let c = crate::area::refine::calibrate(&sightings, &obs.landmarks, &fixed, &pose, &k, a.prior_deg);
    if c.sightings == 0 {
        bail!(
            "{} landmarks converged over {} frames ({} sightings), but every one had a sighting far off the first fit and was left out \
             (per-frame telemetry noise that one shared offset cannot explain): nothing to calibrate against; calibrate on a flight \
             with better positions and attitude, or over a surveyed marker (--marker)",
            obs.landmarks.len(),
            summary.frames,
            obs.sightings.len()
        );
    }
    // The solver's SD counts each sighting as independent; a frame's position and gimbal
    // errors are shared by all its sightings, which it does not see (2 m of height noise
    // per frame moved the pitch by 2.3 deg where it claimed 0.03). The SD reported is a
    // delete-a-group jackknife over contiguous groups of frames instead.
    let frames: Vec<u64> = records.keys().copied().collect();
    let groups = JACKKNIFE_GROUPS.min(frames.len());
    let mut estimates = Vec::new();
    for g in 0..groups {
        let (lo, hi) = (frames.len() * g / groups, frames.len() * (g + 1) / groups);
        let dropped: std::collections::BTreeSet<u64> = frames[lo..hi].iter().copied().collect();
        let kept: Vec<_> = sightings.iter().filter(|s| !dropped.contains(&s.0)).copied().collect();
        let e = crate::area::refine::calibrate(&kept, &obs.landmarks, &fixed, &pose, &k, a.prior_deg);
        estimates.push(e.offsets_deg);
    }
    let jack_sd: Vec<f64> = (0..3)
        .map(|i| {
            let mean = estimates.iter().map(|e| e[i]).sum::<f64>() / groups as f64;
            let ss: f64 = estimates.iter().map(|e| (e[i] - mean).powi(2)).sum();
            ((groups as f64 - 1.0) / groups as f64 * ss).sqrt()
        })
        .collect();
    println!(
        "{} landmarks{}, {} sightings in {} frames; sightings reproject within {:.1} px -> {:.1} px (median, pipeline resolution)",
        obs.landmarks.len(),
        if fixed.is_empty() { "" } else { " and the marker" },
        c.sightings,
        c.frames,
        c.median_before_px,
        c.median_after_px
    );
    let names = ["yaw_offset_deg", "pitch_offset_deg", "roll_offset_deg"];
    let total: Vec<f64> = (0..3).map(|i| base[i] + c.offsets_deg[i]).collect();
    for i in 0..3 {
        println!(
            "gimbal.{} = {:.3}  (SD {:.2} deg over groups of frames, {:.3} from the sightings alone; was {:.3})",
            names[i], total[i], jack_sd[i], c.sd_deg[i], base[i]
        );
    }
    // An estimate the flight does not determine is not a calibration: written into a
    // configuration it would turn every later map (50 deg SDs from 50 video frames).
    // With fewer than three groups of frames the jackknife has no spread to measure (one
    // group gives an SD of 0 whatever the estimate): nothing is determined.
    let unsure: Vec<String> = (0..3)
        .filter(|&i| !(groups >= 3 && total[i].is_finite() && jack_sd[i] <= a.max_sd_deg))
        .map(|i| format!("{} (SD {:.2} deg)", names[i], jack_sd[i]))
        .collect();
    if !unsure.is_empty() {
        eprintln!(
            "mavloc calibrate gimbal: {} not determined within --max-sd-deg {}: {}; fly longer, over several lines or a turn, or over a surveyed marker",
            unsure.join(", "),
            a.max_sd_deg,
            a.write.as_ref().map_or("not to be used".to_string(), |p| format!("{} left unchanged", p.display()))
        );
        return Ok(ExitCode::from(2));
    }
    if let Some(path) = &a.write {
        let text = std::fs::read_to_string(path).unwrap_or_default();
        let mut doc: toml_edit::DocumentMut =
            text.parse().with_context(|| format!("{} is not valid TOML", path.display()))?;
        if doc.get("gimbal").is_none() {
            doc["gimbal"] = toml_edit::table();
        }
        for i in 0..3 {
            let v = (total[i] * 1000.0).round() / 1000.0;
            match doc["gimbal"].get_mut(names[i]) {
                // The value replaced, its comments (`# deg`) and spacing kept.
                Some(toml_edit::Item::Value(old)) => {
                    let decor = old.decor().clone();
                    *old = v.into();
                    *old.decor_mut() = decor;
                }
                _ => doc["gimbal"][names[i]] = toml_edit::value(v),
            }
        }
        crate::data::write_atomic(path, doc.to_string().as_bytes())
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("written into [gimbal] of {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}
