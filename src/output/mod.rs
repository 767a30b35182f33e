//! Result files: CSV, PLY, GeoJSON and KML of area landmarks and border lines.
//!
//! Every file is written to a temporary name in the same folder, synced and renamed over
//! the old one, so a crash or power cut at any moment leaves either the previous complete
//! file or the new complete file, never a torn one.

pub mod plot;

use std::fmt::Write as _;
use std::fs;
use std::io::Write;
use std::path::Path;

use crate::geometry::{LocalFrame, Vec3};

/// A converged landmark as the area pipeline reports it.
#[derive(Clone, Debug, PartialEq)]
pub struct LandmarkRecord {
    pub id: u64,
    /// Local NED, metres.
    pub position: Vec3,
    /// Largest standard deviation of the estimate (area seed eq. 5.21), metres.
    pub sigma_max_m: f64,
    pub observations: u32,
    pub first_frame: u64,
    pub last_frame: u64,
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    fs::rename(&tmp, path)?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        // Make the rename itself durable.
        if let Ok(d) = fs::File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(())
}

/// `landmarks.csv`: id, north, east, down, sigma_max_m, observations, first_frame, last_frame.
pub fn landmarks_csv(landmarks: &[LandmarkRecord]) -> String {
    let mut s = String::from("id,north,east,down,sigma_max_m,observations,first_frame,last_frame\n");
    for l in landmarks {
        let _ = writeln!(
            s,
            "{},{:.4},{:.4},{:.4},{:.4},{},{},{}",
            l.id,
            l.position.x,
            l.position.y,
            l.position.z,
            l.sigma_max_m,
            l.observations,
            l.first_frame,
            l.last_frame
        );
    }
    s
}

/// Parses `landmarks.csv`; errors name the line.
pub fn parse_landmarks_csv(text: &str, origin: &str) -> Result<Vec<LandmarkRecord>, String> {
    let mut out = Vec::new();
    let mut lines = text.lines();
    match lines.next() {
        Some(h) if h.starts_with("id,north,east,down") => {}
        _ => return Err(format!("{origin}: not a landmarks.csv (header id,north,east,down,... missing)")),
    }
    for (n, line) in lines.enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let bad = |what: &str| format!("{origin} line {}: {what}: {line}", n + 2);
        let c: Vec<&str> = line.split(',').collect();
        if c.len() != 8 {
            return Err(bad("expected 8 columns"));
        }
        let f = |i: usize| c[i].trim().parse::<f64>().map_err(|_| bad("not a number"));
        let u = |i: usize| c[i].trim().parse::<u64>().map_err(|_| bad("not an integer"));
        out.push(LandmarkRecord {
            id: u(0)?,
            position: Vec3::new(f(1)?, f(2)?, f(3)?),
            sigma_max_m: f(4)?,
            observations: u(5)? as u32,
            first_frame: u(6)?,
            last_frame: u(7)?,
        });
    }
    Ok(out)
}

/// `landmarks.ply`: ASCII PLY point cloud in local NED (x north, y east, z down).
pub fn landmarks_ply(landmarks: &[LandmarkRecord]) -> String {
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment mavloc area landmarks, local NED metres (x north, y east, z down)\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float sigma\nend_header\n",
        landmarks.len()
    );
    for l in landmarks {
        let _ =
            writeln!(s, "{:.4} {:.4} {:.4} {:.4}", l.position.x, l.position.y, l.position.z, l.sigma_max_m);
    }
    s
}

