//! Map evaluation (indoor seed sec. 3.4.1-3.4.2): how well a floor image suits texton
//! localisation, before it is printed.
//!
//! Synthetic views of the image are rendered from random poses (roll, pitch, yaw, height,
//! brightness, contrast, blur; sec. 3.4.2) by the simulator with the image as the floor
//! (`crate::simulated::mapeval`, as the pipeline does not depend on the simulator); their
//! histograms give the global loss
//! `L(D) = 1/N^2 sum_i sum_j [CS(h_i, h_j) - f(x_i; x_j, s_x) f(y_i; y_j, s_y)]`
//! with `CS` the cosine similarity and `f` an unnormalised Gaussian: the actual similarity
//! minus the ideal one, which falls with distance. Each view's row mean is its own loss;
//! the heat map smooths those over the map (fig. 3.10). Lower is better; a map whose
//! distant places look alike scores high where they are.

use std::path::Path;

use rand::SeedableRng;
use rayon::prelude::*;

use super::derotate::Canvas;
use super::textons::{cosine, Dictionary};
use crate::settings::Indoor;

#[derive(Clone, Debug, serde::Serialize)]
pub struct MapEvaluation {
    pub views: usize,
    pub global_loss: f64,
    /// (x, y, loss) per view.
    pub samples: Vec<(f64, f64, f64)>,
    /// The map's half extent in x and y, metres.
    pub half_extent_m: [f64; 2],
}

/// The global loss of a dataset of histograms and positions (sec. 3.4.1), and each
/// sample's row mean.
pub fn global_loss(histograms: &[Vec<f32>], positions: &[[f64; 2]], sigma: [f64; 2]) -> (f64, Vec<f64>) {
    let n = histograms.len();
    if n == 0 {
        return (f64::NAN, Vec::new());
    }
    let f = |a: f64, b: f64, s: f64| (-(a - b) * (a - b) / (2.0 * s * s)).exp();
    let rows: Vec<f64> = (0..n)
        .into_par_iter()
        .map(|i| {
            (0..n)
                .map(|j| {
                    let cs = cosine(&histograms[i], &histograms[j]) as f64;
                    let ideal = f(positions[i][0], positions[j][0], sigma[0])
                        * f(positions[i][1], positions[j][1], sigma[1]);
                    cs - ideal
                })
                .sum::<f64>()
                / n as f64
        })
        .collect();
    (rows.iter().sum::<f64>() / n as f64, rows)
}

/// Evaluates prepared views of a floor image (each with its x, y): a dictionary learnt
/// from them, their histograms and the global loss. `half_extent_m` is the map's, for the
/// heat map. The views come from the simulator (`crate::simulated::mapeval`).
pub fn evaluate_views(
    canvases: &[(Canvas, [f64; 2])],
    half_extent_m: [f64; 2],
    sigma_m: f64,
    s: &Indoor,
    seed: u64,
) -> Result<MapEvaluation, String> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let patch = (s.patch_w as usize, s.patch_h as usize);
    let samples: Vec<Vec<f32>> = canvases
        .iter()
        .flat_map(|(c, _)| Dictionary::sample_patches(&c.img, &c.mask, patch, 200, &mut rng))
        .collect();
    let dict = super::offline::learn_dictionary(samples, s, seed)?;
    let histograms: Vec<Vec<f32>> =
        canvases.par_iter().map(|(c, _)| dict.histogram_full_serial(&c.img, Some(&c.mask))).collect();
    let positions: Vec<[f64; 2]> = canvases.iter().map(|(_, p)| *p).collect();
    let (loss, rows) = global_loss(&histograms, &positions, [sigma_m, sigma_m]);
    Ok(MapEvaluation {
        views: histograms.len(),
        global_loss: loss,
        samples: positions.iter().zip(&rows).map(|(p, l)| (p[0], p[1], *l)).collect(),
        half_extent_m,
    })
}

/// The per-view loss smoothed over the map (Gaussian, `smooth_m`), as a PNG heat map.
pub fn heatmap(path: &Path, e: &MapEvaluation, smooth_m: f64, title: &str) -> Result<(), String> {
    use crate::output::plot::{err, font};
    use plotters::prelude::*;
    font()?;
    let [hx, hy] = e.half_extent_m;
    let cells = 80usize;
    let grid: Vec<(f64, f64, f64)> = (0..cells * cells)
        .map(|c| {
            let (i, j) = (c / cells, c % cells);
            let y = -hy + (j as f64 + 0.5) * 2.0 * hy / cells as f64;
            let x = hx - (i as f64 + 0.5) * 2.0 * hx / cells as f64;
            let (mut num, mut den) = (0.0, 0.0);
            for (sx, sy, l) in &e.samples {
                let w = (-((sx - x).powi(2) + (sy - y).powi(2)) / (2.0 * smooth_m * smooth_m)).exp();
                num += w * l;
                den += w;
            }
            (x, y, if den > 1e-9 { num / den } else { f64::NAN })
        })
        .collect();
    let (lo, hi) = grid
        .iter()
        .filter(|g| g.2.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), g| (a.min(g.2), b.max(g.2)));
    crate::output::plot::png(path, (760, 700), |root| {
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(-hy..hy, -hx..hx)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("y (east), m")
            .y_desc("x (north), m")
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(err)?;
        let (dy, dx) = (hy / cells as f64, hx / cells as f64);
        chart
            .draw_series(grid.iter().filter(|g| g.2.is_finite()).map(|(x, y, l)| {
                // Blue (low loss, good) to red (high loss: looks like distant places).
                let t = if hi > lo { ((l - lo) / (hi - lo)).clamp(0.0, 1.0) } else { 0.5 };
                let colour = RGBColor(
                    (255.0 * t) as u8,
                    (80.0 * (1.0 - (2.0 * t - 1.0).abs())) as u8,
                    (255.0 * (1.0 - t)) as u8,
                );
                Rectangle::new([(y - dy, x - dx), (y + dy, x + dx)], colour.filled())
            }))
            .map_err(err)?;
        chart
            .draw_series(e.samples.iter().map(|(x, y, _)| Circle::new((*y, *x), 1, BLACK.mix(0.4).filled())))
            .map_err(err)?;
        root.present().map_err(err)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distinct_places_score_lower_than_look_alikes() {
        let positions: Vec<[f64; 2]> = (0..6).map(|i| [i as f64, 0.0]).collect();
        // Every place has its own texton: actual similarity equals the ideal at zero distance.
        let distinct: Vec<Vec<f32>> =
            (0..6).map(|i| (0..6).map(|j| if i == j { 1.0 } else { 0.0 }).collect()).collect();
        // Every place looks the same.
        let alike = vec![vec![1.0f32, 0.0]; 6];
        let (l_distinct, rows) = global_loss(&distinct, &positions, [0.3, 0.3]);
        let (l_alike, _) = global_loss(&alike, &positions, [0.3, 0.3]);
        // Only the ideal similarity of neighbours 1 m apart (exp(-1 / 0.18)) is left.
        assert!(l_distinct.abs() < 0.01, "{l_distinct}");
        assert!(l_alike > 0.8, "{l_alike}");
        assert_eq!(rows.len(), 6);
    }
}
