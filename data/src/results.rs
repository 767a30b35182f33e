//! Result files of the pipelines, as plain data: area landmarks (CSV, PLY, GeoJSON, KML),
//! border lines (CSV), indoor trajectories and landing trials (CSV). Writing them to disk is
//! [`crate::write_atomic`]'s job (or a [`crate::table::Appender`] for live, growing
//! tables); plots stay with the pipelines.

use std::fmt::Write as _;
use std::path::Path;

use mavloc_geometry::{LocalFrame, Vec3};
use serde::{Deserialize, Serialize};

use crate::table::{self, fixed, Columns, Header, Row};

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

/// A row of `landmarks.csv`.
#[derive(Serialize, Deserialize)]
struct LandmarkRow {
    id: u64,
    #[serde(serialize_with = "fixed::dp4")]
    north: f64,
    #[serde(serialize_with = "fixed::dp4")]
    east: f64,
    #[serde(serialize_with = "fixed::dp4")]
    down: f64,
    #[serde(serialize_with = "fixed::nan_empty_dp4", deserialize_with = "fixed::de_nan_empty")]
    sigma_max_m: f64,
    observations: u32,
    first_frame: u64,
    last_frame: u64,
}

impl Row for LandmarkRow {
    const COLUMNS: &'static str = "id,north,east,down,sigma_max_m,observations,first_frame,last_frame";
}

/// `landmarks.csv`: id, north, east, down, sigma_max_m, observations, first_frame, last_frame.
pub fn landmarks_csv(landmarks: &[LandmarkRecord]) -> String {
    let rows: Vec<LandmarkRow> = landmarks
        .iter()
        .map(|l| LandmarkRow {
            id: l.id,
            north: l.position.x,
            east: l.position.y,
            down: l.position.z,
            sigma_max_m: l.sigma_max_m,
            observations: l.observations,
            first_frame: l.first_frame,
            last_frame: l.last_frame,
        })
        .collect();
    table::to_string(&rows)
}

/// Parses `landmarks.csv`; errors name the line.
pub fn parse_landmarks_csv(text: &str, origin: &str) -> Result<Vec<LandmarkRecord>, String> {
    let rows: Vec<LandmarkRow> =
        table::parse_with(text, origin, Header::StartsWith("id,north,east,down"), Columns::Exact)?;
    Ok(rows
        .into_iter()
        .map(|r| LandmarkRecord {
            id: r.id,
            position: Vec3::new(r.north, r.east, r.down),
            sigma_max_m: r.sigma_max_m,
            observations: r.observations,
            first_frame: r.first_frame,
            last_frame: r.last_frame,
        })
        .collect())
}

/// A point of `border.csv`.
#[derive(Serialize, Deserialize)]
struct BorderRow {
    line: usize,
    index: usize,
    #[serde(serialize_with = "fixed::dp4")]
    north: f64,
    #[serde(serialize_with = "fixed::dp4")]
    east: f64,
    #[serde(serialize_with = "fixed::dp4")]
    down: f64,
}

impl Row for BorderRow {
    const COLUMNS: &'static str = "line,index,north,east,down";
}

/// `border.csv`: the fitted border polylines, local NED.
pub fn border_csv(lines: &[Vec<Vec3>]) -> String {
    let rows: Vec<BorderRow> = lines
        .iter()
        .enumerate()
        .flat_map(|(li, l)| {
            l.iter().enumerate().map(move |(i, p)| BorderRow {
                line: li,
                index: i,
                north: p.x,
                east: p.y,
                down: p.z,
            })
        })
        .collect();
    table::to_string(&rows)
}

/// Reads `border.csv` back. Lenient, as the border is an optional extra of a result: rows
/// that do not parse are skipped, and text that is no border table gives no lines.
pub fn parse_border_csv(text: &str) -> Vec<Vec<Vec3>> {
    let rows: Vec<BorderRow> = table::parse_lenient(text);
    let mut lines: Vec<Vec<Vec3>> = Vec::new();
    for r in rows {
        while lines.len() <= r.line {
            lines.push(Vec::new());
        }
        lines[r.line].push(Vec3::new(r.north, r.east, r.down));
    }
    lines
}

/// One row of `trajectory.csv` (`mavloc indoor run`, and the daemon's indoor pipeline).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrajectoryRow {
    pub frame: u64,
    #[serde(serialize_with = "fixed::dp4")]
    pub t: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub y: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub sigma_x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub sigma_y: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub true_x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub true_y: f64,
    /// 1 when the estimate is a position fix (the particles agree on one place), 0 while
    /// the filter still searches the floor. Files written before the column: every row 1.
    #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01", default = "yes")]
    pub fix: bool,
}

