//! `mavloc eval indoor`: the indoor seed's measures (ch. 4) of a run against the dataset's
//! ground truth: mean absolute error in x and in y, RMS error, the lag between estimate
//! and truth (the shift, in frames, that minimises the RMS error; the seed found about 6),
//! and landing outcomes when the result folder has `landings.csv`.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::offline::RunSummary;
use mavloc_data::dataset::{Dataset, TelemetryRecord};
use mavloc_data::results::{read_landings, read_trajectory, TrajectoryRow};

/// Largest lag searched, frames.
const MAX_LAG: i64 = 30;

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct IndoorEval {
    pub frames: usize,
    pub rmse_m: f64,
    pub rmse_x_m: f64,
    pub rmse_y_m: f64,
    pub mean_err_x_m: f64,
    pub mean_err_y_m: f64,
    pub max_err_m: f64,
    /// RMS error without the first 2 s (global localisation from a uniform start).
    pub rmse_after_2s_m: f64,
    /// Largest error without the first 2 s.
    pub max_err_after_2s_m: f64,
    /// Shift (frames) of the estimate against the truth that minimises the RMS error;
    /// positive when the estimate trails the truth.
    pub lag_frames: i64,
    pub rmse_at_lag_m: f64,
    /// Frames whose estimate is a position fix (`fix` in `trajectory.csv`: the particles
    /// agree on one place); the estimates a flight can use.
    #[serde(default)]
    pub fix_frames: usize,
    /// Seconds from the first frame to the first fix (NaN: none).
    #[serde(default)]
    pub first_fix_s: f64,
    /// RMS and largest error over the fixes.
    #[serde(default)]
    pub rmse_fix_m: f64,
    #[serde(default)]
    pub max_err_fix_m: f64,
    pub frames_per_s: f64,
    pub landings_in_zone: usize,
    pub landing_tries: usize,
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        (s / n as f64).sqrt()
    }
}

/// Measures over estimate/truth pairs.
pub fn measure(est: &[(f64, f64, f64)], truth: &[(f64, f64)]) -> IndoorEval {
    let n = est.len().min(truth.len());
    let errs: Vec<(f64, f64)> = (0..n).map(|i| (est[i].1 - truth[i].0, est[i].2 - truth[i].1)).collect();
    let mut e = IndoorEval { frames: n, ..IndoorEval::default() };
    if n == 0 {
        return e;
    }
    e.rmse_x_m = rms(errs.iter().map(|d| d.0));
    e.rmse_y_m = rms(errs.iter().map(|d| d.1));
    e.rmse_m = rms(errs.iter().map(|d| d.0.hypot(d.1)));
    e.mean_err_x_m = errs.iter().map(|d| d.0.abs()).sum::<f64>() / n as f64;
    e.mean_err_y_m = errs.iter().map(|d| d.1.abs()).sum::<f64>() / n as f64;
    e.max_err_m = errs.iter().map(|d| d.0.hypot(d.1)).fold(0.0, f64::max);
    let t0 = est[0].0;
    let after = || (0..n).filter(move |&i| est[i].0 - t0 >= 2.0).map(|i| errs[i].0.hypot(errs[i].1));
    e.rmse_after_2s_m = rms(after());
    e.max_err_after_2s_m = after().fold(0.0, f64::max);
    let mut best = (f64::INFINITY, 0);
    for lag in -MAX_LAG..=MAX_LAG {
        // Estimate i against truth i - lag.
        let pairs = (0..n as i64).filter(|&i| i - lag >= 0 && i - lag < n as i64).map(|i| {
            let (a, b) = (est[i as usize], truth[(i - lag) as usize]);
            (a.1 - b.0).hypot(a.2 - b.1)
        });
        let r = rms(pairs);
        if r < best.0 {
            best = (r, lag);
        }
    }
    (e.rmse_at_lag_m, e.lag_frames) = best;
    e
}

