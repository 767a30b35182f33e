//! Simulated landing approaches (indoor seed sec. 4.7): the closed loop of localiser,
//! guidance and landing trigger over the simulated floor, as the daemon will run it live.
//!
//! Each trial picks a random landing zone and a start at least 2 m from it. The vehicle
//! hovers until the particles agree (spread below the trigger's gate), then flies towards
//! the zone *as estimated* (so a wrong estimate takes it to the wrong place, as it would
//! with PX4 flying on the vision position), with a first-order velocity response, small
//! attitude wobble and noisy velocity telemetry. Frames are rendered from the true pose
//! with the flight's appearance change. A trial succeeds when the trigger fires while the
//! vehicle is truly inside the zone; it fails when it fires outside or not within the
//! time limit.

use nalgebra::Vector2;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::imaging::bgr_from_rgb;
use crate::indoor::derotate::Preprocessor;
use crate::indoor::landing::{LandingTrigger, LandingZone};
use crate::indoor::localizer::{Localizer, LocalizerParams};
use crate::indoor::model::Model;
use crate::settings::Indoor;
use mavloc_data::dataset::Appearance;
use mavloc_data::results::LandingRow;
use mavloc_geometry::{GimbalAngles, Vec3};
use mavloc_sim::state::State;
use mavloc_sim::{views, Mission, Renderer, Scenario, World};

/// Approach parameters.
#[derive(Clone, Debug)]
pub struct ApproachOptions {
    pub trials: usize,
    pub seed: u64,
    /// Give up after this long, seconds.
    pub max_s: f64,
    /// Rendered frame size (the model's working width or more).
    pub size: (u32, u32),
    pub appearance: Appearance,
    /// Zone centres are drawn within this half side, metres.
    pub zone_half_extent_m: f64,
}

impl Default for ApproachOptions {
    fn default() -> Self {
        ApproachOptions {
            trials: 20,
            seed: 1,
            max_s: 60.0,
            size: (320, 240),
            appearance: Appearance { brightness: 15.0, contrast: 0.9, blur_px: 3 },
            zone_half_extent_m: 2.5,
        }
    }
}

const FRAME_RATE_HZ: f64 = 15.0;
const HEIGHT_M: f64 = 1.0;
const MAX_SPEED_M_S: f64 = 0.5;
/// Proportional gain of the guidance, 1/s.
const GAIN: f64 = 0.8;
/// Time constant of the velocity response, seconds.
const RESPONSE_S: f64 = 0.4;
const VELOCITY_NOISE_M_S: f64 = 0.05;
const WOBBLE_RAD: f64 = 0.03;

