//! `mavloc config check FILE` and `mavloc config show` (with the tuned-over-MAVLink layer).

use std::process::ExitCode;

use super::Global;
use crate::cli::ConfigCommand;
use crate::link::params::Tuned;
use crate::settings;

pub fn run(command: ConfigCommand, global: Global) -> anyhow::Result<ExitCode> {
    match command {
        ConfigCommand::Check { file } => {
            // FILE, else --config (or MAVLOC_CONFIG), else the system file: one file, named.
            // MAVLOC_CONFIG is a standing default (a shell profile, a unit's environment):
            // the file named on the command line wins over it; two files named on the
            // command line are refused.
            let from_env = global.config.as_ref().is_some_and(|c| {
                std::env::var_os("MAVLOC_CONFIG").is_some_and(|e| std::path::Path::new(&e) == c.as_path())
            });
            let file = match (file, &global.config) {
                (Some(f), Some(c)) if !from_env && !same_file(&f, c) => anyhow::bail!(
                    "two files to check: {} (the argument) and {} (--config); give one",
                    f.display(),
                    c.display()
                ),
                (Some(f), _) => f,
                (None, _) => match global.config_file() {
                    Some(f) => f,
                    None => {
                        use std::io::Write;
                        let _ = writeln!(
                            crate::logging::stderr(),
                            "mavloc: no configuration file: give one (`mavloc config check FILE`) or install {}",
                            settings::SYSTEM_CONFIG
                        );
                        // What `config check` promises for a configuration `run` cannot use.
                        return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
                    }
                },
            };
            let layers = settings::Layers::from_process(Some(file.clone()), global.overrides);
            let loaded = match settings::check(&layers, &crate::commands::FILE_CHECKS) {
                Ok(l) => l,
                Err(e) => {
                    use std::io::Write;
                    let _ = writeln!(crate::logging::stderr(), "mavloc: {e}");
                    // The code `run` exits with on the same configuration.
                    return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
                }
            };
            println!(
                "{}: valid ({} key{} set in the file or overridden)",
                file.display(),
                loaded.origins.len(),
                if loaded.origins.len() == 1 { "" } else { "s" }
            );
            if let Some(note) = serial_note(&loaded.settings.mavlink.connection) {
                println!("note: mavlink.connection: {note}");
            }
            if let Some(note) = camera_note(&loaded.settings) {
                println!("note: camera.device: {note}");
            }
            Ok(ExitCode::SUCCESS)
        }
        ConfigCommand::Show => {
            let mut loaded = match global.load() {
                Ok(l) => l,
                Err(e) => {
                    use std::io::Write;
                    let _ = writeln!(crate::logging::stderr(), "mavloc: {e:#}");
                    // As `config check` and `run` exit on the same configuration.
                    return Ok(ExitCode::from(crate::daemon::EXIT_UNUSABLE));
                }
            };
            let (path, tuned) = super::params::tuned_layer(&mut loaded);
            print!("{}", settings::render_effective(&loaded));
            for t in tuned {
                if let Tuned::Pinned { name, key, value } = t {
                    println!("# {name} = {value} is tuned in {} but --set {key} wins", path.display());
                }
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// What `run` would meet on its serial device now. Not an error (the daemon waits for a
/// device that is not there yet, as a USB adapter plugged in after boot), but the first
/// fault of a new harness, which `config check` is run to find.
fn serial_note(connection: &str) -> Option<String> {
    use std::os::unix::fs::FileTypeExt;
    let Ok(settings::LinkAddress::Serial { device, .. }) = settings::LinkAddress::parse(connection) else {
        return None;
    };
    match std::fs::metadata(&device) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Some(format!("{device} does not exist now (unplugged? `mavloc run` waits for it)"))
        }
        Err(e) => Some(format!("{device}: {e}")),
        Ok(m) if !m.file_type().is_char_device() => Some(format!(
            "{device} is not a serial device (a character device such as /dev/ttyAMA0 or /dev/ttyACM0)"
        )),
        // access() says yes to root for any device: checked as root (`sudo mavloc config
        // check`, as the README says for the service), judge by what the service's dynamic
        // user, in the dialout group, will meet.
        Ok(m) if unsafe { libc::geteuid() } == 0 => service_note(&device, &m),
        Ok(_) => {
            let rw = rustix::fs::Access::READ_OK | rustix::fs::Access::WRITE_OK;
            rustix::fs::access(device.as_str(), rw).err().map(|_| {
                format!(
                    "{device} cannot be opened for reading and writing by this user (the dialout group? the \
                     systemd service has it)"
                )
            })
        }
    }
}

/// What `run` would meet on its V4L2 camera now: like a serial device, a camera not there
/// yet is waited for, so it is noted, not refused (a missing /dev/video0 passed unsaid).
fn camera_note(s: &settings::Settings) -> Option<String> {
    use std::os::unix::fs::FileTypeExt;
    if s.camera.source != settings::CameraSource::V4l2 || s.daemon.pipeline == settings::PipelineKind::None {
        return None;
    }
    let device = &s.camera.device;
    match std::fs::metadata(device) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            Some(format!("{device} does not exist now (unplugged? `mavloc run` retries it)"))
        }
        Err(e) => Some(format!("{device}: {e}")),
        Ok(m) if !m.file_type().is_char_device() => {
            Some(format!("{device} is not a video device (a character device such as /dev/video0)"))
        }
        Ok(_) => None,
    }
}

/// Whether the service (a dynamic user in the dialout group) can open `device`, from its
/// owner group and mode.
fn service_note(device: &str, m: &std::fs::Metadata) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let mode = m.mode() & 0o777;
    let group = group_name(m.gid());
    let open_to = |bits: u32| mode & bits == bits;
    if open_to(0o006) || (open_to(0o060) && group.as_deref() == Some("dialout")) {
        return None;
    }
    let group = group.unwrap_or_else(|| m.gid().to_string());
    Some(if group == "tty" {
        format!(
            "{device} belongs to the tty group (mode {mode:o}): a serial login console on the port? The service, in \
             the dialout group, cannot open it: turn the console off"
        )
    } else {
        format!(
            "{device} is not open to the dialout group (group {group}, mode {mode:o}): the service, a dynamic user \
             in that group, cannot open it"
        )
    })
}

/// The name of group `gid`, from the system's group database (`getgrgid_r`, which follows
/// NSS as `ls -l` does).
fn group_name(gid: u32) -> Option<String> {
    let mut buf = vec![0 as libc::c_char; 16 * 1024];
    // SAFETY: a zeroed `group` is valid to overwrite; `buf` outlives the call and the name
    // is copied out of it before it is dropped.
    unsafe {
        let mut group: libc::group = std::mem::zeroed();
        let mut found: *mut libc::group = std::ptr::null_mut();
        let r = libc::getgrgid_r(gid, &mut group, buf.as_mut_ptr(), buf.len(), &mut found);
        if r != 0 || found.is_null() {
            return None;
        }
        Some(std::ffi::CStr::from_ptr(group.gr_name).to_string_lossy().into_owned())
    }
}

/// Whether two paths name the same file (either may not exist).
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    a == b || matches!((a.canonicalize(), b.canonicalize()), (Ok(x), Ok(y)) if x == y)
}
