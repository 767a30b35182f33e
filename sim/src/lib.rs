//! mavloc's simulated world. Nothing here knows about the pipelines; only [`vehicle`]
//! speaks MAVLink.
//!
//! * [`scenario`]: scenario files (`sim/scenarios/*.toml`), deterministic from a seed,
//!   with their noise and random-view specifications.
//! * [`state`]: the vehicle's true state at one instant.
//! * [`terrain`]: the height field.
//! * [`texture`]: ground textures in world units, mirrored tiling, mip levels.
//! * [`world`]: worlds built from scenarios: terrain, appearance, target area, ground truth.
//! * [`render`]: the camera renderer (RGB frame + target mask), sharing the geometry crate.
//! * [`mission`]: flights along the border (area) or over the floor (indoor); QGC plans.
//! * [`views`]: random labelled views and photometric changes (indoor seed sec. 3.4.2).
//! * [`dataset`]: renders a scenario into a dataset, written through `mavloc_data`
//!   (which owns the format and its reader).
//! * [`vehicle`]: a PX4-like simulated vehicle with a gimbal, over MAVLink.
//!
//! Modules depend one way: `state`, `scenario`, `terrain` and `texture` are leaves;
//! `world` builds on `scenario`; `mission` on `world`; `views` on `scenario` and `state`;
//! `render` on `world`; `dataset` and `vehicle` on all of them.

pub mod dataset;
pub mod mission;
pub mod render;
pub mod scenario;
pub mod state;
pub mod terrain;
pub mod texture;
pub mod vehicle;
pub mod views;
pub mod world;

pub use dataset::{render_dataset, render_dataset_until, RenderOptions};
pub use mission::Mission;
pub use render::{Frame, Renderer};
pub use scenario::Scenario;
pub use world::World;
