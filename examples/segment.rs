//! Segments images with `area.segmenter` and draws contact sheets of each beside its mask,
//! to look at what a segmenter takes for the target on any photo (no dataset needed).
//!
//! `cargo run --release --example segment -- OUT_DIR IMAGE... [--set KEY=VALUE]... [--shadow U,V,U,V,...] [--train IMAGE[=MASK]]...`
//!
//! `--train` segments with `area.segmenter = "learned"`, trained on the given images and
//! masks (without `=MASK`, the image's mask from the configured rule, `water` unless set).
//!
//! `--shadow` first casts a synthetic shadow over a polygon (corners as fractions of the
//! width and height) of each image: each channel scaled as skylight alone lights the
//! ground, blue 0.45, green 0.38, red 0.30 (set so the shadow on DJI_0030's road has the
//! hue, saturation and value of the real tree shadow on its beach: H 110, S 92, V 86
//! against 119, 107, 91; the sunlit road is S 23, V 199), and prints how much of the
//! polygon the segmenter took for the target. Each image's line gives the share of the frame
//! the mask covers and the share the water rule's shadow check (`area::shadow`) takes for
//! cast shadows.

use mavloc::area::segment::{contact_sheets, segment, Learned, SheetRow};
use mavloc::settings::{self, Layers};
use opencv::core::{self, Mat, Point, Scalar, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

/// Per channel (B, G, R) scale of a shadow lit by the sky alone.
const SKYLIGHT: [f64; 3] = [0.45, 0.38, 0.30];

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let Some(out) = args.next() else {
        anyhow::bail!("usage: segment OUT_DIR IMAGE... [--set KEY=VALUE]... [--shadow U,V,U,V,...]")
    };
    let (mut images, mut overrides, mut shadow, mut train) = (Vec::new(), Vec::new(), None, Vec::new());
    while let Some(a) = args.next() {
        if a == "--set" {
            overrides.push(args.next().ok_or_else(|| anyhow::anyhow!("--set needs KEY=VALUE"))?);
        } else if a == "--train" {
            train.push(args.next().ok_or_else(|| anyhow::anyhow!("--train needs IMAGE[=MASK]"))?);
        } else if a == "--shadow" {
            let v = args.next().ok_or_else(|| anyhow::anyhow!("--shadow needs U,V,U,V,..."))?;
            let f: Vec<f64> = v.split(',').map(str::parse).collect::<Result<_, _>>()?;
            anyhow::ensure!(
                f.len() >= 6 && f.len().is_multiple_of(2),
                "--shadow needs three or more U,V corners"
            );
            shadow = Some(f);
        } else {
            images.push(a);
        }
    }
    let layers = Layers::from_process(None, overrides);
    let mut s = settings::load(&layers)?.settings;
    if matches!(s.area.segmenter, mavloc::settings::Segmenter::Masks | mavloc::settings::Segmenter::Learned) {
        s.area.segmenter = mavloc::settings::Segmenter::Water;
    }
    let mut examples = Vec::new();
    for t in &train {
        let (img, mask) = t.split_once('=').map_or((t.as_str(), None), |(i, m)| (i, Some(m)));
        let frame = imgcodecs::imread(img, imgcodecs::IMREAD_COLOR)?;
        anyhow::ensure!(!frame.empty(), "{img}: cannot read it");
        let mask = match mask {
            Some(m) => imgcodecs::imread(m, imgcodecs::IMREAD_GRAYSCALE)?,
            None => segment(&frame, &s.area)?.expect("a rule segmenter"),
        };
        examples.push((frame, mask));
    }
    let learned = if train.is_empty() {
        None
    } else {
        Some(
            Learned::train(&examples)?
                .ok_or_else(|| anyhow::anyhow!("the training masks hold one class only"))?,
        )
    };
    let mut rows = Vec::new();
    for (i, path) in images.iter().enumerate() {
        let mut img = imgcodecs::imread(path, imgcodecs::IMREAD_COLOR)?;
        anyhow::ensure!(!img.empty(), "{path}: cannot read it");
        let cast = match &shadow {
            Some(f) => Some(cast_shadow(&mut img, f)?),
            None => None,
        };
        let mask = match &learned {
            Some(l) => l.segment(&img)?,
            None => segment(&img, &s.area)?.expect("a segmenter that makes masks"),
        };
        if let Some(area) = cast {
            let mut both = Mat::default();
            core::bitwise_and(&mask, &area, &mut both, &core::no_array())?;
            let taken = core::count_non_zero(&both)? as f64 / core::count_non_zero(&area)?.max(1) as f64;
            println!("{path}: {:.1} % of the shadow taken for the target", 100.0 * taken);
        }
        // What the water rule's shadow check finds (at the segmenter's working size).
        let shadows = mavloc::area::shadow::cast_shadows(&mavloc::area::segment::shrunk(&img)?)?;
        let share = |m: &Mat| -> anyhow::Result<f64> {
            Ok(100.0 * core::count_non_zero(m)? as f64 / (m.rows() * m.cols()).max(1) as f64)
        };
        println!(
            "{path}: target {:.1} % of the frame; cast shadows found {:.1} %",
            share(&mask)?,
            share(&shadows)?
        );
        rows.push(SheetRow::new(i as u64, &img, &mask)?);
    }
    std::fs::create_dir_all(&out)?;
    for p in contact_sheets(std::path::Path::new(&out), &rows, &Default::default())? {
        println!("{}", p.display());
    }
    Ok(())
}

/// Darkens the polygon (corners as fractions of the size) as a shadow; returns its mask.
fn cast_shadow(img: &mut Mat, corners: &[f64]) -> anyhow::Result<Mat> {
    let (w, h) = (img.cols() as f64, img.rows() as f64);
    let poly: Vector<Point> =
        corners.chunks(2).map(|c| Point::new((c[0] * w).round() as i32, (c[1] * h).round() as i32)).collect();
    let mut area = Mat::zeros(img.rows(), img.cols(), core::CV_8UC1)?.to_mat()?;
    let polys: Vector<Vector<Point>> = std::iter::once(poly).collect();
    imgproc::fill_poly(&mut area, &polys, Scalar::all(255.0), imgproc::LINE_8, 0, Point::new(0, 0))?;
    let mut dark = Mat::default();
    core::multiply(&*img, &Scalar::new(SKYLIGHT[0], SKYLIGHT[1], SKYLIGHT[2], 0.0), &mut dark, 1.0, -1)?;
    dark.copy_to_masked(img, &area)?;
    Ok(area)
}
