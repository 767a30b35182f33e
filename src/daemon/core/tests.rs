//! Whole scenarios on the simulated clock (see `sim.rs`): the autopilot appears,
//! reboots and vanishes; a parameter list under a flood; a landing; commands that each
//! get exactly one final ACK. Each runs minutes of daemon time in milliseconds.

use std::time::Duration;

use mavlink::dialects::common::*;
use proptest::prelude::*;

use super::sim::*;
use super::*;

fn secs(s: u64) -> Mono {
    Mono::from_millis(s * 1000)
}

fn heartbeats(sim: &Sim, from: Mono, to: Mono) -> usize {
    sim.sent_between(from, to).filter(|m| matches!(m, MavMessage::HEARTBEAT(_))).count()
}

fn count(sim: &Sim, from: Mono, to: Mono, cmd: MavCmd) -> usize {
    sim.sent_between(from, to).filter(|m| is_command(m, cmd)).count()
}

fn timesyncs(sim: &Sim, from: Mono, to: Mono) -> usize {
    sim.sent_between(from, to).filter(|m| matches!(m, MavMessage::TIMESYNC(t) if t.tc1 == 0)).count()
}

/// `MAV_CMD_USER_1` (pipeline control) from the ground station, addressed to mavloc.
fn pipeline_command(param1: f32, param2: f32) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command: MavCmd::MAV_CMD_USER_1,
        param1,
        param2,
        target_system: 1,
        target_component: 191,
        ..Default::default()
    })
}

/// The results of every COMMAND_ACK the ground station got, in order.
fn acks_to_gcs(sim: &Sim) -> Vec<MavResult> {
    sim.to_gcs
        .iter()
        .filter_map(|(_, m)| match m {
            MavMessage::COMMAND_ACK(a) => Some(a.result),
            _ => None,
        })
        .collect()
}

fn settings() -> Settings {
    let mut s = Settings::default();
    s.daemon.pipeline = PipelineKind::None;
    s
}

#[test]
fn autopilot_appears_reboots_and_vanishes() {
    let mut sim = Sim::new(settings());
    // t = 0..2 s: alone. STANDBY heartbeats at 1 Hz, nothing asked of anyone.
    sim.run_until(secs(2));
    assert_eq!(heartbeats(&sim, Mono::ZERO, secs(2)), 2);
    assert_eq!(count(&sim, Mono::ZERO, secs(2), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL), 0);
    assert!(sim.sent.iter().all(
        |(_, m)| !matches!(m, MavMessage::HEARTBEAT(h) if h.system_status != MavState::MAV_STATE_STANDBY)
    ));

    // t = 2 s: the autopilot appears; its streams are requested one at a time, all accepted.
    sim.ap = FakeAutopilot::new(secs(2));
    sim.run_until(secs(10));
    assert!(sim.core.autopilot_found());
    let states = sim.core.streams().states().to_vec();
    assert!(states.iter().all(|s| *s == streams::StreamState::Accepted), "{states:?}");
    assert_eq!(count(&sim, Mono::ZERO, secs(10), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL), STREAMS.len());
    assert!(sim.core.aligner().clock.offset().0.is_some(), "the clock is synchronised");

    // t = 60 s: reboot. Counted once, one warning, streams asked again, gimbal released.
    sim.run_until(secs(60));
    let texts_before = sim.statustexts().len();
    sim.ap.reboot(sim.now);
    sim.run_until(secs(70));
    assert_eq!(sim.core.counters().autopilot_reboots, 1);
    let new_texts = &sim.statustexts()[texts_before..];
    assert_eq!(new_texts.iter().filter(|t| t.contains("rebooted")).count(), 1, "{new_texts:?}");
    assert_eq!(count(&sim, secs(60), secs(70), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL), STREAMS.len());
    assert_eq!(sim.core.gimbal().control(), gimbal::Control::Released);

    // t = 120 s: the autopilot vanishes; lost after the timeout; then only heartbeats.
    sim.run_until(secs(120));
    sim.ap.alive = false;
    let timeout = sim.core.settings().mavlink.autopilot_timeout_s;
    sim.run_until(secs(180));
    assert!(!sim.core.autopilot_found());
    let lost_at = sim
        .sent
        .iter()
        .find(|(_, m)| matches!(m, MavMessage::STATUSTEXT(s) if String::from_utf8_lossy(&s.text[..]).contains("autopilot lost")))
        .map(|(t, _)| *t)
        .expect("autopilot lost is said");
    // Its last heartbeat left at 119 s, its last telemetry just before 120 s: any message
    // from it says it is there (a flood can drop three heartbeats in a row).
    let after = lost_at.secs() - 120.0;
    assert!((after - timeout).abs() < 0.1, "lost {after} s after the last message, timeout {timeout}");
    assert_eq!(
        count(&sim, lost_at + Duration::from_millis(1), secs(180), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL),
        0
    );
    assert_eq!(timesyncs(&sim, lost_at + Duration::from_millis(1), secs(180)), 0);
    let hb = heartbeats(&sim, secs(120), secs(180));
    assert!((59..=61).contains(&hb), "{hb} heartbeats in the last 60 s");
    assert!(sim.steps < 100_000, "{} steps", sim.steps);
}

#[test]
fn refused_streams_are_reported_once_in_one_line() {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.ap.streams = StreamAnswer::Ignore;
    sim.run_until(secs(60));
    // One STATUSTEXT, in one piece (the names go to the log, see streams.rs's test).
    let texts = sim.statustexts();
    let about: Vec<&String> = texts.iter().filter(|t| t.contains("streams")).collect();
    assert_eq!(about.len(), 1, "{texts:?}");
    assert!(
        about[0].contains(&format!("{} of {} streams not set up", STREAMS.len(), STREAMS.len())),
        "{about:?}"
    );
    let chunked = sim.sent.iter().any(|(_, m)| matches!(m, MavMessage::STATUSTEXT(s) if s.id != 0 && String::from_utf8_lossy(&s.text[..]).contains("streams")));
    assert!(!chunked, "not split over two STATUSTEXTs");
    assert_eq!(count(&sim, Mono::ZERO, secs(60), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL), 5 * STREAMS.len());

    // Refused outright: asked once each, reported once.
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.ap.streams = StreamAnswer::Refuse;
    sim.run_until(secs(60));
    assert_eq!(count(&sim, Mono::ZERO, secs(60), MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL), STREAMS.len());
    assert_eq!(sim.statustexts().concat().matches("streams not set up").count(), 1);
}

fn param_request_list() -> MavMessage {
    MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA { target_system: 1, target_component: 191 })
}

fn param_read(index: i16) -> MavMessage {
    MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
        param_index: index,
        target_system: 1,
        target_component: 191,
        param_id: "".into(),
    })
}

fn param_values(to_gcs: &[(Mono, MavMessage)]) -> Vec<(Mono, u16)> {
    to_gcs
        .iter()
        .filter_map(|(t, m)| match m {
            MavMessage::PARAM_VALUE(p) => Some((*t, p.param_index)),
            _ => None,
        })
        .collect()
}

#[test]
fn a_parameter_list_under_a_flood_is_paced_complete_and_leaves_the_heartbeat_alone() {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(5));
    let n = param_table::PARAMS.len();
    // Within one second: a LIST, 3 more LISTs, 500 READs and ATTITUDE at 1 kHz.
    let start = sim.now;
    let mut max_queue = 0;
    for ms in 0..1000u64 {
        if ms % 250 == 0 {
            sim.gcs_sends(param_request_list());
        }
        if ms % 2 == 0 {
            sim.gcs_sends(param_read((ms / 2 % n as u64) as i16));
        }
        sim.deliver(frame(
            1,
            1,
            MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: 5000 + ms as u32, ..Default::default() }),
        ));
        sim.run_until(start + Duration::from_millis(ms + 1));
        max_queue = max_queue.max(sim.core.params_queued());
    }
    sim.run_for(Duration::from_secs(5));
    let values = param_values(&sim.to_gcs);
    let mut seen: Vec<u16> = values.iter().map(|v| v.1).collect();
    seen.sort();
    seen.dedup();
    assert_eq!(seen.len(), n, "every index arrives");
    for (i, (t, _)) in values.iter().enumerate() {
        let within = values[i..].iter().take_while(|u| u.0 < *t + Duration::from_millis(50)).count();
        assert!(within <= 10, "{within} PARAM_VALUEs within 50 ms");
    }
    assert!(max_queue <= 2 * n, "owed values stay bounded: {max_queue}");
    // The heartbeat kept its 1 Hz through the flood.
    let beats: Vec<Mono> = sim
        .sent
        .iter()
        .filter(|(t, m)| *t >= start && matches!(m, MavMessage::HEARTBEAT(_)))
        .map(|(t, _)| *t)
        .collect();
    for w in beats.windows(2) {
        let gap = w[1].saturating_sub(w[0]).as_secs_f64();
        assert!((0.99..=1.01).contains(&gap), "heartbeat gap {gap}");
    }
}

#[test]
fn with_30_percent_loss_the_gcs_completes_the_list_by_read() {
    let mut sim = Sim::new(settings());
    // Deterministic 30 % loss: drop 3 of every 10 messages to the ground station.
    sim.gcs_loss = |n| n % 10 < 3;
    sim.gcs_sends(param_request_list());
    sim.run_for(Duration::from_secs(2));
    let n = param_table::PARAMS.len() as u16;
    for _round in 0..10 {
        let have: std::collections::BTreeSet<u16> =
            param_values(&sim.to_gcs).into_iter().map(|v| v.1).collect();
        let missing: Vec<u16> = (0..n).filter(|i| !have.contains(i)).collect();
        if missing.is_empty() {
            return;
        }
        for i in missing {
            sim.gcs_sends(param_read(i as i16));
        }
        sim.run_for(Duration::from_secs(1));
    }
    panic!("the list did not complete by READ");
}

fn flying_sim(landing_enabled: bool) -> Sim {
    let mut s = settings();
    s.indoor.landing_enabled = landing_enabled;
    let mut sim = Sim::new(s);
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.ap.armed = true;
    sim.ap.in_air = true;
    sim.run_until(secs(3));
    sim
}

fn landing_report() -> Input {
    Input::Pipeline {
        now: Mono::ZERO,
        event: PipelineEvent::Report {
            capture: 0.0,
            attitude: (0.0, 0.0, 0.0),
            report: Report { landing_requested: true, ..Report::default() },
        },
    }
}

#[test]
fn a_landing_is_sent_until_acknowledged_and_only_when_flying_with_landing_enabled() {
    let mut sim = flying_sim(true);
    sim.ap.land_answer = None; // silent for a while
    sim.input(landing_report());
    sim.run_for(Duration::from_millis(2500));
    assert_eq!(sim.ap.land_commands, 3, "once a second");
    sim.ap.land_answer = Some(MavResult::MAV_RESULT_ACCEPTED);
    sim.run_for(Duration::from_secs(10));
    assert_eq!(sim.ap.land_commands, 4, "none after the ACK");
    assert!(sim.statustexts().iter().any(|t| t.contains("accepted the landing")));

    let mut sim = flying_sim(false);
    sim.input(landing_report());
    sim.run_for(Duration::from_secs(5));
    assert_eq!(sim.ap.land_commands, 0, "landing disabled");

    let mut sim = flying_sim(true);
    sim.ap.in_air = false;
    sim.run_for(Duration::from_secs(2));
    sim.input(landing_report());
    sim.run_for(Duration::from_secs(5));
    assert_eq!(sim.ap.land_commands, 0, "on the ground");
    assert!(sim.core.on_ground());
}

#[test]
fn an_unanswered_landing_gives_up_after_five_tries_with_an_error() {
    let mut sim = flying_sim(true);
    sim.ap.land_answer = None;
    sim.input(landing_report());
    sim.run_for(Duration::from_secs(20));
    assert_eq!(sim.ap.land_commands, landing::TRIES);
    assert!(sim.statustexts().concat().contains("did not acknowledge MAV_CMD_NAV_LAND"));
}

/// The pipeline's aim, 30 times a second for `for_s` seconds.
fn aim_for(sim: &mut Sim, for_s: u64) {
    for _ in 0..for_s * 30 {
        sim.input(Input::Pipeline {
            now: sim.now,
            event: PipelineEvent::Report {
                capture: 0.0,
                attitude: (0.0, 0.0, 0.0),
                report: Report { aim: Some((0.3, -0.5)), ..Report::default() },
            },
        });
        sim.run_for(Duration::from_millis(33)); // a 30 Hz camera
    }
}

