//! `mavloc import photos DIR --out DATASET`: geotagged drone photos to a dataset in the
//! simulation-world format (`sim/src/dataset.rs`), so `mavloc area` runs on real imagery.
//!
//! Read per photo: EXIF (GPS latitude, longitude, altitude; DateTimeOriginal; FocalLength;
//! FocalLengthIn35mmFilm; pixel size) with `kamadak-exif`, and DJI's XMP packet
//! (`drone-dji:` AbsoluteAltitude, RelativeAltitude, Gimbal{Roll,Yaw,Pitch}Degree,
//! Flight{Roll,Yaw,Pitch}Degree) with `quick-xml`, whether written as attributes or as
//! elements. A photo missing any tag the pose needs is reported by name and skipped, never
//! guessed.
//!
//! Conventions (documented assumptions):
//! - Local NED around the first photo (by capture time): north/east from its latitude and
//!   longitude, and the origin's altitude is the take-off point's (AbsoluteAltitude -
//!   RelativeAltitude of the first photo), so the ground near take-off is at down = 0, the
//!   area pipeline's default ground plane for new landmarks.
//! - DJI gimbal angles are earth-frame Euler angles (yaw from north, pitch from the
//!   horizon, roll), applied yaw, then pitch, then roll: `chain = "yaw-pitch-roll"`,
//!   `gimbal_frame = "earth"`. The flight angles go into `attitude_deg`.
//! - Intrinsics from the 35 mm-equivalent focal length, defined on the diagonal (CIPA
//!   DC-008): fx = fy = f35 * sqrt(w^2 + h^2) / 43.27 mm, principal point at the centre,
//!   no distortion; a photo wider than 4:3 is taken as a crop of a 4:3 sensor of the same
//!   width (h = 3w/4 in the formula), as DJI's 16:9 modes are: the FC300S's 3.61 mm on its
//!   6.17 mm-wide sensor gives 2340 px at 4000 px, this rule 2311 px, the 16:9 diagonal
//!   2121 px. A calibration file (`--calibration FILE`, TOML with fx, fy, cx, cy and
//!   optionally OpenCV's `distortion` coefficients) overrides this; with distortion the
//!   frames are written undistorted (same camera matrix, JPEG quality 95), so the dataset
//!   stays pinhole like every other. The estimate is good to a few per cent. Along one straight line of
//!   nadir photos a focal error trades against height (landmarks move up or down by
//!   metres) and barely shows in the residual report: README "Real photos" has the table.
//! - The origin's altitude is EXIF GPS altitude minus RelativeAltitude. EXIF altitude is
//!   above sea level, not the ellipsoid, so absolute heights in the results are off by the
//!   geoid (about 30 m at the sample); local heights and map positions are not.
//! - Frames are the original JPEGs, copied unchanged unless undistorted (`frames/NNNNNN.jpg`); photos have no
//!   ground truth, so each record's `true` pose repeats the measured one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::geometry::{Geodetic, LocalFrame};
use mavloc_data::dataset::{self, CameraFile, GimbalFrame, PoseRecord, TelemetryRecord};

/// `config/photo-survey.toml`, written into every imported dataset as its own settings.
pub const PHOTO_SURVEY_SETTINGS: &str = include_str!("../config/photo-survey.toml");

/// Diagonal of the 35 mm film frame (36 x 24 mm), millimetres.
const FILM_DIAGONAL_MM: f64 = 43.266_615;

/// What one photo says about where it was taken.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PhotoTags {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// GPS altitude (EXIF), metres.
    pub gps_alt_m: f64,
    /// "YYYY:MM:DD HH:MM:SS" as EXIF writes it.
    pub time: String,
    pub focal_mm: Option<f64>,
    pub focal_35mm: Option<f64>,
    pub absolute_alt_m: f64,
    pub relative_alt_m: f64,
    /// Gimbal yaw, pitch, roll, degrees.
    pub gimbal_deg: [f64; 3],
    /// Vehicle roll, pitch, yaw, degrees.
    pub flight_deg: [f64; 3],
}

