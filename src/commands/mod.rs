//! The subcommands, one module each, following [`crate::cli::Command`]: each `run` takes
//! the parsed arguments and returns the process's exit code, so `main.rs` only parses and
//! dispatches, and a test may call a command in-process.
//!
//! Errors are returned, not printed: `main.rs` prints them and exits 1. A command that ran
//! to completion but whose result is a failure (the demo's FAIL) returns its own code.

pub mod area;
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

fn load(file: Option<PathBuf>, overrides: Vec<String>) -> anyhow::Result<Loaded> {
    Ok(settings::load(&Layers::from_process(file, overrides))?)
}

/// The progress bar of the commands that work through frames.
fn progress_bar(what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames, {per_sec}, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}
