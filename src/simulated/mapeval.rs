//! `mavloc indoor map-eval`: renders random labelled views of a floor image with the
//! simulator (indoor seed sec. 3.4.2) and scores them with the pipeline's map evaluation
//! ([`crate::indoor::mapeval`]).

use std::path::Path;

use opencv::prelude::*;
use rayon::prelude::*;

use crate::imaging::bgr_from_rgb;
use crate::indoor::derotate::Canvas;
use crate::indoor::mapeval::{self, MapEvaluation};
use crate::settings::Indoor;
use mavloc_sim::{views, Mission, Renderer, Scenario, World};

/// Evaluates a floor image of `metres_per_px` from `count` synthetic views;
/// `progress(done, count)` after each view is rendered (from worker threads).
pub fn evaluate(
    map: &Path,
    metres_per_px: f64,
    count: usize,
    sigma_m: f64,
    s: &Indoor,
    seed: u64,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<MapEvaluation, String> {
    let img = opencv::imgcodecs::imread(map, opencv::imgcodecs::IMREAD_COLOR)
        .map_err(|e| format!("cannot read map {}: {e}", map.display()))?;
    if img.empty() {
        return Err(format!("cannot read map {} as an image", map.display()));
    }
    let (w, h) = (img.cols() as u32, img.rows() as u32);
    let mut scenario = Scenario::load("indoor-floor")?;
    scenario.ground.texture = map.display().to_string();
    scenario.ground.metres_per_texel = metres_per_px;
    // Views stay half a footprint inside the image.
    let half = [h as f64 * metres_per_px / 2.0 - 0.6, w as f64 * metres_per_px / 2.0 - 0.6];
    if half[0] <= 0.1 || half[1] <= 0.1 {
        return Err(format!(
            "map {} is {:.1} x {:.1} m at {metres_per_px} m per pixel; it must be over 1.4 m on each side",
            map.display(),
            h as f64 * metres_per_px,
            w as f64 * metres_per_px
        ));
    }
    let mut spec = scenario.views.clone().unwrap_or_default();
    spec.half_extent_m = half[0].min(half[1]);
    scenario.camera.width = 320;
    scenario.camera.height = 240;
    let world = World::build(&scenario)?;
    let mission = Mission::plan(&world)?;
    let renderer = Renderer::new(&world);
    let k = scenario.intrinsics();
    let pre = crate::indoor::offline::preprocessor(k, s);
    let shots = views::random_views(&spec, count, seed);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let canvases: Vec<(Canvas, [f64; 2])> = shots
        .par_iter()
        .map(|(state, appearance)| {
            let pose = mission.camera_pose(state);
            let mut frame = renderer.render(&pose, &k);
            views::apply(appearance, frame.width as usize, frame.height as usize, &mut frame.rgb);
            let bgr = bgr_from_rgb(&frame.rgb, frame.height).map_err(|e| e.to_string())?;
            let c = pre
                .prepare(&bgr, Some(&pose.local_from_camera()), Some(-pose.position.z))
                .map_err(|e| e.to_string())?;
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, count);
            Ok((c, [state.position.x, state.position.y]))
        })
        .collect::<Result<_, String>>()?;
    mapeval::evaluate_views(&canvases, half, sigma_m, s, seed)
}