fn border_aiming() -> Sim {
    let mut s = settings();
    s.gimbal.aim = GimbalAim::Border;
    let mut sim = Sim::new(s);
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(2));
    sim
}

#[test]
fn border_aiming_takes_control_and_streams_at_most_5_hz() {
    let mut sim = border_aiming();
    aim_for(&mut sim, 1);
    let cmds = &sim.ap.gimbal_commands;
    assert_eq!(cmds[0].1.command, MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE);
    assert_eq!(cmds.iter().filter(|c| c.1.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE).count(), 1);
    let setpoints: Vec<_> =
        cmds.iter().filter(|c| c.1.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW).collect();
    let times: Vec<f64> = setpoints.iter().map(|s| s.0.secs()).collect();
    assert!((4..=6).contains(&setpoints.len()), "{} setpoints in 1 s: {times:?}", setpoints.len());
    for w in setpoints.windows(2) {
        assert!(w[1].0.saturating_sub(w[0].0) >= gimbal::MIN_INTERVAL);
    }
    assert!(setpoints.iter().all(|s| s.1.param5 == 92.0), "every axis earth-locked");
    assert_eq!(sim.core.gimbal().control(), gimbal::Control::InControl);
}

/// A ground station takes the gimbal while mavloc points it (audit, session 37: mavloc
/// took it back within 0.3 s, every time): mavloc sends the gimbal nothing while the
/// manager names another holder, says so once, and points it again once it is let go.
#[test]
fn border_aiming_leaves_a_gimbal_the_ground_station_took_until_it_is_let_go() {
    let mut sim = border_aiming();
    aim_for(&mut sim, 1);
    let taken = sim.now;
    let status = sim.ap.gimbal_taken_by((255, 190), taken);
    sim.deliver(frame(1, 1, status));
    aim_for(&mut sim, 20);
    let after: Vec<_> =
        sim.ap.gimbal_commands.iter().filter(|c| c.0 > taken + Duration::from_millis(300)).collect();
    assert!(after.is_empty(), "sent while the ground station held it: {:?}", after.len());
    assert_eq!(sim.ap.gimbal_primary, (255, 190));
    let said = sim.statustexts().concat();
    assert_eq!(said.matches("gimbal held by a ground station (255/190)").count(), 1, "{said}");
    let released = sim.now;
    let status = sim.ap.gimbal_taken_by((0, 0), released);
    sim.deliver(frame(1, 1, status));
    aim_for(&mut sim, 1);
    assert_eq!(sim.ap.gimbal_primary, (1, 191), "taken again once let go");
    assert!(sim
        .ap
        .gimbal_commands
        .iter()
        .any(|c| c.0 > released && c.1.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW));
}

/// PX4 runs no gimbal manager by default (MNT_MODE_IN = -1) and answers nothing: one
/// warning naming the parameter; no setpoints into the void; the autopilot's own
/// pointing is not reported as mavloc's error.
#[test]
fn border_aiming_without_a_gimbal_manager_says_so_and_sends_no_setpoints() {
    let mut sim = border_aiming();
    sim.ap.gimbal_manager = false;
    aim_for(&mut sim, 20);
    let cmds = &sim.ap.gimbal_commands;
    assert!(cmds.iter().all(|c| c.1.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE));
    assert!((2..=3).contains(&cmds.len()), "a CONFIGURE every 13 s: {}", cmds.len());
    let said = sim.statustexts().concat();
    assert_eq!(said.matches("MNT_MODE_IN=4").count(), 1, "{said}");
    assert_eq!(sim.core.gimbal_error_median_deg(), None);
}

/// The vehicle landing (PX4's RTL or land mode levels the camera for the touchdown):
/// mavloc lets go of the gimbal and sends it nothing until the landing is over.
#[test]
fn border_aiming_lets_go_of_the_gimbal_while_landing() {
    let mut sim = border_aiming();
    sim.ap.in_air = true;
    aim_for(&mut sim, 2);
    assert_eq!(sim.ap.gimbal_primary, (1, 191));
    sim.ap.landing = true;
    aim_for(&mut sim, 2); // the landed state comes once a second
    assert_eq!(sim.ap.gimbal_primary, (0, 0));
    // Levelled first (as PX4's navigator does for the touchdown), then let go.
    let last: Vec<(f32, f32)> =
        sim.ap.gimbal_commands.iter().rev().take(2).map(|c| (c.1.param1, c.1.param5)).collect();
    assert_eq!(last[0], (-3.0, 0.0), "let go last");
    assert!(last[1].0.is_nan() && last[1].1 == 2.0, "GIMBAL_MANAGER_FLAGS_NEUTRAL before it: {last:?}");
    let since = sim.now;
    aim_for(&mut sim, 10);
    assert!(sim.ap.gimbal_commands.iter().all(|c| c.0 < since), "nothing sent while landing");
}

/// The daemon stopping lets go of the gimbal it holds, so the ground station can point
/// it at once.
#[test]
fn border_aiming_lets_go_of_the_gimbal_at_shutdown() {
    let mut sim = border_aiming();
    aim_for(&mut sim, 1);
    assert_eq!(sim.ap.gimbal_primary, (1, 191));
    sim.core.shutting_down();
    sim.run_for(Duration::from_millis(10));
    assert_eq!(sim.ap.gimbal_primary, (0, 0));
}

fn gimbal_report(time_boot_ms: u32, q: [f32; 4]) -> MavMessage {
    MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
        time_boot_ms,
        q,
        flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME,
        ..Default::default()
    })
}

/// Gimbal reports are put on the autopilot's clock whoever sends them (audit, session
/// 37): one report from the autopilot stamped 600 s ahead stopped every frame's
/// alignment for good, and a MAVLink gimbal device (its own boot clock, 3 s behind)
/// gave no aligned frame at all. The first is refused and counted; the device's report
/// is placed at its arrival.
#[test]
fn gimbal_reports_are_on_the_autopilots_clock_whoever_sends_them() {
    let mut sim = border_aiming();
    sim.ap.streams = StreamAnswer::Accept;
    sim.run_until(secs(10));
    let level = [1.0, 0.0, 0.0, 0.0];
    let at = |sim: &Sim| ((sim.now.0 / 1000) as u32, sim.now.secs());
    // From the autopilot, 600 s ahead: refused.
    let (ms, _) = at(&sim);
    sim.deliver(frame(1, 1, gimbal_report(ms + 600_000, level)));
    sim.run_for(Duration::from_millis(10));
    assert_eq!(sim.core.telemetry().implausible, 1);
    // From a gimbal device (component 154) whose clock is 3 s behind: placed at its
    // arrival, so the frame captured now finds it.
    let now = sim.now.secs() + 0.2;
    for _ in 0..10 {
        let (ms, _) = at(&sim);
        sim.deliver(frame(1, 154, gimbal_report(ms.saturating_sub(3000), level)));
        sim.run_for(Duration::from_millis(50));
    }
    let pose = sim.core.telemetry().aligner.align(now, sim.now.secs());
    assert!(pose.is_ok(), "{pose:?}");
}

/// A refused report (a NaN quaternion) does not count the last good one again in the
/// pointing statistics (a flood of them moved the median from 1.27 to 0.61 degrees).
#[test]
fn refused_gimbal_reports_are_not_counted_as_pointing() {
    let mut sim = border_aiming();
    aim_for(&mut sim, 2);
    let good = |sim: &Sim| gimbal_report((sim.now.0 / 1000) as u32, [1.0, 0.0, 0.0, 0.0]);
    let m = good(&sim);
    sim.deliver(frame(1, 1, m));
    sim.run_for(Duration::from_millis(20));
    let counted = sim.core.gimbal().errors.len();
    assert_eq!(counted, 1);
    for _ in 0..50 {
        let ms = (sim.now.0 / 1000) as u32;
        sim.deliver(frame(1, 1, gimbal_report(ms, [f32::NAN, 0.0, 0.0, 0.0])));
        sim.run_for(Duration::from_millis(5));
    }
    assert_eq!(sim.core.gimbal().errors.len(), counted);
}

/// An acknowledgement the autopilot sends someone else (a router shows mavloc every
/// ACK) is not an answer to mavloc's command.
#[test]
fn an_ack_addressed_to_another_component_is_not_mavlocs() {
    let mut sim = border_aiming();
    aim_for(&mut sim, 1);
    let ack = MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command: MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
        result: MavResult::MAV_RESULT_DENIED,
        target_system: 255,
        target_component: 190,
        ..Default::default()
    });
    sim.deliver(frame(1, 1, ack));
    sim.run_for(Duration::from_millis(10));
    assert_eq!(sim.core.gimbal().control(), gimbal::Control::InControl);
}

#[test]
fn heartbeat_is_active_only_with_autopilot_clock_camera_and_pipeline() {
    let mut s = Settings::default();
    s.daemon.pipeline = PipelineKind::Area;
    let mut sim = Sim::new(s);
    sim.run_until(secs(1));
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area));
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_STANDBY, "no autopilot");
    sim.ap = FakeAutopilot::new(sim.now);
    sim.run_for(Duration::from_secs(3));
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_STANDBY, "no frames yet");
    sim.input(Input::Camera { now: sim.now, event: CameraEvent::Up("test".into()) });
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_STANDBY, "no frame processed yet");
    let report = |now: Mono, processed| Input::Pipeline {
        now,
        event: PipelineEvent::Report {
            capture: 0.0,
            attitude: (0.0, 0.0, 0.0),
            report: Report { processed, ..Report::default() },
        },
    };
    // Frames skipped (say, no target mask): running, but producing nothing.
    for _ in 0..10 {
        sim.input(report(sim.now, false));
    }
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_STANDBY, "skipping every frame is not ACTIVE");
    assert_eq!(sim.core.counters().frames_skipped, 10);
    sim.input(report(sim.now, true));
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_ACTIVE);
    // The pipeline stops producing: STANDBY again after 3 s, in the next heartbeat too.
    sim.run_for(Duration::from_secs(5));
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_STANDBY);
    let last_beat = sim.sent.iter().rev().find_map(|(_, m)| match m {
        MavMessage::HEARTBEAT(h) => Some(h.system_status),
        _ => None,
    });
    assert_eq!(last_beat, Some(MavState::MAV_STATE_STANDBY));
    sim.input(report(sim.now, true));
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_ACTIVE);
    sim.input(Input::Pipeline { now: sim.now, event: PipelineEvent::Failed("boom".into()) });
    assert_eq!(sim.core.mav_state(), MavState::MAV_STATE_CRITICAL);
}

#[test]
fn a_pipeline_that_cannot_start_is_denied_and_failed() {
    let mut s = settings();
    s.indoor.model = "/nonexistent.model".into();
    let mut sim = Sim::new(s);
    sim.start_result = Err("model /nonexistent.model does not exist".into());
    sim.gcs_sends(pipeline_command(2.0, 1.0));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(acks_to_gcs(&sim), vec![MavResult::MAV_RESULT_DENIED]);
    assert_eq!(sim.core.pipeline(), PipelineState::Failed(PipelineKind::Indoor));
    assert!(sim.statustexts().concat().contains("does not exist"));
}