fn yes() -> bool {
    true
}

pub const TRAJECTORY_HEADER: &str = "frame,t,x,y,sigma_x,sigma_y,true_x,true_y,fix";
/// The columns of `trajectory.csv` before `fix` (still read).
const TRAJECTORY_HEADER_V1: &str = "frame,t,x,y,sigma_x,sigma_y,true_x,true_y";

impl Row for TrajectoryRow {
    const COLUMNS: &'static str = TRAJECTORY_HEADER;
}

/// `trajectory.csv` as text.
pub fn trajectory_csv(rows: &[TrajectoryRow]) -> String {
    table::to_string(rows)
}

/// Reads `trajectory.csv`, naming the line of any malformed row.
pub fn read_trajectory(path: &Path) -> Result<Vec<TrajectoryRow>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let origin = path.display().to_string();
    Ok(table::parse_with(
        &text,
        &origin,
        table::Header::StartsWith(TRAJECTORY_HEADER_V1),
        table::Columns::AtLeast(8),
    )?)
}

/// One simulated landing trial, a row of `landings.csv` (`mavloc indoor landings`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LandingRow {
    pub trial: usize,
    #[serde(serialize_with = "fixed::dp4")]
    pub zone_x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub zone_y: f64,
    #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01")]
    pub fired: bool,
    #[serde(serialize_with = "fixed::dp3")]
    pub t_fire: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub true_x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub true_y: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub est_x: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub est_y: f64,
    #[serde(serialize_with = "fixed::bool01", deserialize_with = "fixed::de_bool01")]
    pub inside: bool,
}

pub const LANDINGS_HEADER: &str = "trial,zone_x,zone_y,fired,t_fire,true_x,true_y,est_x,est_y,inside";

impl Row for LandingRow {
    const COLUMNS: &'static str = LANDINGS_HEADER;
}

/// `landings.csv` as text.
pub fn landings_csv(rows: &[LandingRow]) -> String {
    table::to_string(rows)
}

/// Reads `landings.csv`, naming the line of any malformed row.
pub fn read_landings(path: &Path) -> Result<Vec<LandingRow>, String> {
    Ok(table::read(path)?)
}

/// `landmarks.ply`: ASCII PLY point cloud in local NED (x north, y east, z down), its
/// origin stated in the header (a PLY has no coordinate reference of its own).
pub fn landmarks_ply(frame: &LocalFrame, landmarks: &[LandmarkRecord]) -> String {
    let o = frame.origin;
    let mut s = format!(
        "ply\nformat ascii 1.0\ncomment mavloc area landmarks, local NED metres (x north, y east, z down)\n\
         comment origin latitude {:.8} longitude {:.8} deg, {:.3} m above mean sea level ({:.3} m above the WGS84 ellipsoid, EGM96)\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float sigma\nend_header\n",
        o.lat_deg,
        o.lon_deg,
        o.alt_m,
        crate::geoid::ellipsoid_height_m(o.lat_deg, o.lon_deg, o.alt_m),
        landmarks.len()
    );
    for l in landmarks {
        let _ =
            writeln!(s, "{:.4} {:.4} {:.4} {:.4}", l.position.x, l.position.y, l.position.z, l.sigma_max_m);
    }
    s
}

/// Longitude, latitude and height above the WGS84 ellipsoid (RFC 7946's third
/// coordinate), and the height above mean sea level, of a local point.
/// Rounded to 1e-8 deg (1.1 mm) and 1 mm: RFC 7946 (sec. 11.2) asks for no more precision
/// than the data has, and full doubles (15 decimals) made the file a quarter larger for
/// MAVLink FTP over a telemetry radio.
pub(crate) fn wgs84(frame: &LocalFrame, p: &Vec3) -> ([f64; 3], f64) {
    let g = frame.to_geodetic(p);
    // Divided by the power of ten, not multiplied by its inverse: the nearest double to
    // the decimal, which serde_json then writes with no trailing digits.
    let round = |v: f64, per_unit: f64| (v * per_unit).round() / per_unit;
    let h = crate::geoid::ellipsoid_height_m(g.lat_deg, g.lon_deg, g.alt_m);
    ([round(g.lon_deg, 1e8), round(g.lat_deg, 1e8), round(h, 1e3)], g.alt_m)
}

