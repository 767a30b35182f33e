//! PNG plots: the area seed's histogram of landmark distances (log y, fig. 6.6/6.13) and
//! top and side views of landmarks over the ground truth (fig. 6.12/6.15).
//!
//! Text is drawn with the DejaVu Sans font Debian ships (`fonts-dejavu-core`, installed by
//! `make deps`); plotters' own font stack would pull in system font libraries to build.

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::geometry::Vec3;

const FONT_PATHS: &[&str] =
    &["/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", "/usr/share/fonts/TTF/DejaVuSans.ttf"];

/// Registers the font once per process; plotting fails with a clear message without it.
pub(crate) fn font() -> Result<(), String> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            for p in FONT_PATHS {
                if let Ok(bytes) = std::fs::read(p) {
                    // plotters keeps fonts for the life of the process.
                    let leaked: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                    if plotters::style::register_font("sans-serif", FontStyle::Normal, leaked).is_ok() {
                        return Ok(());
                    }
                }
            }
            Err(format!(
                "no font for plots; install fonts-dejavu-core (looked for {})",
                FONT_PATHS.join(", ")
            ))
        })
        .clone()
}

/// Draws on an RGB canvas of `size` and writes it to `path` as a PNG, whole
/// (`mavloc_data::pngfile`; plotters' own encoder would build `image` and its PNG stack).
pub(crate) fn png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), String> {
    let mut buf = vec![0u8; size.0 as usize * size.1 as usize * 3];
    draw(BitMapBackend::with_buffer(&mut buf, size).into_drawing_area())?;
    mavloc_data::pngfile::write(path, size.0, size.1, &buf, mavloc_data::pngfile::Channels::Rgb)
        .map_err(|e| format!("{}: {e}", path.display()))
}

pub(crate) fn err<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Histogram of distances (metres) with a logarithmic count axis and the mean marked.
pub fn distance_histogram(path: &Path, distances: &[f64], title: &str) -> Result<(), String> {
    font()?;
    let max = distances.iter().cloned().fold(1.0f64, f64::max).ceil();
    let bins = 40usize;
    let width = max / bins as f64;
    let mut counts = vec![0u32; bins];
    for d in distances {
        counts[((d / width) as usize).min(bins - 1)] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1) as f64 * 2.0;
    let mean = distances.iter().sum::<f64>() / distances.len().max(1) as f64;
    png(path, (900, 500), |root| {
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(55)
            .build_cartesian_2d(0.0..max, (0.8f64..top).log_scale())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("distance to ground-truth border (m)")
            .y_desc("landmarks (log)")
            .draw()
            .map_err(err)?;
        chart
            .draw_series(counts.iter().enumerate().filter(|(_, &c)| c > 0).map(|(i, &c)| {
                let x0 = i as f64 * width;
                Rectangle::new([(x0, 0.8), (x0 + width * 0.95, c as f64)], BLUE.mix(0.6).filled())
            }))
            .map_err(err)?;
        chart
            .draw_series(LineSeries::new(vec![(mean, 0.8), (mean, top)], RED.stroke_width(2)))
            .map_err(err)?
            .label(format!("mean {mean:.2} m"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
        chart.configure_series_labels().border_style(BLACK).background_style(WHITE).draw().map_err(err)?;
        root.present().map_err(err)
    })
}

/// Top view (north up, east right) and side view (east vs height) of landmarks over the
/// ground truth, with the fitted border line.
pub fn landmark_views(
    path: &Path,
    landmarks: &[Vec3],
    truth: &[Vec<Vec3>],
    border: &[Vec<Vec3>],
    title: &str,
) -> Result<(), String> {
    font()?;
    let all: Vec<&Vec3> = landmarks.iter().chain(truth.iter().flatten()).collect();
    if all.is_empty() {
        return Err("nothing to plot".into());
    }
    let (mut n0, mut n1, mut e0, mut e1, mut h0, mut h1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in &all {
        n0 = n0.min(p.x);
        n1 = n1.max(p.x);
        e0 = e0.min(p.y);
        e1 = e1.max(p.y);
        h0 = h0.min(-p.z);
        h1 = h1.max(-p.z);
    }
    let pad = 5.0;
    png(path, (1200, 760), |root| {
        root.fill(&WHITE).map_err(err)?;
        let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
        let (top, side) = root.split_vertically(520);
        let mut chart = ChartBuilder::on(&top)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(e0 - pad..e1 + pad, n0 - pad..n1 + pad)
            .map_err(err)?;
        chart.configure_mesh().x_desc("east (m)").y_desc("north (m)").draw().map_err(err)?;
        for line in truth {
            chart
                .draw_series(LineSeries::new(line.iter().map(|p| (p.y, p.x)), RED.stroke_width(2)))
                .map_err(err)?;
        }
        chart
            .draw_series(landmarks.iter().map(|p| Circle::new((p.y, p.x), 2, GREEN.mix(0.7).filled())))
            .map_err(err)?;
        for line in border {
            chart
                .draw_series(LineSeries::new(line.iter().map(|p| (p.y, p.x)), BLUE.stroke_width(2)))
                .map_err(err)?;
        }
        let mut chart = ChartBuilder::on(&side)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(e0 - pad..e1 + pad, h0 - 2.0..h1 + 2.0)
            .map_err(err)?;
        chart.configure_mesh().x_desc("east (m)").y_desc("height (m)").draw().map_err(err)?;
        for line in truth {
            chart
                .draw_series(LineSeries::new(line.iter().map(|p| (p.y, -p.z)), RED.stroke_width(2)))
                .map_err(err)?;
        }
        chart
            .draw_series(landmarks.iter().map(|p| Circle::new((p.y, -p.z), 2, GREEN.mix(0.7).filled())))
            .map_err(err)?;
        root.present().map_err(err)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plots_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let d: Vec<f64> = (0..300).map(|i| (i % 17) as f64 * 0.3).collect();
        distance_histogram(&dir.path().join("h.png"), &d, "test").unwrap();
        let truth = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(10.0, 5.0, -2.0)]];
        let lm = vec![Vec3::new(1.0, 1.0, 0.0), Vec3::new(5.0, 3.0, -1.0)];
        landmark_views(&dir.path().join("v.png"), &lm, &truth, &truth, "test").unwrap();
        for f in ["h.png", "v.png"] {
            let bytes = std::fs::read(dir.path().join(f)).unwrap();
            assert_eq!(&bytes[1..4], b"PNG");
        }
    }
}