/// Runs the trials; `progress(done, total)` after each.
pub fn run(
    model: &Model,
    s: &Indoor,
    opts: &ApproachOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<LandingRow>, String> {
    let scenario = Scenario::load("indoor-floor")?;
    let world = World::build(&scenario)?;
    let mission = Mission::plan(&world)?;
    let renderer = Renderer::new(&world);
    let mut camera = scenario.clone();
    camera.camera.width = opts.size.0;
    camera.camera.height = opts.size.1;
    let k = camera.intrinsics();
    let mut pre = Preprocessor::new(
        k,
        model.frame.work_width,
        model.frame.derotate,
        (model.dictionary.w, model.dictionary.h),
    );
    pre.normalise = model.frame.normalise;
    pre.height_ref = model.frame.height_ref_m;
    let mut rng = rand::rngs::StdRng::seed_from_u64(opts.seed);
    let noise = Normal::new(0.0, 1.0).map_err(|e| e.to_string())?;
    let dt = 1.0 / FRAME_RATE_HZ;
    let mut rows = Vec::with_capacity(opts.trials);
    for trial in 0..opts.trials {
        let h = opts.zone_half_extent_m;
        let zone_c = Vector2::new(rng.random_range(-h..h), rng.random_range(-h..h));
        let mut start;
        loop {
            start = Vector2::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
            if (start - zone_c).norm() >= 2.0 {
                break;
            }
        }
        let yaw = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let zone = LandingZone {
            centre: zone_c,
            radius_m: s.landing_radius_m,
            sigma_gate_m: s.landing_sigma_gate_m,
            frames: s.landing_frames,
        };
        let mut trigger = LandingTrigger::new(zone);
        let mut loc =
            Localizer::new(model, LocalizerParams::from_settings(s, opts.seed.wrapping_add(trial as u64)))?;
        let (mut pos, mut vel) = (start, Vector2::zeros());
        let mut row = LandingRow {
            trial,
            zone_x: zone_c.x,
            zone_y: zone_c.y,
            fired: false,
            t_fire: f64::NAN,
            true_x: f64::NAN,
            true_y: f64::NAN,
            est_x: f64::NAN,
            est_y: f64::NAN,
            inside: false,
        };
        let mut estimate: Option<(Vector2<f64>, (f64, f64))> = None;
        let steps = (opts.max_s * FRAME_RATE_HZ) as usize;
        for i in 0..steps {
            let t = i as f64 * dt;
            // Guidance on the estimate, once the particles agree.
            let command = match estimate {
                Some((e, spread)) if spread.0.max(spread.1) < s.landing_sigma_gate_m => {
                    let v = (zone_c - e) * GAIN;
                    if v.norm() > MAX_SPEED_M_S {
                        v * (MAX_SPEED_M_S / v.norm())
                    } else {
                        v
                    }
                }
                _ => Vector2::zeros(),
            };
            let accel = (command - vel) / RESPONSE_S;
            vel += accel * dt;
            pos += vel * dt;
            let (sy, cy) = yaw.sin_cos();
            let a_fwd = accel.x * cy + accel.y * sy;
            let a_right = -accel.x * sy + accel.y * cy;
            let state = State {
                t,
                position: Vec3::new(pos.x, pos.y, -HEIGHT_M),
                velocity: Vec3::new(vel.x, vel.y, 0.0),
                attitude: [
                    (a_right / 9.81).atan() + WOBBLE_RAD * (1.7 * t + trial as f64).sin(),
                    (-a_fwd / 9.81).atan() + WOBBLE_RAD * (1.3 * t).sin(),
                    yaw,
                ],
                gimbal: GimbalAngles { yaw: 0.0, pitch: -std::f64::consts::FRAC_PI_2, roll: 0.0 },
            };
            let pose = mission.camera_pose(&state);
            let mut frame = renderer.render(&pose, &k);
            views::apply(&opts.appearance, frame.width as usize, frame.height as usize, &mut frame.rgb);
            let bgr = bgr_from_rgb(&frame.rgb, frame.height).map_err(|e| e.to_string())?;
            let measured_v =
                vel + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng)) * VELOCITY_NOISE_M_S;
            let e = loc
                .step_frame(
                    t,
                    &pre,
                    &bgr,
                    Some(&pose.local_from_camera()),
                    Some(-pose.position.z),
                    Some(measured_v),
                )
                .map_err(|e| e.to_string())?;
            estimate = Some((e.position, e.spread));
            // As the daemon: a landing on a position fix only.
            if trigger.observe(&e).is_ok() {
                row.fired = true;
                row.t_fire = t;
                (row.true_x, row.true_y) = (pos.x, pos.y);
                (row.est_x, row.est_y) = (e.position.x, e.position.y);
                row.inside = (pos - zone_c).norm() <= zone.radius_m;
                break;
            }
        }
        if !row.fired {
            (row.true_x, row.true_y) = (pos.x, pos.y);
            if let Some((e, _)) = estimate {
                (row.est_x, row.est_y) = (e.x, e.y);
            }
        }
        rows.push(row);
        progress(trial + 1, opts.trials);
    }
    Ok(rows)
}
