//! `mavloc import photos DIR --out DATASET`: geotagged drone photos to a dataset in the
//! simulation-world format (`sim/src/dataset.rs`), so `mavloc area` runs on real imagery.
//!
//! Read per photo: EXIF (GPS latitude, longitude, altitude; DateTimeOriginal; FocalLength;
//! FocalLengthIn35mmFilm; pixel size) with `kamadak-exif`, and DJI's XMP packet
//! (`drone-dji:` AbsoluteAltitude, RelativeAltitude, Gimbal{Roll,Yaw,Pitch}Degree,
//! Flight{Roll,Yaw,Pitch}Degree) with `quick-xml`, whether written as attributes or as
//! elements. senseFly photos (`sensefly:` XMP: Latitude, Longitude, AltitudeAMSL, Height,
//! Heading, PitchAngle, RollAngle, UTCTime) import with the camera fixed to the body.
//! Parrot photos (`drone-parrot:` XMP of the ANAFI family: Camera{Yaw,Pitch,Roll}Degree,
//! the gimbal's earth-frame angles with pitch -90 straight down as DJI's) import with
//! EXIF's GPS position and altitude and the ground's altitude from the user, as plain
//! EXIF photos do: their XMP has no height above take-off. A
//! photo missing any tag the pose needs is reported by name and skipped, never guessed.
//! Before anything is written, consecutive photos are checked against each other for a
//! half-turned image (`area::imageup`).
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
//! - The origin's altitude is AbsoluteAltitude minus RelativeAltitude (senseFly:
//!   AltitudeAMSL minus Height), above mean sea level like every altitude in mavloc; the
//!   result writers add the geoid where a format wants the ellipsoid (GeoJSON).
//! - Frames are the original JPEGs, copied unchanged unless undistorted (`frames/NNNNNN.jpg`); photos have no
//!   ground truth, so each record's `true` pose repeats the measured one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::geometry::{Geodetic, Intrinsics, LocalFrame};
use mavloc_data::dataset::{self, CameraFile, GimbalFrame, PoseRecord, TelemetryRecord};

/// `config/photo-survey.toml`, written into every imported dataset as its own settings.
pub const PHOTO_SURVEY_SETTINGS: &str = include_str!("../config/photo-survey.toml");

/// Diagonal of the 35 mm film frame (36 x 24 mm), millimetres.
const FILM_DIAGONAL_MM: f64 = 43.266_615;

/// What one photo says about where it was taken.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
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
    /// Gimbal yaw, pitch, roll, degrees: earth-frame (DJI) or, for a camera fixed to the
    /// body, the mount relative to the body.
    pub gimbal_deg: [f64; 3],
    /// Vehicle roll, pitch, yaw, degrees.
    pub flight_deg: [f64; 3],
    /// Whose tags gave the pose: "dji" or "parrot" (gimbal angles in the earth frame),
    /// "sensefly" (the aircraft's attitude; the camera is fixed to the body) or "exif"
    /// (no attitude).
    pub vendor: String,
    /// Focal length in pixels of this file from EXIF FocalLength and FocalPlaneXResolution,
    /// when both are there (scaled from the EXIF image width to the file's).
    pub focal_px: Option<f64>,
    /// The file's CRC-32 and length: two files alike in both are copies of one photo.
    #[serde(skip)]
    pub file_id: (u32, u64),
}

/// Where the camera's attitude comes from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Vendor {
    /// DJI: gimbal angles in the earth frame (`drone-dji:` XMP).
    Dji,
    /// senseFly: the aircraft's heading, pitch and roll (`sensefly:` XMP); the camera is
    /// fixed to the airframe.
    SenseFly,
    /// Parrot ANAFI: gimbal angles in the earth frame (`drone-parrot:` XMP), pitch -90
    /// straight down as DJI's (OpenDroneMap reads CameraPitchDegree -82 as 8 deg off
    /// nadir; a public ANAFI photo's tags are pitch -78.4, yaw 176.3); no height above
    /// take-off (`ImportOptions::ground_alt_m` required).
    Parrot,
    /// Plain EXIF GPS, no attitude: a camera fixed to the airframe, the aircraft taken as
    /// level and heading along its track (`ImportOptions::ground_alt_m` required).
    Exif,
}

/// `drone-dji:` values of a JPEG's XMP packet, attribute or element form.
pub fn dji_xmp(jpeg: &[u8]) -> BTreeMap<String, String> {
    xmp_values(jpeg, "drone-dji:")
}

/// The values under one namespace prefix (e.g. `sensefly:`) of a JPEG's XMP packet.
pub fn xmp_values(jpeg: &[u8], prefix: &str) -> BTreeMap<String, String> {
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
                    if let Some(k) = key.strip_prefix(prefix) {
                        out.insert(k.to_string(), String::from_utf8_lossy(&a.value).trim().to_string());
                    }
                }
                let name = String::from_utf8_lossy(e.name().as_ref()).to_string();
                element = name.strip_prefix(prefix).map(str::to_string);
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

