//! End-to-end tests of `mavloc run`: the real binary, driven over UDP loopback by
//! pymavlink (`tests/e2e/daemon.py`, installed by `make deps`). Bounded in time.

use std::process::Command;
use std::time::{Duration, Instant};

fn run_python(tests: &[&str], limit: Duration) {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/e2e/daemon.py");
    let mut child = Command::new("python3")
        .arg(script)
        .arg(env!("CARGO_BIN_EXE_mavloc"))
        .args(tests)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .expect("python3 runs (make deps installs pymavlink)");
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let mut out = String::new();
            std::io::Read::read_to_string(child.stdout.as_mut().unwrap(), &mut out).unwrap();
            print!("{out}");
            assert!(status.success(), "end-to-end tests failed:\n{out}");
            return;
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("end-to-end tests did not finish within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn link_parameters_commands_garbage_and_peer_loss() {
    run_python(&["test_link_params_commands_garbage_and_peer_loss"], Duration::from_secs(60));
}

#[test]
fn signing_refuses_unsigned_and_wrongly_signed_sets() {
    run_python(&["test_signing"], Duration::from_secs(30));
}

#[test]
fn sigterm_exits_zero_quickly_with_complete_files() {
    run_python(&["test_sigterm_leaves_complete_results"], Duration::from_secs(30));
}
