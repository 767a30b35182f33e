//! Datasets on disk: the one format the simulator and the photo importer write, and the
//! pipelines, `mavloc eval` and the daemon's replay camera read.
//!
//! ```text
//! DIR/
//!   frames/NNNNNN.png      RGB frames (.jpg for imported photos)
//!   masks/NNNNNN.png       target masks (255 inside the target area, 0 outside)
//!   telemetry.jsonl        one JSON object per frame: time, true and measured pose, gimbal
//!   camera.toml            intrinsics, resolution, gimbal kinematic chain
//!   ground_truth.csv       border polylines: line, index, north, east, down, lat, lon, alt
//!   ground_truth.geojson   the same in WGS84 (RFC 7946: lon, lat, height above the ellipsoid)
//!   scenario.toml          everything needed to re-render the dataset
//!   mission.plan           the flight as a QGroundControl plan
//!   mavloc.toml            optional: settings the data needs, layered over the
//!                          configuration file by `mavloc area` (imported photos have one)
//! ```
//!
//! Files are written atomically ([`crate::write_atomic`]); `telemetry.jsonl` is written
//! last, so a dataset whose writing was interrupted is recognisably incomplete. The ground
//! truth travels with the data: evaluation reads it from here and never rebuilds the world.

use std::fs;
use std::path::{Path, PathBuf};

use mavloc_geometry::{GimbalAngles, GimbalChain, Intrinsics, LocalFrame, Vec3};
use serde::{Deserialize, Serialize};

use crate::table::{self, fixed, Columns, Header, Row};

/// Settings a dataset carries for the commands that run on it (see the module doc).
pub const SETTINGS_FILE: &str = "mavloc.toml";
pub const CAMERA_FILE: &str = "camera.toml";
pub const TELEMETRY_FILE: &str = "telemetry.jsonl";
pub const GROUND_TRUTH_CSV: &str = "ground_truth.csv";
pub const GROUND_TRUTH_GEOJSON: &str = "ground_truth.geojson";

/// Where the gimbal's angles are measured from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GimbalFrame {
    /// Yaw from north, pitch and roll from the horizon (stabilised gimbal).
    Earth,
    /// Angles relative to the vehicle body (camera fixed to the frame).
    Body,
}

/// Photometric change applied to a frame (indoor seed sec. 3.4.2), recorded with it; the
/// simulator applies it (`mavloc_sim::views::apply`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Appearance {
    pub brightness: f64,
    pub contrast: f64,
    /// Box-blur kernel size in pixels (1 = none).
    pub blur_px: u32,
}

impl Default for Appearance {
    fn default() -> Self {
        Appearance { brightness: 0.0, contrast: 1.0, blur_px: 1 }
    }
}

impl Appearance {
    pub fn is_identity(&self) -> bool {
        *self == Appearance::default()
    }
}

/// A pose as the dataset records it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseRecord {
    /// Local NED position, metres.
    pub position: [f64; 3],
    /// Vehicle roll, pitch, yaw, degrees.
    pub attitude_deg: [f64; 3],
    /// Gimbal yaw, pitch, roll in the camera's kinematic chain, degrees.
    pub gimbal_deg: [f64; 3],
    /// Local NED velocity, m/s.
    pub velocity: [f64; 3],
}

impl PoseRecord {
    pub fn position(&self) -> Vec3 {
        Vec3::from(self.position)
    }

    pub fn gimbal(&self) -> GimbalAngles {
        GimbalAngles::from_degrees(self.gimbal_deg[0], self.gimbal_deg[1], self.gimbal_deg[2])
    }

    /// Camera pose with the given chain and gimbal frame.
    pub fn camera_pose(&self, chain: GimbalChain, frame: GimbalFrame) -> mavloc_geometry::CameraPose {
        use mavloc_geometry::{body_rotation, CameraPose, Mount};
        let a = self.attitude_deg.map(f64::to_radians);
        let mount = match frame {
            GimbalFrame::Earth => Mount::Earth,
            GimbalFrame::Body => Mount::Body { attitude: body_rotation(a[0], a[1], a[2]) },
        };
        CameraPose::from_gimbal(self.position(), chain, self.gimbal(), mount)
    }
}