/// Reads a photo's tags; the error names the photo and every missing tag. The size is the
/// JPEG's own (its frame header), not EXIF's, which some cameras leave at the sensor's
/// (the senseFly sample says 4000x3000 in files of 3600x2700). EXIF that cannot be parsed
/// (an odd maker block) is not fatal when the XMP has what the pose needs; a JPEG cut
/// short is refused.
pub fn read_tags(path: &Path) -> Result<PhotoTags, String> {
    let name = path.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    let bytes = std::fs::read(path).map_err(|e| format!("{name}: {e}"))?;
    if bytes.is_empty() {
        return Err(format!("{name}: empty file (0 bytes)"));
    }
    let file_id = (crc32fast::hash(&bytes), bytes.len() as u64);
    let (width, height) = jpeg_size(&bytes).ok_or_else(|| {
        // A JPEG's start with no frame header after it is a file cut short (inside its
        // EXIF, say), not another format.
        if bytes.starts_with(&[0xFF, 0xD8]) {
            format!("{name}: truncated or damaged JPEG (no frame header in its {} bytes)", bytes.len())
        } else {
            format!("{name}: not a JPEG (no frame header)")
        }
    })?;
    // What can be read of a damaged EXIF is kept (the GPS directory of a file whose maker
    // block or next-directory pointer is broken): the values are range-checked below.
    let mut reader = exif::Reader::new();
    reader.continue_on_error(true);
    let exif = reader.read_from_container(&mut std::io::Cursor::new(&bytes)).or_else(|e| {
        e.distill_partial_result(|errors| {
            let first = errors.first().map(|e| e.to_string()).unwrap_or_default();
            tracing::warn!("{name}: EXIF partly unreadable ({first}); using what could be read");
        })
    });
    let dji = xmp_values(&bytes, "drone-dji:");
    let sensefly = xmp_values(&bytes, "sensefly:");
    let parrot = xmp_values(&bytes, "drone-parrot:");
    let vendor = if !dji.is_empty() {
        Vendor::Dji
    } else if !sensefly.is_empty() {
        Vendor::SenseFly
    } else if !parrot.is_empty() {
        Vendor::Parrot
    } else {
        match &exif {
            Ok(_) => Vendor::Exif,
            Err(e) => {
                return Err(format!("{name}: no readable EXIF ({e}) and no DJI, senseFly or Parrot XMP"))
            }
        }
    };
    let exif = match (exif, vendor) {
        (Ok(e), _) => Some(e),
        (Err(e), Vendor::Dji | Vendor::Parrot | Vendor::Exif) => {
            return Err(format!("{name}: no readable EXIF ({e})"))
        }
        (Err(e), Vendor::SenseFly) => {
            tracing::warn!("{name}: EXIF unreadable ({e}); position and attitude from XMP");
            None
        }
    };
    let field = |t| exif.as_ref().and_then(|e| e.get_field(t, exif::In::PRIMARY));
    let mut missing: Vec<&str> = Vec::new();
    // Tags that are there but hold no usable number (`abc`, NaN, inf): named as such, not
    // as missing.
    let mut bad: Vec<String> = Vec::new();
    let dms = |t, r| -> Option<f64> {
        let v = field(t).and_then(|f| {
            let (d, m, s) = (rational_f64(f, 0)?, rational_f64(f, 1)?, rational_f64(f, 2)?);
            Some(d + m / 60.0 + s / 3600.0)
        })?;
        let sign = match field(r).map(|f| f.display_value().to_string()) {
            Some(s) if s.starts_with('S') || s.starts_with('W') => -1.0,
            _ => 1.0,
        };
        Some(sign * v)
    };
    let gps_alt = field(exif::Tag::GPSAltitude).and_then(|f| rational_f64(f, 0));
    let below = field(exif::Tag::GPSAltitudeRef).and_then(|f| f.value.get_uint(0)) == Some(1);
    let gps_alt = gps_alt.map(|a| if below { -a } else { a });
    let exif_time = field(exif::Tag::DateTimeOriginal)
        .or_else(|| field(exif::Tag::DateTime))
        .map(|f| f.display_value().to_string().replace('-', ":"));
    let focal_mm = field(exif::Tag::FocalLength).and_then(|f| rational_f64(f, 0));
    let focal_35mm =
        field(exif::Tag::FocalLengthIn35mmFilm).and_then(|f| f.value.get_uint(0)).map(|v| v as f64);
    // Pixels per millimetre on the focal plane, at the EXIF image width.
    let plane = field(exif::Tag::FocalPlaneXResolution).and_then(|f| rational_f64(f, 0)).and_then(|r| {
        let unit_mm = match field(exif::Tag::FocalPlaneResolutionUnit).and_then(|f| f.value.get_uint(0)) {
            Some(3) => 10.0,
            Some(4) => 1.0,
            Some(5) => 0.001,
            _ => 25.4, // 2 = inch, the default
        };
        (r > 0.0).then_some(r / unit_mm)
    });
    let exif_width = field(exif::Tag::PixelXDimension).and_then(|f| f.value.get_uint(0)).filter(|&w| w > 0);
    let focal_px = match (focal_mm, plane) {
        (Some(f), Some(px_per_mm)) => {
            Some(f * px_per_mm * exif_width.map_or(1.0, |w| width as f64 / w as f64))
        }
        _ => None,
    };
    let mut num = |xmp: &BTreeMap<String, String>, key: &'static str| -> f64 {
        match xmp.get(key) {
            Some(text) => match text.trim_start_matches('+').parse::<f64>() {
                Ok(v) if v.is_finite() => v,
                _ => {
                    bad.push(format!(
                        "{key} `{}` is not a number",
                        text.chars().take(40).collect::<String>()
                    ));
                    f64::NAN
                }
            },
            None => {
                missing.push(key);
                f64::NAN
            }
        }
    };
    // Position, altitude and time from EXIF (DJI, Parrot and plain EXIF photos), the
    // altitude from `fallback_alt` where EXIF has none; the attitude and the height above
    // the ground are the caller's.
    let exif_position = |missing: &mut Vec<&'static str>, fallback_alt: Option<f64>| {
        let lat = dms(exif::Tag::GPSLatitude, exif::Tag::GPSLatitudeRef);
        let lon = dms(exif::Tag::GPSLongitude, exif::Tag::GPSLongitudeRef);
        // Without its reference a coordinate's hemisphere is a guess (EXIF requires both):
        // a west longitude read as east put a photo 3000 km away.
        for (v, r, tag) in [
            (lat, exif::Tag::GPSLatitudeRef, "GPSLatitudeRef"),
            (lon, exif::Tag::GPSLongitudeRef, "GPSLongitudeRef"),
        ] {
            if v.is_some() && field(r).is_none() {
                missing.push(tag);
            }
        }
        let gps_alt = gps_alt.or(fallback_alt);
        for (v, tag) in [(lat, "GPSLatitude"), (lon, "GPSLongitude"), (gps_alt, "GPSAltitude")] {
            if v.is_none() {
                missing.push(tag);
            }
        }
        let alt = gps_alt.unwrap_or(f64::NAN);
        PhotoTags {
            name: name.clone(),
            width,
            height,
            lat_deg: lat.unwrap_or(f64::NAN),
            lon_deg: lon.unwrap_or(f64::NAN),
            gps_alt_m: alt,
            time: exif_time.clone().unwrap_or_default(),
            focal_mm,
            focal_35mm,
            absolute_alt_m: alt,
            relative_alt_m: f64::NAN,
            gimbal_deg: [f64::NAN; 3],
            flight_deg: [f64::NAN; 3],
            vendor: String::new(),
            focal_px,
            file_id,
        }
    };
    let tags = match vendor {
        Vendor::Dji => {
            let absolute = num(&dji, "AbsoluteAltitude");
            let relative = num(&dji, "RelativeAltitude");
            let gimbal =
                [num(&dji, "GimbalYawDegree"), num(&dji, "GimbalPitchDegree"), num(&dji, "GimbalRollDegree")];
            let flight =
                [num(&dji, "FlightRollDegree"), num(&dji, "FlightPitchDegree"), num(&dji, "FlightYawDegree")];
            // EXIF GPSAltitude, else DJI's own AbsoluteAltitude (missing is then named).
            PhotoTags {
                absolute_alt_m: absolute,
                relative_alt_m: relative,
                gimbal_deg: gimbal,
                flight_deg: flight,
                vendor: "dji".into(),
                ..exif_position(&mut missing, Some(absolute).filter(|a| a.is_finite()))
            }
        }
        Vendor::SenseFly => {
            // senseFly writes its own position (the EXIF GPS repeats it, rounded), the
            // altitude above sea level and `Height`, a fixed offset below it (take-off
            // height), and the aircraft's heading, pitch and roll.
            let lat = num(&sensefly, "Latitude");
            let lon = num(&sensefly, "Longitude");
            let absolute = num(&sensefly, "AltitudeAMSL");
            let relative = num(&sensefly, "Height");
            let attitude =
                [num(&sensefly, "RollAngle"), num(&sensefly, "PitchAngle"), num(&sensefly, "Heading")];
            // UTC "2013-06-04T17:50:37" (the camera's own clock is off by hours and seconds).
            let time =
                sensefly.get("UTCTime").map(|t| t.replace('-', ":").replace('T', " ")).or(exif_time.clone());
            PhotoTags {
                name: name.clone(),
                width,
                height,
                lat_deg: lat,
                lon_deg: lon,
                gps_alt_m: gps_alt.unwrap_or(absolute),
                time: time.unwrap_or_default(),
                focal_mm,
                focal_35mm,
                absolute_alt_m: absolute,
                relative_alt_m: relative,
                gimbal_deg: [0.0, -90.0, 0.0],
                flight_deg: attitude,
                vendor: "sensefly".into(),
                focal_px,
                file_id,
            }
        }
        Vendor::Parrot => {
            // Position, altitude and time from EXIF; the gimbal's earth-frame angles from
            // the XMP (the airframe's, Flight*Degree, when written); the height above the
            // ground from the user at import.
            let gimbal = [
                num(&parrot, "CameraYawDegree"),
                num(&parrot, "CameraPitchDegree"),
                num(&parrot, "CameraRollDegree"),
            ];
            let opt = |k: &str| parrot.get(k).and_then(|v| v.trim_start_matches('+').parse::<f64>().ok());
            let flight = [
                opt("FlightRollDegree").unwrap_or(0.0),
                opt("FlightPitchDegree").unwrap_or(0.0),
                opt("FlightYawDegree").unwrap_or(gimbal[0]),
            ];
            PhotoTags {
                gimbal_deg: gimbal,
                flight_deg: flight,
                vendor: "parrot".into(),
                ..exif_position(&mut missing, None)
            }
        }
        Vendor::Exif => {
            // Position and time from EXIF alone; the attitude comes from the track at
            // import (`import_photos`), the height above ground from the user.
            PhotoTags {
                gimbal_deg: [0.0, -90.0, 0.0],
                flight_deg: [0.0, 0.0, f64::NAN],
                vendor: "exif".into(),
                ..exif_position(&mut missing, None)
            }
        }
    };
    if tags.time.is_empty() {
        missing.push("DateTimeOriginal");
    }
    if !missing.is_empty() || !bad.is_empty() {
        let missing = (!missing.is_empty()).then(|| format!("missing {}", missing.join(", ")));
        let all: Vec<String> = missing.into_iter().chain(bad).collect();
        return Err(format!("{name}: {}", all.join("; ")));
    }
    check_values(&tags).map_err(|e| format!("{name}: {e}"))?;
    // Tags come first in the file, so a cut photo still has them: check the image too.
    if crate::imaging::jpeg_truncated(&bytes) {
        return Err(format!("{name}: truncated JPEG (the image data ends early)"));
    }
    Ok(tags)
}