/// A line of WGS84 positions (longitude first) as a GeoJSON geometry, cut where it crosses
/// the antimeridian as RFC 7946 (sec. 3.1.9) asks: a line from 179.9999 to -179.9999 is
/// otherwise drawn the long way round the globe. Each cut ends one part at 180 (or -180)
/// and starts the next at the other, at the latitude and height interpolated there.
/// Written here: the geometry crates do not cut lines at the antimeridian.
pub(crate) fn line_geometry(line: Vec<[f64; 3]>) -> geojson::Geometry {
    let mut parts: Vec<Vec<[f64; 3]>> = vec![Vec::new()];
    for (i, &p) in line.iter().enumerate() {
        if let Some(q) = i.checked_sub(1).map(|j| line[j]) {
            let step = p[0] - q[0];
            if step.abs() > 180.0 {
                // The short way: east across it when the longitude jumps down.
                let side = if step < 0.0 { 180.0 } else { -180.0 };
                let t = (side - q[0]) / (step + 2.0 * side);
                let at = |k: usize| q[k] + t * (p[k] - q[k]);
                parts.last_mut().expect("one part").push([side, at(1), at(2)]);
                parts.push(vec![[-side, at(1), at(2)]]);
            }
        }
        parts.last_mut().expect("one part").push(p);
    }
    if parts.len() == 1 {
        geojson::Geometry::new_line_string(parts.remove(0))
    } else {
        geojson::Geometry::new_multi_line_string(parts)
    }
}