/// One line of `telemetry.jsonl`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TelemetryRecord {
    /// Frame index; the files are `frames/{frame:06}.png` and `masks/{frame:06}.png`.
    pub frame: u64,
    /// Capture time, seconds from the start of the flight.
    pub t: f64,
    /// The true pose (ground truth).
    #[serde(rename = "true")]
    pub truth: PoseRecord,
    /// The pose as the vehicle reported it: noise, offsets and gimbal lag applied.
    pub measured: PoseRecord,
    /// Photometric change applied to the frame, when there was one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<Appearance>,
    /// The autopilot's clock at the capture (s since its boot, as its telemetry stamps
    /// it), in recordings (`daemon.record`): what joins a frame to the autopilot's log.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub autopilot_time: Option<f64>,
}

/// `camera.toml`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraFile {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub chain: GimbalChain,
    pub gimbal_frame: GimbalFrame,
    /// WGS84 origin of the local NED frame.
    pub origin: mavloc_geometry::Geodetic,
}

impl CameraFile {
    pub fn new(
        k: Intrinsics,
        chain: GimbalChain,
        gimbal_frame: GimbalFrame,
        origin: mavloc_geometry::Geodetic,
    ) -> Self {
        CameraFile {
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            chain,
            gimbal_frame,
            origin,
        }
    }

    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics {
            width: self.width,
            height: self.height,
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
        }
    }
}

/// One point of `ground_truth.csv`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroundTruthRow {
    pub line: usize,
    pub index: usize,
    #[serde(serialize_with = "fixed::dp4")]
    pub north: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub east: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub down: f64,
    #[serde(serialize_with = "fixed::dp9")]
    pub lat: f64,
    #[serde(serialize_with = "fixed::dp9")]
    pub lon: f64,
    #[serde(serialize_with = "fixed::dp4")]
    pub alt: f64,
}

impl Row for GroundTruthRow {
    const COLUMNS: &'static str = "line,index,north,east,down,lat,lon,alt";
}

/// What a reader needs of a ground-truth point: the local columns (WGS84 ones may be
/// missing in hand-made files).
#[derive(Deserialize, Serialize)]
struct GroundTruthPoint {
    line: usize,
    _index: usize,
    north: f64,
    east: f64,
    down: f64,
}

impl Row for GroundTruthPoint {
    const COLUMNS: &'static str = "line,index,north,east,down";
}

/// Polylines (local NED) grouped by their `line` column.
fn group_lines(points: impl IntoIterator<Item = (usize, Vec3)>) -> Vec<Vec<Vec3>> {
    let mut lines: Vec<Vec<Vec3>> = Vec::new();
    for (li, p) in points {
        while lines.len() <= li {
            lines.push(Vec::new());
        }
        lines[li].push(p);
    }
    lines
}

/// Parses `ground_truth.csv` into polylines, local NED.
pub fn parse_ground_truth(text: &str, origin: &str) -> Result<Vec<Vec<Vec3>>, String> {
    let rows: Vec<GroundTruthPoint> =
        table::parse_with(text, origin, Header::StartsWith(GroundTruthPoint::COLUMNS), Columns::AtLeast(5))?;
    Ok(group_lines(rows.into_iter().map(|r| (r.line, Vec3::new(r.north, r.east, r.down)))))
}

/// Writes `ground_truth.csv` and `ground_truth.geojson` for border polylines in `frame`.
pub fn write_ground_truth(dir: &Path, frame: &LocalFrame, lines: &[Vec<Vec3>]) -> Result<(), String> {
    let mut rows = Vec::new();
    let mut features = Vec::new();
    for (li, line) in lines.iter().enumerate() {
        let mut coords = Vec::new();
        for (pi, p) in line.iter().enumerate() {
            let g = frame.to_geodetic(p);
            rows.push(GroundTruthRow {
                line: li,
                index: pi,
                north: p.x,
                east: p.y,
                down: p.z,
                lat: g.lat_deg,
                lon: g.lon_deg,
                alt: g.alt_m,
            });
            // Heights as area.geojson has them (above the ellipsoid, RFC 7946), so the two
            // files lie on each other (they were 38 m apart where the geoid is -38 m).
            coords.push(crate::results::wgs84(frame, p).0);
        }
        let mut props = geojson::JsonObject::new();
        props.insert("name".into(), format!("ground truth border {li}").into());
        features.push(geojson::Feature {
            bbox: None,
            geometry: Some(crate::results::line_geometry(coords)),
            id: None,
            properties: Some(props),
            foreign_members: None,
        });
    }
    let mut members = geojson::JsonObject::new();
    members.insert(
        "heights".into(),
        "third coordinate: metres above the WGS84 ellipsoid (mean sea level + EGM96 undulation); ground_truth.csv's alt: above mean sea level".into(),
    );
    let fc = geojson::FeatureCollection { bbox: None, features, foreign_members: Some(members) };
    write_file(dir, GROUND_TRUTH_CSV, table::to_string(&rows).as_bytes())?;
    write_file(dir, GROUND_TRUTH_GEOJSON, geojson::GeoJson::from(fc).to_string().as_bytes())
}