/// `LOC_PIPELINE` set from the ground: a pipeline that cannot start (indoor, no floor
/// model) is refused with the unchanged value and the running one goes on; one that failed
/// to start (its model unreadable) is replaced by the next value set, and LOC_PIPELINE 0
/// is undone by setting a pipeline again (an outside trial: `Failed(Indoor)` stayed so
/// whatever was set, and 0 -> 1 stayed `Stopped`).
#[test]
fn the_pipeline_parameter_refuses_what_cannot_start_and_recovers_from_a_failed_start() {
    let set = |v: i32| {
        MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: f32::from_bits(v as u32),
            target_system: 1,
            target_component: 191,
            param_id: "LOC_PIPELINE".into(),
            param_type: MavParamType::MAV_PARAM_TYPE_INT32,
        })
    };
    let answered = |sim: &Sim| {
        sim.sent.iter().rev().find_map(|(_, m)| match m {
            MavMessage::PARAM_VALUE(p) if p.param_id.to_str().unwrap_or_default() == "LOC_PIPELINE" => {
                Some(p.param_value.to_bits() as i32)
            }
            _ => None,
        })
    };
    let mut s = settings();
    s.daemon.pipeline = PipelineKind::Area;
    let mut sim = Sim::new(s.clone());
    sim.run_until(secs(1));
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area));
    sim.gcs_sends(set(2));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(answered(&sim), Some(1), "the unchanged value back");
    assert!(sim.statustexts().concat().contains("indoor.model is not set"), "{:?}", sim.statustexts());
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area), "the area one goes on");

    // A model named but unusable: taken, the start fails; setting area again starts it.
    s.indoor.model = "/nonexistent.model".into();
    let mut sim = Sim::new(s);
    sim.run_until(secs(1));
    sim.start_result = Err("model /nonexistent.model does not exist".into());
    sim.gcs_sends(set(2));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Failed(PipelineKind::Indoor));
    sim.start_result = Ok(());
    sim.gcs_sends(set(1));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area), "recovered");
    // None stops it; a pipeline set again starts it.
    sim.gcs_sends(set(0));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Stopped);
    sim.gcs_sends(set(1));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area));
    // Stopped by command, it stays stopped whatever the parameter says.
    sim.gcs_sends(pipeline_command(0.0, 0.0));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Stopped);
    sim.gcs_sends(set(2));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(sim.core.pipeline(), PipelineState::Stopped);
}

#[test]
fn echoes_and_other_components_commands_are_ignored() {
    let mut sim = Sim::new(settings());
    let cmd = |target_component| {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            target_system: 1,
            target_component,
            ..Default::default()
        })
    };
    // Our own heartbeat echoed back by PX4's forwarding is not an autopilot.
    sim.deliver(frame(
        1,
        191,
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            ..Default::default()
        }),
    ));
    sim.gcs_sends(cmd(1));
    sim.gcs_sends(cmd(0));
    sim.run_for(Duration::from_millis(100));
    assert!(!sim.core.autopilot_found());
    assert!(!sim.to_gcs.iter().any(|(_, m)| matches!(m, MavMessage::COMMAND_ACK(_))));
    sim.gcs_sends(cmd(191));
    sim.run_for(Duration::from_millis(100));
    assert!(sim.to_gcs.iter().any(|(_, m)| matches!(m,
        MavMessage::COMMAND_ACK(a) if a.result == MavResult::MAV_RESULT_UNSUPPORTED && a.target_system == 255)));
}

#[test]
fn vision_position_covariance_is_the_upper_triangle() {
    let e = PositionEstimate {
        autopilot_time: 0.0,
        north: 1.5,
        east: -2.0,
        down: -1.0,
        cov: [[0.04, 0.01], [0.01, 0.09]],
    };
    let MavMessage::VISION_POSITION_ESTIMATE(v) =
        vision_position_estimate(&e, 1_000_000, (0.0, 0.0, 0.3), None)
    else {
        unreachable!()
    };
    assert_eq!((v.x, v.y, v.usec), (1.5, -2.0, 1_000_000));
    // Upper-triangle indices of the diagonal: 0, 6, 11, 15, 18, 20.
    assert_eq!((v.covariance[0], v.covariance[1], v.covariance[6]), (0.04, 0.01, 0.09));
    assert!(v.covariance[11] >= 1e3 && v.covariance[20] >= 1e3);
    assert_eq!(v.covariance[2], 0.0);
    let MavMessage::VISION_POSITION_ESTIMATE(v) =
        vision_position_estimate(&e, 0, (0.0, 0.0, 0.0), Some(0.01))
    else {
        unreachable!()
    };
    assert_eq!((v.z, v.covariance[11]), (-1.0, 0.01), "z measured");
    assert!(
        v.covariance[15] <= 0.01 && v.covariance[18] <= 0.01,
        "PX4 floors z's variance with roll's and pitch's"
    );
}

/// A command from the ground station, as the property test draws them.
fn gcs_command(kind: u8, p1: f32, p2: f32) -> MavMessage {
    let command = match kind % 4 {
        0 => MavCmd::MAV_CMD_USER_1,
        1 => MavCmd::MAV_CMD_USER_2,
        2 => MavCmd::MAV_CMD_REQUEST_MESSAGE,
        _ => MavCmd::MAV_CMD_DO_SET_MODE,
    };
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command,
        param1: p1,
        param2: p2,
        target_system: 1,
        target_component: 191,
        ..Default::default()
    })
}

fn run_commands(cmds: &[(u8, f32, f32, u16)]) -> (Vec<(Mono, MavMessage)>, Sim) {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    for &(kind, p1, p2, gap_ms) in cmds {
        sim.gcs_sends(gcs_command(kind, p1, p2));
        sim.run_for(Duration::from_millis(gap_ms as u64));
    }
    sim.run_for(Duration::from_secs(2));
    (sim.sent.clone(), sim)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// Every command addressed to mavloc gets exactly one final ACK (IN_PROGRESS is not
    /// final), whatever the interleaving; and the same inputs give the same outputs.
    #[test]
    fn every_command_gets_exactly_one_final_ack_and_runs_are_deterministic(
        cmds in proptest::collection::vec((0u8..4, prop_oneof![Just(f32::NAN), -1.0f32..3.0, (0u8..3).prop_map(f32::from)], prop_oneof![Just(f32::NAN), (0u8..23).prop_map(f32::from)], 0u16..300), 1..25)
    ) {
        let (log, sim) = run_commands(&cmds);
        let finals = log.iter().filter(|(_, m)| matches!(m, MavMessage::COMMAND_ACK(a) if a.result != MavResult::MAV_RESULT_IN_PROGRESS)).count();
        prop_assert_eq!(finals, cmds.len());
        prop_assert_eq!(sim.core.acks_owed(), 0);
        // After handle_timeout(now), the next deadline lies in the future.
        let mut core = sim.core;
        core.handle_timeout(sim.now);
        while core.poll_transmit(sim.now).is_some() {}
        prop_assert!(core.poll_timeout().is_none_or(|t| t > sim.now));
        let (again, _) = run_commands(&cmds);
        prop_assert_eq!(format!("{log:?}"), format!("{again:?}"));
    }
}

/// The core stays sans-I/O: no clock, runtime, file system, socket or thread in its
/// code (comments may name them). Fails naming the file and line that breaks it.
#[test]
fn the_core_reads_no_clock_and_does_no_io() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/daemon/core");
    let forbidden = [
        "Instant::now",
        "SystemTime",
        "tokio",
        "std::fs",
        "std::net",
        "std::thread",
        "std::process",
        "std::env",
        "sleep(",
    ];
    let mut violations = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        // This file reads the sources (and names what it forbids); it is not the core.
        if path.ends_with("tests.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        for (i, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for f in forbidden {
                if code.contains(f) {
                    violations.push(format!("{}:{}: {f}", path.display(), i + 1));
                }
            }
        }
    }
    assert!(violations.is_empty(), "the core must not do I/O or read clocks:\n{}", violations.join("\n"));
}

#[test]
fn a_foreign_flood_of_parameter_requests_and_sets_costs_counters_not_the_link() {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(3));
    let before = sim.sent.len();
    let start = sim.now;
    for ms in 0..1000u64 {
        let foreign = |m| frame(77, 1, m);
        sim.deliver(foreign(param_request_list()));
        sim.deliver(foreign(param_read((ms % 10) as i16)));
        sim.deliver(foreign(MavMessage::PARAM_SET(PARAM_SET_DATA {
            param_value: 0.9,
            target_system: 1,
            target_component: 191,
            param_id: "AREA_RATIO".into(),
            param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
        })));
        sim.run_until(start + Duration::from_millis(ms + 1));
    }
    // The ground station's own list goes through the same second.
    sim.gcs_sends(param_request_list());
    sim.run_for(Duration::from_secs(3));
    let c = sim.core.counters();
    assert_eq!(c.param_requests_refused, 2000);
    assert_eq!(c.params_refused, 1000);
    assert!(c.peer_lines_suppressed >= 1990, "{}", c.peer_lines_suppressed);
    let texts: Vec<String> = sim.statustexts().into_iter().filter(|t| t.contains("refused")).collect();
    assert!(texts.len() <= 2, "one line per sender per 10 s: {texts:?}");
    // Exactly one list went out: the ground station's.
    let values = sim.sent[before..].iter().filter(|(_, m)| matches!(m, MavMessage::PARAM_VALUE(_))).count();
    assert_eq!(values, param_table::PARAMS.len());
    let tuned = param_table::find("AREA_RATIO").map(|(_, d)| param_table::value_of(sim.core.settings(), d));
    assert_ne!(tuned, Some(0.9_f32 as f64), "the foreign set changed nothing");
}

/// A read or set by name sent to every component of the system (MAV_COMP_ID_ALL) is
/// answered when the name is mavloc's, as PX4 answers; by index, or for another
/// component's name, it is left to the others.
#[test]
fn a_parameter_read_or_set_by_name_to_every_component_is_answered_when_the_name_is_ours() {
    let mut sim = Sim::new(settings());
    sim.run_until(secs(1));
    let values = |sim: &Sim| {
        sim.sent
            .iter()
            .filter_map(|(_, m)| match m {
                MavMessage::PARAM_VALUE(p) => {
                    Some((p.param_id.to_str().unwrap_or_default().to_string(), p.param_value))
                }
                _ => None,
            })
            .collect::<Vec<_>>()
    };
    let read = |id: &str, index: i16| {
        MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
            param_index: index,
            target_system: 1,
            target_component: 0,
            param_id: id.into(),
        })
    };
    sim.gcs_sends(read("AREA_L_MAX", -1));
    sim.gcs_sends(read("", 3));
    sim.gcs_sends(read("MPC_XY_VEL_MAX", -1));
    sim.run_for(Duration::from_millis(200));
    let got = values(&sim);
    assert_eq!(got.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(), ["AREA_L_MAX"], "{got:?}");
    sim.gcs_sends(MavMessage::PARAM_SET(PARAM_SET_DATA {
        param_value: 300.0,
        target_system: 1,
        target_component: 0,
        param_id: "AREA_L_MAX".into(),
        param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
    }));
    sim.run_for(Duration::from_millis(200));
    // An integer parameter, answered in PX4's byte-wise encoding.
    assert_eq!(values(&sim).last().map(|(n, v)| (n.as_str(), v.to_bits())), Some(("AREA_L_MAX", 300)));
}

/// A parameter set while the disk is full is saved once there is room again: tried every
/// 10 s, said when it fails first and when it succeeds (it used to be tried once, and the
/// tuned value was lost at the next start: an outside audit on a 1 MB tmpfs).
#[test]
fn a_parameter_set_on_a_full_disk_is_saved_once_there_is_room() {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(3));
    sim.disk_full = true;
    sim.gcs_sends(MavMessage::PARAM_SET(PARAM_SET_DATA {
        param_value: 300.0,
        target_system: 1,
        target_component: 191,
        param_id: "AREA_L_MAX".into(),
        param_type: MavParamType::MAV_PARAM_TYPE_REAL32,
    }));
    sim.run_for(Duration::from_secs(35));
    let saves =
        |sim: &Sim| sim.actions.iter().filter(|(_, a)| matches!(a, Action::SaveParams { .. })).count();
    let tries = saves(&sim);
    assert!((3..=5).contains(&tries), "the first save and one every 10 s: {tries}");
    let texts = sim.statustexts();
    assert_eq!(texts.iter().filter(|t| t.contains("not saved")).count(), 1, "said once: {texts:?}");
    sim.disk_full = false;
    sim.run_for(Duration::from_secs(12));
    let (_, last) = sim.actions.iter().rev().find(|(_, a)| matches!(a, Action::SaveParams { .. })).unwrap();
    let Action::SaveParams { json, .. } = last else { unreachable!() };
    assert!(json.contains("\"AREA_L_MAX\": 300"), "{json}");
    assert!(sim.statustexts().iter().any(|t| t.contains("tuned parameters saved (after")));
    let after = saves(&sim);
    sim.run_for(Duration::from_secs(30));
    assert_eq!(saves(&sim), after, "saved: no more tries");
}

