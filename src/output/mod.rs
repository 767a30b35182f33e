//! Result files. Their formats (CSV, PLY, GeoJSON and KML of area landmarks and border
//! lines, trajectories, landings) and the atomic writer live in the `mavloc-data` crate,
//! shared with the simulator and the tests; they are re-exported here for the daemon's
//! modules. Plots, which need a drawing library, are [`plot`].

pub mod plot;

pub use mavloc_data::atomic::write_atomic;
pub use mavloc_data::results::{
    area_geojson, area_kml, landmarks_csv, landmarks_ply, parse_landmarks_csv, LandmarkRecord,
};
