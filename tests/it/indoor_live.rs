//! The live indoor pipeline's accuracy on the closed-loop test's flight, in simulated
//! time. `closed_loop.rs` flies the same mission over UDP against the real binary and
//! checks what needs the wire (estimate rate, landing in the zone); how accurate the
//! estimates are depends there on how busy the machine is (frames dropped under load).
//! Here every frame of the flight is rendered at its exact time, aligned from the
//! vehicle's 30 Hz telemetry by the daemon's own aligner, seen through the sim camera's
//! noise, and processed in order by the daemon's live pipeline: the same figure, the
//! same bound, every run.

use mavloc::align::{Aligner, VehicleSample};
use mavloc::daemon::live::IndoorLive;
use mavloc::daemon::worker::{LiveFrame, LivePipeline};
use mavloc::settings::Settings;
use mavloc_sim::{Mission, Renderer, Scenario, World};
use rand::SeedableRng;

#[test]
fn live_indoor_estimates_are_within_0_2_m_median_at_the_capture() {
    let dir = tempfile::tempdir().unwrap();
    let model = crate::fixtures::small_indoor_model();
    let mut s = Settings::default();
    s.indoor.model = model.display().to_string();
    s.camera.width = 320;
    s.camera.height = 240;
    s.camera.fps = 15.0;
    s.camera.scenario = "indoor-floor".into();

    let scenario = Scenario::load("indoor-floor").unwrap();
    let world = World::build(&scenario).unwrap();
    let mission = Mission::plan(&world).unwrap();
    let renderer = Renderer::new(&world);
    let k = mavloc::camera::intrinsics(&s).unwrap();
    let (ap, mount, offsets) = mavloc::daemon::core::telemetry::align_params(&s);
    let mut aligner = Aligner::new(ap, mount, offsets);
    let mut rng = rand::rngs::StdRng::seed_from_u64(mavloc::camera::sim::noise_seed(scenario.seed));
    let mut live = IndoorLive::new(&s, k, dir.path().join("indoor")).unwrap();

    // 35 s of flight, as the live test flies: telemetry at 30 Hz (the simulated vehicle's
    // LOCAL_POSITION_NED and ATTITUDE rate), frames at 15 Hz.
    let (duration, telemetry_hz) = (35.0, 30.0);
    let mut next_telemetry = 0.0;
    let mut errors = Vec::new();
    for i in 0..(duration * s.camera.fps) as u64 {
        let t = i as f64 / s.camera.fps;
        // Telemetry up to a little after the capture, as it stands when the frame is aligned.
        while next_telemetry <= t + 0.1 {
            let st = mission.state(next_telemetry);
            let [roll, pitch, yaw] = st.attitude;
            aligner.clock.observe_stamp(next_telemetry, next_telemetry);
            aligner.push_vehicle(
                next_telemetry,
                VehicleSample {
                    position: st.position,
                    velocity: st.velocity,
                    attitude: nalgebra::UnitQuaternion::from_euler_angles(roll, pitch, yaw),
                },
            );
            next_telemetry += 1.0 / telemetry_hz;
        }
        let pose = aligner.align(t, t + 0.1).expect("telemetry covers the capture");
        let seen_from = match s.camera.sim_noise {
            true => {
                mavloc::camera::sim::perturb(&scenario.noise, scenario.camera.chain, &mut rng, &pose.camera)
            }
            false => pose.camera,
        };
        let rendered = renderer.render(&seen_from, &k);
        let image = mavloc::indoor::derotate::bgr_from_rgb(&rendered.rgb, rendered.height).unwrap();
        let frame = LiveFrame {
            index: i,
            capture_s: t,
            pose,
            image,
            mask: None,
            origin: None,
            truth: Some(seen_from.position.into()),
        };
        let report = live.process(&frame);
        if let Some(p) = report.position {
            if i >= 30 {
                // The particle filter's first two seconds are left out, as in the live test.
                errors.push((p.north - seen_from.position.x).hypot(p.east - seen_from.position.y));
            }
        }
    }

    assert!(errors.len() > 450, "{} estimates", errors.len());
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let p90 = errors[errors.len() * 9 / 10];
    println!(
        "indoor live, simulated time: {} estimates, median error {median:.3} m, 90th percentile {p90:.3} m",
        errors.len()
    );
    assert!(median < 0.2, "median error {median} m");
}