#[test]
fn a_stamp_from_the_future_is_no_reboot_and_moves_nothing() {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(10));
    let offset = sim.core.aligner().clock.offset().0.unwrap();
    // One forged (or corrupt) ATTITUDE, stamped an hour ahead.
    sim.deliver(frame(
        1,
        1,
        MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: 3_600_000, ..Default::default() }),
    ));
    sim.run_until(secs(20));
    assert_eq!(sim.core.counters().autopilot_reboots, 0);
    assert!(!sim.statustexts().concat().contains("rebooted"));
    let now = sim.core.aligner().clock.offset().0.unwrap();
    assert!((now - offset).abs() < 0.05, "offset {offset} -> {now}");
    // A true reboot is still seen.
    sim.ap.reboot(sim.now);
    sim.run_for(Duration::from_secs(5));
    assert_eq!(sim.core.counters().autopilot_reboots, 1);
}

#[test]
fn an_unknown_command_id_is_answered_unsupported_with_its_own_id() {
    let mut core = Core::new(settings(), BTreeMap::new(), false, None);
    let placeholder = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        command: MavCmd::MAV_CMD_NAV_WAYPOINT,
        target_system: 1,
        target_component: 191,
        ..Default::default()
    });
    let mut f = frame(255, 190, placeholder);
    f.unknown_command = Some(42424);
    core.handle(Input::Mav { rx: Mono::ZERO, frame: f.clone() });
    let out: Vec<_> = std::iter::from_fn(|| core.poll_transmit(Mono::ZERO)).collect();
    let acks: Vec<_> = out
        .iter()
        .filter_map(|o| match &o.message {
            MavMessage::COMMAND_ACK(a) => Some((a.result, a.target_system, o.unknown_command)),
            _ => None,
        })
        .collect();
    assert_eq!(acks, vec![(MavResult::MAV_RESULT_UNSUPPORTED, 255, Some(42424))]);
    // Broadcast: not ours to answer. And the placeholder is never acted on.
    if let MavMessage::COMMAND_LONG(c) = &mut f.message {
        c.target_component = 0;
    }
    core.handle(Input::Mav { rx: Mono::ZERO, frame: f });
    assert!(!std::iter::from_fn(|| core.poll_transmit(Mono::ZERO))
        .any(|o| matches!(o.message, MavMessage::COMMAND_ACK(_))));
}

#[test]
fn command_int_is_handled_like_command_long() {
    let mut sim = Sim::new(settings());
    sim.gcs_sends(MavMessage::COMMAND_INT(COMMAND_INT_DATA {
        command: MavCmd::MAV_CMD_DO_SET_MODE,
        target_system: 1,
        target_component: 191,
        ..Default::default()
    }));
    sim.run_for(Duration::from_millis(100));
    assert!(sim.to_gcs.iter().any(|(_, m)| matches!(m,
        MavMessage::COMMAND_ACK(a) if a.command == MavCmd::MAV_CMD_DO_SET_MODE
            && a.result == MavResult::MAV_RESULT_UNSUPPORTED)));
}

/// An autopilot that booted with mavloc, 30 s of telemetry ago: its clock is mavloc's.
fn autopilot_booted_with_mavloc_30_s_ago() -> Sim {
    let mut sim = Sim::new(settings());
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.run_until(secs(30));
    sim
}

#[test]
fn a_spoofed_reboot_is_not_believed_while_the_autopilot_speaks_on_its_old_clock() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    assert!(sim.core.autopilot_found());
    // A stranger sends "ATTITUDE at boot + 0.1 s" as the autopilot, ten times a second
    // for 5 s, while the real one goes on streaming on its own clock.
    for i in 0..50u32 {
        sim.deliver(frame(
            1,
            1,
            MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: 100 + i * 100, ..Default::default() }),
        ));
        sim.run_for(Duration::from_millis(100));
    }
    sim.run_for(Duration::from_secs(1));
    assert_eq!(sim.core.counters().autopilot_reboots, 0, "{:?}", sim.statustexts());
    assert!(!sim.statustexts().concat().contains("rebooted"));
    assert!(sim.core.counters().reboot_claims_rejected >= 1);
    // A real reboot is still seen (within a second of the first new stamp).
    sim.ap.reboot(sim.now);
    sim.run_for(Duration::from_secs(3));
    assert_eq!(sim.core.counters().autopilot_reboots, 1);
}

const CLASH: &str = "same MAV_SYS_ID twice?";

/// Two vehicles with one system id: the second one's telemetry is screened out by its
/// clock, and the user hears of it, once a minute at most, so the ids can be fixed.
#[test]
fn a_second_vehicle_with_the_autopilots_system_id_is_named_once_a_minute() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    assert!(sim.core.autopilot_found());
    assert!(!warnings(&sim).contains(CLASH), "one autopilot alone: {}", warnings(&sim));
    // The second vehicle booted 20 s ago and streams ATTITUDE at 10 Hz for 2 minutes.
    let booted = sim.now - Duration::from_secs(20);
    for _ in 0..1200 {
        let ms = sim.now.saturating_sub(booted).as_millis() as u32;
        sim.deliver(frame(
            1,
            1,
            MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: ms, ..Default::default() }),
        ));
        sim.run_for(Duration::from_millis(100));
    }
    assert_eq!(sim.core.counters().autopilot_reboots, 0);
    let said = warnings(&sim).matches(CLASH).count();
    assert!((2..=3).contains(&said), "said {said} times in 2 minutes: {:?}", sim.statustexts());
}

/// One vehicle alone: a gimbal device whose clock jumps ahead (its reports refused for a
/// minute) and the autopilot's messages arriving 10 s late by another path, two within
/// seconds and a third 90 s later, are not taken for a second vehicle (the gimbal's
/// refusals counted as the autopilot's before, and strays added up over any time).
#[test]
fn a_gimbals_clock_or_two_late_messages_are_not_taken_for_a_second_vehicle() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    let level = [1.0, 0.0, 0.0, 0.0];
    for i in 0..600 {
        let ms = (sim.now.0 / 1000) as u32 + if i < 20 { 0 } else { 600_000 };
        sim.deliver(frame(1, 154, gimbal_report(ms, level)));
        sim.run_for(Duration::from_millis(100));
    }
    assert!(sim.core.telemetry().implausible > 100, "the gimbal's reports were refused");
    for _ in 0..2 {
        let ms = (sim.now.0 / 1000) as u32 - 10_000;
        sim.deliver(frame(
            1,
            1,
            MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: ms, ..Default::default() }),
        ));
        sim.run_for(Duration::from_secs(5));
    }
    // A third late one, a minute and a half after them: strays, not a second clock.
    sim.run_for(Duration::from_secs(90));
    let ms = (sim.now.0 / 1000) as u32 - 10_000;
    sim.deliver(frame(1, 1, MavMessage::ATTITUDE(ATTITUDE_DATA { time_boot_ms: ms, ..Default::default() })));
    sim.run_for(Duration::from_secs(5));
    assert!(sim.core.counters().reboot_claims_rejected >= 3, "the late messages were screened");
    assert!(!warnings(&sim).contains(CLASH), "{}", warnings(&sim));
}

/// A real reboot is one backwards step and no clash.
#[test]
fn an_autopilot_reboot_is_not_taken_for_a_second_vehicle() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    sim.ap.reboot(sim.now);
    sim.run_for(Duration::from_secs(60));
    assert_eq!(sim.core.counters().autopilot_reboots, 1);
    assert!(!warnings(&sim).contains(CLASH), "{}", warnings(&sim));
}

/// The WARNING STATUSTEXTs sent, chunks joined.
fn warnings(sim: &Sim) -> String {
    sim.sent
        .iter()
        .filter_map(|(_, m)| match m {
            MavMessage::STATUSTEXT(s) if s.severity == MavSeverity::MAV_SEVERITY_WARNING => {
                Some(String::from_utf8_lossy(&s.text[..]).trim_end_matches('\0').to_string())
            }
            _ => None,
        })
        .collect()
}

#[test]
fn a_failed_result_write_is_a_counted_warning_and_a_full_disk_no_flood() {
    let mut sim = Sim::new(settings());
    sim.run_until(secs(1));
    let disk_full = "area: cannot write results: No space left on device (os error 28)";
    let failing = |now| Input::Pipeline {
        now,
        event: PipelineEvent::Report {
            capture: 0.0,
            attitude: (0.0, 0.0, 0.0),
            report: Report {
                processed: true,
                warnings: vec![Warning::WriteFailed(disk_full.into())],
                ..Report::default()
            },
        },
    };
    // A full disk fails every checkpoint: said once, every one counted.
    for _ in 0..5 {
        sim.input(failing(sim.now));
        sim.run_for(Duration::from_millis(500));
    }
    assert_eq!(sim.core.counters().result_writes_failed, 5);
    assert_eq!(warnings(&sim).matches("No space left on device").count(), 1, "{}", warnings(&sim));
    // Ten seconds on, the next failure is said again, with how many went unsaid.
    sim.run_for(Duration::from_secs(10));
    sim.input(failing(sim.now));
    sim.run_for(Duration::from_millis(100));
    assert_eq!(warnings(&sim).matches("No space left on device").count(), 2);
    assert!(warnings(&sim).contains("(4 more failed writes since the last warning)"), "{}", warnings(&sim));
    // The write when the pipeline stops, reported by the worker.
    sim.run_for(Duration::from_secs(10));
    let at_stop = "cannot write the pipeline's results at stop: Read-only file system (os error 30)";
    sim.input(Input::Pipeline { now: sim.now, event: PipelineEvent::WriteFailed(at_stop.into()) });
    sim.run_for(Duration::from_millis(100));
    assert!(warnings(&sim).contains("Read-only file system"), "{}", warnings(&sim));
    assert_eq!(sim.core.counters().result_writes_failed, 7);
    // status.json shows the counter with the others.
    let json = serde_json::to_value(sim.core.counters()).unwrap();
    assert_eq!(json["result_writes_failed"], 7);
    // Other warnings of a report are WARNINGs too, not INFO notes.
    let other = vec![Warning::Other("indoor: model and camera disagree".into())];
    let report = Report { warnings: other, ..Report::default() };
    let event = PipelineEvent::Report { capture: 0.0, attitude: (0.0, 0.0, 0.0), report };
    sim.input(Input::Pipeline { now: sim.now, event });
    sim.run_for(Duration::from_millis(100));
    assert!(warnings(&sim).contains("model and camera disagree"));
}

// ---- GPS-denied start-up (issue #18), against a fake autopilot that behaves as PX4
// v1.16 with EKF2_GPS_CTRL 0 (../shared/data/px4-sitl) ----

fn gps_denied_settings() -> Settings {
    let mut s = settings();
    s.indoor.gps_denied = true;
    s.indoor.origin = vec![52.0, 4.37, 0.0];
    s.indoor.pad_x_m = -2.5;
    s.indoor.pad_y_m = -2.5;
    s
}

/// GPS-denied settings with the indoor pipeline running (the fake shell starts any).
fn indoor_without_gps_settings() -> Settings {
    let mut s = gps_denied_settings();
    s.daemon.pipeline = PipelineKind::Indoor;
    s.indoor.model = "floor.model".into();
    s
}

/// A core with settings `s` whose autopilot without GPS, up for 12 s, is now armed and
/// in the air.
fn airborne_without_gps(s: Settings) -> Sim {
    let mut sim = Sim::new(s);
    px4_without_gps(&mut sim);
    sim.run_until(secs(12));
    sim.ap.armed = true;
    sim.ap.in_air = true;
    sim
}

/// A core started (mavloc started again after a crash) while its autopilot without GPS
/// is armed and in the air, the indoor pipeline running.
fn started_in_flight_without_gps() -> Sim {
    let mut sim = Sim::new(indoor_without_gps_settings());
    px4_without_gps(&mut sim);
    sim.ap.armed = true;
    sim.ap.in_air = true;
    sim
}

fn px4_without_gps(sim: &mut Sim) {
    sim.ap = FakeAutopilot::new(sim.now);
    sim.ap.gps = false;
    sim.ap.truth = (-2.5, -2.5);
}