/// Writes one file of a dataset atomically; the error names it.
pub fn write_file(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), String> {
    let path = dir.join(name);
    crate::write_atomic(&path, bytes).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// Makes `dir` ready for a dataset: `frames/` and `masks/` exist, and any old
/// `telemetry.jsonl` is gone so the dataset reads as incomplete until it is written again.
pub fn prepare(dir: &Path) -> Result<(), String> {
    for sub in ["frames", "masks"] {
        fs::create_dir_all(dir.join(sub))
            .map_err(|e| format!("cannot create {}: {e}", dir.join(sub).display()))?;
    }
    let _ = fs::remove_file(dir.join(TELEMETRY_FILE));
    Ok(())
}

/// Writes `camera.toml`.
pub fn write_camera(dir: &Path, camera: &CameraFile) -> Result<(), String> {
    write_file(dir, CAMERA_FILE, toml::to_string(camera).map_err(|e| e.to_string())?.as_bytes())
}

/// Writes `telemetry.jsonl`: last, as it marks the dataset complete.
pub fn write_telemetry(dir: &Path, records: &[TelemetryRecord]) -> Result<(), String> {
    let mut lines = String::new();
    for r in records {
        lines.push_str(&serde_json::to_string(r).map_err(|e| e.to_string())?);
        lines.push('\n');
    }
    write_file(dir, TELEMETRY_FILE, lines.as_bytes())
}

/// The CRC-32 of a dataset's telemetry file, hex (`None` when it cannot be read): what a
/// result records of the dataset it was made from, so an evaluation against another
/// dataset is refused.
pub fn telemetry_crc32(dir: &Path) -> Option<String> {
    fs::read(dir.join(TELEMETRY_FILE)).ok().map(|b| format!("{:08x}", crc32fast::hash(&b)))
}

/// A dataset opened for reading.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub dir: PathBuf,
    pub camera: CameraFile,
    pub records: Vec<TelemetryRecord>,
    /// Ground-truth polylines, local NED (empty when the dataset has none).
    pub ground_truth: Vec<Vec<Vec3>>,
    /// The line of `telemetry.jsonl` that was torn (the last, without its newline: a
    /// recording cut off as it wrote it), left out; the frames before it are the dataset.
    pub torn_line: Option<usize>,
}

