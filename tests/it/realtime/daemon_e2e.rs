//! End-to-end tests of `mavloc run`: the real binary, driven over UDP loopback by
//! pymavlink (`tests/e2e/daemon.py`, installed by `make deps`). Bounded in time.

use std::os::unix::process::CommandExt;
use std::process::Command;
use std::time::{Duration, Instant};

/// Runs the named tests of `daemon.py`. The script's folders (each daemon's state, key
/// files) go under a temporary directory this test owns and removes, whatever the
/// script does; the script and the daemons it starts form one process group, killed as
/// a whole on timeout, so no daemon outlives its test.
fn run_python(tests: &[&str], limit: Duration) {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/e2e/daemon.py");
    let tmp = tempfile::tempdir().unwrap();
    let mut child = Command::new(crate::fixtures::python())
        .arg(script)
        .env("TMPDIR", tmp.path())
        .process_group(0)
        .arg(env!("CARGO_BIN_EXE_mavloc"))
        .args(tests)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .expect("python runs (make deps creates .venv with pymavlink)");
    let reader = crate::fixtures::read_in_background(child.stdout.take().unwrap());
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            let out = reader.join().unwrap();
            print!("{out}");
            assert!(status.success(), "end-to-end tests failed:\n{out}");
            return;
        }
        if start.elapsed() > limit {
            // The group's id is the script's pid (process_group(0) above).
            unsafe { libc::kill(-(child.id() as i32), libc::SIGKILL) };
            let _ = child.wait();
            panic!("end-to-end tests did not finish within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn link_parameters_commands_garbage_and_peer_loss() {
    run_python(&["test_link_params_commands_garbage_and_peer_loss"], Duration::from_secs(60));
}

/// The link over a serial device (a pseudo-terminal, as a UART or USB port to PX4 is a
/// terminal): raw both ways, and an unplugged device waited for and taken again.
#[test]
fn a_serial_link_is_raw_both_ways_and_survives_an_unplug() {
    run_python(&["test_serial_link_is_raw_both_ways_and_survives_an_unplug"], Duration::from_secs(90));
}

/// `tcpout` to a router's TCP server: refused at first (said), then connected, then the
/// server restarting and the link taken again.
#[test]
fn tcpout_reconnects_to_a_router_that_restarts() {
    run_python(&["test_tcpout_reconnects_to_a_router_that_restarts"], Duration::from_secs(60));
}

#[test]
fn signing_refuses_unsigned_and_wrongly_signed_sets() {
    run_python(&["test_signing"], Duration::from_secs(30));
}

#[test]
fn sigterm_exits_zero_quickly_with_complete_files() {
    run_python(&["test_sigterm_leaves_complete_results"], Duration::from_secs(30));
}

#[test]
fn hostile_peers_on_udpin_cannot_hijack_flood_or_poison() {
    run_python(&["test_hostile_peers_on_udpin"], Duration::from_secs(60));
}

#[test]
fn spoofed_autopilots_leave_room_for_the_ground_station() {
    run_python(&["test_spoofed_autopilots_leave_room_for_the_ground_station"], Duration::from_secs(40));
}

#[test]
fn a_signed_command_replayed_after_a_crash_is_refused() {
    run_python(&["test_signed_replay_after_a_crash_is_refused"], Duration::from_secs(40));
}

#[test]
fn tcpin_serves_a_reader_beside_a_client_that_never_reads() {
    run_python(&["test_tcpin_serves_a_reader_beside_a_client_that_never_reads"], Duration::from_secs(40));
}

#[test]
fn an_unusable_state_directory_exits_78_naming_it() {
    run_python(&["test_unusable_state_directory_exits_78_naming_it"], Duration::from_secs(30));
}

#[test]
fn corrupt_state_files_are_moved_aside_and_mavloc_starts() {
    run_python(&["test_corrupt_state_files_are_moved_aside"], Duration::from_secs(30));
}

#[test]
fn component_metadata_is_served_over_mavlink_ftp() {
    run_python(&["test_component_metadata_over_mavlink_ftp"], Duration::from_secs(60));
}

#[test]
fn a_second_daemon_on_the_same_state_directory_is_refused() {
    run_python(&["test_a_second_daemon_on_the_same_state_directory_is_refused"], Duration::from_secs(40));
}