/// The vision positions sent (VISION_POSITION_ESTIMATE, or ODOMETRY with a position).
fn vision(sim: &Sim, from: Mono, to: Mono) -> Vec<VISION_POSITION_ESTIMATE_DATA> {
    sim.sent_between(from, to)
        .filter_map(|m| match m {
            MavMessage::VISION_POSITION_ESTIMATE(v) => Some(v.clone()),
            MavMessage::ODOMETRY(o) if o.x.is_finite() => Some(VISION_POSITION_ESTIMATE_DATA {
                usec: o.time_usec,
                x: o.x,
                y: o.y,
                z: o.z,
                covariance: o.pose_covariance,
                ..Default::default()
            }),
            _ => None,
        })
        .collect()
}

/// The body-frame velocities sent with them (ODOMETRY): velocity and its variances.
fn velocities(sim: &Sim, from: Mono, to: Mono) -> Vec<([f32; 3], [f32; 3])> {
    sim.sent_between(from, to)
        .filter_map(|m| match m {
            MavMessage::ODOMETRY(o) if o.vx.is_finite() => {
                assert_eq!(o.child_frame_id, MavFrame::MAV_FRAME_BODY_FRD);
                let c = &o.velocity_covariance;
                Some(([o.vx, o.vy, o.vz], [c[0], c[6], c[11]]))
            }
            _ => None,
        })
        .collect()
}

#[allow(deprecated)]
fn origins_sent(sim: &Sim) -> Vec<(Mono, SET_GPS_GLOBAL_ORIGIN_DATA)> {
    sim.sent
        .iter()
        .filter_map(|(t, m)| match m {
            MavMessage::SET_GPS_GLOBAL_ORIGIN(o) => Some((*t, o.clone())),
            _ => None,
        })
        .collect()
}

#[test]
fn without_gps_the_pad_goes_out_from_power_on_then_the_origin_and_px4_lets_the_vehicle_arm() {
    let mut sim = Sim::new(gps_denied_settings());
    px4_without_gps(&mut sim);
    sim.run_until(secs(3));
    let v = vision(&sim, secs(1), secs(2));
    assert!(v.len() >= 28, "about 30 Hz while standing, got {}", v.len());
    assert!(
        v.iter().all(|v| v.x == -2.5 && v.y == -2.5 && v.covariance[0] > 0.0),
        "the pad, with its variance"
    );
    // Standing: still, and said so (EKF2's velocity would otherwise wander as the motors
    // spin up).
    let still = velocities(&sim, secs(1), secs(2));
    assert_eq!(still.len(), v.len());
    assert!(still.iter().all(|(v, var)| *v == [0.0; 3] && var.iter().all(|s| *s > 0.0 && *s <= 0.0026)));
    assert!(origins_sent(&sim).is_empty(), "no origin before 5 s of vision");
    assert_eq!(sim.ap.arm(sim.now).0, MavResult::MAV_RESULT_TEMPORARILY_REJECTED, "PX4 cannot arm yet");

    sim.run_until(secs(20));
    let origins = origins_sent(&sim);
    assert_eq!(origins.len(), 1, "sent once, echoed, not resent");
    let (at, o) = &origins[0];
    #[allow(deprecated)]
    let (lat, lon) = (o.latitude, o.longitude);
    assert_eq!((lat, lon), (520_000_000, 43_700_000));
    let first_vision = sim.sent.iter().find(|(_, m)| matches!(m, MavMessage::ODOMETRY(_))).unwrap().0;
    let after = at.saturating_sub(first_vision).as_secs_f64();
    assert!((5.0..5.2).contains(&after), "origin {after} s after the first estimate");
    assert_eq!(sim.core.gps_denied().origin_state(), gpsdenied::OriginState::Confirmed);
    assert_eq!(sim.ap.vision_rejected, 0, "the pad is where the vehicle is");
    assert_eq!(sim.core.prearm_ok(), Some(true));
    assert!(sim.statustexts().iter().any(|t| t.contains("pre-arm checks pass")));
    assert_eq!(sim.ap.arm(sim.now).0, MavResult::MAV_RESULT_ACCEPTED);
    assert!(sim.core.counters().standing_estimates_sent > 500);
}

#[test]
fn with_gps_nothing_is_sent_for_the_standing_vehicle_and_px4s_refusal_is_shown_in_words() {
    let mut sim = Sim::new(settings());
    px4_without_gps(&mut sim);
    sim.run_until(secs(10));
    assert!(vision(&sim, Mono::ZERO, secs(10)).is_empty());
    assert!(origins_sent(&sim).is_empty());
    // The ground station's arming attempt is refused; PX4 says why in an EVENT only.
    let (result, event) = sim.ap.arm(sim.now);
    assert_eq!(result, MavResult::MAV_RESULT_TEMPORARILY_REJECTED);
    sim.deliver(frame(1, 1, event.unwrap()));
    sim.run_for(Duration::from_secs(1));
    let events: Vec<_> = sim.core.autopilot_events().recent().map(|e| e.text.clone()).collect();
    assert_eq!(events.len(), 1);
    assert!(events[0].contains("Arming denied: Resolve system health failures first"), "{events:?}");
    assert_eq!(sim.core.counters().autopilot_events, 1);
    assert_eq!(sim.core.prearm_ok(), Some(false));
}

fn estimate(now: Mono, north: f64, east: f64) -> Input {
    Input::Pipeline {
        now,
        event: PipelineEvent::Report {
            capture: now.secs(),
            attitude: (0.0, 0.0, 0.0),
            report: Report {
                processed: true,
                position: Some(PositionEstimate {
                    autopilot_time: now.secs(),
                    north,
                    east,
                    down: -1.0,
                    cov: [[0.01, 0.0], [0.0, 0.01]],
                }),
                ..Report::default()
            },
        },
    }
}

#[test]
fn in_the_air_the_pipeline_speaks_and_after_touchdown_the_vehicle_stands_where_it_was_last_seen() {
    let mut sim = airborne_without_gps(gps_denied_settings());
    sim.run_until(secs(14));
    let standing = sim.core.counters().standing_estimates_sent;
    // Flying: the pipeline's estimates at 15 Hz, none for the standing vehicle.
    for i in 0..30 {
        let t = secs(14) + Duration::from_millis(66 * i);
        sim.run_until(t);
        sim.input(estimate(t, 2.4 + 0.001 * i as f64, 1.0));
    }
    assert_eq!(sim.core.counters().standing_estimates_sent, standing, "none while flying");
    sim.ap.in_air = false;
    sim.ap.armed = false;
    sim.run_for(Duration::from_secs(3));
    let v = vision(&sim, sim.now - Duration::from_secs(1), sim.now);
    assert!(v.len() >= 28, "standing again: {}", v.len());
    assert!(
        v.iter().all(|v| (v.x - 2.429).abs() < 1e-3 && v.y == 1.0),
        "the last estimate in the air: {:?}",
        v[0]
    );
}

/// mavloc started again in a flight without GPS (killed, and started by systemd): an
/// autopilot found armed and in the air has an origin already (it could not have armed
/// without), and a new one moves its local frame under it mid-flight (PX4 v1.16's
/// `setLatLonOrigin`); the pad is not where the vehicle is. Neither goes out in the air:
/// the pipeline's estimates do, and the origin once the vehicle stands again. (Before,
/// the restarted daemon sent the origin 5 s into the flight: PX4 SITL took it.)
#[test]
fn without_gps_started_again_in_flight_sends_no_origin_and_no_pad_until_the_vehicle_stands() {
    let mut sim = started_in_flight_without_gps();
    let mut t = secs(1);
    while t < secs(12) {
        sim.run_until(t);
        sim.deliver(range_m(1.0));
        sim.input(estimate(t, 2.0, 1.0));
        t = t + Duration::from_millis(66);
    }
    assert!(origins_sent(&sim).is_empty(), "an origin sent in flight");
    let v = vision(&sim, Mono::ZERO, sim.now);
    assert!(v.len() > 100, "the pipeline's estimates went out: {}", v.len());
    assert!(
        v.iter().all(|v| v.x == 2.0 && v.y == 1.0),
        "the pad went out: {:?}",
        v.iter().find(|v| v.x != 2.0)
    );
    assert!(sim.statustexts().concat().contains("the origin only once it stands"), "not said why");
    // Landed: standing where it was last seen, and now the origin.
    sim.ap.in_air = false;
    sim.ap.armed = false;
    sim.run_for(Duration::from_secs(8));
    let origins = origins_sent(&sim);
    assert!(!origins.is_empty() && origins[0].0 >= secs(12), "no origin once standing: {origins:?}");
    let standing = vision(&sim, secs(13), sim.now);
    assert!(!standing.is_empty() && standing.iter().all(|v| v.x == 2.0 && v.y == 1.0), "standing at the pad");
}

/// Higher than `indoor.max_height_m` the camera localises nothing (over the simulated
/// floor the fixes from 9 m were 4.3 m RMS off; PX4's precision landing, its target lost,
/// climbs to 10 m to search): the frames only measure the motion and, without GPS, the
/// estimates go out loose, as below `min_height_m`.
#[test]
fn above_the_heights_it_localises_from_the_camera_only_measures_the_motion() {
    let mut sim = airborne_without_gps(indoor_without_gps_settings());
    for (cm, paused) in [(100, false), (290, false), (310, true), (900, true), (150, false)] {
        sim.deliver(range_m(cm as f64 / 100.0));
        sim.run_for(Duration::from_millis(100));
        assert_eq!(sim.core.vision_paused(), paused, "at {cm} cm");
        let phase = if paused { gpsdenied::Phase::Blind } else { gpsdenied::Phase::Seeing };
        assert_eq!(sim.core.gps_phase(), phase, "at {cm} cm");
    }
}

/// The downward rangefinder's reading, `m` metres.
fn range_m(m: f64) -> Frame {
    frame(
        1,
        1,
        MavMessage::DISTANCE_SENSOR(DISTANCE_SENSOR_DATA {
            current_distance: (m * 100.0) as u16,
            min_distance: 1,
            max_distance: 40_000,
            orientation: MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270,
            ..Default::default()
        }),
    )
}

/// Found in the air without GPS, with nothing from the pipeline before the touchdown (a
/// restart low in the descent): where the vehicle stands is unknown, and it goes out as
/// such (x and y NaN, which EKF2 drops), not as the pad to a few centimetres.
#[test]
fn without_gps_started_again_in_flight_never_claims_the_pad() {
    let mut sim = started_in_flight_without_gps();
    sim.run_until(secs(3));
    sim.ap.in_air = false;
    sim.ap.armed = false;
    sim.run_until(secs(6));
    let pad = sim.core.settings().indoor.pad_x_m as f32;
    let claimed: Vec<_> = sim
        .sent_between(Mono::ZERO, sim.now)
        .filter_map(|m| match m {
            MavMessage::ODOMETRY(o) => Some((o.x, o.y)),
            MavMessage::VISION_POSITION_ESTIMATE(v) => Some((v.x, v.y)),
            _ => None,
        })
        .collect();
    assert!(sim.core.counters().standing_estimates_sent > 0, "nothing for the standing vehicle");
    assert!(
        claimed.iter().all(|(x, y)| x.is_nan() && y.is_nan()),
        "{:?}",
        claimed.iter().find(|c| c.0 == pad)
    );
}

