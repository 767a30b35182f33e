//! mavloc's simulated world. Nothing here knows about MAVLink or the pipelines.
//!
//! * [`scenario`]: scenario files (`sim/scenarios/*.toml`), deterministic from a seed.
//! * [`terrain`]: the height field.
//! * [`texture`]: ground textures in world units, mirrored tiling, mip levels.
//! * [`world`]: worlds built from scenarios: terrain, appearance, target area, ground truth.
//! * [`render`]: the camera renderer (RGB frame + target mask), sharing the geometry crate.
//! * [`mission`]: flights along the border (area) or over the floor (indoor); QGC plans.
//! * [`views`]: random labelled views and photometric changes (indoor seed sec. 3.4.2).
//! * [`dataset`]: the dataset format on disk, written by `render_dataset`, read by `Dataset`.

pub mod dataset;
pub mod mission;
pub mod render;
pub mod scenario;
pub mod terrain;
pub mod texture;
pub mod vehicle;
pub mod views;
pub mod world;

pub use dataset::{render_dataset, Dataset, RenderOptions};
pub use mission::Mission;
pub use render::{Frame, Renderer};
pub use scenario::Scenario;
pub use world::World;
