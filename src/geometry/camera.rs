//! The pinhole camera and the camera pose: 3D point <-> pixel, pixel -> viewing ray and
//! bearing (area seed eq. 2.7-2.8 and 5.12-5.18).
//!
//! The seed turns a pixel into a bearing through two half-angles (eq. 5.13-5.15) and then
//! reads the bearing back out of a rotation matrix (eq. 5.18, missing a square root). Both
//! steps amount to: take the ray `A^-1 [u v 1]^T` in the camera frame, rotate it into the
//! local frame, and take its bearing. That is what [`CameraPose::pixel_bearing`] does, and
//! the property tests check it against the direct bearing of eq. 5.5. Lens distortion is
//! not modelled here: frames are undistorted before they reach the geometry.

use serde::{Deserialize, Serialize};

use crate::rotation::gimbal_from_camera;
use crate::{ground_plane_point, Bearing, GimbalAngles, GimbalChain, Rot3, Vec3};

/// Image coordinates in pixels (column `u`, row `v`), pixel centres at integers.
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct Pixel {
    pub u: f64,
    pub v: f64,
}

impl Pixel {
    pub fn new(u: f64, v: f64) -> Self {
        Pixel { u, v }
    }
}

/// Pinhole intrinsics (seed eq. 2.8) with the image size they belong to.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    /// Focal lengths in pixels.
    pub fx: f64,
    pub fy: f64,
    /// Principal point in pixels.
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Square pixels, principal point at the image centre, horizontal field of view
    /// `hfov` radians (AirSim's default camera is 90 deg).
    pub fn from_hfov(width: u32, height: u32, hfov: f64) -> Intrinsics {
        let f = (width as f64 / 2.0) / (hfov / 2.0).tan();
        Intrinsics {
            width,
            height,
            fx: f,
            fy: f,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
        }
    }

    /// Checks the values are usable; the message names the offending field.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!("image size {}x{} is empty", self.width, self.height));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} = {v} must be a positive number of pixels"));
            }
        }
        // The principal point on the image: a calibration of another camera (or with its
        // axes swapped) is otherwise taken and bends every bearing.
        for (name, v, side) in [("cx", self.cx, self.width), ("cy", self.cy, self.height)] {
            if !(v.is_finite() && (-0.5..=side as f64 - 0.5).contains(&v)) {
                return Err(format!(
                    "{name} = {v} must be on the {}x{} image (-0.5 to {})",
                    self.width,
                    self.height,
                    side as f64 - 0.5
                ));
            }
        }
        Ok(())
    }

    /// Intrinsics of the image shrunk by an integer `factor` with area averaging (OpenCV
    /// `resize` with `INTER_AREA`): destination pixel `i` covers source pixels
    /// `[f i, f i + f)`, so its centre is at source `f i + (f - 1) / 2`.
    pub fn downscaled(&self, factor: u32) -> Intrinsics {
        let f = factor.max(1) as f64;
        let off = (f - 1.0) / 2.0;
        Intrinsics {
            width: self.width / factor.max(1),
            height: self.height / factor.max(1),
            fx: self.fx / f,
            fy: self.fy / f,
            cx: (self.cx - off) / f,
            cy: (self.cy - off) / f,
        }
    }

    /// Horizontal field of view, radians.
    pub fn hfov(&self) -> f64 {
        2.0 * (self.width as f64 / 2.0 / self.fx).atan()
    }

    /// Viewing ray of a pixel in the camera frame, scaled to `z = 1` (seed eq. 5.12).
    pub fn ray(&self, px: Pixel) -> Vec3 {
        Vec3::new((px.u - self.cx) / self.fx, (px.v - self.cy) / self.fy, 1.0)
    }

    /// Pixel of a point given in the camera frame; `None` if it is not in front of the
    /// camera.
    pub fn project_camera(&self, p: &Vec3) -> Option<Pixel> {
        if p.z.is_nan() || p.z <= 0.0 {
            return None;
        }
        let px = Pixel { u: self.fx * p.x / p.z + self.cx, v: self.fy * p.y / p.z + self.cy };
        (px.u.is_finite() && px.v.is_finite()).then_some(px)
    }

    /// Whether a pixel lies on the image (pixel `i` spans `[i - 0.5, i + 0.5)`).
    pub fn contains(&self, px: Pixel) -> bool {
        px.u >= -0.5 && px.v >= -0.5 && px.u < self.width as f64 - 0.5 && px.v < self.height as f64 - 0.5
    }
}

/// What the gimbal's yaw is measured against.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mount {
    /// Gimbal angles relative to the local frame (yaw from north, pitch and roll from
    /// the horizon), as a stabilised gimbal in earth-frame mode reports them.
    Earth,
    /// Pitch and roll from the horizon, yaw relative to the vehicle's heading (MAVLink
    /// gimbal protocol v2 without `YAW_IN_EARTH_FRAME`). `vehicle_yaw` in radians.
    VehicleHeading { vehicle_yaw: f64 },
    /// Angles relative to the vehicle body (a fixed camera mount): `attitude` is the
    /// vehicle's "local <- body" rotation.
    Body { attitude: Rot3 },
}