/// An unmeasured velocity (the camera's flow failed on a frame) goes out as a placeholder
/// EKF2 weighs at nothing while its vision fusion runs, but as unknown (NaN) on the first
/// vision message after a pause: EKF2 starts its fusion again there and, with no other
/// horizontal aiding, resets its velocity to whatever it is sent (against PX4 SITL, to
/// zero at a 220 m/s SD after a 4 s camera gap, and PX4's failsafe landed the vehicle).
#[test]
fn after_a_pause_in_vision_an_unmeasured_velocity_goes_out_as_unknown() {
    let mut sim = airborne_without_gps(gps_denied_settings());
    sim.run_until(secs(14));
    let measured = VelocityEstimate { body: [0.5, 0.0, 0.0], var: [0.004, 0.004, 0.09] };
    let with = |now: Mono, v: VelocityEstimate| match estimate(now, 1.0, 1.0) {
        Input::Pipeline { now, event: PipelineEvent::Report { capture, attitude, mut report } } => {
            report.velocity = Some(v);
            Input::Pipeline { now, event: PipelineEvent::Report { capture, attitude, report } }
        }
        _ => unreachable!(),
    };
    // The last ODOMETRY sent: its velocity and variances.
    let last = |sim: &Sim| {
        sim.sent
            .iter()
            .rev()
            .find_map(|(_, m)| match m {
                MavMessage::ODOMETRY(o) => Some(([o.vx, o.vy, o.vz], o.velocity_covariance[0])),
                _ => None,
            })
            .unwrap()
    };
    let mut t = secs(14);
    let frame = |sim: &mut Sim, t: &mut Mono, v| {
        sim.run_until(*t);
        sim.input(with(*t, v));
        sim.run_for(Duration::from_millis(10));
        *t = *t + Duration::from_millis(66);
        last(sim)
    };
    for _ in 0..10 {
        frame(&mut sim, &mut t, measured);
    }
    // Mid-stream: the placeholder.
    let (v, var) = frame(&mut sim, &mut t, VelocityEstimate::UNMEASURED);
    assert_eq!((v, var), ([0.0; 3], 1.0e4));
    frame(&mut sim, &mut t, measured);
    // The camera away for 2 s: the first message after carries no velocity.
    t = t + Duration::from_secs(2);
    let (v, var) = frame(&mut sim, &mut t, VelocityEstimate::UNMEASURED);
    assert!(v.iter().all(|c| c.is_nan()) && var.is_nan(), "{v:?} {var}");
    // Nor the next: EKF2 fuses no velocity until a measured one has gone out; after it,
    // the placeholder is harmless again.
    let (v, _) = frame(&mut sim, &mut t, VelocityEstimate::UNMEASURED);
    assert!(v.iter().all(|c| c.is_nan()), "{v:?}");
    let (v, var) = frame(&mut sim, &mut t, measured);
    assert_eq!((v, var), ([0.5, 0.0, 0.0], 0.004));
    let (v, _) = frame(&mut sim, &mut t, VelocityEstimate::UNMEASURED);
    assert_eq!(v, [0.0; 3]);
    // A measured velocity after a pause goes out as it is.
    t = t + Duration::from_secs(2);
    let (v, _) = frame(&mut sim, &mut t, measured);
    assert_eq!(v, [0.5, 0.0, 0.0]);
    // A loose position ("somewhere near here", 10 m SD) never starts EKF2's position
    // fusion, which would reset to it: after a pause it goes out without x and y.
    let loose = |now: Mono| match with(now, measured) {
        Input::Pipeline { now, event: PipelineEvent::Report { capture, attitude, mut report } } => {
            report.position.as_mut().unwrap().cov = [[100.0, 0.0], [0.0, 100.0]];
            Input::Pipeline { now, event: PipelineEvent::Report { capture, attitude, report } }
        }
        _ => unreachable!(),
    };
    let last_xy = |sim: &Sim| {
        sim.sent.iter().rev().find_map(|(_, m)| match m {
            MavMessage::ODOMETRY(o) => Some((o.x, o.y)),
            _ => None,
        })
    };
    t = t + Duration::from_secs(2);
    sim.run_until(t);
    sim.input(loose(t));
    sim.run_for(Duration::from_millis(10));
    let (x, y) = last_xy(&sim).unwrap();
    assert!(x.is_nan() && y.is_nan(), "{x} {y}");
    // While positions are fused, it goes on (it weighs next to nothing there).
    t = t + Duration::from_millis(66);
    frame(&mut sim, &mut t, measured);
    sim.run_until(t);
    sim.input(loose(t));
    sim.run_for(Duration::from_millis(10));
    assert_eq!(last_xy(&sim), Some((1.0, 1.0)));
}

/// Frames that stop in flight without the camera saying so (a hung driver): the ground
/// station is warned once, a second after the last frame, that the autopilot has no
/// position from mavloc, and told when frames come back; on the ground, nothing.
#[test]
fn frames_that_stop_in_flight_are_said_once_and_their_return_with_the_time_away() {
    let mut sim = Sim::new(indoor_without_gps_settings());
    px4_without_gps(&mut sim);
    sim.run_until(secs(12));
    assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Indoor));
    sim.input(Input::Camera { now: sim.now, event: CameraEvent::Up("test".into()) });
    let stop_on_ground = sim.now;
    // Standing, the frames stop for 3 s: not flying, not said.
    sim.input(estimate(sim.now, -2.5, -2.5));
    sim.run_for(Duration::from_secs(3));
    sim.ap.armed = true;
    sim.ap.in_air = true;
    let mut t = secs(16);
    for _ in 0..30 {
        sim.run_until(t);
        sim.input(estimate(t, 1.0, 1.0));
        t = t + Duration::from_millis(66);
    }
    let last = t - Duration::from_millis(66);
    sim.run_for(Duration::from_secs(3));
    let said: Vec<(Mono, String)> = sim
        .sent
        .iter()
        .filter_map(|(at, m)| match m {
            MavMessage::STATUSTEXT(st) => {
                let text = String::from_utf8_lossy(&st.text[..]).trim_end_matches('\0').to_string();
                text.contains("camera frame").then_some((*at, text))
            }
            _ => None,
        })
        .collect();
    assert_eq!(said.len(), 1, "{said:?}");
    let whole = "no camera frame for 1.0 s in flight: the autopilot has no position from mavloc";
    assert!(warnings(&sim).contains(whole), "{}", warnings(&sim));
    let after = said[0].0.saturating_sub(last).as_secs_f64();
    assert!((1.0..1.1).contains(&after), "said {after} s after the last frame");
    assert!(said[0].0 > stop_on_ground + Duration::from_secs(3));
    // Frames again: said, with how long they were away.
    sim.input(estimate(sim.now, 1.5, 1.0));
    sim.run_for(Duration::from_millis(100));
    let texts = sim.statustexts();
    assert!(texts.iter().any(|t| t.contains("camera frames again after 3.0 s without")), "{texts:?}");
}

/// Without GPS, frames that stop in flight leave EKF2 without its height (vision is its
/// height reference): the floor's distance goes on at 5 Hz, with x and y where the
/// autopilot itself puts the vehicle, loose, and no velocity; once frames are back, the
/// pipeline's estimates alone. (Against PX4 SITL, without it the vehicle sank 0.36 m in a
/// 4 s gap and PX4's failsafe landed it.)
#[test]
fn without_gps_a_silent_camera_in_flight_has_the_height_held() {
    let mut sim = airborne_without_gps(indoor_without_gps_settings());
    let range = frame(
        1,
        1,
        MavMessage::DISTANCE_SENSOR(DISTANCE_SENSOR_DATA {
            current_distance: 100,
            min_distance: 1,
            max_distance: 10_000,
            orientation: MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270,
            ..Default::default()
        }),
    );
    // Flying at 1 m, the pipeline's estimates at 15 Hz, then none for 2 s, then again.
    let mut t = secs(14);
    while t < secs(19) {
        sim.run_until(t);
        sim.deliver(range.clone());
        let silent = (secs(16)..secs(18)).contains(&t);
        if !silent {
            sim.input(estimate(t, 2.0, 1.0));
        }
        t = t + Duration::from_millis(66);
    }
    let sent: Vec<(Mono, ODOMETRY_DATA)> = sim
        .sent
        .iter()
        .filter_map(|(at, m)| match m {
            MavMessage::ODOMETRY(o) => Some((*at, o.clone())),
            _ => None,
        })
        .collect();
    let held: Vec<&(Mono, ODOMETRY_DATA)> =
        sent.iter().filter(|(at, o)| *at >= secs(15) && o.pose_covariance[0] > 99.0).collect();
    // Every vision sample (the estimates go out as VISION_POSITION_ESTIMATE: no velocity).
    let samples: Vec<Mono> = sim
        .sent
        .iter()
        .filter(|(_, m)| matches!(m, MavMessage::ODOMETRY(_) | MavMessage::VISION_POSITION_ESTIMATE(_)))
        .map(|(at, _)| *at)
        .collect();
    let before = *samples.iter().rfind(|at| **at < secs(16)).unwrap();
    assert!(held.len() >= 8 && held.len() <= 10, "5 Hz over the 1.75 s left of the gap: {}", held.len());
    let first = held[0].0.saturating_sub(before).as_secs_f64();
    assert!((0.25..0.3).contains(&first), "held {first} s after the last estimate");
    for (at, o) in &held {
        assert!(*at < secs(18) + Duration::from_millis(70), "held after the frames came back");
        // The autopilot's own x and y (the fake's LOCAL_POSITION_NED), the floor 1 m below.
        assert_eq!((o.x, o.y, o.z), (0.0, 0.0, -1.0));
        assert!(o.vx.is_nan() && o.velocity_covariance[0].is_nan());
    }
    assert_eq!(sim.core.counters().held_estimates_sent, held.len() as u64);
    // Every gap between vision samples stays under EKF2's 0.4 s.
    let gaps = samples.windows(2).filter(|w| w[0] >= secs(15)).map(|w| w[1].saturating_sub(w[0]));
    assert!(gaps.max().unwrap() < Duration::from_millis(400));
}

#[test]
fn after_an_autopilot_reboot_the_origin_is_given_again() {
    let mut sim = Sim::new(gps_denied_settings());
    px4_without_gps(&mut sim);
    sim.run_until(secs(10));
    assert_eq!(origins_sent(&sim).len(), 1);
    sim.ap.reboot(sim.now);
    sim.run_until(secs(30));
    assert_eq!(origins_sent(&sim).len(), 2, "once per boot");
    assert_eq!(sim.core.gps_denied().origin_state(), gpsdenied::OriginState::Confirmed);
}

#[test]
fn a_precision_landing_streams_the_zone_until_the_vehicle_is_down() {
    let mut s = settings();
    s.indoor.landing_enabled = true;
    s.indoor.landing_x_m = 2.5;
    s.indoor.landing_y_m = 1.0;
    let mut sim = Sim::new(s);
    sim.ap = FakeAutopilot::new(Mono::ZERO);
    sim.ap.armed = true;
    sim.ap.in_air = true;
    sim.run_until(secs(3));
    sim.input(landing_report());
    sim.run_for(Duration::from_secs(3));
    assert_eq!(sim.ap.precision_commands, 1, "NAV_LAND_LOCAL (PX4: precision landing), acknowledged");
    let n = sim.ap.landing_targets.len();
    assert!((29..=32).contains(&n), "10 Hz: {n}");
    assert!(sim.ap.landing_targets.iter().all(|t| *t == (2.5, 1.0)));
    sim.ap.in_air = false;
    sim.run_for(Duration::from_secs(2));
    let n = sim.ap.landing_targets.len();
    sim.run_for(Duration::from_secs(2));
    assert_eq!(sim.ap.landing_targets.len(), n, "none once on the ground");
}