/// How far from one another a survey's photos may be: a photo farther than this from the
/// photo with the most others within it is skipped. A long corridor flown in one go fits
/// (50 km is an hour of a fixed-wing survey); a tag from the wrong continent does not.
const SURVEY_RADIUS_M: f64 = 50_000.0;

/// For each position (latitude, longitude in degrees), its distance in km from the
/// survey's centre photo when over [`SURVEY_RADIUS_M`], else `None`. The centre is the
/// photo with the most others within the radius (the first of equals), not the median,
/// which two sites in one folder would put between them.
fn far_from_the_survey(positions: &[(f64, f64)]) -> Vec<Option<f64>> {
    let Some(&(lat, lon)) = positions.first() else {
        return Vec::new();
    };
    // On the ellipsoid, in one local frame: the straight line between two points is the
    // difference of their local coordinates, however far apart they are.
    let frame = LocalFrame::new(Geodetic::new(lat, lon, 0.0));
    let at: Vec<crate::geometry::Vec3> =
        positions.iter().map(|&(lat, lon)| frame.to_ned(&Geodetic::new(lat, lon, 0.0))).collect();
    // Quadratic in the photos: a few thousand is milliseconds.
    let within = |p: &crate::geometry::Vec3| at.iter().filter(|q| (*q - p).norm() <= SURVEY_RADIUS_M).count();
    let centre =
        at.iter().reduce(|best, p| if within(p) > within(best) { p } else { best }).expect("one photo");
    at.iter()
        .map(|p| {
            let d = (p - centre).norm();
            (d > SURVEY_RADIUS_M).then_some(d / 1000.0)
        })
        .collect()
}

/// The tags' numbers within what a photo from a drone can hold: a position on the globe
/// (an EXIF rational of 46/0 read as an infinite latitude, and 91 deg, were imported), a
/// finite height, angles of at most two turns. Each photo on its own: only the first was
/// checked, and a later one 3000 km off or 1e308 m high was imported without a word.
fn check_values(t: &PhotoTags) -> Result<(), String> {
    Geodetic::new(t.lat_deg, t.lon_deg, t.absolute_alt_m).validate()?;
    // The height above take-off is NaN until --ground-alt-m gives it (Parrot, plain EXIF).
    if t.relative_alt_m.abs() > 20_000.0 {
        let h = crate::geometry::readable(t.relative_alt_m);
        return Err(format!("height above take-off {h} m is outside [-20000, 20000]"));
    }
    let angles = [("gimbal", t.gimbal_deg), ("aircraft", t.flight_deg)];
    for (what, deg) in angles {
        // The aircraft's yaw of a plain-EXIF photo comes from its track later (NaN here).
        if let Some(a) = deg.iter().find(|a| a.abs() > 720.0) {
            let a = crate::geometry::readable(*a);
            return Err(format!("{what} angle {a} deg is not an angle (at most two turns either way)"));
        }
    }
    Ok(())
}

