//! `mavloc run` under systemd's notify protocol, with a fake NOTIFY_SOCKET: READY comes
//! once the configuration and the state directory are usable, not when the link opens,
//! so an absent serial device does not get mavloc killed by the start timeout.

use std::os::unix::net::UnixDatagram;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[test]
fn ready_comes_before_the_link_with_an_absent_serial_device() {
    let dir = tempfile::tempdir().unwrap();
    let sock_path = dir.path().join("notify");
    let sock = UnixDatagram::bind(&sock_path).unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .args(["run", "--mavlink", "serial:/dev/ttyNOPE-mavloc-test:921600"])
        .args(["--set", &format!("daemon.state_dir={}", dir.path().join("state").display())])
        .args(["--set", "daemon.pipeline=none", "--set", "camera.source=none"])
        .env("NOTIFY_SOCKET", &sock_path)
        .env_remove("STATE_DIRECTORY")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let mut said = String::new();
    while start.elapsed() < Duration::from_secs(10) && !said.contains("READY=1") {
        let mut buf = [0u8; 4096];
        if let Ok(n) = sock.recv(&mut buf) {
            said.push_str(&String::from_utf8_lossy(&buf[..n]));
            said.push('\n');
        }
    }
    let took = start.elapsed();
    // Then the link's state, as STATUS=.
    while start.elapsed() < took + Duration::from_secs(3) && !said.contains("STATUS=link down") {
        let mut buf = [0u8; 4096];
        if let Ok(n) = sock.recv(&mut buf) {
            said.push_str(&String::from_utf8_lossy(&buf[..n]));
            said.push('\n');
        }
    }
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let status = child.wait().unwrap();
    assert!(said.contains("READY=1"), "no READY within 10 s: {said:?}");
    assert!(took < Duration::from_secs(3), "READY took {took:?}");
    assert!(said.contains("STATUS=link down"), "the absent device is reported: {said:?}");
    assert!(said.contains("ttyNOPE"), "{said:?}");
    assert!(status.success(), "{status:?}");
}

/// With the link up and no autopilot, systemd's status line (what `systemctl status mavloc`
/// shows) says why after the wait, beside the link's state, and `status.json` says it too;
/// once the autopilot comes, the line is the link's state alone.
#[test]
fn the_status_line_says_why_no_autopilot_came() {
    let dir = tempfile::tempdir().unwrap();
    let sock_path = dir.path().join("notify");
    let sock = UnixDatagram::bind(&sock_path).unwrap();
    sock.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
    let port = std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let state = dir.path().join("state");
    let mut child = Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .args(["run", "--mavlink", &format!("udpin:127.0.0.1:{port}")])
        .args(["--set", &format!("daemon.state_dir={}", state.display())])
        .args(["--set", "daemon.pipeline=none", "--set", "camera.source=none"])
        .env("NOTIFY_SOCKET", &sock_path)
        .env_remove("STATE_DIRECTORY")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = Instant::now();
    let mut said = String::new();
    let why = "no autopilot: nothing from it heard";
    while start.elapsed() < Duration::from_secs(20) && !said.contains(why) {
        let mut buf = [0u8; 4096];
        if let Ok(n) = sock.recv(&mut buf) {
            said.push_str(&String::from_utf8_lossy(&buf[..n]));
            said.push('\n');
        }
    }
    let took = start.elapsed();
    // status.json, rewritten every second, says it within the next report.
    let json = format!("\"autopilot_missing\": \"{why}\"");
    let mut status = String::new();
    while start.elapsed() < took + Duration::from_secs(3) && !status.contains(&json) {
        std::thread::sleep(Duration::from_millis(100));
        status = std::fs::read_to_string(state.join("status.json")).unwrap_or_default();
    }
    // Two more seconds: the line is not told again.
    while start.elapsed() < took + Duration::from_secs(5) {
        let mut buf = [0u8; 4096];
        if let Ok(n) = sock.recv(&mut buf) {
            said.push_str(&String::from_utf8_lossy(&buf[..n]));
            said.push('\n');
        }
    }
    // The autopilot comes: the line goes back to the link's state alone.
    use mavlink::dialects::common::{MavAutopilot, MavMessage, HEARTBEAT_DATA};
    let ap = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
        ..Default::default()
    });
    let mut frame = Vec::new();
    mavlink::write_v2_msg(&mut frame, mavlink::MavHeader { system_id: 1, component_id: 1, sequence: 0 }, &hb)
        .unwrap();
    let plain = format!("STATUS=link up: listening on udp 127.0.0.1:{port}");
    let found_at = Instant::now();
    while found_at.elapsed() < Duration::from_secs(5) && !said.trim_end().ends_with(&plain) {
        ap.send_to(&frame, ("127.0.0.1", port)).unwrap();
        let mut buf = [0u8; 4096];
        if let Ok(n) = sock.recv(&mut buf) {
            said.push_str(&String::from_utf8_lossy(&buf[..n]));
            said.push('\n');
        }
    }
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let exit = child.wait().unwrap();
    let line =
        said.lines().find(|l| l.contains(why)).unwrap_or_else(|| panic!("not said within 20 s: {said:?}"));
    assert_eq!(line, format!("STATUS=link up: listening on udp 127.0.0.1:{port}; {why}"));
    assert!(took >= Duration::from_secs(10), "said after {took:?}, before the wait was over");
    assert!(status.contains(&json), "{status}");
    assert_eq!(said.matches(why).count(), 1, "told once: {said:?}");
    assert!(
        said.trim_end().ends_with(&plain),
        "the autopilot found, the diagnosis leaves the line: {said:?}"
    );
    assert!(exit.success(), "{exit:?}");
}