#[test]
fn a_take_off_px4_declares_while_its_rangefinder_still_reads_the_floor_keeps_the_vehicle_standing_then_the_climb_goes_out_loose(
) {
    // Measured on PX4 v1.16 SIH: in the air by its land detector 7 s before the
    // rangefinder left 0; localising the ground-level frames then dragged EKF2 away.
    let mut sim = airborne_without_gps(indoor_without_gps_settings());
    let range = |cm: u16| {
        frame(
            1,
            1,
            MavMessage::DISTANCE_SENSOR(DISTANCE_SENSOR_DATA {
                current_distance: cm,
                min_distance: 1,
                max_distance: 10_000,
                orientation: MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270,
                ..Default::default()
            }),
        )
    };
    for i in 0..20 {
        sim.run_until(secs(12) + Duration::from_millis(100 * i));
        sim.deliver(range(0));
    }
    sim.run_until(secs(14));
    assert!(
        sim.core.outside_heights() && sim.core.vision_paused(),
        "{:?} {:?}",
        sim.core.pipeline(),
        sim.core.height_above_floor()
    );
    let standing = vision(&sim, secs(13), secs(14));
    assert!(standing.len() >= 28, "still the pad while the camera is at the floor");
    assert!(standing.iter().all(|v| v.covariance[0] <= 0.05 * 0.05 + 1e-6), "the pad, to centimetres");
    assert_eq!(sim.core.gps_phase(), gpsdenied::Phase::Standing);
    // Climbing through 0.3 m: off the floor, too low to localise. Where it is now is
    // not known: x and y loose (EKF2 keeps its inertial track), z the rangefinder's.
    for i in 0..10 {
        sim.run_until(secs(14) + Duration::from_millis(100 * i));
        sim.deliver(range(30));
    }
    assert_eq!(sim.core.gps_phase(), gpsdenied::Phase::Blind);
    let blind = vision(&sim, secs(14) + Duration::from_millis(200), secs(15));
    assert!(blind.len() >= 20, "{}", blind.len());
    for v in &blind {
        let sd = gpsdenied::BLIND_SD_M as f32;
        assert_eq!((v.covariance[0], v.covariance[6]), (sd * sd, sd * sd));
        assert!(
            (v.z + 0.3).abs() < 0.01 && v.covariance[11] <= 0.01 + 1e-6,
            "z {} var {}",
            v.z,
            v.covariance[11]
        );
        assert!((v.x, v.y) == (standing[0].x, standing[0].y), "the same place, loosely");
    }
    // No velocity from the camera yet (the fake pipeline measures none): not claimed.
    let loose = velocities(&sim, secs(14) + Duration::from_millis(200), secs(15));
    assert!(loose.iter().all(|(_, var)| var.iter().all(|s| *s >= 1.0e4)), "{loose:?}");
    // The camera's velocity, fresh, goes out with the next of them, once.
    let climb = VelocityEstimate { body: [0.1, -0.2, -0.4], var: [0.0004, 0.0004, 0.09] };
    sim.core.handle(Input::Pipeline {
        now: sim.now,
        event: PipelineEvent::Report {
            capture: sim.now.secs(),
            attitude: (0.0, 0.0, 0.0),
            report: Report { velocity: Some(climb), ..Report::default() },
        },
    });
    let t = sim.now;
    sim.run_until(t + Duration::from_millis(100));
    let sent = velocities(&sim, t, t + Duration::from_millis(100));
    let measured: Vec<_> = sent.iter().filter(|(_, var)| var[0] < 1.0).collect();
    assert!(sent.len() >= 2, "{sent:?}");
    assert_eq!(measured.len(), 1, "{sent:?}");
    assert_eq!(measured[0].0, [0.1, -0.2, -0.4]);
    assert!(
        vision(&sim, t, t + Duration::from_millis(100)).iter().all(|v| v.covariance[0] >= 99.0),
        "loose still"
    );
    // Stale after 0.2 s: not claimed any more.
    sim.run_until(t + Duration::from_millis(400));
    let stale = velocities(&sim, t + Duration::from_millis(250), t + Duration::from_millis(400));
    assert!(!stale.is_empty() && stale.iter().all(|(_, var)| var[0] >= 1.0e4), "{stale:?}");
    // Where the particles, carried on that velocity, put the vehicle: not a measurement
    // (still loose), but where it stands if it touches down.
    let coasted = PositionEstimate {
        autopilot_time: 0.0,
        north: -2.2,
        east: -2.6,
        down: -0.3,
        cov: [[0.01, 0.0], [0.0, 0.01]],
    };
    sim.core.handle(Input::Pipeline {
        now: sim.now,
        event: PipelineEvent::Report {
            capture: sim.now.secs(),
            attitude: (0.0, 0.0, 0.0),
            report: Report { velocity: Some(climb), coasted: Some(coasted), ..Report::default() },
        },
    });
    let t = sim.now;
    sim.run_until(t + Duration::from_millis(100));
    let loose = vision(&sim, t, t + Duration::from_millis(100));
    assert!(!loose.is_empty() && loose.iter().all(|v| (v.x, v.y) == (-2.2, -2.6) && v.covariance[0] >= 99.0));
    for i in 0..31 {
        sim.run_until(secs(15) + Duration::from_millis(100 * i));
        sim.deliver(range(100));
    }
    assert!(!sim.core.vision_paused(), "1 m up: the pipeline's turn");
    // It says nothing here: in the air without GPS its silence has the height held, x and
    // y loose (a pipeline started in the air, or a camera gone, is silent the same way).
    let held = vision(&sim, secs(17), secs(18));
    assert!(
        sim.core.counters().held_estimates_sent > 0 && held.iter().all(|v| v.covariance[0] >= 99.0),
        "{held:?}"
    );
    // Down again and settled into SIH's ground: its rangefinder sends the negative
    // distance wrapped round to 655 m. That is the floor, not a missing reading (which
    // would fall back to the autopilot's height and localise the floor at arm's length).
    for i in 0..20 {
        sim.run_until(secs(18) + Duration::from_millis(100 * i));
        sim.deliver(range(65_506));
    }
    assert_eq!(sim.core.height_above_floor(), Some(0.0));
    assert!(sim.core.outside_heights() && sim.core.vision_paused());
    // Standing again where the particles last put it (no fix came after), tight.
    let t = sim.now;
    sim.run_until(t + Duration::from_millis(200));
    let down = vision(&sim, t, t + Duration::from_millis(200));
    assert!(
        !down.is_empty() && down.iter().all(|v| (v.x, v.y) == (-2.2, -2.6) && v.covariance[0] <= 0.0101),
        "{:?}",
        down.first()
    );
}

/// The area pipeline adjusts its map at each touchdown, once (`daemon::flightlog`): not
/// for the vehicle standing when mavloc starts, nor for each landed-state report on the
/// ground after; by the disarm when the autopilot never says its landed state; not at all
/// with `area.attitude_prior_deg` 0. What the pipeline says of its work outside a frame
/// goes to the ground as INFO.
#[test]
fn each_touchdown_adjusts_the_map_once_and_the_pipelines_notes_reach_the_ground() {
    let adjusted = |sim: &Sim| {
        sim.actions
            .iter()
            .filter(|(_, a)| *a == Action::Worker(WorkerRequest::AdjustMap("landed")))
            .map(|(t, _)| *t)
            .collect::<Vec<_>>()
    };
    // Two flights; the times of the requests.
    let fly = |says_landed_state: bool, prior: f64| {
        let mut s = Settings::default();
        s.daemon.pipeline = PipelineKind::Area;
        s.area.attitude_prior_deg = prior;
        let mut sim = Sim::new(s);
        sim.ap = FakeAutopilot::new(Mono::ZERO);
        sim.ap.says_landed_state = says_landed_state;
        sim.run_until(secs(10));
        assert_eq!(sim.core.pipeline(), PipelineState::Running(PipelineKind::Area));
        assert!(adjusted(&sim).is_empty(), "standing at the start is no touchdown");
        for (n, down) in [(0, 40), (1, 90)] {
            sim.ap.armed = true;
            sim.ap.in_air = true;
            sim.run_until(secs(down));
            let want = if prior > 0.0 { n } else { 0 };
            assert_eq!(
                adjusted(&sim).len(),
                want,
                "none in the air (landed state said: {says_landed_state})"
            );
            sim.ap.in_air = false;
            sim.ap.armed = false;
            sim.run_until(secs(down + 20));
        }
        (adjusted(&sim), sim)
    };
    for says in [true, false] {
        let (at, _) = fly(says, 1.5);
        assert_eq!(at.len(), 2, "two touchdowns (landed state said: {says}): {at:?}");
        assert!(at[0] >= secs(40) && at[0] < secs(42) && at[1] >= secs(90) && at[1] < secs(92), "{at:?}");
    }
    let (at, mut sim) = fly(true, 0.0);
    assert!(at.is_empty(), "off: {at:?}");

    let line = "area: map adjusted in 70 s";
    sim.input(Input::Pipeline { now: sim.now, event: PipelineEvent::Note(line.into()) });
    sim.run_for(Duration::from_secs(1));
    let said = sim.sent.iter().any(|(_, m)| {
        matches!(m, MavMessage::STATUSTEXT(t) if t.severity == MavSeverity::MAV_SEVERITY_INFO
            && String::from_utf8_lossy(&t.text[..]).contains(line))
    });
    assert!(said, "{:?}", sim.statustexts());
}

/// `MAV_CMD_USER_1` with param2 = 3 asks for the adjustment now: accepted with the area
/// pipeline running and a prior set, denied with no prior (and why), temporarily
/// rejected with the pipeline stopped.
#[test]
fn the_map_is_adjusted_on_command_when_it_can_be() {
    let ask = |prior: f64, pipeline: PipelineKind| {
        let mut s = Settings::default();
        s.daemon.pipeline = pipeline;
        s.area.attitude_prior_deg = prior;
        let mut sim = Sim::new(s);
        sim.run_until(secs(1));
        sim.gcs_sends(pipeline_command(1.0, 3.0));
        sim.run_for(Duration::from_millis(100));
        let acks = acks_to_gcs(&sim);
        let asked = sim
            .actions
            .iter()
            .filter(|(_, a)| *a == Action::Worker(WorkerRequest::AdjustMap("asked to")))
            .count();
        (acks, asked, sim.statustexts().concat())
    };
    let (acks, asked, said) = ask(1.5, PipelineKind::Area);
    assert_eq!((acks, asked), (vec![MavResult::MAV_RESULT_ACCEPTED], 1));
    assert!(!said.contains("not adjusted"), "{said}");
    let (acks, asked, said) = ask(0.0, PipelineKind::Area);
    assert_eq!((acks, asked), (vec![MavResult::MAV_RESULT_DENIED], 0));
    assert!(said.contains("AREA_ADJ_PRIOR"), "{said}");
    let (acks, asked, _) = ask(1.5, PipelineKind::None);
    assert_eq!((acks, asked), (vec![MavResult::MAV_RESULT_TEMPORARILY_REJECTED], 0));
}

/// A stranger's commands are DENIED, but a flood of them is not reflected at its rate: at
/// most 5 answers a second to each stranger and 20 to all (every answer goes to every
/// peer, the autopilot's link included); each command is still counted as refused. The
/// ground station's own command is answered within the same second.
#[test]
fn a_strangers_command_flood_is_answered_a_bounded_number_of_times() {
    let mut sim = Sim::new(settings());
    sim.run_until(secs(1));
    let sent_before = sim.sent.len();
    // 2 s of 500 commands a second from 10 strangers in turn.
    for i in 0..1000u32 {
        sim.deliver(frame(42 + (i % 10) as u8, 1, pipeline_command(1.0, 0.0)));
        sim.run_for(Duration::from_millis(2));
    }
    sim.run_for(Duration::from_millis(100));
    let denied = sim.sent[sent_before..]
        .iter()
        .filter(|(_, m)| matches!(m, MavMessage::COMMAND_ACK(a) if a.result == MavResult::MAV_RESULT_DENIED))
        .count();
    assert!((2 * 20..=3 * 20).contains(&denied), "{denied} answers to 1000 commands over 2 s");
    assert_eq!(sim.core.counters().commands_refused, 1000);
    sim.gcs_sends(pipeline_command(0.0, 0.0));
    sim.run_for(Duration::from_millis(100));
    let last = sim.sent.iter().rev().find_map(|(_, m)| match m {
        MavMessage::COMMAND_ACK(a) => Some(a.target_system),
        _ => None,
    });
    assert_eq!(last, Some(255), "the ground station is answered");
}

/// A vehicle whose MAV_SYS_ID is 2 where mavloc expects 1, beside a ground station: after
/// ten seconds mavloc says which systems it hears and which setting to check, once; a
/// vehicle with the right id found within the wait is not doubted.
#[test]
fn no_autopilot_after_the_wait_is_said_once_with_the_systems_heard() {
    let mut sim = Sim::new(settings());
    let mut t = 0;
    while t < 40 {
        let hb = HEARTBEAT_DATA { autopilot: MavAutopilot::MAV_AUTOPILOT_PX4, ..Default::default() };
        sim.deliver(frame(2, 1, MavMessage::HEARTBEAT(hb)));
        sim.gcs_sends(MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()));
        t += 1;
        sim.run_until(secs(t));
    }
    assert!(!sim.core.autopilot_found());
    let said: Vec<String> = sim.statustexts().into_iter().filter(|t| t.contains("no autopilot")).collect();
    assert_eq!(said, ["mavloc: no autopilot: another system id heard"], "{:?}", sim.statustexts());
    let at = sim.sent.iter().find(|(_, m)| matches!(m, MavMessage::STATUSTEXT(s) if String::from_utf8_lossy(&s.text[..]).contains("no autopilot"))).unwrap().0;
    assert!(at >= secs(10) && at < secs(12), "said at {at:?}");

    // The right vehicle, 5 s after start: nothing to say.
    let mut sim = Sim::new(settings());
    sim.run_until(secs(5));
    sim.ap = FakeAutopilot::new(secs(5));
    sim.run_until(secs(60));
    assert!(sim.core.autopilot_found());
    assert!(!sim.statustexts().iter().any(|t| t.contains("no autopilot")), "{:?}", sim.statustexts());
}