/// Adds the measures over the frames marked as fixes (`fix[i]` for estimate `i`).
pub fn measure_fixes(e: &mut IndoorEval, est: &[(f64, f64, f64)], truth: &[(f64, f64)], fix: &[bool]) {
    let n = est.len().min(truth.len()).min(fix.len());
    let errs: Vec<f64> =
        (0..n).filter(|&i| fix[i]).map(|i| (est[i].1 - truth[i].0).hypot(est[i].2 - truth[i].1)).collect();
    e.fix_frames = errs.len();
    e.first_fix_s = (0..n).find(|&i| fix[i]).map_or(f64::NAN, |i| est[i].0 - est[0].0);
    e.rmse_fix_m = rms(errs.iter().copied());
    e.max_err_fix_m = errs.iter().copied().fold(if errs.is_empty() { f64::NAN } else { 0.0 }, f64::max);
}

/// Evaluates a run folder against its dataset.
pub fn evaluate(dataset: &Path, result: &Path) -> Result<(IndoorEval, Vec<TrajectoryRow>), String> {
    let ds = Dataset::open(dataset)?;
    let rows = read_trajectory(&result.join("trajectory.csv"))?;
    let by_frame: std::collections::HashMap<u64, &TelemetryRecord> =
        ds.records.iter().map(|r| (r.frame, r)).collect();
    let mut est = Vec::with_capacity(rows.len());
    let mut truth = Vec::with_capacity(rows.len());
    for r in &rows {
        let rec = by_frame
            .get(&r.frame)
            .ok_or_else(|| format!("trajectory frame {} is not in {}", r.frame, dataset.display()))?;
        est.push((r.t, r.x, r.y));
        truth.push((rec.truth.position[0], rec.truth.position[1]));
    }
    let mut e = measure(&est, &truth);
    let fix: Vec<bool> = rows.iter().map(|r| r.fix).collect();
    measure_fixes(&mut e, &est, &truth, &fix);
    let summary = result.join("summary.json");
    if let Ok(text) = std::fs::read_to_string(&summary) {
        let s: RunSummary =
            serde_json::from_str(&text).map_err(|err| format!("{}: {err}", summary.display()))?;
        e.frames_per_s = s.frames_per_s;
    }
    let landings = result.join("landings.csv");
    if landings.exists() {
        let l = read_landings(&landings)?;
        e.landing_tries = l.len();
        e.landings_in_zone = l.iter().filter(|r| r.fired && r.inside).count();
    }
    Ok((e, rows))
}

