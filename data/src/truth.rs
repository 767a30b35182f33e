//! `truth.csv`: the true track of a simulated vehicle (`mavloc sim vehicle --truth-log`),
//! appended ten times a second while it flies, read by the demo and the closed-loop tests
//! to score what mavloc estimated live.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::table::{self, fixed, Row};

/// One sample of the true state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthRow {
    /// Vehicle time, seconds.
    #[serde(serialize_with = "fixed::dp3")]
    pub t: f64,
    /// Local NED position, metres.
    #[serde(serialize_with = "fixed::dp4")]
    pub north: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub east: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub down: f64,
    /// Attitude, radians.
    #[serde(serialize_with = "fixed::dp5")]
    pub roll: f64,
    #[serde(serialize_with = "fixed::dp5")]
    pub pitch: f64,
    #[serde(serialize_with = "fixed::dp5")]
    pub yaw: f64,
    /// Flight phase, as the simulator names it (`Mission`, `Landing`, `Landed`, ...).
    pub phase: String,
}

impl Row for TruthRow {
    const COLUMNS: &'static str = "t,north,east,down,roll,pitch,yaw,phase";
}

/// Reads a truth log, naming the line of any malformed row.
pub fn read_truth(path: &Path) -> Result<Vec<TruthRow>, String> {
    Ok(table::read(path)?)
}

/// Opens a truth log for writing (a new file with its header).
pub fn create(path: &Path) -> std::io::Result<table::Appender<TruthRow>> {
    table::Appender::create(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truth_log_round_trips_in_its_layout() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("truth.csv");
        let row = TruthRow {
            t: 0.1,
            north: 1.0,
            east: -2.0,
            down: -1.0,
            roll: 0.01,
            pitch: -0.02,
            yaw: 1.5,
            phase: "Mission".into(),
        };
        create(&p).unwrap().push(&row).unwrap();
        assert_eq!(
            std::fs::read_to_string(&p).unwrap(),
            "t,north,east,down,roll,pitch,yaw,phase\n0.100,1.0000,-2.0000,-1.0000,0.01000,-0.02000,1.50000,Mission\n"
        );
        assert_eq!(read_truth(&p).unwrap(), vec![row]);
    }
}