/// PX4 maps the stamps of what mavloc sends onto its own clock with an offset it filters
/// from TIMESYNC (Timesync.cpp). Against PX4 v1.16 SIH, whose lockstep clock ran 1.2-2.5 %
/// slower than the wall clock, that offset drifted by 1.6 s in 95 s and the filter lagged
/// it by 40-78 ms in flight: EKF2 took each vision estimate for one made that much later.
/// mavloc answers the autopilot's TIMESYNC requests and stamps its estimates on the
/// autopilot's clock as it tracks it, so with a clock 2 % slow the offset PX4 observes
/// stays within the link's asymmetry of zero for minutes (hundreds of milliseconds off
/// before), and each estimate's stamp is the autopilot's time when it left; a request
/// that comes before mavloc knows that clock is not answered.
#[test]
fn timesync_answers_and_vision_stamps_are_on_an_autopilot_clock_that_runs_slow() {
    let mut sim = Sim::new(gps_denied_settings());
    px4_without_gps(&mut sim);
    sim.ap.clock_rate = 0.98;
    let request = |ts1: i64| {
        frame(
            1,
            1,
            MavMessage::TIMESYNC(TIMESYNC_DATA { tc1: 0, ts1, target_system: 1, target_component: 191 }),
        )
    };
    let answer = |sim: &Sim, from: Mono, ts1: i64| {
        sim.sent.iter().filter(|(at, _)| *at >= from).find_map(|(at, m)| match m {
            MavMessage::TIMESYNC(r) if r.tc1 != 0 && r.ts1 == ts1 => Some((*at, r.tc1)),
            _ => None,
        })
    };
    // Before anything from the autopilot has told mavloc its clock: no answer.
    sim.deliver(request(1));
    sim.run_for(sim.latency + Duration::from_millis(1));
    assert!(sim.core.aligner().clock.to_autopilot(sim.now.secs()).is_none());
    assert_eq!(answer(&sim, Mono::ZERO, 1), None, "answered before the clock was known");
    let (mut offsets_ms, mut stamp_errors_ms) = (Vec::new(), Vec::new());
    for t in (20..=180).step_by(20) {
        sim.run_until(secs(t));
        let (from, ts1) = (sim.now, sim.ap.boot_us(sim.now) as i64 * 1000);
        sim.deliver(request(ts1));
        sim.run_for(Duration::from_millis(100));
        let (at, tc1) = answer(&sim, from, ts1).expect("the request answered");
        // As PX4 computes it, the answer coming back a link latency after it left.
        let back = sim.ap.boot_us(at + sim.latency) as i64 * 1000;
        offsets_ms.push(((ts1 + back) / 2 - tc1) as f64 * 1e-6);
        let (left, usec) = sim
            .sent
            .iter()
            .filter(|(at, _)| *at >= from)
            .find_map(|(at, m)| match m {
                MavMessage::ODOMETRY(o) => Some((*at, o.time_usec)),
                _ => None,
            })
            .expect("standing estimates go out");
        stamp_errors_ms.push((usec as f64 - sim.ap.boot_us(left) as f64) * 1e-3);
    }
    // The fake autopilot answers mavloc's requests the moment they arrive and its answer
    // takes the link's latency back, 2 ms, all of the round trip on one leg: mavloc's
    // clock is off by half of it, 1 ms, which PX4 sees in both measures.
    assert_eq!(answer(&sim, Mono::ZERO, 1), None, "the early request was answered later");
    assert!(offsets_ms.iter().all(|o| o.abs() < 1.5), "the offset PX4 observes, ms: {offsets_ms:?}");
    assert!(
        stamp_errors_ms.iter().all(|e| e.abs() < 1.5),
        "stamps against the autopilot's clock, ms: {stamp_errors_ms:?}"
    );
}

/// Telemetry that is not a number (a NaN or infinite attitude, position or velocity: a
/// faulty estimator, or a peer sending as the autopilot) is refused and counted. Taken
/// in, it made every pose aligned near it NaN, and the landmarks or the indoor estimate
/// made from that pose with it.
#[test]
fn telemetry_that_is_not_a_number_is_refused_and_counted() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    let bad = [
        MavMessage::ATTITUDE(ATTITUDE_DATA { roll: f32::NAN, ..Default::default() }),
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            x: f32::NAN,
            z: -10.0,
            ..Default::default()
        }),
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA { z: f32::INFINITY, ..Default::default() }),
        MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            z: -10.0,
            vy: f32::NAN,
            ..Default::default()
        }),
    ];
    for _ in 0..10 {
        sim.run_for(Duration::from_millis(50));
        let ms = (sim.now.0 / 1000) as u32;
        for m in &bad {
            let mut m = m.clone();
            match &mut m {
                MavMessage::ATTITUDE(a) => a.time_boot_ms = ms,
                MavMessage::LOCAL_POSITION_NED(p) => p.time_boot_ms = ms,
                _ => {}
            }
            sim.deliver(frame(1, 1, m));
        }
        // Aligned where the refused messages were stamped, between good ones.
        let at = sim.now.secs();
        sim.run_for(Duration::from_millis(150));
        let pose = sim.core.telemetry().aligner.align(at, sim.now.secs()).expect("a pose");
        let v = pose.vehicle;
        let finite = v.position.iter().chain(v.velocity.iter()).all(|x| x.is_finite())
            && v.attitude.coords.iter().all(|x| x.is_finite());
        assert!(finite, "{v:?}");
    }
    assert_eq!(sim.core.telemetry().not_finite, 40);
    sim.run_for(Duration::from_secs(2));
    assert_eq!(sim.core.counters().telemetry_not_finite, 40);
}

/// HOME_POSITION gives the results' origin: home moved back by its local offset. A home
/// whose offset is not a number is refused and counted, and the last good one stands; it
/// had put every landmark at NaN degrees.
#[test]
fn a_home_whose_local_offset_is_not_a_number_is_refused() {
    let mut sim = autopilot_booted_with_mavloc_30_s_ago();
    let home = |x: f32| {
        MavMessage::HOME_POSITION(HOME_POSITION_DATA {
            latitude: 520_000_000,
            longitude: 43_700_000,
            altitude: 10_000,
            x,
            y: 20.0,
            z: 0.0,
            ..Default::default()
        })
    };
    sim.deliver(frame(1, 1, home(10.0)));
    sim.run_for(Duration::from_millis(50));
    let o = sim.core.origin().expect("an origin");
    // 10 m north and 20 m east of the origin is home: the origin is south-west of it.
    assert!(o.lat_deg < 52.0 && o.lon_deg < 4.37 && (o.lat_deg - 52.0).abs() < 1e-3, "{o:?}");
    for bad in [f32::NAN, f32::INFINITY] {
        sim.deliver(frame(1, 1, home(bad)));
        sim.run_for(Duration::from_millis(50));
        assert_eq!(sim.core.origin(), Some(o), "x = {bad}");
    }
    assert_eq!(sim.core.telemetry().not_finite, 2);
}

/// A payload of 32-bit words (MAVLink orders a payload's fields by size, so its floats
/// fall on them), each any bits, or NaN, an infinity or zero, which random bits would
/// make one time in 256.
fn payload() -> impl Strategy<Value = Vec<u8>> {
    let word = prop_oneof![
        4 => any::<u32>(),
        1 => Just(f32::NAN.to_bits()),
        1 => Just(f32::INFINITY.to_bits()),
        1 => Just(f32::NEG_INFINITY.to_bits()),
        1 => Just(0),
    ];
    proptest::collection::vec(word, 0..64).prop_map(|w| w.iter().flat_map(|x| x.to_le_bytes()).collect())
}

/// Message ids to draw from: those the core reads, then every other id of the dialect.
fn message_ids() -> (Vec<u32>, Vec<u32>) {
    use mavlink::Message;
    let read = [
        "HEARTBEAT",
        "ATTITUDE",
        "LOCAL_POSITION_NED",
        "GLOBAL_POSITION_INT",
        "HOME_POSITION",
        "TIMESYNC",
        "COMMAND_LONG",
        "COMMAND_INT",
        "COMMAND_ACK",
        "PARAM_SET",
        "PARAM_REQUEST_READ",
        "PARAM_REQUEST_LIST",
        "FILE_TRANSFER_PROTOCOL",
        "GIMBAL_DEVICE_ATTITUDE_STATUS",
        "GIMBAL_MANAGER_STATUS",
        "DISTANCE_SENSOR",
        "SYS_STATUS",
        "STATUSTEXT",
        "EVENT",
        "GPS_GLOBAL_ORIGIN",
        "EXTENDED_SYS_STATE",
        "HIL_STATE_QUATERNION",
    ];
    let read: Vec<u32> = read.iter().map(|n| MavMessage::message_id_from_name(n).expect(n)).collect();
    let all = (0..20_000).filter(|id| MavMessage::default_message_from_id(*id).is_some()).collect();
    (read, all)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

    /// Any message of the dialect with any content (random payload bytes parsed as its
    /// type: NaN and infinite floats, any ids, indices, names and enum values the crate
    /// accepts), as the autopilot or as the ground station: the core does not panic,
    /// takes no pose or origin that is not a number, and its heartbeat and watchdog go on.
    #[test]
    fn any_message_with_any_content_leaves_the_core_working(
        msgs in proptest::collection::vec((any::<bool>(), any::<prop::sample::Index>(), any::<bool>(), payload()), 1..150)
    ) {
        let (read, all) = message_ids();
        let mut sim = autopilot_booted_with_mavloc_30_s_ago();
        let mut delivered = 0;
        let mut telemetry_at = Vec::new();
        for (one_it_reads, i, from_autopilot, payload) in msgs {
            let ids = if one_it_reads { &read } else { &all };
            let id = ids[i.index(ids.len())];
            if let Ok(mut m) = <MavMessage as mavlink::Message>::parse(mavlink::MavlinkVersion::V2, id, &payload) {
                // Telemetry stamped now, so the aligner takes it in rather than refusing
                // a random stamp as from the future.
                let ms = (sim.now.0 / 1000) as u32;
                match &mut m {
                    MavMessage::ATTITUDE(a) => a.time_boot_ms = ms,
                    MavMessage::LOCAL_POSITION_NED(p) => p.time_boot_ms = ms,
                    _ => {}
                }
                if matches!(m, MavMessage::ATTITUDE(_) | MavMessage::LOCAL_POSITION_NED(_)) && from_autopilot {
                    telemetry_at.push(sim.now.secs());
                }
                let (sys, comp) = if from_autopilot { (1, 1) } else { (255, 190) };
                sim.deliver(frame(sys, comp, m));
                delivered += 1;
            }
            sim.run_for(Duration::from_millis(20));
        }
        // A random HOME_POSITION sets the results' origin: it must be a place.
        if let Some(o) = sim.core.origin() {
            prop_assert!(o.validate().is_ok(), "{:?}", o);
        }
        // Poses where the random telemetry was stamped, with the next good samples in.
        sim.run_for(Duration::from_millis(200));
        for t in telemetry_at.iter().filter(|t| **t > sim.now.secs() - 2.0) {
            for dt in [-0.01, 0.0, 0.01, 0.05] {
                if let Ok(pose) = sim.core.telemetry().aligner.align(t + dt, sim.now.secs()) {
                    let v = pose.vehicle;
                    let finite = v.position.iter().chain(v.velocity.iter()).all(|x| x.is_finite())
                        && v.attitude.coords.iter().all(|x| x.is_finite());
                    prop_assert!(finite, "{:?}", pose);
                }
            }
        }
        prop_assume!(delivered > 0);
        let quiet_from = sim.now;
        // The sim's watchdog interval is 10 s.
        sim.run_for(Duration::from_secs(11));
        let heartbeats =
            sim.sent_between(quiet_from, sim.now).filter(|m| matches!(m, MavMessage::HEARTBEAT(_))).count();
        prop_assert!(heartbeats >= 10, "{heartbeats} heartbeats in 11 s");
        let pings = sim.actions.iter().filter(|(t, a)| *t >= quiet_from && matches!(a, Action::Watchdog)).count();
        prop_assert!(pings >= 1, "no watchdog ping in 11 s");
    }
}