/// Width and height from a JPEG's start-of-frame marker (SOF0..SOF15 but DHT, JPG, DAC).
pub fn jpeg_size(bytes: &[u8]) -> Option<(u32, u32)> {
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return None;
    }
    let mut i = 2;
    while i + 9 < bytes.len() {
        if bytes[i] != 0xFF {
            return None;
        }
        let marker = bytes[i + 1];
        if marker == 0xFF {
            i += 1; // fill byte
            continue;
        }
        let len = u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]) as usize;
        if (0xC0..=0xCF).contains(&marker) && ![0xC4, 0xC8, 0xCC].contains(&marker) {
            let h = u16::from_be_bytes([bytes[i + 5], bytes[i + 6]]) as u32;
            let w = u16::from_be_bytes([bytes[i + 7], bytes[i + 8]]) as u32;
            return (w > 0 && h > 0).then_some((w, h));
        }
        if marker == 0xDA {
            return None; // image data before any frame header
        }
        i += 2 + len;
    }
    None
}

/// Seconds since 0000-01-01 of an EXIF time, for ordering and intervals.
fn exif_seconds(t: &str) -> Option<f64> {
    let p: Vec<f64> = t.split([':', ' ']).map(|x| x.trim().parse::<f64>().ok()).collect::<Option<_>>()?;
    if p.len() < 6 {
        return None;
    }
    // Days from a civil date (proleptic Gregorian), enough for differences. A camera
    // whose clock was never set writes zeros ("0000:00:00 00:00:00"): no date.
    let (y, m, d) = (p[0] as i64, p[1] as i64, p[2] as i64);
    let clock = (p[3], p[4], p[5]);
    if y < 1970
        || !(1..=12).contains(&m)
        || !(1..=31).contains(&d)
        || !(0.0..24.0).contains(&clock.0)
        || !(0.0..60.0).contains(&clock.1)
        || !(0.0..61.0).contains(&clock.2)
    {
        return None;
    }
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
    /// The coefficients, for photos of `width` x `height`.
    fn check(&self, width: u32, height: u32) -> Result<(), String> {
        if ![0, 4, 5, 8].contains(&self.distortion.len()) {
            return Err(format!(
                "distortion has {} coefficients; OpenCV's model takes 4, 5 or 8 ([k1, k2, p1, p2, k3, ...])",
                self.distortion.len()
            ));
        }
        if let Some(d) = self.distortion.iter().find(|d| !d.is_finite()) {
            return Err(format!("distortion coefficient {d} is not a finite number"));
        }
        if !(self.fx >= 1.0 && self.fy >= 1.0 && self.fx.is_finite() && self.fy.is_finite()) {
            return Err(format!("fx = {} and fy = {} must be focal lengths in pixels", self.fx, self.fy));
        }
        let k = Intrinsics { width, height, fx: self.fx, fy: self.fy, cx: self.cx, cy: self.cy };
        match crate::lens::fold_problem(&k, &self.distortion) {
            Some(problem) => {
                Err(format!("distortion {:?} on {width}x{height} photos: {problem}", self.distortion))
            }
            None => Ok(()),
        }
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

/// The error of an import stopped by [`ImportOptions::stop`].
pub const STOPPED: &str = "stopped by Ctrl-C";

/// How to import.
#[derive(Clone, Debug, Default)]
pub struct ImportOptions {
    /// Intrinsics (and distortion) instead of the estimate from the EXIF focal length.
    pub calibration: Option<PathBuf>,
    /// Replace a non-empty output folder (`--force`).
    pub replace: bool,
    /// For a camera fixed to the airframe (senseFly): its yaw, pitch, roll relative to the
    /// body, degrees; default `[0, -90, 0]`, looking straight down with the image's top
    /// towards the nose.
    pub mount_deg: Option<[f64; 3]>,
    /// The ground's altitude in the photos' altitude datum (m). For photos with no height
    /// above take-off (plain EXIF GPS, Parrot): where new landmarks start. For photos with
    /// one (DJI, senseFly): the take-off's altitude, instead of the tags' absolute altitude
    /// less that height.
    pub ground_alt_m: Option<f64>,
    /// What the photos' absolute altitudes are heights above; default by vendor
    /// ([`AltitudeDatum::of_vendor`]).
    pub altitude_datum: Option<AltitudeDatum>,
    /// Set (by Ctrl-C) to stop after the photo in hand: the import then fails, its staging
    /// folder is removed and `out` stays as it was.
    pub stop: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

/// What a photo's absolute altitude is a height above. A dataset's altitudes are above
/// mean sea level (the EGM96 geoid), as KML shows them; one above the WGS84 ellipsoid is
/// taken down to it by the geoid's undulation there (tens of metres in places: -28.7 m at
/// the DJI sample's lake shore).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum AltitudeDatum {
    /// The WGS84 ellipsoid: DJI's AbsoluteAltitude, which DJI documents as geodetic height
    /// (the Zenmuse P1's XMP field list) and which on the sample (Phantom 3, FC300S) puts
    /// the lake shore 28 m below the lake's 183 m above sea level, the geoid's undulation
    /// there to 0.5 m, until taken down to the geoid.
    Ellipsoid,
    /// Mean sea level: EXIF's GPSAltitude as the EXIF standard defines it.
    SeaLevel,
}

impl AltitudeDatum {
    /// DJI's tags above the ellipsoid, every other vendor's above sea level.
    pub fn of_vendor(vendor: &str) -> AltitudeDatum {
        if vendor == "dji" {
            AltitudeDatum::Ellipsoid
        } else {
            AltitudeDatum::SeaLevel
        }
    }
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
    /// How the photos' altitudes were read (their datum and, for the ellipsoid, the geoid's
    /// undulation at the origin).
    pub altitudes: String,
    /// Set when the user's edited settings file was kept (and why).
    pub kept_settings: Option<String>,
    /// Median ground disagreement of consecutive overlapping photos, after any turn, m.
    pub overlap_median_m: Option<f64>,
    /// Photos whose image was found turned half a turn from their tags (yaw corrected).
    pub turned: Vec<String>,
}

impl ImportReport {
    /// Skips a photo: said in the log as it happens, and named with the reason in the report.
    fn skip(&mut self, name: &str, why: String) {
        tracing::warn!("skipped {name}: {why}");
        self.skipped.push((name.to_string(), why));
    }
}

/// A photo as the import holds it: capture time (s), path, tags.
type Photo = (f64, PathBuf, PhotoTags);

/// Keeps the photos whose `key` most of them share (of equals, the earliest photo's, the
/// photos being in capture order) and skips the others, each named with `why(its, kept)`.
fn keep_the_most_common<K: PartialEq>(
    photos: &mut Vec<Photo>,
    report: &mut ImportReport,
    key: impl Fn(&PhotoTags) -> K,
    why: impl Fn(&K, &K) -> String,
) {
    let keys: Vec<K> = photos.iter().map(|(_, _, t)| key(t)).collect();
    let count = |k: &K| keys.iter().filter(|x| *x == k).count();
    let Some(kept) = keys.iter().reduce(|best, k| if count(k) > count(best) { k } else { best }) else {
        return;
    };
    let mut keys_in_order = keys.iter();
    photos.retain(|(_, _, t)| {
        let k = keys_in_order.next().expect("one key a photo");
        let keep = k == kept;
        if !keep {
            report.skip(&t.name, why(k, kept));
        }
        keep
    });
}

/// Each photo's heading (degrees, clockwise from north) along the track, photos in capture
/// order: the courses to and from its neighbours, averaged where they agree; where they do
/// not (the first and last photo of a survey line, beside the turn to the next line) the
/// one that continues its own line (agrees with the course one photo further out). A photo
/// with no course (taken where its neighbours were) gets the nearest one's.
fn track_headings(photos: &mut [Photo]) {
    let n = photos.len();
    let course = |a: usize, b: usize| -> Option<f64> {
        if a >= n || b >= n || a == b {
            return None;
        }
        let (a, b) = (&photos[a].2, &photos[b].2);
        // Local east and north over a short distance.
        let north = (b.lat_deg - a.lat_deg).to_radians() * 6_371_000.0;
        let east = (b.lon_deg - a.lon_deg).to_radians() * 6_371_000.0 * a.lat_deg.to_radians().cos();
        (north.hypot(east) > 0.5).then(|| east.atan2(north).to_degrees().rem_euclid(360.0))
    };
    let diff = |a: f64, b: f64| ((a - b + 540.0).rem_euclid(360.0) - 180.0).abs();
    let agree = |a: Option<f64>, b: Option<f64>| matches!((a, b), (Some(a), Some(b)) if diff(a, b) <= 20.0);
    let courses: Vec<Option<f64>> = (0..n)
        .map(|i| {
            let before = i.checked_sub(1).and_then(|a| course(a, i));
            let after = course(i, i + 1);
            match (before, after) {
                (Some(b), Some(a)) if diff(a, b) <= 20.0 => {
                    let (sb, cb) = b.to_radians().sin_cos();
                    let (sa, ca) = a.to_radians().sin_cos();
                    Some((sb + sa).atan2(cb + ca).to_degrees().rem_euclid(360.0))
                }
                (Some(b), Some(a)) => {
                    let further_back = i.checked_sub(2).and_then(|x| course(x, x + 1));
                    if agree(Some(b), further_back) {
                        Some(b)
                    } else if agree(Some(a), course(i + 1, i + 2)) {
                        Some(a)
                    } else {
                        Some(b)
                    }
                }
                (b, a) => b.or(a),
            }
        })
        .collect();
    for i in 0..n {
        let c = courses[i].or_else(|| {
            (1..n).find_map(|d| {
                courses.get(i + d).copied().flatten().or(i.checked_sub(d).and_then(|j| courses[j]))
            })
        });
        photos[i].2.flight_deg[2] = c.unwrap_or(0.0);
    }
    if courses.iter().all(Option::is_none) {
        tracing::warn!(
            "no track to take a heading from ({} photo{} less than 0.5 m apart): heading 0 (north) assumed; \
             the alignment by tie points cannot correct a heading without overlapping photos",
            n,
            if n == 1 { "" } else { "s" }
        );
    }
}

/// Nadir within this: turning the image about the optical axis is then a yaw of 180 deg.
const NADIR_TOLERANCE_DEG: f64 = 15.0;

/// Runs the image-up check on the written frames and corrects the yaw of turned photos.
/// Returns the median ground disagreement after correction and the turned indices.
fn image_up(
    dir: &Path,
    camera: &CameraFile,
    records: &mut [TelemetryRecord],
    stopped: &dyn Fn() -> bool,
) -> Result<(Option<f64>, Vec<usize>), String> {
    use crate::area::imageup;
    let k = camera.intrinsics();
    let pose = |r: &TelemetryRecord| r.measured.camera_pose(camera.chain, camera.gimbal_frame);
    let mut feats = Vec::with_capacity(records.len());
    // Checked per photo and per pair: decoding and matching full-size photos is most of an
    // import's time, so each is decoded only as large as the check needs.
    let (flags, factor) = imageup::reduced_read(camera.width);
    for r in records.iter() {
        if stopped() {
            return Err(STOPPED.into());
        }
        let path = dir.join("frames").join(format!("{:06}.jpg", r.frame));
        let err = |e: opencv::Error| format!("{}: {e}", path.display());
        let img = crate::imaging::read_image(&path, flags)?;
        let reduced =
            imageup::features_of_reduced(&img, (camera.width, camera.height), factor).map_err(err)?;
        let f = match reduced {
            Some(f) => f,
            None => {
                let img = crate::imaging::read_image(&path, opencv::imgcodecs::IMREAD_COLOR)?;
                imageup::features(&img).map_err(err)?
            }
        };
        feats.push(f);
    }
    let mut votes = Vec::new();
    for i in 1..records.len() {
        if stopped() {
            return Err(STOPPED.into());
        }
        let (pa, pb) = (pose(&records[i - 1]), pose(&records[i]));
        if let Some(v) = imageup::vote((i - 1, &feats[i - 1], &pa), (i, &feats[i], &pb), &k, 0.0)
            .map_err(|e| format!("matching photos {} and {}: {e}", i - 1, i))?
        {
            tracing::debug!(pair = ?(i - 1, i), matches = v.matches, median_m = ?v.median_m, "image-up vote");
            votes.push(v);
        }
    }
    let verdicts = imageup::verdicts(records.len(), &votes);
    let mut turned = Vec::new();
    for (i, r) in records.iter_mut().enumerate().filter(|(i, _)| verdicts[*i]) {
        // A yaw of 180 deg about the gimbal's (or, fixed to the body, the mount's) vertical
        // is a half turn about the optical axis only for a camera pointing along it.
        if (r.measured.gimbal_deg[1] + 90.0).abs() > NADIR_TOLERANCE_DEG {
            tracing::warn!("photo {i} looks turned half a turn, but its camera is not nadir: left as tagged");
            continue;
        }
        let yaw = (r.measured.gimbal_deg[0] + 360.0) % 360.0 - 180.0;
        r.measured.gimbal_deg[0] = yaw;
        r.truth.gimbal_deg[0] = yaw;
        turned.push(i);
    }
    // The agreement that remains, each pair with its photos as they now are.
    let mut medians: Vec<f64> = votes
        .iter()
        .map(|v| {
            let idx = (verdicts[v.a] && turned.contains(&v.a)) as usize * 2
                + (verdicts[v.b] && turned.contains(&v.b)) as usize;
            v.median_m[idx]
        })
        .filter(|m| m.is_finite())
        .collect();
    medians.sort_by(f64::total_cmp);
    Ok((medians.get(medians.len() / 2).copied(), turned))
}

/// Imports the photos of `dir` (JPEG) into a dataset at `out`, written beside it and put
/// in place whole; a non-empty `out` is replaced only with `replace` (`--force`), keeping
/// a `mavloc.toml` the user edited.
pub fn import_photos(dir: &Path, out: &Path, opts: &ImportOptions) -> Result<ImportReport, String> {
    let (calibration, replace) = (opts.calibration.as_deref(), opts.replace);
    if mavloc_data::staged::nested(dir, out) {
        return Err(format!(
            "--out {} and the photos' folder {} are the same or one is inside the other: choose an output folder elsewhere",
            out.display(),
            dir.display()
        ));
    }
    let entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    let is_photo = |p: &PathBuf| {
        let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        p.is_file() && (ext == "jpg" || ext == "jpeg")
    };
    let mut paths: Vec<PathBuf> = entries.iter().filter(|p| is_photo(p)).cloned().collect();
    paths.sort();
    // Anything else in the folder is said once (a PNG, a link that leads nowhere), so a
    // photo left out is not left out unnoticed.
    let others: Vec<String> = entries
        .iter()
        .filter(|p| !is_photo(p) && !p.is_dir())
        .map(|p| {
            let name = p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            if p.is_symlink() && !p.exists() {
                format!("{name} (a link that leads nowhere)")
            } else {
                name
            }
        })
        .collect();
    if !others.is_empty() {
        let shown: Vec<&str> = others.iter().take(5).map(String::as_str).collect();
        let more = if others.len() > 5 { format!(" and {} more", others.len() - 5) } else { String::new() };
        tracing::warn!("not photos (only .jpg and .jpeg files are read): {}{more}", shown.join(", "));
    }
    // One folder, not a tree: said, so photos in a subfolder are not missed unnoticed.
    // (A link to the folder itself or above it is not a subfolder.)
    let here = dir.canonicalize().ok();
    let subfolders = entries
        .iter()
        .filter(|p| {
            p.is_dir() && !p.canonicalize().is_ok_and(|c| here.as_ref().is_some_and(|d| d.starts_with(&c)))
        })
        .count();
    if subfolders > 0 {
        tracing::warn!(
            "{} subfolder{} of {} not searched: import each folder of photos on its own",
            subfolders,
            if subfolders == 1 { "" } else { "s" },
            dir.display()
        );
    }
    if paths.is_empty() {
        return Err(format!(
            "{} holds no JPEG photos{}",
            dir.display(),
            if subfolders > 0 { " (its subfolders are not searched)" } else { "" }
        ));
    }
    let mut report = ImportReport::default();
    let mut photos = Vec::new();
    for p in &paths {
        match read_tags(p) {
            Ok(t) => match exif_seconds(&t.time) {
                Some(s) => photos.push((s, p.clone(), t)),
                None => report.skip(
                    &t.name,
                    format!("capture time `{}` is not a date (a camera clock never set?)", t.time),
                ),
            },
            Err(e) => {
                let name = p.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
                // The reason without the name `read_tags` puts first (the report names it).
                let why = e.strip_prefix(&format!("{name}: ")).unwrap_or(&e).to_string();
                report.skip(&name, why);
            }
        }
    }
    // The same photo twice (a copy beside the original): one shot, not two views from one
    // place, which would make the overlap checks and the alignment agree with themselves.
    // The bytes decide (their CRC-32 and length), not the tags alone: a camera that shoots
    // twice a second with GPS at 1 Hz and no attitude tags tags two shots alike.
    let mut seen: std::collections::BTreeMap<(u32, u64), String> = std::collections::BTreeMap::new();
    photos.retain(|(_, _, t)| match seen.get(&t.file_id) {
        Some(first) => {
            report.skip(&t.name, format!("the same file as {first}"));
            false
        }
        None => {
            seen.insert(t.file_id, t.name.clone());
            true
        }
    });
    // A photo whose tags read but whose image OpenCV cannot decode (a forged or damaged
    // header) is named and skipped here, not found later by the overlap check, which
    // failed the whole import naming the staging copy. Decoded at an eighth of its size
    // (libjpeg's DCT scaling): about 10 ms a photo.
    photos.retain(|(_, path, t)| {
        // OpenCV refuses images over 2^30 pixels (CV_IO_MAX_IMAGE_PIXELS) at full size but
        // decodes the reduced one, so the header's size is checked too.
        let decoded = (t.width as u64) * (t.height as u64) <= 1 << 30
            && opencv::imgcodecs::imread(path, opencv::imgcodecs::IMREAD_REDUCED_GRAYSCALE_8)
                .map(|m| {
                    use opencv::prelude::MatTraitConst;
                    !m.empty()
                })
                .unwrap_or(false);
        if !decoded {
            report.skip(
                &t.name,
                format!("not an image OpenCV can decode (its header says {}x{})", t.width, t.height),
            );
        }
        decoded
    });
    if photos.is_empty() {
        let (first, why) = &report.skipped[0];
        let more = match report.skipped.len() {
            1 => String::new(),
            n => format!(" (and {} more; each is named above)", n - 1),
        };
        return Err(format!("no photo in {} could be used: {first}: {why}{more}", dir.display()));
    }
    // A stray photo without attitude tags among DJI or senseFly ones (an edited copy) is
    // skipped, not taken for a camera of its own.
    if photos.iter().any(|(_, _, t)| t.vendor != "exif") {
        let (keep, plain): (Vec<_>, Vec<_>) = photos.into_iter().partition(|(_, _, t)| t.vendor != "exif");
        for (_, _, t) in plain {
            report.skip(&t.name, "EXIF GPS but no attitude tags, among photos that have them".into());
        }
        photos = keep;
    }
    // One camera per dataset: photos of another kind of tags or of another size are the
    // fewer ones, skipped and named, not the end of the import.
    photos.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    keep_the_most_common(
        &mut photos,
        &mut report,
        |t| t.vendor.clone(),
        |its, kept| format!("{its} tags among {kept} photos: one camera per dataset"),
    );
    keep_the_most_common(
        &mut photos,
        &mut report,
        |t| (t.width, t.height),
        |its, kept| format!("{}x{} among {}x{} photos: one camera per dataset", its.0, its.1, kept.0, kept.1),
    );
    // A photo far from the survey (a GPS fix from elsewhere, a corrupted tag) is skipped:
    // the survey is where most photos are within `SURVEY_RADIUS_M` of one of them.
    let far = far_from_the_survey(&photos.iter().map(|(_, _, t)| (t.lat_deg, t.lon_deg)).collect::<Vec<_>>());
    let mut far = far.into_iter();
    photos.retain(|(_, _, t)| match far.next().flatten() {
        Some(km) => {
            let within = SURVEY_RADIUS_M / 1000.0;
            report.skip(
                &t.name,
                format!("{km:.0} km from the survey (the most photos within {within} km of one another): a wrong GPS tag?"),
            );
            false
        }
        None => true,
    });
    let body_mounted = photos[0].2.vendor == "sensefly" || photos[0].2.vendor == "exif";
    let needs_ground = matches!(photos[0].2.vendor.as_str(), "exif" | "parrot");
    if needs_ground {
        let ground = opts.ground_alt_m.ok_or_else(|| {
            let what = if photos[0].2.vendor == "parrot" {
                "Parrot XMP, which has no height above take-off"
            } else {
                "EXIF GPS but no attitude tags (no DJI, senseFly or Parrot XMP)"
            };
            format!(
                "{} has {what}: give the ground's altitude with --ground-alt-m (in the photos' GPS altitude, {:.1} m for this one){}",
                photos[0].2.name,
                photos[0].2.gps_alt_m,
                if photos[0].2.vendor == "exif" {
                    ", and the camera's mount with --mount-deg if it is not straight down with its top to the nose"
                } else {
                    ""
                }
            )
        })?;
        photos.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        if photos[0].2.vendor == "exif" {
            // No attitude in the photos: level, heading along the track (the alignment by
            // tie points finds the rest, as it does for senseFly's 10-20 deg heading errors).
            track_headings(&mut photos);
        }
        for (_, _, t) in photos.iter_mut() {
            t.relative_alt_m = t.absolute_alt_m - ground;
            if t.relative_alt_m <= 0.0 {
                return Err(format!(
                    "{}: its GPS altitude {:.1} m is not above --ground-alt-m {ground} m (is the ground in the photos' altitude datum?)",
                    t.name, t.absolute_alt_m
                ));
            }
        }
    } else if let Some(ground) = opts.ground_alt_m {
        // Photos with a height above take-off: the ground's altitude stands for the
        // absolute altitude's take-off (consumer DJI models write a barometric one that
        // drifts with the weather by tens of metres).
        let first = &photos[0].2;
        tracing::info!(
            "--ground-alt-m {ground} m is the take-off's altitude, where the tags put it at {:.2} m",
            first.absolute_alt_m - first.relative_alt_m
        );
        for (_, _, t) in photos.iter_mut() {
            t.absolute_alt_m = ground + t.relative_alt_m;
        }
    }
    // Heights above the ellipsoid to heights above sea level, each at its own place (after
    // the ground's altitude above, which is in the photos' own datum).
    let datum = opts.altitude_datum.unwrap_or_else(|| AltitudeDatum::of_vendor(&photos[0].2.vendor));
    let n_m = mavloc_data::geoid::undulation_m(photos[0].2.lat_deg, photos[0].2.lon_deg);
    report.altitudes = match datum {
        AltitudeDatum::Ellipsoid => {
            for (_, _, t) in photos.iter_mut() {
                t.absolute_alt_m -= mavloc_data::geoid::undulation_m(t.lat_deg, t.lon_deg);
            }
            format!(
                "the photos' altitudes are above the WGS84 ellipsoid (--altitude-datum ellipsoid{}): taken to above sea level by the EGM96 geoid's undulation there ({n_m:+.1} m)",
                if opts.altitude_datum.is_none() { ", DJI's" } else { "" }
            )
        }
        AltitudeDatum::SeaLevel => format!(
            "the photos' altitudes are above sea level (--altitude-datum sea-level{}; the EGM96 geoid's undulation here is {n_m:+.1} m)",
            if opts.altitude_datum.is_none() { ", EXIF's" } else { "" },
        ),
    };
    let mount_deg = opts.mount_deg.unwrap_or([0.0, -90.0, 0.0]);
    // By capture time; the name breaks ties (DJI writes whole seconds).
    photos.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let first = &photos[0].2;
    let (w, h) = (first.width, first.height);
    let origin = Geodetic::new(first.lat_deg, first.lon_deg, first.absolute_alt_m - first.relative_alt_m);
    origin.validate().map_err(|e| format!("{}: {e}", first.name))?;
    let mut undistort = None;
    let (fx, fy, cx, cy, from) = match calibration {
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
            let c: Calibration = toml::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))?;
            c.check(w, h).map_err(|e| format!("{}: {e}", p.display()))?;
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
            let cx = (w as f64 - 1.0) / 2.0;
            let cy = (h as f64 - 1.0) / 2.0;
            // One camera per dataset (`keep_the_most_common`): a photo whose EXIF lost its
            // focal length (damaged, or never written) takes the others'.
            let has_focal = |t: &PhotoTags| t.focal_35mm.is_some() || t.focal_px.is_some();
            let Some(lens) = photos.iter().map(|p| &p.2).find(|t| has_focal(t)) else {
                return Err(format!(
                    "no photo carries a focal length (FocalLengthIn35mmFilm, or FocalLength with FocalPlaneXResolution): give the camera's intrinsics with --calibration (first photo {})",
                    first.name
                ));
            };
            let without: Vec<&str> =
                photos.iter().map(|p| &p.2).filter(|t| !has_focal(t)).map(|t| t.name.as_str()).collect();
            if !without.is_empty() {
                tracing::warn!(
                    "{} photo(s) carry no focal length and take {}'s, the same camera: {}",
                    without.len(),
                    lens.name,
                    without.join(", ")
                );
            }
            match (lens.focal_35mm, lens.focal_px) {
                (Some(f35), _) => {
                    // The equivalent focal length refers to the whole sensor; a photo wider
                    // than 4:3 is taken as a crop of a 4:3 sensor of the same width (DJI's
                    // 16:9 modes).
                    let sensor_h = (h as f64).max(w as f64 * 3.0 / 4.0);
                    let f = f35 * ((w as f64).powi(2) + sensor_h.powi(2)).sqrt() / FILM_DIAGONAL_MM;
                    (f, f, cx, cy, format!("35 mm-equivalent focal length {f35} mm on the diagonal"))
                }
                (None, Some(f)) => {
                    // A file smaller than EXIF's image width is taken as scaled, not cropped:
                    // nothing in the tags says which (README, "Real photos").
                    let from = format!(
                        "focal length {} mm at the focal-plane resolution, scaled to the file's width",
                        lens.focal_mm.unwrap_or(f64::NAN)
                    );
                    (f, f, cx, cy, from)
                }
                (None, None) => unreachable!("a photo with a focal length was found"),
            }
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
        gimbal_frame: if body_mounted { GimbalFrame::Body } else { GimbalFrame::Earth },
        origin,
    };
    camera.intrinsics().validate().map_err(|e| format!("intrinsics: {e}"))?;
    let staged = mavloc_data::staged::begin_dataset(out, replace)?;
    let (final_dir, out) = (out, staged.path());
    dataset::prepare(out)?;
    let frame = LocalFrame::new(origin);
    let t0 = photos[0].0;
    let mut records = Vec::with_capacity(photos.len());
    let stopped = || opts.stop.as_ref().is_some_and(|s| s.load(std::sync::atomic::Ordering::SeqCst));
    for (i, (s, path, t)) in photos.iter().enumerate() {
        if stopped() {
            return Err(STOPPED.into());
        }
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
            gimbal_deg: if body_mounted { mount_deg } else { t.gimbal_deg },
            velocity: [0.0; 3],
        };
        records.push(TelemetryRecord {
            frame: i as u64,
            t: s - t0,
            truth: pose,
            measured: pose,
            appearance: None,
            autopilot_time: None,
        });
        report.imported.push(t.name.clone());
    }
    // Which way up: overlapping photos must see the same ground (area::imageup). A photo
    // whose image is turned half a turn from its tags gets its yaw corrected here, before
    // any landmark is estimated from it.
    let check = image_up(out, &camera, &mut records, &stopped)?;
    report.overlap_median_m = check.0;
    report.turned = check.1.iter().map(|&i| photos[i].2.name.clone()).collect();
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
    // Last: its presence marks a complete dataset. A stop up to here leaves `out` as it was.
    if stopped() {
        return Err(STOPPED.into());
    }
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

    /// The survey is where the most photos are: a photo from another continent and a
    /// smaller group 200 km off are far from it, whatever their order; photos across a
    /// 40 km corridor are not.
    #[test]
    fn photos_far_from_the_survey_are_found_whatever_their_order() {
        let site = |lat: f64, lon: f64, n: usize| (0..n).map(move |i| (lat + i as f64 * 1e-4, lon));
        let mut p: Vec<(f64, f64)> = site(46.84, -91.99, 3).collect();
        p.extend(site(45.0, -91.99, 2)); // 205 km south
        p.extend(site(46.84, -91.99, 7));
        p.push((46.84, 91.99)); // a west longitude read as east
        let far = far_from_the_survey(&p);
        let flagged: Vec<usize> =
            far.iter().enumerate().filter(|(_, d)| d.is_some()).map(|(i, _)| i).collect();
        assert_eq!(flagged, [3, 4, 12], "{far:?}");
        assert!((far[3].unwrap() - 205.0).abs() < 2.0 && far[12].unwrap() > 5000.0, "{far:?}");
        let corridor: Vec<(f64, f64)> = (0..41).map(|i| (46.84 + i as f64 * 0.009, -91.99)).collect();
        assert!(far_from_the_survey(&corridor).iter().all(Option::is_none), "40 km of one line");
    }

    /// The size most photos have is kept, whichever comes first; of equal groups, the
    /// earliest photo's.
    #[test]
    fn the_most_common_camera_is_kept_and_of_equals_the_earliests() {
        let photo = |name: &str, width: u32| {
            (0.0, PathBuf::from(name), PhotoTags { name: name.into(), width, ..PhotoTags::default() })
        };
        let names = |p: &[Photo]| p.iter().map(|(_, _, t)| t.name.clone()).collect::<Vec<_>>();
        let keep = |mut photos: Vec<Photo>| {
            let mut report = ImportReport::default();
            keep_the_most_common(
                &mut photos,
                &mut report,
                |t| t.width,
                |its, kept| format!("{its} among {kept}"),
            );
            (names(&photos), report.skipped)
        };
        let (kept, skipped) = keep(vec![photo("a", 2000), photo("b", 4000), photo("c", 4000)]);
        assert_eq!(kept, ["b", "c"]);
        assert_eq!(skipped, [("a".to_string(), "2000 among 4000".to_string())]);
        let (kept, _) = keep(vec![photo("a", 2000), photo("b", 4000)]);
        assert_eq!(kept, ["a"]);
    }

    /// Each photo's numbers are checked, each problem named: before, only the first
    /// photo's position was, and 1e308 m or an infinite latitude went into the dataset.
    #[test]
    fn impossible_tag_values_are_named() {
        let good = PhotoTags {
            lat_deg: 46.8,
            lon_deg: -92.0,
            absolute_alt_m: 198.6,
            relative_alt_m: 40.1,
            gimbal_deg: [44.2, -89.9, 0.0],
            flight_deg: [2.9, 1.3, f64::NAN],
            ..PhotoTags::default()
        };
        assert_eq!(check_values(&good), Ok(()));
        let bad = |f: &dyn Fn(&mut PhotoTags)| {
            let mut t = good.clone();
            f(&mut t);
            check_values(&t).unwrap_err()
        };
        assert!(bad(&|t| t.lat_deg = f64::INFINITY).starts_with("latitude inf deg"));
        assert!(bad(&|t| t.lat_deg = 91.0).starts_with("latitude 91 deg"));
        assert!(bad(&|t| t.lon_deg = 500.0).starts_with("longitude 500 deg"));
        assert!(bad(&|t| t.absolute_alt_m = 1e308).starts_with("altitude 1e308 m"));
        assert!(bad(&|t| t.relative_alt_m = f64::INFINITY).starts_with("height above take-off inf m"));
        assert!(bad(&|t| t.gimbal_deg[1] = 1e308).starts_with("gimbal angle 1e308 deg"));
        assert!(bad(&|t| t.flight_deg[0] = -1000.0).starts_with("aircraft angle -1000 deg"));
    }

    #[test]
    fn a_clock_never_set_gives_no_time() {
        assert_eq!(exif_seconds("0000:00:00 00:00:00"), None);
        assert_eq!(exif_seconds("2016:13:01 10:00:00"), None);
        assert!(exif_seconds("2016:06:23 16:33:27").is_some());
    }

    /// A survey of three lines flown back and forth, photos 12.5 m apart along a line, 30 m
    /// between lines: each photo heads along its own line, the first and last of a line
    /// too (the course to the next line's first photo is a diagonal 67 deg off).
    #[test]
    fn headings_follow_each_line_through_the_turns() {
        let metre = 1.0 / 111_195.0;
        let mut photos = Vec::new();
        for line in 0..3 {
            for k in 0..6 {
                let along = if line % 2 == 0 { k } else { 5 - k } as f64 * 12.5;
                let t = PhotoTags {
                    lat_deg: along * metre,
                    lon_deg: line as f64 * 30.0 * metre,
                    flight_deg: [0.0, 0.0, f64::NAN],
                    ..Default::default()
                };
                photos.push((photos.len() as f64, PathBuf::new(), t));
            }
        }
        track_headings(&mut photos);
        for (i, (_, _, t)) in photos.iter().enumerate() {
            let want = if (i / 6) % 2 == 0 { 0.0 } else { 180.0 };
            let off = ((t.flight_deg[2] - want + 540.0).rem_euclid(360.0) - 180.0).abs();
            assert!(off < 0.5, "photo {i}: heading {} where its line runs {want}", t.flight_deg[2]);
        }
    }

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