/// `drone-dji:` values of a JPEG's XMP packet, attribute or element form.
pub fn dji_xmp(jpeg: &[u8]) -> BTreeMap<String, String> {
    use quick_xml::events::Event;
    let mut out = BTreeMap::new();
    let (Some(start), Some(end)) = (find(jpeg, b"<x:xmpmeta"), find(jpeg, b"</x:xmpmeta>")) else {
        return out;
    };
    if end <= start {
        return out;
    }
    let packet = &jpeg[start..end + b"</x:xmpmeta>".len()];
    let mut reader = quick_xml::Reader::from_reader(packet);
    let mut element: Option<String> = None;
    let mut buf = Vec::new();
    loop {
        match reader.read_event_into(&mut buf) {
            Ok(Event::Start(e)) | Ok(Event::Empty(e)) => {
                for a in e.attributes().flatten() {
                    let key = String::from_utf8_lossy(a.key.as_ref()).to_string();
                    if let Some(k) = key.strip_prefix("drone-dji:") {
                        out.insert(k.to_string(), String::from_utf8_lossy(&a.value).trim().to_string());
                    }
                }
                let name = String::from_utf8_lossy(e.name().as_ref()).to_string();
                element = name.strip_prefix("drone-dji:").map(str::to_string);
            }
            Ok(Event::Text(t)) => {
                if let Some(k) = element.take() {
                    let v = String::from_utf8_lossy(&t).trim().to_string();
                    if !v.is_empty() {
                        out.insert(k, v);
                    }
                }
            }
            Ok(Event::End(_)) => element = None,
            Ok(Event::Eof) | Err(_) => break,
            _ => {}
        }
        buf.clear();
    }
    out
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

fn rational_f64(f: &exif::Field, i: usize) -> Option<f64> {
    match &f.value {
        exif::Value::Rational(v) => v.get(i).map(|r| r.to_f64()),
        exif::Value::SRational(v) => v.get(i).map(|r| r.to_f64()),
        exif::Value::Short(v) => v.get(i).map(|&x| x as f64),
        exif::Value::Long(v) => v.get(i).map(|&x| x as f64),
        _ => None,
    }
}

/// Reads a photo's tags; the error names the photo and every missing tag.
pub fn read_tags(path: &Path) -> Result<PhotoTags, String> {
    let name = path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    let bytes = std::fs::read(path).map_err(|e| format!("{name}: {e}"))?;
    let exif = exif::Reader::new()
        .read_from_container(&mut std::io::Cursor::new(&bytes))
        .map_err(|e| format!("{name}: no readable EXIF ({e})"))?;
    let field = |t| exif.get_field(t, exif::In::PRIMARY);
    let mut missing: Vec<&str> = Vec::new();
    let dms = |t, r, label: &'static str, missing: &mut Vec<&str>| -> f64 {
        let v = field(t).and_then(|f| {
            let (d, m, s) = (rational_f64(f, 0)?, rational_f64(f, 1)?, rational_f64(f, 2)?);
            Some(d + m / 60.0 + s / 3600.0)
        });
        let sign = match field(r).map(|f| f.display_value().to_string()) {
            Some(s) if s.starts_with('S') || s.starts_with('W') => -1.0,
            _ => 1.0,
        };
        match v {
            Some(v) => sign * v,
            None => {
                missing.push(label);
                f64::NAN
            }
        }
    };
    let lat = dms(exif::Tag::GPSLatitude, exif::Tag::GPSLatitudeRef, "GPSLatitude", &mut missing);
    let lon = dms(exif::Tag::GPSLongitude, exif::Tag::GPSLongitudeRef, "GPSLongitude", &mut missing);
    let gps_alt = field(exif::Tag::GPSAltitude).and_then(|f| rational_f64(f, 0));
    let below = field(exif::Tag::GPSAltitudeRef).and_then(|f| f.value.get_uint(0)) == Some(1);
    let gps_alt = gps_alt.map(|a| if below { -a } else { a });
    let time = field(exif::Tag::DateTimeOriginal)
        .or_else(|| field(exif::Tag::DateTime))
        .map(|f| f.display_value().to_string().replace('-', ":"))
        .unwrap_or_default();
    if time.is_empty() {
        missing.push("DateTimeOriginal");
    }
    let focal_mm = field(exif::Tag::FocalLength).and_then(|f| rational_f64(f, 0));
    let focal_35mm =
        field(exif::Tag::FocalLengthIn35mmFilm).and_then(|f| f.value.get_uint(0)).map(|v| v as f64);
    let size = (
        field(exif::Tag::PixelXDimension).and_then(|f| f.value.get_uint(0)),
        field(exif::Tag::PixelYDimension).and_then(|f| f.value.get_uint(0)),
    );
    let xmp = dji_xmp(&bytes);
    let mut num = |key: &'static str| -> f64 {
        match xmp.get(key).and_then(|v| v.trim_start_matches('+').parse::<f64>().ok()) {
            Some(v) => v,
            None => {
                missing.push(key);
                f64::NAN
            }
        }
    };
    let absolute = num("AbsoluteAltitude");
    let relative = num("RelativeAltitude");
    let gimbal = [num("GimbalYawDegree"), num("GimbalPitchDegree"), num("GimbalRollDegree")];
    let flight = [num("FlightRollDegree"), num("FlightPitchDegree"), num("FlightYawDegree")];
    if focal_35mm.is_none() {
        missing.push("FocalLengthIn35mmFilm");
    }
    let (width, height) = match size {
        (Some(w), Some(h)) if w > 0 && h > 0 => (w, h),
        _ => {
            missing.push("PixelXDimension/PixelYDimension");
            (0, 0)
        }
    };
    if !missing.is_empty() {
        return Err(format!("{name}: missing {}", missing.join(", ")));
    }
    Ok(PhotoTags {
        name,
        width,
        height,
        lat_deg: lat,
        lon_deg: lon,
        gps_alt_m: gps_alt.unwrap_or(absolute),
        time,
        focal_mm,
        focal_35mm,
        absolute_alt_m: absolute,
        relative_alt_m: relative,
        gimbal_deg: gimbal,
        flight_deg: flight,
    })
}

