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