/// Estimate against truth: x(t), y(t) with the particles' 2-sigma band, and the track.
pub fn plot(path: &Path, rows: &[TrajectoryRow], title: &str) -> Result<(), String> {
    use crate::output::plot::{err, font};
    use plotters::prelude::*;
    font()?;
    crate::output::plot::png(path, (1300, 620), |root| {
        root.fill(&WHITE).map_err(err)?;
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        let (left, right) = root.split_horizontally(760);
        let (top, bottom) = left.split_vertically(300);
        let t_max = rows.last().map_or(1.0, |r| r.t).max(1e-3);
        let t_min = rows.first().map_or(0.0, |r| r.t);
        let lim = rows
            .iter()
            .flat_map(|r| [r.x.abs(), r.y.abs(), r.true_x.abs(), r.true_y.abs()])
            .fold(1.0f64, f64::max)
            * 1.1;
        for (area, name, get) in [
            (
                &top,
                "x (north), m",
                (|r: &TrajectoryRow| (r.x, r.sigma_x, r.true_x)) as fn(&TrajectoryRow) -> (f64, f64, f64),
            ),
            (&bottom, "y (east), m", |r: &TrajectoryRow| (r.y, r.sigma_y, r.true_y)),
        ] {
            let mut chart = ChartBuilder::on(area)
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(50)
                .build_cartesian_2d(t_min..t_max, -lim..lim)
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_desc("t, s")
                .y_desc(name)
                .label_style(("sans-serif", 14))
                .draw()
                .map_err(err)?;
            let band: Vec<(f64, f64)> = rows
                .iter()
                .map(|r| (r.t, get(r).0 + 2.0 * get(r).1))
                .chain(rows.iter().rev().map(|r| (r.t, get(r).0 - 2.0 * get(r).1)))
                .collect();
            chart
                .draw_series(std::iter::once(Polygon::new(band, RGBColor(255, 150, 80).mix(0.25))))
                .map_err(err)?;
            chart
                .draw_series(LineSeries::new(rows.iter().map(|r| (r.t, get(r).2)), BLACK.stroke_width(2)))
                .map_err(err)?
                .label("truth")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.stroke_width(2)));
            chart
                .draw_series(LineSeries::new(
                    rows.iter().map(|r| (r.t, get(r).0)),
                    RGBColor(220, 60, 20).stroke_width(2),
                ))
                .map_err(err)?
                .label("estimate (MAP), band: 2 SD of particles")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], RGBColor(220, 60, 20).stroke_width(2))
                });
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .label_font(("sans-serif", 13))
                .draw()
                .map_err(err)?;
        }
        let mut chart = ChartBuilder::on(&right)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(-lim..lim, -lim..lim)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("y (east), m")
            .y_desc("x (north), m")
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(err)?;
        chart
            .draw_series(LineSeries::new(rows.iter().map(|r| (r.true_y, r.true_x)), BLACK.stroke_width(2)))
            .map_err(err)?;
        chart
            .draw_series(rows.iter().map(|r| Circle::new((r.y, r.x), 2, RGBColor(220, 60, 20).filled())))
            .map_err(err)?;
        root.present().map_err(err)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lag_is_found_and_errors_are_measured() {
        // Truth moves along x at one unit per frame; the estimate trails it by 6 frames.
        let truth: Vec<(f64, f64)> = (0..200).map(|i| ((i as f64 * 0.1).sin(), 0.5)).collect();
        let est: Vec<(f64, f64, f64)> =
            (0..200).map(|i| (i as f64 / 15.0, truth[i.max(6) - 6].0, 0.5 + 0.1)).collect();
        let e = measure(&est, &truth);
        assert_eq!(e.lag_frames, 6);
        assert!(e.rmse_at_lag_m < 0.1 + 1e-9 && e.rmse_m > e.rmse_at_lag_m);
        assert!((e.mean_err_y_m - 0.1).abs() < 1e-9);
        let same = measure(&truth.iter().map(|p| (0.0, p.0, p.1)).collect::<Vec<_>>(), &truth);
        assert_eq!((same.lag_frames, same.rmse_m), (0, 0.0));
    }

    #[test]
    fn fixes_are_measured_apart_from_the_search() {
        // Three search frames 3 m off, then fixes 0.1 m off, one 0.4 m off.
        let truth: Vec<(f64, f64)> = (0..20).map(|i| (i as f64 * 0.1, 0.0)).collect();
        let est: Vec<(f64, f64, f64)> = (0..20)
            .map(|i| {
                let off = if i < 3 {
                    3.0
                } else if i == 10 {
                    0.4
                } else {
                    0.1
                };
                (i as f64 * 0.5, truth[i].0, off)
            })
            .collect();
        let fix: Vec<bool> = (0..20).map(|i| i >= 3).collect();
        let mut e = measure(&est, &truth);
        measure_fixes(&mut e, &est, &truth, &fix);
        assert_eq!(e.fix_frames, 17);
        assert!((e.first_fix_s - 1.5).abs() < 1e-12);
        assert!((e.max_err_fix_m - 0.4).abs() < 1e-12 && (e.max_err_m - 3.0).abs() < 1e-12);
        let want = ((16.0 * 0.01 + 0.16) / 17.0f64).sqrt();
        assert!((e.rmse_fix_m - want).abs() < 1e-12);
        measure_fixes(&mut e, &est, &truth, &[false; 20]);
        assert!(e.fix_frames == 0 && e.first_fix_s.is_nan() && e.max_err_fix_m.is_nan());
    }
}
