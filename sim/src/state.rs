//! The true state of the simulated vehicle at one instant: what missions, random views and
//! the simulated vehicle produce and the renderer and dataset writer consume. A leaf of the
//! crate, so those modules share it without depending on each other.

use mavloc_geometry::{GimbalAngles, Vec3};

/// The true state at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct State {
    pub t: f64,
    pub position: Vec3,
    pub velocity: Vec3,
    /// Vehicle roll, pitch, yaw (radians).
    pub attitude: [f64; 3],
    pub gimbal: GimbalAngles,
}
