//! PX4 v1.16 SITL's own traffic replayed through mavloc's decoder and core: the captured
//! GPS-denied flight in `../shared/data/px4-sitl` (every frame PX4 sent on its onboard
//! link, with its arrival time). What mavloc makes of a real PX4, not of our fake one:
//! its pre-arm verdict, its origin echo, its EVENTs, its landed states, its home resets,
//! its ground truth. Skipped, saying so, when the folder is absent.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::PathBuf;

use mavlink::dialects::common::*;
use mavloc::daemon::core::{gpsdenied::OriginState, Core, Input, Mono};
use mavloc::link::codec::Decoder;
use mavloc::settings::{CameraSource, PipelineKind, Settings, SimPose};

fn data_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("MAVLOC_PX4_SITL_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/px4-sitl"));
    dir.join("px4_sih_vision_only_flight_rx.tlog.gz").exists().then_some(dir)
}

/// A tlog: each record is the arrival time (µs since the epoch, big-endian) and one frame.
fn records(path: &std::path::Path) -> Vec<(u64, Vec<u8>)> {
    let mut gz = flate2::read::GzDecoder::new(std::fs::File::open(path).unwrap());
    let mut b = Vec::new();
    gz.read_to_end(&mut b).unwrap();
    let mut out = Vec::new();
    let mut i = 0;
    while i + 8 < b.len() {
        let t = u64::from_be_bytes(b[i..i + 8].try_into().unwrap());
        let f = &b[i + 8..];
        let len = match f[0] {
            0xFD => 12 + f[1] as usize + if f[2] & 1 != 0 { 13 } else { 0 },
            0xFE => 8 + f[1] as usize,
            other => panic!("not a MAVLink frame at byte {i}: {other:#x}"),
        };
        out.push((t, f[..len].to_vec()));
        i += 8 + len;
    }
    out
}

struct Replay {
    core: Core,
    sent: Vec<(f64, MavMessage)>,
    /// When (s) the core first held each pre-arm verdict.
    prearm: BTreeMap<bool, f64>,
    landed: Vec<(f64, MavLandedState)>,
    origin_echo: Option<f64>,
    events: usize,
    truth: usize,
}

fn replay() -> Option<Replay> {
    let Some(dir) = data_dir() else {
        eprintln!("px4_replay: skipped: ../shared/data/px4-sitl (or MAVLOC_PX4_SITL_DATA) is absent");
        return None;
    };
    let mut s = Settings::default();
    s.daemon.pipeline = PipelineKind::None;
    s.camera.source = CameraSource::Sim;
    s.camera.sim_pose = SimPose::Truth;
    s.indoor.gps_denied = true;
    // The capture's origin (its README).
    s.indoor.origin = vec![47.3977432, 8.5455942, 489.399];
    let mut r = Replay {
        core: Core::new(s, BTreeMap::new(), false, None),
        sent: Vec::new(),
        prearm: BTreeMap::new(),
        landed: Vec::new(),
        origin_echo: None,
        events: 0,
        truth: 0,
    };
    let recs = records(&dir.join("px4_sih_vision_only_flight_rx.tlog.gz"));
    let t0 = recs[0].0;
    let mut decoder = Decoder::new();
    for (t, bytes) in recs {
        let now = Mono(t - t0);
        let secs = now.secs();
        if r.core.poll_timeout().is_some_and(|d| d <= now) {
            r.core.handle_timeout(now);
        }
        decoder.push(&bytes);
        while let Some(frame) = decoder.next_frame(None) {
            match &frame.message {
                MavMessage::EXTENDED_SYS_STATE(e) if r.landed.last().map(|l| l.1) != Some(e.landed_state) => {
                    r.landed.push((secs, e.landed_state));
                }
                MavMessage::GPS_GLOBAL_ORIGIN(_) => r.origin_echo = r.origin_echo.or(Some(secs)),
                MavMessage::EVENT(_) => r.events += 1,
                MavMessage::HIL_STATE_QUATERNION(_) => r.truth += 1,
                _ => {}
            }
            r.core.handle(Input::Mav { rx: now, frame });
        }
        while let Some(o) = r.core.poll_transmit(now) {
            r.sent.push((secs, o.message));
        }
        while r.core.poll_action().is_some() {}
        if let Some(ok) = r.core.prearm_ok() {
            r.prearm.entry(ok).or_insert(secs);
        }
    }
    Some(r)
}