/// Seconds since 0000-01-01 of an EXIF time, for ordering and intervals.
fn exif_seconds(t: &str) -> Option<f64> {
    let p: Vec<f64> = t.split([':', ' ']).map(|x| x.trim().parse::<f64>().ok()).collect::<Option<_>>()?;
    if p.len() < 6 {
        return None;
    }
    // Days from a civil date (proleptic Gregorian), enough for differences.
    let (y, m, d) = (p[0] as i64, p[1] as i64, p[2] as i64);
    let (y, m) = if m <= 2 { (y - 1, m + 12) } else { (y, m) };
    let days = 365 * y + y / 4 - y / 100 + y / 400 + (153 * (m - 3) + 2) / 5 + d;
    Some(days as f64 * 86400.0 + p[3] * 3600.0 + p[4] * 60.0 + p[5])
}

/// Intrinsics override: a TOML file with fx, fy, cx, cy (pixels at the photos' size) and
/// optionally `distortion`, OpenCV's coefficients `[k1, k2, p1, p2(, k3(, k4, k5, k6))]`
/// (what `calibrateCamera` or OpenDroneMap's `cameras.json` give).
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub distortion: Vec<f64>,
}

impl Calibration {
    fn check(&self) -> Result<(), String> {
        if ![0, 4, 5, 8].contains(&self.distortion.len()) {
            return Err(format!(
                "distortion has {} coefficients; OpenCV's model takes 4, 5 or 8 ([k1, k2, p1, p2, k3, ...])",
                self.distortion.len()
            ));
        }
        if let Some(d) = self.distortion.iter().find(|d| !d.is_finite()) {
            return Err(format!("distortion coefficient {d} is not a finite number"));
        }
        Ok(())
    }

    /// Whether the photos need undistorting.
    fn distorted(&self) -> bool {
        self.distortion.iter().any(|&d| d != 0.0)
    }
}

/// Writes `src` undistorted with camera matrix `(fx, fy, cx, cy)` and `distortion`, keeping
/// the same camera matrix, so the dataset's pinhole intrinsics hold for the new frame.
/// JPEG at quality 95: the frames stay photos, at a fifth of PNG's size.
fn undistort_photo(src: &Path, dest: &Path, c: &Calibration) -> Result<(), String> {
    use opencv::core::{Mat, Vector};
    use opencv::prelude::*;
    let err = |e: opencv::Error| format!("{}: {e}", src.display());
    let img = opencv::imgcodecs::imread(src, opencv::imgcodecs::IMREAD_COLOR).map_err(err)?;
    if img.empty() {
        return Err(format!("{}: not a readable image", src.display()));
    }
    let k = Mat::from_slice_2d(&[[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]]).map_err(err)?;
    let d = Mat::from_slice(&c.distortion).map_err(err)?.try_clone().map_err(err)?;
    let mut out = Mat::default();
    opencv::calib3d::undistort(&img, &mut out, &k, &d, &k).map_err(err)?;
    let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 95]);
    if !opencv::imgcodecs::imwrite(dest, &out, &params).map_err(err)? {
        return Err(format!("cannot write {}", dest.display()));
    }
    Ok(())
}