/// Where a camera is and which way it looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    /// Optical centre, local NED, metres.
    pub position: Vec3,
    /// Rotation "local <- gimbal (FRD)".
    pub attitude: Rot3,
}

impl CameraPose {
    /// Pose of a camera on a gimbal with the given chain, angles and mount.
    pub fn from_gimbal(position: Vec3, chain: GimbalChain, angles: GimbalAngles, mount: Mount) -> Self {
        let attitude = match mount {
            Mount::Earth => chain.rotation(angles),
            Mount::VehicleHeading { vehicle_yaw } => {
                chain.rotation(GimbalAngles { yaw: angles.yaw + vehicle_yaw, ..angles })
            }
            Mount::Body { attitude } => attitude * chain.rotation(angles),
        };
        CameraPose { position, attitude }
    }

    /// A level-roll camera at `position` whose optical axis points at `target`.
    /// `None` if the two coincide.
    pub fn looking_at(position: Vec3, target: &Vec3) -> Option<Self> {
        let b = Bearing::from_direction(&(target - position))?;
        let angles = GimbalAngles { yaw: b.yaw, pitch: b.pitch, roll: 0.0 };
        Some(CameraPose::from_gimbal(position, GimbalChain::YawPitchRoll, angles, Mount::Earth))
    }

    /// Rotation "local <- camera (OpenCV axes)".
    pub fn local_from_camera(&self) -> Rot3 {
        self.attitude * gimbal_from_camera()
    }

    /// Unit viewing direction of a pixel in the local frame.
    pub fn direction(&self, k: &Intrinsics, px: Pixel) -> Vec3 {
        (self.local_from_camera() * k.ray(px)).normalize()
    }

    /// The bearing measurement of a pixel (seed eq. 5.12-5.18, derived as in the module
    /// doc).
    pub fn pixel_bearing(&self, k: &Intrinsics, px: Pixel) -> Bearing {
        // The ray has z = 1 in the camera frame, so it is never the zero vector.
        Bearing::from_direction(&(self.local_from_camera() * k.ray(px))).expect("a pixel ray is never zero")
    }

    /// Point in the camera frame.
    pub fn to_camera(&self, point: &Vec3) -> Vec3 {
        self.local_from_camera().inverse() * (point - self.position)
    }

    /// Pixel where a local point appears; `None` if it is behind the camera. The pixel
    /// may lie off the image: check with [`Intrinsics::contains`].
    pub fn project(&self, k: &Intrinsics, point: &Vec3) -> Option<Pixel> {
        k.project_camera(&self.to_camera(point))
    }