/// `area.geojson`: landmarks as points and border lines as line strings, in WGS84 with
/// heights above the ellipsoid (RFC 7946); each landmark also states its height above
/// mean sea level, and the collection says which height is which.
pub fn area_geojson(frame: &LocalFrame, landmarks: &[LandmarkRecord], borders: &[Vec<Vec3>]) -> String {
    use geojson::{Feature, FeatureCollection, Geometry, JsonObject};
    let mut features = Vec::new();
    for l in landmarks {
        let (c, amsl) = wgs84(frame, &l.position);
        let mut props = JsonObject::new();
        props.insert("kind".into(), "landmark".into());
        props.insert("id".into(), l.id.into());
        props.insert("sigma_max_m".into(), ((l.sigma_max_m * 1000.0).round() / 1000.0).into());
        props.insert("observations".into(), l.observations.into());
        props.insert("height_amsl_m".into(), ((amsl * 1000.0).round() / 1000.0).into());
        features.push(Feature {
            bbox: None,
            geometry: Some(Geometry::new_point(c)),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    for (i, line) in borders.iter().enumerate() {
        let coords: Vec<[f64; 3]> = line.iter().map(|p| wgs84(frame, p).0).collect();
        let mut props = JsonObject::new();
        props.insert("kind".into(), "border".into());
        props.insert("index".into(), i.into());
        features.push(Feature {
            bbox: None,
            geometry: Some(line_geometry(coords)),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    let mut members = JsonObject::new();
    members.insert(
        "heights".into(),
        "third coordinate: metres above the WGS84 ellipsoid (mean sea level + EGM96 undulation); height_amsl_m: above mean sea level".into(),
    );
    geojson::GeoJson::from(FeatureCollection { bbox: None, features, foreign_members: Some(members) })
        .to_string()
}

/// `area.kml`: the same for QGroundControl (Plan view: File > Import KML) and Google Earth.
/// Written by hand: KML is a few fixed elements, and a crate would add a dependency tree
/// for nothing QGC needs. KML's absolute altitudes are above mean sea level, as mavloc's
/// are (MAVLink's and the photo tags' altitudes), so landmarks and border lines stand at
/// their estimated heights (`altitudeMode` absolute).
pub fn area_kml(
    frame: &LocalFrame,
    name: &str,
    landmarks: &[LandmarkRecord],
    borders: &[Vec<Vec3>],
) -> String {
    // XML 1.0 has no place for control characters other than tab and line ends (a folder
    // name can hold them; lxml and GDAL then refuse the whole file): each becomes U+FFFD.
    let esc = |s: &str| {
        let allowed = |c: char| c >= ' ' || matches!(c, '\t' | '\n' | '\r');
        let s: String = s
            .chars()
            .map(|c| if allowed(c) && !matches!(c, '\u{FFFE}' | '\u{FFFF}') { c } else { '\u{FFFD}' })
            .collect();
        s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
    };
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<kml xmlns=\"http://www.opengis.net/kml/2.2\">\n<Document>\n");
    let _ = writeln!(s, "<name>{}</name>", esc(name));
    s.push_str(
        "<Style id=\"border\"><LineStyle><color>ff0000ff</color><width>3</width></LineStyle></Style>\n\
         <Style id=\"landmark\"><IconStyle><scale>0.4</scale></IconStyle><LabelStyle><scale>0</scale></LabelStyle></Style>\n",
    );
    for (i, line) in borders.iter().enumerate() {
        let _ = write!(
            s,
            "<Placemark><name>border {i}</name><styleUrl>#border</styleUrl><LineString><altitudeMode>absolute</altitudeMode><coordinates>"
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
            "<Placemark><name>{}</name><description>sigma {}, {} observations, {:.2} m above mean sea level</description><styleUrl>#landmark</styleUrl>\
             <Point><altitudeMode>absolute</altitudeMode><coordinates>{:.8},{:.8},{:.3}</coordinates></Point></Placemark>",
            l.id,
            // The ground-plane baseline has no uncertainty to give.
            if l.sigma_max_m.is_finite() { format!("{:.2} m", l.sigma_max_m) } else { "unknown".into() },
            l.observations,
            g.alt_m,
            g.lon_deg,
            g.lat_deg,
            g.alt_m
        );
    }
    s.push_str("</Folder>\n</Document>\n</kml>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavloc_geometry::Geodetic;

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
    fn files_keep_their_layout() {
        // The layout older results and their readers have: fixed decimals, 0/1 booleans.
        assert_eq!(
            landmarks_csv(&sample()[..1]),
            "id,north,east,down,sigma_max_m,observations,first_frame,last_frame\n\
             3,10.5000,-2.2500,0.7500,0.3100,12,4,40\n"
        );
        // An unknown sigma (the ground-plane baseline's) is an empty field, read back as NaN;
        // "NaN", as older files have it, still reads.
        let nan = LandmarkRecord { sigma_max_m: f64::NAN, ..sample()[0].clone() };
        let text = landmarks_csv(&[nan]);
        assert_eq!(text.lines().nth(1), Some("3,10.5000,-2.2500,0.7500,,12,4,40"), "{text}");
        assert!(parse_landmarks_csv(&text, "x").unwrap()[0].sigma_max_m.is_nan());
        let old = text.replace(",,", ",NaN,");
        assert!(parse_landmarks_csv(&old, "x").unwrap()[0].sigma_max_m.is_nan());
        let bad = text.replace(",,", ",wide,");
        let err = parse_landmarks_csv(&bad, "x").unwrap_err();
        assert!(err.contains("`wide` is not a number"), "{err}");
        let border = vec![vec![Vec3::new(1.0, 2.0, 3.0)], vec![Vec3::new(-1.5, 0.0, 0.25)]];
        let text = border_csv(&border);
        assert_eq!(text, "line,index,north,east,down\n0,0,1.0000,2.0000,3.0000\n1,0,-1.5000,0.0000,0.2500\n");
        assert_eq!(parse_border_csv(&text), border);
        assert_eq!(parse_border_csv(&format!("{text}garbage,1\n")), border, "bad rows are skipped");
        assert!(parse_border_csv("").is_empty());
        let row = TrajectoryRow {
            frame: 7,
            t: 0.5,
            x: 1.0,
            y: -2.0,
            sigma_x: 0.1,
            sigma_y: 0.2,
            true_x: f64::NAN,
            true_y: 1.0 / 3.0,
            fix: false,
        };
        let text = trajectory_csv(std::slice::from_ref(&row));
        assert_eq!(
            text,
            format!("{TRAJECTORY_HEADER}\n7,0.5000,1.0000,-2.0000,0.1000,0.2000,NaN,0.3333,0\n")
        );
        let dir = std::env::temp_dir().join(format!("mavloc-traj-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("trajectory.csv");
        std::fs::write(&path, &text).unwrap();
        let back = read_trajectory(&path).unwrap();
        assert!(!back[0].fix && back[0].frame == 7 && (back[0].true_y - 0.3333).abs() < 1e-9);
        // A file from before the `fix` column: every row counts as a fix.
        std::fs::write(&path, "frame,t,x,y,sigma_x,sigma_y,true_x,true_y\n7,0.5,1,-2,0.1,0.2,0,0\n").unwrap();
        assert!(read_trajectory(&path).unwrap()[0].fix);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn landings_round_trip_and_name_bad_lines() {
        let rows = vec![LandingRow {
            trial: 0,
            zone_x: 1.0,
            zone_y: -1.0,
            fired: true,
            t_fire: 3.5,
            true_x: 1.1,
            true_y: -0.9,
            est_x: 1.0,
            est_y: -1.0,
            inside: true,
        }];
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("landings.csv");
        std::fs::write(&p, landings_csv(&rows)).unwrap();
        assert!(std::fs::read_to_string(&p)
            .unwrap()
            .ends_with("\n0,1.0000,-1.0000,1,3.500,1.1000,-0.9000,1.0000,-1.0000,1\n"));
        assert_eq!(read_landings(&p).unwrap(), rows);
        std::fs::write(&p, format!("{LANDINGS_HEADER}\n1,2,3\n")).unwrap();
        assert!(read_landings(&p).unwrap_err().contains("line 2"));
    }

    /// A line across the antimeridian is cut there (RFC 7946 sec. 3.1.9): two parts meeting
    /// at 180 and -180 at the latitude between; a line that stays on one side is whole.
    #[test]
    fn a_line_across_the_antimeridian_is_cut_there() {
        let json = |g: geojson::Geometry| serde_json::to_value(&g).unwrap();
        let g = json(line_geometry(vec![[179.9, 10.0, 5.0], [-179.9, 11.0, 7.0], [-179.8, 12.0, 7.0]]));
        assert_eq!(g["type"], "MultiLineString");
        let c = &g["coordinates"];
        assert_eq!(c[0], serde_json::json!([[179.9, 10.0, 5.0], [180.0, 10.5, 6.0]]));
        assert_eq!(c[1], serde_json::json!([[-180.0, 10.5, 6.0], [-179.9, 11.0, 7.0], [-179.8, 12.0, 7.0]]));
        // Westward too.
        let g = json(line_geometry(vec![[-179.5, 0.0, 0.0], [179.5, 1.0, 0.0]]));
        assert_eq!(
            g["coordinates"],
            serde_json::json!([
                [[-179.5, 0.0, 0.0], [-180.0, 0.5, 0.0]],
                [[180.0, 0.5, 0.0], [179.5, 1.0, 0.0]]
            ])
        );
        let whole = json(line_geometry(vec![[10.0, 0.0, 0.0], [10.1, 0.0, 0.0]]));
        assert_eq!(whole["type"], "LineString");
    }

    #[test]
    fn geojson_and_kml_are_in_wgs84() {
        let frame = LocalFrame::new(Geodetic::new(57.0, 10.0, 20.0));
        let border = vec![vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(100.0, 0.0, 0.0)]];
        let g: serde_json::Value = serde_json::from_str(&area_geojson(&frame, &sample(), &border)).unwrap();
        assert_eq!(g["features"].as_array().unwrap().len(), 3);
        let line = &g["features"][2]["geometry"]["coordinates"];
        assert!((line[1][1].as_f64().unwrap() - 57.0009).abs() < 1e-4, "100 m north");
        // GeoJSON: ellipsoid heights (EGM96 N is about +41.7 m at 57 N 10 E), AMSL stated.
        let h = line[0][2].as_f64().unwrap();
        let n = crate::geoid::undulation_m(57.0, 10.0);
        assert!((h - (20.0 + n)).abs() < 0.6e-3 && n > 35.0 && n < 45.0, "h {h}, N {n}");
        assert!(g["heights"].as_str().unwrap().contains("ellipsoid"));
        // No more digits than the data has (RFC 7946 sec. 11.2): 8 decimals of a degree.
        for f in g["features"].as_array().unwrap() {
            let text = f["geometry"]["coordinates"].to_string();
            let decimals =
                text.split(['[', ',', ']']).filter_map(|n| n.split_once('.')).map(|(_, d)| d.len());
            assert!(decimals.max().unwrap() <= 8, "{text}");
        }
        let point = &g["features"][0];
        let amsl = point["properties"]["height_amsl_m"].as_f64().unwrap();
        assert!((point["geometry"]["coordinates"][2].as_f64().unwrap() - amsl - n).abs() < 0.01);
        // KML: absolute altitudes above mean sea level, as mavloc's own.
        let kml = area_kml(&frame, "a <test>\u{1}", &sample(), &border);
        assert!(kml.contains("<name>a &lt;test&gt;\u{FFFD}</name>"), "no control character in XML");
        assert!(
            kml.contains("<LabelStyle><scale>0</scale></LabelStyle>"),
            "no label on each of 1000 landmarks"
        );
        let mut baseline = sample();
        baseline[0].sigma_max_m = f64::NAN;
        let plain = area_kml(&frame, "b", &baseline, &border);
        assert!(!plain.contains("NaN") && plain.contains("sigma unknown,"), "{plain}");
        assert!(kml.contains("<coordinates>10.00000000,57.00000000,20.000 "));
        assert!(kml.contains("<altitudeMode>absolute</altitudeMode>") && !kml.contains("clampToGround"));
        assert!(!kml.contains("ellipsoid"));
        assert_eq!(kml.matches("<Placemark>").count(), 3);
        let ply = landmarks_ply(&frame, &sample());
        assert!(ply.contains(
            "comment origin latitude 57.00000000 longitude 10.00000000 deg, 20.000 m above mean sea level"
        ));
    }
}
