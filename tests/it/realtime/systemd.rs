//! `mavloc run` under systemd's notify protocol, with a fake NOTIFY_SOCKET: READY comes
//! once the configuration and the state directory are usable, not when the link opens,
//! so an absent serial device does not get mavloc killed by the start timeout; the status
//! line carries the link's state and why no autopilot came.

use std::os::unix::net::UnixDatagram;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// `mavloc run` on link `mavlink` (no pipeline, no camera) with its notify socket, and
/// everything it has told systemd so far, a line a message.
struct Notified {
    child: Child,
    sock: UnixDatagram,
    said: String,
    start: Instant,
}

impl Notified {
    fn start(dir: &std::path::Path, mavlink: &str) -> Notified {
        let sock_path = dir.join("notify");
        let sock = UnixDatagram::bind(&sock_path).unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(200))).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_mavloc"))
            .args(["run", "--mavlink", mavlink])
            .args(["--set", &format!("daemon.state_dir={}", dir.join("state").display())])
            .args(["--set", "daemon.pipeline=none", "--set", "camera.source=none"])
            .env("NOTIFY_SOCKET", &sock_path)
            .env_remove("STATE_DIRECTORY")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        Notified { child, sock, said: String::new(), start: Instant::now() }
    }

    /// Reads what is told until `done` holds of it or `limit` has passed since the start.
    fn until(&mut self, limit: Duration, done: impl Fn(&str) -> bool) {
        while self.start.elapsed() < limit && !done(&self.said) {
            let mut buf = [0u8; 4096];
            if let Ok(n) = self.sock.recv(&mut buf) {
                self.said.push_str(String::from_utf8_lossy(&buf[..n]).trim_end());
                self.said.push('\n');
            }
        }
    }

    /// SIGTERM, then the exit status.
    fn stop(mut self) -> (std::process::ExitStatus, String) {
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        (self.child.wait().unwrap(), self.said)
    }
}

#[test]
fn ready_comes_before_the_link_with_an_absent_serial_device() {
    let dir = tempfile::tempdir().unwrap();
    let mut n = Notified::start(dir.path(), "serial:/dev/ttyNOPE-mavloc-test:921600");
    n.until(Duration::from_secs(10), |s| s.contains("READY=1"));
    let took = n.start.elapsed();
    // Then the link's state, as STATUS=.
    n.until(took + Duration::from_secs(3), |s| s.contains("STATUS=link down"));
    let (status, said) = n.stop();
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
    let port = std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut n = Notified::start(dir.path(), &format!("udpin:127.0.0.1:{port}"));
    let why = "no autopilot: nothing from it heard";
    n.until(Duration::from_secs(20), |s| s.contains(why));
    let took = n.start.elapsed();
    // status.json, rewritten every second, says it within the next report.
    let json = format!("\"autopilot_missing\": \"{why}\"");
    let mut status = String::new();
    while n.start.elapsed() < took + Duration::from_secs(3) && !status.contains(&json) {
        std::thread::sleep(Duration::from_millis(100));
        status = std::fs::read_to_string(dir.path().join("state/status.json")).unwrap_or_default();
    }
    // Two more seconds: the line is not told again.
    n.until(took + Duration::from_secs(5), |_| false);
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
    let found_by = n.start.elapsed() + Duration::from_secs(5);
    while n.start.elapsed() < found_by && !n.said.trim_end().ends_with(&plain) {
        ap.send_to(&frame, ("127.0.0.1", port)).unwrap();
        n.until(n.start.elapsed() + Duration::from_millis(300), |_| false);
    }
    let (exit, said) = n.stop();
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
