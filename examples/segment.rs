//! Segments images with `area.segmenter` and draws contact sheets of each beside its mask,
//! to look at what a segmenter takes for the target on any photo (no dataset needed).
//!
//! `cargo run --release --example segment -- OUT_DIR IMAGE... [--set KEY=VALUE]...`

use mavloc::area::segment::{contact_sheets, segment, SheetRow};
use mavloc::settings::{self, Layers};
use opencv::imgcodecs;
use opencv::prelude::*;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let Some(out) = args.next() else {
        anyhow::bail!("usage: segment OUT_DIR IMAGE... [--set KEY=VALUE]...")
    };
    let (mut images, mut overrides) = (Vec::new(), Vec::new());
    while let Some(a) = args.next() {
        if a == "--set" {
            overrides.push(args.next().ok_or_else(|| anyhow::anyhow!("--set needs KEY=VALUE"))?);
        } else {
            images.push(a);
        }
    }
    let layers = Layers::from_process(None, overrides);
    let mut s = settings::load(&layers)?.settings;
    if s.area.segmenter == mavloc::settings::Segmenter::Masks {
        s.area.segmenter = mavloc::settings::Segmenter::Water;
    }
    let mut rows = Vec::new();
    for (i, path) in images.iter().enumerate() {
        let img = imgcodecs::imread(path, imgcodecs::IMREAD_COLOR)?;
        anyhow::ensure!(!img.empty(), "{path}: cannot read it");
        let mask = segment(&img, &s.area)?.expect("a segmenter that makes masks");
        rows.push(SheetRow::new(i as u64, &img, &mask)?);
    }
    std::fs::create_dir_all(&out)?;
    for p in contact_sheets(std::path::Path::new(&out), &rows, &Default::default())? {
        println!("{}", p.display());
    }
    Ok(())
}
