//! Are a survey's tie points true? Matches every overlapping pair of photos as the photo
//! alignment does (`area::align::match_pairs`, the tags trusted to `PRIOR_DEG`), then
//! checks each pair's matches against the dataset's true poses (a rendered dataset; for
//! imported photos the "truth" is the tags): a match is false when the point its two
//! rays meet at reprojects more than 5 px off. Per pair it prints the matches, how many
//! are false, and how far apart the tagged poses put a match's two ground points (median):
//! the quantity the alignment's match gate bounds. Then the tracks chained from the pairs,
//! how many hold a false sighting, and how high the true ones lie above the true surface.
//!
//! `cargo run --release --example tie_truth -- DATASET [GROUND_DOWN_M] [PRIOR_DEG]`

use std::collections::BTreeMap;
use std::path::Path;

use mavloc::area::rays::{triangulate, Ray};
use mavloc::area::{align, imageup};
use mavloc::geometry::{CameraPose, Intrinsics, Pixel, Vec3};
use mavloc_data::Dataset;
use opencv::imgcodecs;

const FALSE_PX: f64 = 5.0;

/// The largest reprojection error of the point the rays of `seen` meet at.
fn worst_error(seen: &[(&CameraPose, Pixel)], k: &Intrinsics, start: Vec3) -> f64 {
    let rays: Vec<Ray> =
        seen.iter().map(|(p, px)| Ray { origin: p.position, dir: p.direction(k, *px) }).collect();
    let Some(x) = triangulate(&rays, &start, 1e-3, &[0.0; 3]) else { return f64::INFINITY };
    seen.iter()
        .map(|(p, px)| p.project(k, &x.position).map_or(f64::INFINITY, |q| (q.u - px.u).hypot(q.v - px.v)))
        .fold(0.0, f64::max)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        anyhow::bail!("usage: tie_truth DATASET [GROUND_DOWN_M] [PRIOR_DEG]")
    };
    let ground: f64 = args.get(2).map(|a| a.parse()).transpose()?.unwrap_or(0.0);
    let prior_deg: f64 = args.get(3).map(|a| a.parse()).transpose()?.unwrap_or(5.0);
    let ds = Dataset::open(Path::new(path)).map_err(|e| anyhow::anyhow!(e))?;
    let k = ds.camera.intrinsics();
    let surface =
        mavloc::simulated::surface::true_surface(Path::new(path)).map_err(|e| anyhow::anyhow!(e))?;
    let truth: Vec<CameraPose> = ds.records.iter().map(|r| ds.camera_pose(&r.truth, [0.0; 3])).collect();
    let mut photos = Vec::new();
    for r in &ds.records {
        let img = mavloc::imaging::read_image(&ds.frame_path(r), imgcodecs::IMREAD_COLOR)
            .map_err(anyhow::Error::msg)?;
        let features = imageup::features_sized(&img, align::FEATURES, align::WORK_WIDTH)?;
        photos.push(align::Photo { frame: r.frame, features, pose: ds.camera_pose(&r.measured, [0.0; 3]) });
    }
    let (pairs, tried) = align::match_pairs(&photos, &k, ground, prior_deg)?;
    println!("{} of {tried} overlapping pairs linked", pairs.len());
    println!("pair     matches  false  apart as tagged (median, m)");
    for p in &pairs {
        let (fa, fb) = (photos[p.a].features.pixels(), photos[p.b].features.pixels());
        let start = Vec3::new(truth[p.a].position.x, truth[p.a].position.y, ground);
        let false_ = p
            .matches
            .iter()
            .filter(|&&(x, y)| {
                worst_error(&[(&truth[p.a], fa[x]), (&truth[p.b], fb[y])], &k, start) > FALSE_PX
            })
            .count();
        let mut apart: Vec<f64> = p
            .matches
            .iter()
            .filter_map(|&(x, y)| {
                let ga = imageup::on_ground(&photos[p.a].pose, &k, fa[x], ground)?;
                let gb = imageup::on_ground(&photos[p.b].pose, &k, fb[y], ground)?;
                Some((ga[0] - gb[0]).hypot(ga[1] - gb[1]))
            })
            .collect();
        apart.sort_by(f64::total_cmp);
        let median = apart.get(apart.len() / 2).copied().unwrap_or(f64::NAN);
        println!("{:>3}-{:<3} {:>8} {:>6} {:>8.1}", p.a, p.b, p.matches.len(), false_, median);
    }
    let ties = align::tracks(&photos, &pairs, &k, ground);
    let mut tracks: BTreeMap<u64, Vec<(usize, Pixel)>> = BTreeMap::new();
    let index: BTreeMap<u64, usize> = photos.iter().enumerate().map(|(i, p)| (p.frame, i)).collect();
    for &(frame, id, px) in &ties.sightings {
        tracks.entry(id).or_default().push((index[&frame], px));
    }
    let (mut false_, mut heights) = (0, Vec::new());
    for (id, seen) in &tracks {
        let with: Vec<(&CameraPose, Pixel)> = seen.iter().map(|(i, px)| (&truth[*i], *px)).collect();
        let start = ties.points[*id as usize].position;
        if worst_error(&with, &k, start) > FALSE_PX {
            false_ += 1;
        } else if let Some(surface) = &surface {
            let rays: Vec<Ray> =
                with.iter().map(|(p, px)| Ray { origin: p.position, dir: p.direction(&k, *px) }).collect();
            if let Some(x) = triangulate(&rays, &start, 1e-3, &[0.0; 3]) {
                heights.push(-x.position.z - surface(x.position.x, x.position.y));
            }
        }
    }
    println!("{} tracks, {false_} with a false sighting", tracks.len());
    if !heights.is_empty() {
        heights.sort_by(f64::total_cmp);
        let q = |f: f64| heights[((heights.len() - 1) as f64 * f) as usize];
        println!(
            "true tracks above the true surface: median {:+.3} m (10-90 %: {:+.3} to {:+.3} m)",
            q(0.5),
            q(0.1),
            q(0.9)
        );
    }
    Ok(())
}
