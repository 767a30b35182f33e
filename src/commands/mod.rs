//! The subcommands, one module each, following [`crate::cli::Command`]: each `run` takes
//! the parsed arguments and returns the process's exit code, so `main.rs` only parses and
//! dispatches, and a test may call a command in-process.
//!
//! Errors are returned, not printed: `main.rs` prints them and exits 1. A command that ran
//! to completion but whose result is a failure (the demo's FAIL) returns its own code.

pub mod area;
pub mod calibrate;
pub mod config;
pub mod demo;
pub mod eval;
pub mod import;
pub mod indoor;
pub mod params;
pub mod run;
pub mod sim;

use std::path::{Path, PathBuf};

use crate::settings::{self, Layers, Loaded};

/// How `config check` and `run` look inside what the settings name: the floor model, the
/// signing key and the state directory, each as the module that uses it would.
pub const FILE_CHECKS: settings::FileChecks<'static> = settings::FileChecks {
    model: &crate::indoor::model::Model::check_file,
    signing_key: &signing_key_usable,
    state_dir: &crate::daemon::state_dir,
    scenario: &crate::camera::sim::check_scenario,
};

fn signing_key_usable(p: &Path) -> Result<(), String> {
    // The link's messages name the key file, which the problem names already.
    let named = format!("signing key {}: ", p.display());
    crate::link::signing::load_key(p)
        .map(|_| ())
        .map_err(|e| e.strip_prefix(&named).unwrap_or(&e).to_string())
}

/// The options every subcommand accepts: `--config FILE` and `--set KEY=VALUE`.
#[derive(Clone, Debug, Default)]
pub struct Global {
    pub config: Option<PathBuf>,
    pub overrides: Vec<String>,
}

impl Global {
    /// The configuration file to use: the one given, else the system one if it exists.
    pub fn config_file(&self) -> Option<PathBuf> {
        self.config.clone().or_else(|| {
            Path::new(settings::SYSTEM_CONFIG).exists().then(|| PathBuf::from(settings::SYSTEM_CONFIG))
        })
    }

    /// The configuration from the usual file, the environment and `--set`.
    pub fn load(&self) -> anyhow::Result<Loaded> {
        load(self.config_file(), self.overrides.clone())
    }
}

/// An output file a command can write at `path` (`what` names it), checked before the
/// work that makes it, not after minutes of rendering.
pub(crate) fn writable_file(path: &std::path::Path, what: &str) -> anyhow::Result<()> {
    if path.is_dir() {
        anyhow::bail!("--out {} is a folder: give the {what}'s file name", path.display());
    }
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty() && !p.is_dir()) {
        anyhow::bail!("--out {}: the folder {} does not exist", path.display(), parent.display());
    }
    Ok(())
}

/// Ctrl-C sets the returned flag: the command stops after the frame or photo in hand (an
/// area run puts its results so far in place; an import or a render removes its staging
/// folder and leaves `--out` as it was) and returns [`STOPPED_BY_CTRL_C`]. A second Ctrl-C
/// ends the process at once, leaving the staging folder to the next run into the same
/// `--out`, which removes it (or keeps an area or indoor run's checkpoint in it as
/// `NAME.interrupted-PID`). A process started with SIGINT ignored (a background job of a
/// script) keeps ignoring it: the flag is never set.
pub(crate) fn stop_on_ctrl_c() -> anyhow::Result<std::sync::Arc<std::sync::atomic::AtomicBool>> {
    use std::sync::atomic::{AtomicBool, Ordering};
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    // SAFETY: reads the current action only (a null new action changes nothing).
    let ignored = unsafe {
        let mut old: libc::sigaction = std::mem::zeroed();
        libc::sigaction(libc::SIGINT, std::ptr::null(), &mut old) == 0 && old.sa_sigaction == libc::SIG_IGN
    };
    if ignored {
        return Ok(stop);
    }
    let flag = stop.clone();
    // SAFETY: the action only swaps an atomic and ends the process by signal(2),
    // sigprocmask(2), raise(3) and _exit(2), all async-signal-safe.
    unsafe {
        signal_hook_registry::register(libc::SIGINT, move || {
            if flag.swap(true, Ordering::SeqCst) {
                die_by_sigint();
            }
        })
    }
    .map_err(|e| anyhow::anyhow!("cannot handle Ctrl-C: {e}"))?;
    Ok(stop)
}

/// The exit code a command returns when Ctrl-C stopped it: `main` then ends the process by
/// SIGINT itself ([`die_by_sigint`]), after the command has put its files in place.
pub const STOPPED_BY_CTRL_C: u8 = 130;

/// Ends the process as killed by SIGINT, with SIGINT's default action: what a shell expects
/// of a program that Ctrl-C stopped. A shell that sees an exit code (130) instead takes the
/// interrupt as handled by the program and goes on with the script (the next command of a
/// loop over datasets); killed by SIGINT, the script stops too. Safe in a signal handler.
pub fn die_by_sigint() -> ! {
    // SAFETY: plain system calls on this process's own signal state; each is
    // async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, libc::SIG_DFL);
        // Inside the handler SIGINT is blocked: unblocked, the raised one is delivered now.
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigprocmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut());
        libc::raise(libc::SIGINT);
        libc::_exit(130)
    }
}