/// `area.geojson`: landmarks as points and border lines as line strings, in WGS84.
pub fn area_geojson(frame: &LocalFrame, landmarks: &[LandmarkRecord], borders: &[Vec<Vec3>]) -> String {
    use geojson::{Feature, FeatureCollection, Geometry, JsonObject};
    let mut features = Vec::new();
    for l in landmarks {
        let g = frame.to_geodetic(&l.position);
        let mut props = JsonObject::new();
        props.insert("kind".into(), "landmark".into());
        props.insert("id".into(), l.id.into());
        props.insert("sigma_max_m".into(), l.sigma_max_m.into());
        props.insert("observations".into(), l.observations.into());
        features.push(Feature {
            bbox: None,
            geometry: Some(Geometry::new_point([g.lon_deg, g.lat_deg, g.alt_m])),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    for (i, line) in borders.iter().enumerate() {
        let coords: Vec<[f64; 3]> = line
            .iter()
            .map(|p| {
                let g = frame.to_geodetic(p);
                [g.lon_deg, g.lat_deg, g.alt_m]
            })
            .collect();
        let mut props = JsonObject::new();
        props.insert("kind".into(), "border".into());
        props.insert("index".into(), i.into());
        features.push(Feature {
            bbox: None,
            geometry: Some(Geometry::new_line_string(coords)),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    geojson::GeoJson::from(FeatureCollection { bbox: None, features, foreign_members: None }).to_string()
}

/// `area.kml`: the same for QGroundControl (Plan view: File > Import KML) and Google Earth.
/// Written by hand: KML is a few fixed elements, and a crate would add a dependency tree
/// for nothing QGC needs. KML's absolute altitudes are above mean sea level, mavloc's are
/// WGS84 ellipsoid heights (tens of metres apart, and no geoid model is at hand), so the
/// geometry is clamped to the ground for display and each landmark's ellipsoid height is in
/// its description; `area.geojson` carries the 3D coordinates (RFC 7946 uses the ellipsoid).
pub fn area_kml(
    frame: &LocalFrame,
    name: &str,
    landmarks: &[LandmarkRecord],
    borders: &[Vec<Vec3>],
) -> String {
    let esc = |s: &str| s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;");
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<kml xmlns=\"http://www.opengis.net/kml/2.2\">\n<Document>\n");
    let _ = writeln!(s, "<name>{}</name>", esc(name));
    s.push_str(
        "<Style id=\"border\"><LineStyle><color>ff0000ff</color><width>3</width></LineStyle></Style>\n\
         <Style id=\"landmark\"><IconStyle><scale>0.4</scale></IconStyle></Style>\n",
    );
    for (i, line) in borders.iter().enumerate() {
        let _ = write!(
            s,
            "<Placemark><name>border {i}</name><styleUrl>#border</styleUrl><LineString><altitudeMode>clampToGround</altitudeMode><coordinates>"
        );
        for p in line {
            let g = frame.to_geodetic(p);
            let _ = write!(s, "{:.8},{:.8},{:.3} ", g.lon_deg, g.lat_deg, g.alt_m);
        }
        s.push_str("</coordinates></LineString></Placemark>\n");
    }
    s.push_str("<Folder><name>landmarks</name>\n");
    for l in landmarks {
        let g = frame.to_geodetic(&l.position);
        let _ = writeln!(
            s,
            "<Placemark><name>{}</name><description>sigma {:.2} m, {} observations, ellipsoid height {:.2} m</description><styleUrl>#landmark</styleUrl>\
             <Point><altitudeMode>clampToGround</altitudeMode><coordinates>{:.8},{:.8},{:.3}</coordinates></Point></Placemark>",
            l.id, l.sigma_max_m, l.observations, g.alt_m, g.lon_deg, g.lat_deg, g.alt_m
        );
    }
    s.push_str("</Folder>\n</Document>\n</kml>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Geodetic;

    fn sample() -> Vec<LandmarkRecord> {
        vec![
            LandmarkRecord {
                id: 3,
                position: Vec3::new(10.5, -2.25, 0.75),
                sigma_max_m: 0.31,
                observations: 12,
                first_frame: 4,
                last_frame: 40,
            },
            LandmarkRecord {
                id: 9,
                position: Vec3::new(-1.0, 5.0, -3.0),
                sigma_max_m: 0.2,
                observations: 30,
                first_frame: 7,
                last_frame: 70,
            },
        ]
    }

    #[test]
    fn csv_round_trips() {
        let csv = landmarks_csv(&sample());
        assert_eq!(parse_landmarks_csv(&csv, "x").unwrap(), sample());
        let err = parse_landmarks_csv("id,north,east,down\n1,2,three,4,5,6,7,8\n", "f.csv").unwrap_err();
        assert!(err.contains("f.csv line 2"), "{err}");
    }

    #[test]
    fn geojson_and_kml_are_in_wgs84() {
        let frame = LocalFrame::new(Geodetic::new(57.0, 10.0, 20.0));
        let border = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0)]];
        let g: serde_json::Value = serde_json::from_str(&area_geojson(&frame, &sample(), &border)).unwrap();
        assert_eq!(g["features"].as_array().unwrap().len(), 3);
        let line = &g["features"][2]["geometry"]["coordinates"];
        assert!((line[1][1].as_f64().unwrap() - 57.0009).abs() < 1e-4, "100 m north");
        let kml = area_kml(&frame, "a <test>", &sample(), &border);
        assert!(kml.contains("<name>a &lt;test&gt;</name>"));
        assert!(kml.contains("<coordinates>10.00000000,57.00000000,20.000 "));
        assert_eq!(kml.matches("<Placemark>").count(), 3);
    }

    #[test]
    fn atomic_write_replaces_whole_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"two");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
    }
}
