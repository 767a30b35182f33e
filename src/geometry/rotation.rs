//! Rotations of the gimbal kinematic chains (area seed eq. 2.2-2.4 and 5.17).
//!
//! The seed composes the gimbal rotation in camera axes after a fixed local-to-"gimbal
//! origin" turn (eq. 2.3); conjugating by that turn gives the same rotation as the plain
//! intrinsic Euler products used here, which are easier to check: `Rz` turns about down,
//! `Ry` about right, `Rx` about forward.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

use crate::Rot3;

/// Gimbal kinematic chain: the order of the motors from the vehicle to the camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum GimbalChain {
    /// `Rz(yaw) Ry(pitch) Rx(roll)`: AirSim, most 3-axis gimbals, aerospace Euler order.
    #[default]
    YawPitchRoll,
    /// `Rz(yaw) Rx(roll) Ry(pitch)`: DJI Zenmuse H20T (seed eq. 2.4).
    YawRollPitch,
}

impl GimbalChain {
    /// All chains, for tests and help texts.
    pub const ALL: [GimbalChain; 2] = [GimbalChain::YawPitchRoll, GimbalChain::YawRollPitch];

    /// The name used in configuration files.
    pub fn name(self) -> &'static str {
        match self {
            GimbalChain::YawPitchRoll => "yaw-pitch-roll",
            GimbalChain::YawRollPitch => "yaw-roll-pitch",
        }
    }

    /// Rotation "reference <- gimbal" for the given joint angles, where the reference is
    /// the frame the yaw is measured in (local NED for an earth-frame gimbal).
    pub fn rotation(self, a: GimbalAngles) -> Rot3 {
        let rz = Rotation3::from_axis_angle(&Vector3::z_axis(), a.yaw);
        let ry = Rotation3::from_axis_angle(&Vector3::y_axis(), a.pitch);
        let rx = Rotation3::from_axis_angle(&Vector3::x_axis(), a.roll);
        match self {
            GimbalChain::YawPitchRoll => rz * ry * rx,
            GimbalChain::YawRollPitch => rz * rx * ry,
        }
    }

    /// Joint angles that produce `r` (inverse of [`GimbalChain::rotation`]). At the chain's
    /// singularity (middle angle +-90 deg) the outer angles are not unique; roll is then
    /// set to 0 and the remaining rotation goes into yaw.
    pub fn angles(self, r: &Rot3) -> GimbalAngles {
        let m = r.matrix();
        match self {
            GimbalChain::YawPitchRoll => {
                // Third row of Rz Ry Rx is (-s_p, c_p s_r, c_p c_r).
                let pitch = (-m[(2, 0)]).clamp(-1.0, 1.0).asin();
                if m[(2, 1)].hypot(m[(2, 2)]) < 1e-9 {
                    // Gimbal lock: R = Rz(yaw -+ roll) Ry(+-90deg); choose roll = 0.
                    let yaw = (-m[(0, 1)]).atan2(m[(1, 1)]);
                    GimbalAngles { yaw, pitch, roll: 0.0 }
                } else {
                    GimbalAngles { yaw: m[(1, 0)].atan2(m[(0, 0)]), pitch, roll: m[(2, 1)].atan2(m[(2, 2)]) }
                }
            }
            GimbalChain::YawRollPitch => {
                // Rx(r) Ry(p) has third row (-c_r s_p, s_r, c_r c_p); Rz leaves it alone.
                // Its second column is (0, c_r, s_r), which Rz turns to (-s_y c_r, c_y c_r, s_r).
                let roll = m[(2, 1)].clamp(-1.0, 1.0).asin();
                if m[(2, 0)].hypot(m[(2, 2)]) < 1e-9 {
                    // Gimbal lock (roll +-90 deg): choose pitch = 0.
                    let yaw = m[(1, 0)].atan2(m[(0, 0)]);
                    GimbalAngles { yaw, pitch: 0.0, roll }
                } else {
                    GimbalAngles {
                        yaw: (-m[(0, 1)]).atan2(m[(1, 1)]),
                        pitch: (-m[(2, 0)]).atan2(m[(2, 2)]),
                        roll,
                    }
                }
            }
        }
    }
}

impl std::fmt::Display for GimbalChain {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Gimbal joint angles, radians (conventions in the crate doc).
#[derive(Clone, Copy, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct GimbalAngles {
    pub yaw: f64,
    pub pitch: f64,
    pub roll: f64,
}

impl GimbalAngles {
    /// From degrees, as gimbals and ground stations report them.
    pub fn from_degrees(yaw: f64, pitch: f64, roll: f64) -> Self {
        GimbalAngles { yaw: yaw.to_radians(), pitch: pitch.to_radians(), roll: roll.to_radians() }
    }
}

