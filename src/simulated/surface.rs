//! The true ground of a rendered dataset (`mavloc eval area`): a dataset the simulator
//! rendered carries its `scenario.toml`, from which the world, and so the height of its
//! visible surface everywhere, is rebuilt exactly.

use std::path::Path;

/// The height (m, up) of the visible surface at (north, east) of the world a rendered
/// dataset was made from; `None` for a dataset with no scenario (imported photos).
pub fn true_surface(dataset: &Path) -> Result<Option<impl Fn(f64, f64) -> f64>, String> {
    let path = dataset.join("scenario.toml");
    if !path.exists() {
        return Ok(None);
    }
    let scenario = mavloc_sim::Scenario::load(&path.display().to_string())?;
    let world = mavloc_sim::World::build(&scenario).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(Some(move |n: f64, e: f64| world.surface_height(n, e)))
}
