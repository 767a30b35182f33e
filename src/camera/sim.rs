//! `sim`: the SITL camera adapter ("PX4 SITL with a mock camera"). Each frame is rendered
//! by the `sim` crate's renderer, in the configured scenario's world, from the newest pose
//! the daemon has received over MAVLink (vehicle position and attitude, gimbal attitude),
//! and is stamped with that pose's time: the picture shows what the telemetry says, when
//! it says it.
//!
//! Noise, when `camera.sim_noise` is on, is applied here, between the world and mavloc: the
//! frame is rendered from the received pose minus the scenario's position noise, gimbal
//! noise and static gimbal offsets, which for the pipeline is the same as receiving noisy
//! telemetry of a true pose (the scenario files define the noise as "reported = true +
//! noise"). This keeps the noise model the same whatever flies: the built-in vehicle or
//! PX4 SITL, whose estimator noise then comes on top. The target mask is the renderer's,
//! as AirSim's segmentation image was the seed's (area sec. 4.2.3).

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use super::{Captured, FrameSource, SourceContext, SourceError};
use crate::geometry::{CameraPose, GimbalAngles, Intrinsics, Vec3};
use crate::settings::Settings;
use mavloc_sim::scenario::NoiseSpec;
use mavloc_sim::{Renderer, Scenario, World};

/// The configured size with the scenario's field of view (no focal length configured).
pub fn intrinsics(s: &Settings) -> Result<Intrinsics, String> {
    let c = &s.camera;
    let scenario = Scenario::load(&c.scenario)?;
    Ok(Intrinsics::from_hfov(c.width, c.height, scenario.camera.hfov_deg.to_radians()))
}

/// Poses older than this are not rendered: the vehicle is not reporting.
const MAX_POSE_AGE_S: f64 = 0.5;

pub struct SimCamera {
    renderer: Renderer<'static>,
    scenario: Scenario,
    k: Intrinsics,
    noise: Option<NoiseSpec>,
    rng: rand::rngs::StdRng,
    ctx: SourceContext,
    period: f64,
    next_due: f64,
    index: u64,
    last_pose_t: f64,
}

impl SimCamera {
    pub fn open(s: &Settings, ctx: SourceContext) -> Result<SimCamera, SourceError> {
        let scenario = Scenario::load(&s.camera.scenario)
            .map_err(|e| SourceError::Fatal(format!("camera.scenario: {e}")))?;
        let world = World::build(&scenario).map_err(SourceError::Fatal)?;
        // The world lives as long as the daemon: the sim camera is opened once (it cannot
        // fail after opening), and the renderer borrows the world.
        let world: &'static World = Box::leak(Box::new(world));
        let k = super::intrinsics(s).map_err(SourceError::Fatal)?;
        Ok(SimCamera {
            renderer: Renderer::new(world),
            // The truth is already the true pose: no noise to take off it.
            noise: (s.camera.sim_noise && s.camera.sim_pose == crate::settings::SimPose::Telemetry)
                .then(|| scenario.noise.clone()),
            rng: rand::rngs::StdRng::seed_from_u64(noise_seed(scenario.seed)),
            scenario,
            k,
            period: 1.0 / s.camera.fps,
            next_due: ctx.now(),
            ctx,
            index: 0,
            last_pose_t: f64::NEG_INFINITY,
        })
    }

    /// The pose the picture is taken from: the received one minus the scenario's noise.
    fn perturb(&mut self, pose: &CameraPose) -> CameraPose {
        match &self.noise {
            Some(n) => perturb(n, self.scenario.camera.chain, &mut self.rng, pose),
            None => *pose,
        }
    }
}

/// `pose` minus one draw of the scenario's noise (position, gimbal yaw and pitch) and
/// its static gimbal offsets: what a camera sees when the telemetry says `pose`.
pub fn perturb(
    n: &NoiseSpec,
    chain: crate::geometry::GimbalChain,
    rng: &mut impl rand::Rng,
    pose: &CameraPose,
) -> CameraPose {
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let mut draw = |sd: f64| if sd > 0.0 { sd * unit.sample(rng) } else { 0.0 };
    let dp = Vec3::new(draw(n.position_sd_m[0]), draw(n.position_sd_m[1]), draw(n.position_sd_m[2]));
    let dyaw = (n.gimbal_offset_deg[0] + draw(n.gimbal_yaw_sd_deg)).to_radians();
    let dpitch = (n.gimbal_offset_deg[1] + draw(n.gimbal_pitch_sd_deg)).to_radians();
    let droll = n.gimbal_offset_deg[2].to_radians();
    let a = chain.angles(&pose.attitude);
    let attitude =
        chain.rotation(GimbalAngles { yaw: a.yaw - dyaw, pitch: a.pitch - dpitch, roll: a.roll - droll });
    CameraPose { position: pose.position - dp, attitude }
}

/// The WGS84 origin of the configured scenario's world.
pub fn origin(s: &Settings) -> Option<crate::geometry::Geodetic> {
    Scenario::load(&s.camera.scenario).ok().map(|sc| sc.origin)
}

/// The seed of the sim camera's noise for a scenario (the live test replays it).
pub fn noise_seed(scenario_seed: u64) -> u64 {
    scenario_seed ^ 0x00ca_3e7a
}

impl FrameSource for SimCamera {
    fn next(&mut self) -> Result<Option<Captured>, SourceError> {
        loop {
            if !self.ctx.sleep_until(self.next_due) {
                return Ok(None);
            }
            self.next_due = (self.next_due + self.period).max(self.ctx.now());
            let latest = *self.ctx.latest_pose.lock().expect("pose");
            let Some((t, pose)) = latest else { continue };
            // No telemetry, no picture; and never the same pose twice.
            if self.ctx.now() - t > MAX_POSE_AGE_S || t <= self.last_pose_t {
                continue;
            }
            self.last_pose_t = t;
            if let Some(n) = &self.noise {
                if n.drop_rate > 0.0 && self.rng.random::<f64>() < n.drop_rate {
                    continue;
                }
            }
            let seen_from = self.perturb(&pose);
            let frame = self.renderer.render(&seen_from, &self.k);
            let image = crate::imaging::bgr_from_rgb(&frame.rgb, frame.height)?;
            let mask = opencv::core::Mat::new_rows_cols_with_data(
                frame.height as i32,
                frame.width as i32,
                &frame.mask,
            )?
            .clone_pointee();
            let index = self.index;
            self.index += 1;
            return Ok(Some(Captured {
                index,
                capture_s: t,
                image,
                mask: Some(mask),
                pose: None,
                truth: Some(seen_from.position.into()),
            }));
        }
    }

    fn describe(&self) -> String {
        format!(
            "simulated camera in {} at {}x{}, {:.1} Hz{}",
            self.scenario.name,
            self.k.width,
            self.k.height,
            1.0 / self.period,
            if self.noise.is_some() { ", with the scenario's noise" } else { "" }
        )
    }
}
