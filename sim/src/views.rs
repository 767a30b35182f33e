//! Synthetic views for the indoor pipeline (indoor seed sec. 3.4.2): random camera poses
//! over the floor (roll, pitch, yaw, dx, dy, dz) with photometric changes (brightness,
//! contrast, box blur), each labelled with its x, y. The same photometric changes applied
//! to a whole flight give the "reality gap" between training views and test flights.

use std::f64::consts::PI;

use mavloc_data::dataset::Appearance;
use mavloc_geometry::{GimbalAngles, Vec3};
use rand::{Rng, SeedableRng};

use crate::scenario::ViewSpec;
use crate::state::State;

/// Applies a photometric change to an RGB frame in place: blur, then contrast about
/// mid-grey, then brightness.
pub fn apply(a: &Appearance, width: usize, height: usize, rgb: &mut [u8]) {
    if a.blur_px > 1 {
        box_blur(width, height, rgb, a.blur_px as usize);
    }
    if a.contrast != 1.0 || a.brightness != 0.0 {
        for v in rgb.iter_mut() {
            let x = (*v as f64 - 128.0) * a.contrast + 128.0 + a.brightness;
            *v = x.round().clamp(0.0, 255.0) as u8;
        }
    }
}

/// Separable box blur with edge clamping.
fn box_blur(w: usize, h: usize, rgb: &mut [u8], k: usize) {
    let r = (k / 2) as i64;
    let mut tmp = vec![0u8; rgb.len()];
    let pass = |src: &[u8], dst: &mut [u8], horizontal: bool| {
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let mut acc = 0u32;
                    for d in -r..=r {
                        let (sx, sy) = if horizontal {
                            ((x as i64 + d).clamp(0, w as i64 - 1) as usize, y)
                        } else {
                            (x, (y as i64 + d).clamp(0, h as i64 - 1) as usize)
                        };
                        acc += src[3 * (sy * w + sx) + c] as u32;
                    }
                    dst[3 * (y * w + x) + c] = ((acc as f64) / (2 * r + 1) as f64).round() as u8;
                }
            }
        }
    };
    pass(rgb, &mut tmp, true);
    pass(&tmp, rgb, false);
}

/// `count` random labelled views: vehicle states (camera fixed to the body, looking down)
/// and their photometric changes, deterministic from `seed`.
pub fn random_views(spec: &ViewSpec, count: usize, seed: u64) -> Vec<(State, Appearance)> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let tilt = spec.max_tilt_deg.to_radians();
    (0..count)
        .map(|i| {
            let position = Vec3::new(
                rng.random_range(-spec.half_extent_m..=spec.half_extent_m),
                rng.random_range(-spec.half_extent_m..=spec.half_extent_m),
                -rng.random_range(spec.height_m[0]..=spec.height_m[1]),
            );
            let attitude =
                [rng.random_range(-tilt..=tilt), rng.random_range(-tilt..=tilt), rng.random_range(-PI..PI)];
            let blur_steps = spec.max_blur_px.max(1).div_ceil(2);
            let appearance = Appearance {
                brightness: rng.random_range(spec.brightness[0]..=spec.brightness[1]),
                contrast: rng.random_range(spec.contrast[0]..=spec.contrast[1]),
                blur_px: 2 * rng.random_range(0..blur_steps) + 1,
            };
            let state = State {
                t: i as f64,
                position,
                velocity: Vec3::zeros(),
                attitude,
                gimbal: GimbalAngles { yaw: 0.0, pitch: -PI / 2.0, roll: 0.0 },
            };
            (state, appearance)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn appearance_changes_pixels_as_specified() {
        let mut px = vec![100u8, 150, 200];
        apply(&Appearance { brightness: 10.0, contrast: 2.0, blur_px: 1 }, 1, 1, &mut px);
        assert_eq!(px, vec![82, 182, 255]);
    }

    #[test]
    fn box_blur_averages_and_keeps_constant_images() {
        let mut flat = vec![77u8; 5 * 4 * 3];
        box_blur(5, 4, &mut flat, 3);
        assert!(flat.iter().all(|&v| v == 77));
        let mut spike = vec![0u8; 3 * 3 * 3];
        spike[3 * 4] = 90; // centre pixel, red
        box_blur(3, 3, &mut spike, 3);
        assert_eq!(spike[3 * 4], 10);
        assert_eq!(spike[0], 10);
    }

    #[test]
    fn views_stay_in_their_ranges_and_repeat_for_a_seed() {
        let spec = ViewSpec::default();
        let views = random_views(&spec, 200, 9);
        for (s, a) in &views {
            assert!(s.position.x.abs() <= spec.half_extent_m && s.position.y.abs() <= spec.half_extent_m);
            assert!(-s.position.z >= spec.height_m[0] && -s.position.z <= spec.height_m[1]);
            assert!(s.attitude[0].abs() <= spec.max_tilt_deg.to_radians() + 1e-12);
            assert!(a.blur_px % 2 == 1 && a.blur_px <= spec.max_blur_px);
        }
        assert_eq!(views[17].0, random_views(&spec, 200, 9)[17].0);
    }
}