/// Whether Ctrl-C has set `stop`.
pub(crate) fn stopped(stop: &std::sync::atomic::AtomicBool) -> bool {
    stop.load(std::sync::atomic::Ordering::SeqCst)
}

/// Says that a command writing the folder `out` whole was stopped by Ctrl-C (`why`, its
/// error) before it put anything in place, and gives the shell's exit code for SIGINT.
pub(crate) fn stopped_with_nothing_written(out: &Path, why: &str) -> std::process::ExitCode {
    let state = if out.exists() { "left as it was" } else { "not made" };
    eprintln!("mavloc: {why}; nothing written, {} {state}", out.display());
    std::process::ExitCode::from(STOPPED_BY_CTRL_C)
}

/// Says that `command`, stopped by Ctrl-C after `frames` frames, put their results in
/// `written_to` (`out` itself, or beside complete results kept in `out`), and gives
/// [`STOPPED_BY_CTRL_C`].
pub(crate) fn stopped_with_results(
    command: &str,
    frames: usize,
    written_to: &Path,
    out: &Path,
) -> std::process::ExitCode {
    let beside = if written_to != out {
        format!(", beside the complete results {} kept", out.display())
    } else {
        String::new()
    };
    eprintln!(
        "mavloc {command}: stopped by Ctrl-C after {frames} frames; their results are in {} (summary.json: \"complete\": false){beside}",
        written_to.display()
    );
    std::process::ExitCode::from(STOPPED_BY_CTRL_C)
}

fn load(file: Option<PathBuf>, overrides: Vec<String>) -> anyhow::Result<Loaded> {
    Ok(settings::load(&Layers::from_process(file, overrides))?)
}

/// The plain progress line: `done` of `total`, and once the count has moved since the
/// first report (`done_first`, `since_first` seconds ago) the rate and the time left.
fn progress_line(what: &str, unit: &str, done: u64, total: u64, since_first: f64, done_first: u64) -> String {
    let pct = 100.0 * done as f64 / total.max(1) as f64;
    let mut line = format!("mavloc: {what}: {done}/{total} {unit} ({pct:.0} %)");
    if done > done_first && since_first > 0.0 {
        let rate = (done - done_first) as f64 / since_first;
        line += &format!(", {rate:.1} {unit}/s");
        if done < total {
            line += &format!(", about {:.0} s left", (total - done) as f64 / rate);
        }
    }
    line
}

/// Progress of a command that works through items (frames, views, trials): a bar on a
/// terminal; otherwise a plain line at the first item, every [`PROGRESS_EVERY`] and at the
/// end, so a long render under a pipe, a log file or CI is not minutes of silence.
pub(crate) struct Progress {
    bar: indicatif::ProgressBar,
    what: String,
    unit: &'static str,
    terminal: bool,
    /// When the first report came, and how far it said: rates count from there, so work
    /// done before the items start (a photo survey's alignment before its first frame)
    /// does not pass for a slow first item.
    first: std::sync::OnceLock<(std::time::Instant, u64)>,
    /// When the last line was written, and how far it said.
    last: std::sync::Mutex<Option<(std::time::Instant, u64, u64)>>,
}

/// How often a progress line is written when stderr is not a terminal.
const PROGRESS_EVERY: std::time::Duration = std::time::Duration::from_secs(10);