/// Rotation "gimbal (FRD) <- camera (OpenCV)": camera x = right, y = down, z = forward.
pub fn gimbal_from_camera() -> Rot3 {
    // Columns are the camera axes expressed in the gimbal frame.
    Rotation3::from_matrix_unchecked(Matrix3::new(
        0.0, 0.0, 1.0, //
        1.0, 0.0, 0.0, //
        0.0, 1.0, 0.0,
    ))
}

/// Vehicle attitude "local <- body" from PX4's Euler angles (ATTITUDE message: roll,
/// pitch, yaw, ZYX order), radians.
pub fn body_rotation(roll: f64, pitch: f64, yaw: f64) -> Rot3 {
    GimbalChain::YawPitchRoll.rotation(GimbalAngles { yaw, pitch, roll })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wrap_angle;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    fn close(a: &Rot3, b: &Rot3) -> bool {
        (a.matrix() - b.matrix()).abs().max() < 1e-9
    }

    #[test]
    fn zero_angles_look_north_level() {
        for chain in GimbalChain::ALL {
            let r = chain.rotation(GimbalAngles::default());
            assert!(close(&r, &Rot3::identity()));
        }
    }

    #[test]
    fn positive_pitch_raises_the_optical_axis() {
        let r = GimbalChain::YawPitchRoll.rotation(GimbalAngles::from_degrees(0.0, 30.0, 0.0));
        let fwd = r * Vector3::x();
        // Nose up means the forward axis gets a negative "down" component.
        assert!(fwd.z < -0.49 && fwd.z > -0.51, "{fwd:?}");
    }

    #[test]
    fn yaw_90_points_east() {
        let r = GimbalChain::YawRollPitch.rotation(GimbalAngles::from_degrees(90.0, 0.0, 0.0));
        let fwd = r * Vector3::x();
        assert!((fwd - Vector3::y()).norm() < 1e-12);
    }

    #[test]
    fn chains_differ_when_roll_and_pitch_are_both_nonzero() {
        let a = GimbalAngles::from_degrees(10.0, -40.0, 15.0);
        let r1 = GimbalChain::YawPitchRoll.rotation(a);
        let r2 = GimbalChain::YawRollPitch.rotation(a);
        assert!(!close(&r1, &r2));
    }

    #[test]
    fn camera_permutation_maps_optical_axis_to_forward() {
        let m = gimbal_from_camera();
        assert!((m * Vector3::z() - Vector3::x()).norm() < 1e-15);
        assert!((m * Vector3::x() - Vector3::y()).norm() < 1e-15);
        assert!((m * Vector3::y() - Vector3::z()).norm() < 1e-15);
        assert!((m.matrix().determinant() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn gimbal_lock_still_round_trips_the_rotation() {
        for chain in GimbalChain::ALL {
            let a = match chain {
                GimbalChain::YawPitchRoll => GimbalAngles { yaw: 0.4, pitch: -FRAC_PI_2, roll: 0.3 },
                GimbalChain::YawRollPitch => GimbalAngles { yaw: 0.4, pitch: 0.3, roll: FRAC_PI_2 },
            };
            let r = chain.rotation(a);
            let back = chain.rotation(chain.angles(&r));
            assert!(close(&r, &back), "{chain}");
        }
    }

    proptest! {
        #[test]
        fn angles_invert_rotation(
            yaw in -PI..PI,
            pitch in -1.55f64..1.55,
            roll in -1.55f64..1.55,
            which in 0usize..2,
        ) {
            let chain = GimbalChain::ALL[which];
            let a = GimbalAngles { yaw, pitch, roll };
            let back = chain.angles(&chain.rotation(a));
            prop_assert!(wrap_angle(back.yaw - yaw).abs() < 1e-9, "{back:?} vs {a:?}");
            prop_assert!((back.pitch - pitch).abs() < 1e-9, "{back:?} vs {a:?}");
            prop_assert!((back.roll - roll).abs() < 1e-9, "{back:?} vs {a:?}");
        }

        #[test]
        fn rotations_are_proper(yaw in -PI..PI, pitch in -PI..PI, roll in -PI..PI, which in 0usize..2) {
            let r = GimbalChain::ALL[which].rotation(GimbalAngles { yaw, pitch, roll });
            let m = r.matrix();
            prop_assert!((m.transpose() * m - Matrix3::identity()).abs().max() < 1e-12);
            prop_assert!((m.determinant() - 1.0).abs() < 1e-12);
        }
    }
}