impl Dataset {
    /// Opens a dataset folder; every error names the file (and line) that is wrong.
    pub fn open(dir: &Path) -> Result<Dataset, String> {
        // The folder itself first: "nope/camera.toml: No such file" sent users looking
        // for a file when the folder name was wrong.
        match fs::metadata(dir) {
            Err(e) => return Err(format!("dataset {}: {e}", dir.display())),
            Ok(m) if !m.is_dir() => return Err(format!("dataset {}: not a folder", dir.display())),
            Ok(_) if !dir.join(CAMERA_FILE).exists() => {
                return Err(format!(
                    "{} is not a dataset: it has no {CAMERA_FILE} (datasets are made by `mavloc sim render`, `mavloc import photos` and the daemon's recorder)",
                    dir.display()
                ))
            }
            Ok(_) => {}
        }
        let read = |name: &str| {
            let p = dir.join(name);
            fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))
        };
        let camera: CameraFile = toml::from_str(&read(CAMERA_FILE)?)
            .map_err(|e| format!("{}: {e}", dir.join(CAMERA_FILE).display()))?;
        camera.intrinsics().validate().map_err(|e| format!("{}: {e}", dir.join(CAMERA_FILE).display()))?;
        // An origin off the globe would put every result somewhere else (lat 95 came out
        // as 85 N, 170 W in the KML).
        camera.origin.validate().map_err(|e| format!("{}: origin: {e}", dir.join(CAMERA_FILE).display()))?;

        let tpath = dir.join(TELEMETRY_FILE);
        let text = fs::read_to_string(&tpath)
            .map_err(|e| format!("{}: {e} (an interrupted render leaves no telemetry)", tpath.display()))?;
        let lines: Vec<&str> = crate::table::strip_bom(&text).split_inclusive('\n').collect();
        let mut records: Vec<TelemetryRecord> = Vec::new();
        let mut prev_line = 0;
        let mut torn = None;
        for (n, line) in lines.iter().enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            let r: TelemetryRecord = match serde_json::from_str(line) {
                Ok(r) => r,
                // A recording's telemetry is appended a line at a time: a crash can tear
                // the last line (no newline yet). That frame was never recorded whole.
                Err(_) if n + 1 == lines.len() && !line.ends_with('\n') => {
                    torn = Some(n + 1);
                    break;
                }
                Err(e) => return Err(format!("{} line {}: {e}", tpath.display(), n + 1)),
            };
            // Each frame once, in the order it was taken: a repeated number would pose one
            // frame twice and leave the other out, a step back in time would turn every
            // speed worked out from it around. Both used to pass without a word.
            if let Some(last) = records.last() {
                let m = prev_line;
                if r.frame <= last.frame {
                    return Err(format!(
                        "{} line {}: frame {} after frame {} (line {m}): frames go in increasing order, each once",
                        tpath.display(),
                        n + 1,
                        r.frame,
                        last.frame
                    ));
                }
                if r.t < last.t {
                    return Err(format!(
                        "{} line {}: t {} s is before line {m}'s {} s: records go in time order",
                        tpath.display(),
                        n + 1,
                        r.t,
                        last.t
                    ));
                }
            }
            prev_line = n + 1;
            records.push(r);
        }
        if records.is_empty() {
            return Err(format!("{}: no telemetry record in it, so no frame can be posed", tpath.display()));
        }

        let gpath = dir.join(GROUND_TRUTH_CSV);
        let ground_truth = if gpath.exists() {
            parse_ground_truth(&read(GROUND_TRUTH_CSV)?, &gpath.display().to_string())?
        } else {
            Vec::new()
        };
        Ok(Dataset { dir: dir.to_path_buf(), camera, records, ground_truth, torn_line: torn })
    }

    /// `frames/NNNNNN.png`, or `.jpg` where the dataset holds photos (`mavloc import`).
    pub fn frame_path(&self, r: &TelemetryRecord) -> PathBuf {
        let png = self.dir.join("frames").join(format!("{:06}.png", r.frame));
        if png.exists() {
            return png;
        }
        let jpg = png.with_extension("jpg");
        if jpg.exists() {
            jpg
        } else {
            png
        }
    }

    pub fn mask_path(&self, r: &TelemetryRecord) -> PathBuf {
        self.dir.join("masks").join(format!("{:06}.png", r.frame))
    }

    /// The camera pose of a record on this dataset's gimbal, with static offsets (yaw,
    /// pitch, roll, degrees: the configured `gimbal.*_offset_deg`) added to its angles.
    /// One definition, so the offline area run and the live dataset replay agree.
    pub fn camera_pose(&self, r: &PoseRecord, gimbal_offsets_deg: [f64; 3]) -> mavloc_geometry::CameraPose {
        let o = gimbal_offsets_deg;
        let g = r.gimbal_deg;
        let corrected = PoseRecord { gimbal_deg: [g[0] + o[0], g[1] + o[1], g[2] + o[2]], ..*r };
        corrected.camera_pose(self.camera.chain, self.camera.gimbal_frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavloc_geometry::Geodetic;

    fn camera() -> CameraFile {
        CameraFile {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 31.5,
            cy: 23.5,
            chain: GimbalChain::YawPitchRoll,
            gimbal_frame: GimbalFrame::Earth,
            origin: Geodetic::new(57.0, 10.0, 20.0),
        }
    }

    /// The ground truth's GeoJSON and a result's `area.geojson` give a point the same
    /// height (above the ellipsoid): the same shore loaded from both lies on itself. They
    /// were the geoid's undulation apart (38 m at the coastline's origin), the ground truth
    /// above mean sea level.
    #[test]
    fn ground_truth_and_results_geojson_share_their_heights() {
        let dir = tempfile::tempdir().unwrap();
        // Where the EGM96 undulation is large (about -30 m, Duluth).
        let frame = LocalFrame::new(Geodetic::new(46.8, -92.1, 190.0));
        let p = Vec3::new(12.0, -7.0, 3.0);
        write_ground_truth(dir.path(), &frame, &[vec![p, p + Vec3::new(1.0, 0.0, 0.0)]]).unwrap();
        let truth: serde_json::Value =
            serde_json::from_str(&fs::read_to_string(dir.path().join(GROUND_TRUTH_GEOJSON)).unwrap())
                .unwrap();
        let landmark = crate::results::LandmarkRecord {
            id: 0,
            position: p,
            sigma_max_m: 0.1,
            observations: 3,
            first_frame: 0,
            last_frame: 1,
        };
        let result: serde_json::Value =
            serde_json::from_str(&crate::results::area_geojson(&frame, &[landmark], &[])).unwrap();
        let height = |v: &serde_json::Value| v.as_f64().unwrap();
        let t = height(&truth["features"][0]["geometry"]["coordinates"][0][2]);
        let r = height(&result["features"][0]["geometry"]["coordinates"][2]);
        assert!((t - r).abs() < 1e-6, "ground truth {t} m, result {r} m");
        let amsl = 190.0 - 3.0;
        assert!((t - amsl).abs() > 20.0, "{t} m is the ellipsoid's, not mean sea level's {amsl} m");
        assert!(truth["heights"].as_str().unwrap().contains("ellipsoid"), "{truth}");
    }

    #[test]
    fn a_written_dataset_opens_with_its_ground_truth() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        prepare(d).unwrap();
        write_camera(d, &camera()).unwrap();
        let lines = vec![vec![Vec3::new(1.0, 2.0, 0.5), Vec3::new(3.25, -4.0, 0.0)], vec![Vec3::zeros()]];
        write_ground_truth(d, &LocalFrame::new(camera().origin), &lines).unwrap();
        assert!(Dataset::open(d).unwrap_err().contains("interrupted render"), "no telemetry yet");
        let pose = PoseRecord {
            position: [1.0, 2.0, -30.0],
            attitude_deg: [0.0; 3],
            gimbal_deg: [0.0; 3],
            velocity: [0.0; 3],
        };
        let a = Some(Appearance { brightness: 3.0, ..Appearance::default() });
        let recs = vec![TelemetryRecord {
            frame: 0,
            t: 0.5,
            truth: pose,
            measured: pose,
            appearance: a,
            autopilot_time: None,
        }];
        write_telemetry(d, &recs).unwrap();
        let ds = Dataset::open(d).unwrap();
        assert_eq!(ds.camera, camera());
        assert_eq!(ds.records, recs);
        // An origin off the globe is refused by name.
        write_camera(d, &CameraFile { origin: Geodetic::new(95.0, 10.0, 20.0), ..camera() }).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("camera.toml: origin: latitude 95"), "{e}");
        write_camera(d, &camera()).unwrap();
        assert_eq!(ds.ground_truth, lines);
        let csv = fs::read_to_string(d.join(GROUND_TRUTH_CSV)).unwrap();
        assert!(
            csv.starts_with("line,index,north,east,down,lat,lon,alt\n0,0,1.0000,2.0000,0.5000,57.0000"),
            "{csv}"
        );
        assert_eq!(ds.frame_path(&recs[0]), d.join("frames/000000.png"));
    }

    /// A recording appends its telemetry a line at a time: a crash mid-append leaves a last
    /// line without its newline, which is skipped; the same damage anywhere else, or a bad
    /// line that is complete, is an error naming the line.
    #[test]
    fn a_torn_last_line_is_skipped_and_any_other_bad_line_named() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        write_camera(d, &camera()).unwrap();
        let pose = PoseRecord {
            position: [1.0, 2.0, -30.0],
            attitude_deg: [0.0; 3],
            gimbal_deg: [0.0; 3],
            velocity: [0.0; 3],
        };
        let rec = |frame| TelemetryRecord {
            frame,
            t: frame as f64,
            truth: pose,
            measured: pose,
            appearance: None,
            autopilot_time: None,
        };
        let line = |frame| serde_json::to_string(&rec(frame)).unwrap();
        let torn = &line(2)[..30];
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n{}\n{torn}", line(0), line(1))).unwrap();
        let ds = Dataset::open(d).unwrap();
        assert_eq!(ds.records, vec![rec(0), rec(1)]);
        assert_eq!(ds.torn_line, Some(3), "the torn line is told, so a run can say so");
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n", line(0))).unwrap();
        assert_eq!(Dataset::open(d).unwrap().torn_line, None);
        // A torn first line: nothing to pose a frame with, said as such.
        fs::write(d.join(TELEMETRY_FILE), torn).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("telemetry.jsonl: no telemetry record"), "{e}");
        fs::write(d.join(TELEMETRY_FILE), "").unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("telemetry.jsonl: no telemetry record"), "{e}");
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n{torn}\n{}\n", line(0), line(1))).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("telemetry.jsonl line 2"), "{e}");
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n{torn}\n", line(0))).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("telemetry.jsonl line 2"), "a complete bad last line is an error: {e}");
        // A frame twice, or out of order, and a step back in time, are named by line.
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n{}\n{}\n", line(0), line(1), line(1))).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("telemetry.jsonl line 3: frame 1 after frame 1 (line 2)"), "{e}");
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n\n{}\n{}\n", line(0), line(2), line(1))).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("line 4: frame 1 after frame 2 (line 3)"), "{e}");
        let back = serde_json::to_string(&TelemetryRecord { t: 0.5, ..rec(2) }).unwrap();
        fs::write(d.join(TELEMETRY_FILE), format!("{}\n{}\n{back}\n", line(0), line(1))).unwrap();
        let e = Dataset::open(d).unwrap_err();
        assert!(e.contains("line 3: t 0.5 s is before line 2's 1 s"), "{e}");
        // A byte-order mark (a Windows editor's save) is not a bad first record.
        fs::write(d.join(TELEMETRY_FILE), format!("\u{feff}{}\n{}\n", line(0), line(1))).unwrap();
        assert_eq!(Dataset::open(d).unwrap().records, vec![rec(0), rec(1)]);
    }

    /// A folder that is not there, a file, or a folder without camera.toml is named for
    /// what it is, not as a missing camera.toml inside it.
    #[test]
    fn a_missing_or_foreign_folder_is_named_as_such() {
        let dir = tempfile::tempdir().unwrap();
        let e = Dataset::open(&dir.path().join("nope")).unwrap_err();
        assert!(e.starts_with(&format!("dataset {}:", dir.path().join("nope").display())), "{e}");
        assert!(!e.contains("camera.toml"), "{e}");
        fs::write(dir.path().join("file"), "x").unwrap();
        let e = Dataset::open(&dir.path().join("file")).unwrap_err();
        assert!(e.ends_with("not a folder"), "{e}");
        let e = Dataset::open(dir.path()).unwrap_err();
        assert!(e.contains("is not a dataset: it has no camera.toml"), "{e}");
    }

    #[test]
    fn camera_pose_adds_the_static_gimbal_offsets() {
        let camera = CameraFile { gimbal_frame: GimbalFrame::Body, ..camera() };
        let ds =
            Dataset { dir: PathBuf::new(), camera, records: vec![], ground_truth: vec![], torn_line: None };
        let r = PoseRecord {
            position: [1.0, 2.0, -30.0],
            attitude_deg: [2.0, -3.0, 40.0],
            gimbal_deg: [10.0, -80.0, 0.0],
            velocity: [0.0; 3],
        };
        let shifted = PoseRecord { gimbal_deg: [11.5, -82.0, 0.5], ..r };
        let body = |r: &PoseRecord| r.camera_pose(GimbalChain::YawPitchRoll, GimbalFrame::Body);
        assert_eq!(ds.camera_pose(&r, [1.5, -2.0, 0.5]), body(&shifted));
        assert_eq!(ds.camera_pose(&r, [0.0; 3]), body(&r));
        assert_ne!(body(&shifted), body(&r));
    }

    #[test]
    fn bad_ground_truth_names_the_line() {
        let e =
            parse_ground_truth("line,index,north,east,down\n0,0,1,2,3\n0,1,1,x,3\n", "g.csv").unwrap_err();
        assert!(e.starts_with("g.csv line 3"), "{e}");
        let short = parse_ground_truth("line,index,north,east,down\n1,0,1,2,3\n", "g.csv").unwrap();
        assert_eq!(short, vec![vec![], vec![Vec3::new(1.0, 2.0, 3.0)]]);
    }
}
