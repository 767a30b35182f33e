//! Geometry core of mavloc: frames, rotations, the pinhole camera, bearings, the
//! ground-plane projection and WGS84 geodesy.
//!
//! Area seed (`area-localization-thesis.txt`): sec. 2.1 (eq. 2.1-2.10, the "previous
//! method"), sec. 5.1.2 (eq. 5.4-5.5, the bearing measurement) and sec. 5.4.2
//! (eq. 5.12-5.18, pixel to bearing, gimbal kinematic chains). The seed's formulas
//! carry typos (eq. 2.3 and 2.4 have a sign missing in the x rotation, eq. 5.18 lacks a
//! square root, eq. 5.14 compares focal-plane coordinates with the principal point); this
//! module derives each one again from the conventions below, and the property tests at
//! the bottom of each file prove them by round trips.
//!
//! # Conventions
//!
//! * **Local frame**: North-East-Down (NED), metres, origin at a geodetic point
//!   ([`LocalFrame`]). "Down" is positive below the origin, so an altitude `h` above the
//!   origin is `down = -h`.
//! * **Body / gimbal frame**: Forward-Right-Down (FRD). A rotation "local <- X" maps
//!   vectors expressed in frame X into the local frame; its columns are X's axes in NED.
//! * **Angles**: radians, right-handed. Yaw about down (0 = north, +90 deg = east),
//!   pitch about the (rotated) right axis (positive = nose up, so a camera looking
//!   straight down has pitch -90 deg), roll about the (rotated) forward axis.
//! * **Gimbal kinematic chains** (seed eq. 5.17), as intrinsic rotations from the local
//!   frame: [`GimbalChain::YawPitchRoll`] is `Rz(yaw) Ry(pitch) Rx(roll)` (AirSim and the
//!   usual aerospace order); [`GimbalChain::YawRollPitch`] is `Rz(yaw) Rx(roll) Ry(pitch)`
//!   (DJI Zenmuse H20T, whose roll motor sits between yaw and pitch).
//! * **Camera frame**: OpenCV's: x right, y down, z along the optical axis. The camera
//!   looks along the gimbal's forward axis, so camera (x, y, z) = gimbal (y, z, x). This
//!   fixed permutation is the seed's `R^{L->G0}` (eq. 2.3) written without its typo.
//! * **Pixels**: `(u, v)` = (column, row), `(0, 0)` is the *centre* of the top-left pixel
//!   (OpenCV's convention), so the centre of a `w x h` image is `((w-1)/2, (h-1)/2)`.
//! * **Bearing** (seed eq. 5.4-5.5): from the camera to a point, `yaw = atan2(east,
//!   north)` in `(-pi, pi]` and `pitch = atan2(-down, horizontal)` in `[-pi/2, pi/2]`,
//!   i.e. elevation, negative below the horizon. This is exactly the pair of gimbal angles
//!   (roll 0) that points the optical axis at the point, in either chain.

mod bearing;
mod camera;
mod geodetic;
mod ground;
mod polyline;
mod rotation;

pub use bearing::{angle_diff, bearing_between, wrap_angle, Bearing};
pub use camera::{CameraPose, Intrinsics, Mount, Pixel};
pub use geodetic::{readable, Geodetic, LocalFrame};
pub use ground::ground_plane_point;
pub use polyline::nearest_on_polylines;
pub use rotation::{body_rotation, gimbal_from_camera, GimbalAngles, GimbalChain};

/// A 3-vector in metres; in the local frame unless a name says otherwise.
pub type Vec3 = nalgebra::Vector3<f64>;
/// A rotation matrix.
pub type Rot3 = nalgebra::Rotation3<f64>;