#[test]
fn a_real_px4_gps_denied_flight_reads_as_it_happened() {
    let Some(r) = replay() else { return };
    let c = r.core.counters();
    assert!(r.core.autopilot_found());
    // Home moves at arming, take-off and disarm; the clock never runs back: no reboot.
    assert_eq!((c.autopilot_reboots, c.reboot_claims_rejected, c.telemetry_from_the_future), (0, 0, 0));
    // PX4's pre-arm verdict: failing until ~4.5 s after the origin, then passing.
    let echo = r.origin_echo.expect("PX4 echoes the origin its peer gave");
    let (fail, pass) = (r.prearm[&false], r.prearm[&true]);
    assert!(fail < echo, "failing before the origin");
    let after = pass - echo;
    assert!((3.5..5.5).contains(&after), "pre-arm passed {after:.2} s after the origin");
    // The echo matches mavloc's configured origin: confirmed, not a foreign one.
    assert_eq!(r.core.gps_denied().origin_state(), OriginState::Confirmed);
    // Landed states as the flight went: on the ground, in the air, on the ground.
    let states: Vec<_> = r.landed.iter().map(|l| l.1).collect();
    assert_eq!(states.first(), Some(&MavLandedState::MAV_LANDED_STATE_ON_GROUND));
    assert!(states.contains(&MavLandedState::MAV_LANDED_STATE_IN_AIR));
    assert_eq!(states.last(), Some(&MavLandedState::MAV_LANDED_STATE_ON_GROUND));
    // Every EVENT counted; the truth read (HIL_STATE_QUATERNION, time_usec 0, w < 0).
    assert_eq!(c.autopilot_events as usize, r.events);
    assert!(r.events > 0 && r.truth > 2000);
    assert!(r.core.truth().is_some());
    // Home (HOME_POSITION) gives the local frame's origin: the capture's.
    let o = r.core.origin().expect("an origin from HOME_POSITION");
    assert!((o.lat_deg - 47.3977432).abs() < 2e-6 && (o.lon_deg - 8.5455942).abs() < 3e-6, "{o:?}");
}

#[test]
fn against_a_real_px4_mavloc_stands_the_vehicle_on_its_pad_only_while_it_stands() {
    let Some(r) = replay() else { return };
    let in_air = |t: f64| {
        r.landed
            .iter()
            .rev()
            .find(|l| l.0 <= t)
            .is_some_and(|l| l.1 != MavLandedState::MAV_LANDED_STATE_ON_GROUND)
    };
    let vpe: Vec<f64> = r
        .sent
        .iter()
        .filter(|(_, m)| match m {
            MavMessage::VISION_POSITION_ESTIMATE(_) => true,
            MavMessage::ODOMETRY(o) => o.x.is_finite(),
            _ => false,
        })
        .map(|(t, _)| *t)
        .collect();
    assert!(!vpe.is_empty());
    assert!(vpe.iter().all(|t| !in_air(*t)), "no standing estimate while PX4 says airborne");
    // From PX4's first heartbeat on, at ~30 Hz, until take-off (PX4 says TAKEOFF, then
    // IN_AIR).
    let take_off = r.landed.iter().find(|l| l.1 != MavLandedState::MAV_LANDED_STATE_ON_GROUND).unwrap().0;
    let before = vpe.iter().filter(|t| **t < take_off).count() as f64;
    let first = vpe[0];
    let rate = before / (take_off - first);
    assert!((25.0..=31.0).contains(&rate), "{rate:.1} Hz before take-off");
    // The origin went out once, about 5 s after the first estimate.
    #[allow(deprecated)]
    let origins: Vec<f64> = r
        .sent
        .iter()
        .filter(|(_, m)| matches!(m, MavMessage::SET_GPS_GLOBAL_ORIGIN(_)))
        .map(|(t, _)| *t)
        .collect();
    assert!(!origins.is_empty() && origins.len() <= 3, "{origins:?}");
    assert!(
        (origins[0] - first - 5.0).abs() < 0.2,
        "origin {:.2} s after the first estimate",
        origins[0] - first
    );
}