    /// The seed's previous method: where the pixel's ray meets the ground plane
    /// `down = ground_down` (seed eq. 2.7-2.10).
    pub fn ground_intersection(&self, k: &Intrinsics, px: Pixel, ground_down: f64) -> Option<Vec3> {
        ground_plane_point(&self.position, &(self.local_from_camera() * k.ray(px)), ground_down)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{bearing_between, body_rotation};
    use proptest::prelude::*;
    use std::f64::consts::PI;

    fn k() -> Intrinsics {
        Intrinsics::from_hfov(1920, 1080, 90f64.to_radians())
    }

    #[test]
    fn nadir_camera_sees_north_up_in_the_image() {
        // Pitch -90: looking straight down with the top of the image towards north.
        let pose = CameraPose::from_gimbal(
            Vec3::new(0.0, 0.0, -30.0),
            GimbalChain::YawPitchRoll,
            GimbalAngles::from_degrees(0.0, -90.0, 0.0),
            Mount::Earth,
        );
        let centre = pose.project(&k(), &Vec3::new(0.0, 0.0, 0.0)).unwrap();
        assert!((centre.u - k().cx).abs() < 1e-9 && (centre.v - k().cy).abs() < 1e-9);
        let north = pose.project(&k(), &Vec3::new(5.0, 0.0, 0.0)).unwrap();
        assert!(north.v < k().cy - 100.0 && (north.u - k().cx).abs() < 1e-6);
        let east = pose.project(&k(), &Vec3::new(0.0, 5.0, 0.0)).unwrap();
        assert!(east.u > k().cx + 100.0 && (east.v - k().cy).abs() < 1e-6);
    }

    #[test]
    fn ninety_degree_fov_edge() {
        // A point 45 deg right of the optical axis lands on the image's right edge.
        let pose = CameraPose::looking_at(Vec3::zeros(), &Vec3::new(10.0, 0.0, 0.0)).unwrap();
        let px = pose.project(&k(), &Vec3::new(10.0, 10.0, 0.0)).unwrap();
        assert!((px.u - (k().cx + k().fx)).abs() < 1e-9);
        assert!((px.u - 1919.5).abs() < 1e-9, "{px:?}");
    }

    #[test]
    fn behind_camera_is_not_projected() {
        let pose = CameraPose::looking_at(Vec3::zeros(), &Vec3::new(10.0, 0.0, 0.0)).unwrap();
        assert!(pose.project(&k(), &Vec3::new(-10.0, 0.0, 0.0)).is_none());
    }

    #[test]
    fn downscaled_intrinsics_match_area_resize() {
        let full = k();
        let half = full.downscaled(2);
        assert_eq!((half.width, half.height), (960, 540));
        // The full image's centre is the half image's centre.
        assert!((half.cx - (960.0 - 1.0) / 2.0).abs() < 1e-12);
        // Source pixel 3 (of block [2, 4)) sits at destination 1.25; block centre 2.5 -> 1.0.
        let ray_full = full.ray(Pixel::new(2.5, 2.5));
        let ray_half = half.ray(Pixel::new(1.0, 1.0));
        assert!((ray_full - ray_half).norm() < 1e-12);
    }

    #[test]
    fn validate_names_the_field() {
        let mut bad = k();
        bad.fx = 0.0;
        assert!(bad.validate().unwrap_err().contains("fx"));
        assert!(k().validate().is_ok());
        let off = Intrinsics { cx: 99999.0, ..k() };
        assert!(off.validate().unwrap_err().contains("cx = 99999 must be on the 1920x1080 image"));
        let off = Intrinsics { cy: -5.0, ..k() };
        assert!(off.validate().unwrap_err().contains("cy = -5"));
    }

    fn pose_strategy() -> impl Strategy<Value = (CameraPose, GimbalChain)> {
        (
            -200.0f64..200.0,
            -200.0f64..200.0,
            -120.0f64..-2.0,
            -PI..PI,
            -1.5f64..0.3,
            -0.3f64..0.3,
            0usize..2,
            (-0.2f64..0.2, -0.2f64..0.2, -PI..PI, 0usize..3),
        )
            .prop_map(|(n, e, d, yaw, pitch, roll, c, (vr, vp, vy, m))| {
                let chain = GimbalChain::ALL[c];
                let mount = match m {
                    0 => Mount::Earth,
                    1 => Mount::VehicleHeading { vehicle_yaw: vy },
                    _ => Mount::Body { attitude: body_rotation(vr, vp, vy) },
                };
                let angles = GimbalAngles { yaw, pitch, roll };
                (CameraPose::from_gimbal(Vec3::new(n, e, d), chain, angles, mount), chain)
            })
    }

    proptest! {
        /// point -> pixel -> bearing equals point -> bearing (seed eq. 5.12-5.18 vs 5.5).
        #[test]
        fn pixel_bearing_equals_point_bearing(
            (pose, _chain) in pose_strategy(),
            u in 0.0f64..1919.0,
            v in 0.0f64..1079.0,
            range in 1.0f64..500.0,
        ) {
            let k = k();
            // A point on the ray through (u, v), so it is in view by construction.
            let point = pose.position + pose.direction(&k, Pixel::new(u, v)) * range;
            let px = pose.project(&k, &point).unwrap();
            prop_assert!((px.u - u).abs() < 1e-6 && (px.v - v).abs() < 1e-6);
            let via_pixel = pose.pixel_bearing(&k, px);
            let direct = bearing_between(&pose.position, &point).unwrap();
            let r = via_pixel.residual(&direct);
            prop_assert!(r[0].abs() < 1e-9 && r[1].abs() < 1e-9, "{via_pixel:?} vs {direct:?}");
        }

        /// Ground-plane intersection of the pixel of a point on the plane returns the point.
        #[test]
        fn ground_intersection_recovers_point_on_plane(
            (pose, _chain) in pose_strategy(),
            u in 0.0f64..1919.0,
            v in 0.0f64..1079.0,
            ground_down in -20.0f64..20.0,
        ) {
            let k = k();
            let dir = pose.direction(&k, Pixel::new(u, v));
            // Only rays that go down towards a plane below the camera.
            prop_assume!(dir.z > 0.05 && ground_down > pose.position.z + 1.0);
            let on_plane = ground_plane_point(&pose.position, &dir, ground_down).unwrap();
            let px = pose.project(&k, &on_plane).unwrap();
            let back = pose.ground_intersection(&k, px, ground_down).unwrap();
            let range = (on_plane - pose.position).norm();
            prop_assert!((back - on_plane).norm() < 1e-9 * range.max(1.0), "{back:?} vs {on_plane:?}");
        }

        /// Pointing the gimbal along a bearing centres the target in the image.
        #[test]
        fn bearing_angles_point_the_optical_axis(
            n in -100.0f64..100.0, e in -100.0f64..100.0, d in -50.0f64..50.0, which in 0usize..2,
        ) {
            let target = Vec3::new(n, e, d);
            let position = Vec3::new(0.0, 0.0, -60.0);
            prop_assume!((target - position).norm() > 1.0);
            let b = bearing_between(&position, &target).unwrap();
            let pose = CameraPose::from_gimbal(
                position,
                GimbalChain::ALL[which],
                GimbalAngles { yaw: b.yaw, pitch: b.pitch, roll: 0.0 },
                Mount::Earth,
            );
            let px = pose.project(&k(), &target).unwrap();
            prop_assert!((px.u - k().cx).abs() < 1e-6 && (px.v - k().cy).abs() < 1e-6);
        }
    }
}