impl Progress {
    pub(crate) fn new(what: &str, unit: &'static str) -> Progress {
        let terminal = crate::logging::stderr_is_terminal();
        let bar = indicatif::ProgressBar::with_draw_target(Some(0), crate::logging::progress_target());
        bar.set_style(
            indicatif::ProgressStyle::with_template(&format!(
                "{{msg}} [{{bar:40}}] {{pos}}/{{len}} {unit}, {{per_sec}}, eta {{eta}}"
            ))
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_message(what.to_string());
        Progress {
            bar,
            what: what.to_string(),
            unit,
            terminal,
            first: std::sync::OnceLock::new(),
            last: std::sync::Mutex::new(None),
        }
    }

    /// `done` of `total` items finished (callable from worker threads).
    pub(crate) fn set(&self, done: u64, total: u64) {
        self.first.get_or_init(|| (std::time::Instant::now(), done));
        self.bar.set_length(total);
        self.bar.set_position(done);
        if self.terminal {
            return;
        }
        let mut last = self.last.lock().unwrap_or_else(|e| e.into_inner());
        let due = match *last {
            None => done > 0,
            Some((at, _, _)) => at.elapsed() >= PROGRESS_EVERY,
        };
        if due {
            *last = Some((std::time::Instant::now(), done, total));
            self.line(done, total);
        }
    }

    fn line(&self, done: u64, total: u64) {
        use std::io::Write;
        let (since, done_first) = match self.first.get() {
            Some((at, d)) => (at.elapsed().as_secs_f64(), *d),
            None => (0.0, done),
        };
        let _ = writeln!(
            crate::logging::stderr(),
            "{}",
            progress_line(&self.what, self.unit, done, total, since, done_first)
        );
    }

    /// Clears the bar; off a terminal, says where it ended if that was not said yet.
    pub(crate) fn finish(self) {
        // Read before `finish_and_clear`, which moves the position to the end: a run
        // stopped at 88 of 240 frames said "240/240 (100 %)".
        let (done, total) = (self.bar.position(), self.bar.length().unwrap_or(0));
        self.bar.finish_and_clear();
        if !self.terminal {
            let last = *self.last.lock().unwrap_or_else(|e| e.into_inner());
            if last.is_none_or(|(_, d, t)| (d, t) != (done, total)) && total > 0 {
                self.line(done, total);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::progress_line;

    /// `config check` refuses what `run` would refuse about the signing key and the state
    /// directory (it used to pass a key that was not hexadecimal, a key others could read
    /// and a state directory under a file, and `run` then exited 78 on each), with
    /// mavloc's own checks, naming the key.
    #[test]
    fn check_refuses_a_simulated_cameras_scenario_that_does_not_load() {
        // It passed, and `run` then idled with its camera failed (outside audit).
        let check = |name: &str| {
            let layers = crate::settings::Layers {
                overrides: vec!["camera.source=sim".into(), format!("camera.scenario={name}")],
                ..crate::settings::Layers::default()
            };
            crate::settings::check(&layers, &super::FILE_CHECKS).err().map(|e| e.to_string())
        };
        let said = check("nowhere").expect("refused");
        assert!(said.contains("camera.scenario") && said.contains("nowhere"), "{said}");
        assert_eq!(check("indoor-floor"), None);
    }

    #[test]
    fn check_refuses_the_signing_key_and_state_directory_that_run_refuses() {
        use crate::settings::{self, Layers, SettingsError};
        use std::os::unix::fs::PermissionsExt;
        use std::path::Path;
        let dir = tempfile::tempdir().unwrap();
        let key = |name: &str, text: &str, mode: u32| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
            p
        };
        let hex = "0123456789abcdef".repeat(4);
        let good = key("good.key", &hex, 0o600);
        let not_hex = key("nothex.key", "nothex\n", 0o600);
        let readable = key("readable.key", &hex, 0o644);
        std::fs::write(dir.path().join("a-file"), "").unwrap();
        let state = dir.path().join("state/made/by/run");
        let check_with = |key: &Path, state: &Path| -> Vec<(String, String)> {
            let layers = Layers {
                overrides: vec![
                    format!("mavlink.signing_key={}", key.display()),
                    format!("daemon.state_dir={}", state.display()),
                ],
                ..Layers::default()
            };
            match settings::check(&layers, &super::FILE_CHECKS) {
                Ok(_) => Vec::new(),
                Err(SettingsError::Invalid(p)) => p.into_iter().map(|p| (p.key, p.expected)).collect(),
                Err(e) => panic!("{e}"),
            }
        };
        assert_eq!(check_with(&good, &state), vec![], "a good key and a state directory run can make");
        assert!(!dir.path().join("state").exists(), "the check makes nothing");
        let p = check_with(&not_hex, &state);
        assert_eq!(p.len(), 1, "{p:?}");
        assert_eq!(p[0].0, "mavlink.signing_key");
        assert!(p[0].1.contains("expected 64 hexadecimal characters"), "{}", p[0].1);
        let p = check_with(&readable, &state);
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(p[0].1.contains("lets other users read it") && p[0].1.contains("chmod 600"), "{}", p[0].1);
        let p = check_with(&good, &dir.path().join("a-file/state"));
        assert_eq!(p.len(), 1, "{p:?}");
        assert_eq!(p[0].0, "daemon.state_dir");
        assert!(p[0].1.contains("a-file is not a directory"), "{}", p[0].1);
    }

    /// A photo survey reports its first frame only after aligning the photos (20 s on
    /// Seneca): counted from the command's start, the line said "about 561 s left" for a
    /// run that ended 46 s later. The rate counts from the first report instead.
    #[test]
    fn the_rate_and_time_left_count_from_the_first_report() {
        assert_eq!(progress_line("area", "frames", 1, 27, 0.0, 1), "mavloc: area: 1/27 frames (4 %)");
        assert_eq!(
            progress_line("area", "frames", 11, 27, 10.0, 1),
            "mavloc: area: 11/27 frames (41 %), 1.0 frames/s, about 16 s left"
        );
        assert_eq!(
            progress_line("area", "frames", 27, 27, 26.0, 1),
            "mavloc: area: 27/27 frames (100 %), 1.0 frames/s"
        );
        // A command that reports 0 before its first item counts from there.
        assert_eq!(
            progress_line("rendering coastline", "frames", 30, 60, 15.0, 0),
            "mavloc: rendering coastline: 30/60 frames (50 %), 2.0 frames/s, about 15 s left"
        );
    }
}