/// What an import did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ImportReport {
    pub imported: Vec<String>,
    /// Photo and why it was skipped.
    pub skipped: Vec<(String, String)>,
    pub fx_px: f64,
    pub intrinsics_from: String,
    pub origin: Option<Geodetic>,
    /// Set when the user's edited settings file was kept (and why).
    pub kept_settings: Option<String>,
}

/// Imports the photos of `dir` (JPEG) into a dataset at `out`, written beside it and put
/// in place whole; a non-empty `out` is replaced only with `replace` (`--force`), keeping
/// a `mavloc.toml` the user edited.
pub fn import_photos(
    dir: &Path,
    out: &Path,
    calibration: Option<&Path>,
    replace: bool,
) -> Result<ImportReport, String> {
    if mavloc_data::staged::nested(dir, out) {
        return Err(format!(
            "--out {} and the photos' folder {} are the same or one is inside the other: choose an output folder elsewhere",
            out.display(),
            dir.display()
        ));
    }
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
            ext == "jpg" || ext == "jpeg"
        })
        .collect();
    paths.sort();
    if paths.is_empty() {
        return Err(format!("{} holds no JPEG photos", dir.display()));
    }
    let mut report = ImportReport::default();
    let mut photos = Vec::new();
    for p in &paths {
        match read_tags(p).and_then(|t| {
            // Tags come first in the file, so a cut photo still has them: check the image.
            let bytes = std::fs::read(p).map_err(|e| format!("{}: {e}", t.name))?;
            if crate::imaging::jpeg_truncated(&bytes) {
                return Err(format!("{}: truncated JPEG (the image data ends early)", t.name));
            }
            Ok(t)
        }) {
            Ok(t) => match exif_seconds(&t.time) {
                Some(s) => photos.push((s, p.clone(), t)),
                None => {
                    report.skipped.push((t.name.clone(), format!("unreadable capture time `{}`", t.time)))
                }
            },
            Err(e) => {
                let name = p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
                tracing::warn!("skipped {e}");
                report.skipped.push((name, e));
            }
        }
    }
    if photos.is_empty() {
        return Err(format!("no photo in {} has the tags a pose needs: {:?}", dir.display(), report.skipped));
    }
    // By capture time; the name breaks ties (DJI writes whole seconds).
    photos.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let first = &photos[0].2;
    let (w, h) = (first.width, first.height);
    if let Some((_, _, t)) = photos.iter().find(|(_, _, t)| (t.width, t.height) != (w, h)) {
        return Err(format!(
            "{} is {}x{}, but {} is {w}x{h}: one camera per dataset",
            t.name, t.width, t.height, first.name
        ));
    }
    let origin = Geodetic::new(first.lat_deg, first.lon_deg, first.absolute_alt_m - first.relative_alt_m);
    origin.validate().map_err(|e| format!("{}: {e}", first.name))?;
    let mut undistort = None;
    let (fx, fy, cx, cy, from) = match calibration {
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
            let c: Calibration = toml::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))?;
            c.check().map_err(|e| format!("{}: {e}", p.display()))?;
            let from = if c.distorted() {
                format!("calibration file {} (frames undistorted)", p.display())
            } else {
                format!("calibration file {}", p.display())
            };
            let v = (c.fx, c.fy, c.cx, c.cy, from);
            undistort = Some(c).filter(Calibration::distorted);
            v
        }
        None => {
            let f35 = first.focal_35mm.expect("checked");
            // The equivalent focal length refers to the whole sensor; a photo wider than
            // 4:3 is taken as a crop of a 4:3 sensor of the same width (DJI's 16:9 modes).
            let sensor_h = (h as f64).max(w as f64 * 3.0 / 4.0);
            let f = f35 * ((w as f64).powi(2) + sensor_h.powi(2)).sqrt() / FILM_DIAGONAL_MM;
            let cx = (w as f64 - 1.0) / 2.0;
            let cy = (h as f64 - 1.0) / 2.0;
            (f, f, cx, cy, format!("35 mm-equivalent focal length {f35} mm on the diagonal"))
        }
    };
    let camera = CameraFile {
        width: w,
        height: h,
        fx,
        fy,
        cx,
        cy,
        chain: crate::geometry::GimbalChain::YawPitchRoll,
        gimbal_frame: GimbalFrame::Earth,
        origin,
    };
    camera.intrinsics().validate().map_err(|e| format!("intrinsics: {e}"))?;
    let staged = mavloc_data::staged::StagedDir::begin(out, replace)?;
    let (final_dir, out) = (out, staged.path());
    dataset::prepare(out)?;
    let frame = LocalFrame::new(origin);
    let t0 = photos[0].0;
    let mut records = Vec::with_capacity(photos.len());
    for (i, (s, path, t)) in photos.iter().enumerate() {
        let dest = out.join("frames").join(format!("{i:06}.jpg"));
        match &undistort {
            Some(c) => undistort_photo(path, &dest, c)?,
            None => {
                std::fs::copy(path, &dest)
                    .map_err(|e| format!("{} -> {}: {e}", path.display(), dest.display()))?;
            }
        }
        let p = frame.to_ned(&Geodetic::new(t.lat_deg, t.lon_deg, t.absolute_alt_m));
        let pose = PoseRecord {
            position: p.into(),
            attitude_deg: t.flight_deg,
            gimbal_deg: t.gimbal_deg,
            velocity: [0.0; 3],
        };
        records.push(TelemetryRecord {
            frame: i as u64,
            t: s - t0,
            truth: pose,
            measured: pose,
            appearance: None,
        });
        report.imported.push(t.name.clone());
    }
    let write = |name: &str, bytes: &[u8]| dataset::write_file(out, name, bytes);
    dataset::write_camera(out, &camera)?;
    // The settings photos need (segment water, the photo-survey tuning), so `mavloc area
    // --dataset D` runs right without a --config; edit the file to change them.
    // A settings file the user edited in the old dataset is kept; ours goes beside it.
    let theirs = std::fs::read_to_string(final_dir.join(dataset::SETTINGS_FILE)).ok();
    match theirs.filter(|t| t != PHOTO_SURVEY_SETTINGS) {
        Some(t) => {
            write(dataset::SETTINGS_FILE, t.as_bytes())?;
            let new_name = format!("{}.new", dataset::SETTINGS_FILE);
            write(&new_name, PHOTO_SURVEY_SETTINGS.as_bytes())?;
            report.kept_settings = Some(format!(
                "{} was edited, so it is kept; the import's own settings are in {}",
                final_dir.join(dataset::SETTINGS_FILE).display(),
                final_dir.join(new_name).display()
            ));
        }
        None => write(dataset::SETTINGS_FILE, PHOTO_SURVEY_SETTINGS.as_bytes())?,
    }
    let tags: Vec<&PhotoTags> = photos.iter().map(|(_, _, t)| t).collect();
    write("photos.json", serde_json::to_string_pretty(&tags).map_err(|e| e.to_string())?.as_bytes())?;
    // Last: its presence marks a complete dataset.
    dataset::write_telemetry(out, &records)?;
    staged.commit()?;
    report.fx_px = fx;
    report.intrinsics_from = from;
    report.origin = Some(origin);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xmp_attributes_and_elements_are_both_read() {
        let attr = br#"xx<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description drone-dji:GimbalYawDegree="+44.20" drone-dji:RelativeAltitude="+40.10"/></rdf:RDF></x:xmpmeta>yy"#;
        let m = dji_xmp(attr);
        assert_eq!(m["GimbalYawDegree"], "+44.20");
        assert_eq!(m["RelativeAltitude"], "+40.10");
        let elem = br#"<x:xmpmeta><rdf:RDF><rdf:Description><drone-dji:FlightYawDegree>-12.5</drone-dji:FlightYawDegree></rdf:Description></rdf:RDF></x:xmpmeta>"#;
        assert_eq!(dji_xmp(elem)["FlightYawDegree"], "-12.5");
        assert!(dji_xmp(b"no packet here").is_empty());
    }

    #[test]
    fn exif_times_order_and_subtract() {
        let a = exif_seconds("2016:06:23 14:59:58").unwrap();
        let b = exif_seconds("2016:06:23 15:00:03").unwrap();
        assert_eq!(b - a, 5.0);
        let c = exif_seconds("2016:07:01 00:00:00").unwrap();
        assert_eq!(c - exif_seconds("2016:06:30 00:00:00").unwrap(), 86400.0);
        assert!(exif_seconds("garbage").is_none());
    }
}
