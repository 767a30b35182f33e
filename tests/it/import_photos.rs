//! The photo importer on three real DJI photos (`tests/data/dji-sample/`, BSD-2, see its
//! LICENSE.txt): tags parsed to the values the files hold, photos without the needed tags
//! named and skipped, capture-time order, and `mavloc area` running on the result.

use std::path::{Path, PathBuf};
use std::process::Command;

use mavloc::import::{import_photos, read_tags, ImportOptions};

fn with_calibration(cal: &Path) -> ImportOptions {
    ImportOptions { calibration: Some(cal.to_path_buf()), ..Default::default() }
}

/// `mavloc area` on dataset `ds` into `result` with `extra` arguments, the configuration
/// file left out; its standard output (the run must succeed).
fn area(ds: &Path, result: &Path, extra: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .env_remove("MAVLOC_CONFIG")
        .arg("area")
        .args(extra)
        .arg("--dataset")
        .arg(ds)
        .arg("--out")
        .arg(result)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn sample() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dji-sample")
}

#[test]
fn tags_are_read_from_exif_and_dji_xmp() {
    let t = read_tags(&sample().join("DJI_0030.JPG")).unwrap();
    assert_eq!((t.width, t.height), (4000, 2250));
    assert!((t.lat_deg - 46.842_281_6).abs() < 1e-6, "{}", t.lat_deg);
    assert!((t.lon_deg + 91.994_084_2).abs() < 1e-6, "{}", t.lon_deg);
    assert!((t.gps_alt_m - 198.609).abs() < 1e-3);
    assert_eq!(t.time, "2016:06:23 16:33:27");
    assert_eq!((t.focal_mm, t.focal_35mm), (Some(3.61), Some(20.0)));
    assert_eq!((t.absolute_alt_m, t.relative_alt_m), (198.61, 40.10));
    assert_eq!(t.gimbal_deg, [44.2, -89.9, 0.0], "yaw, pitch, roll");
    assert_eq!(t.flight_deg, [2.9, 1.3, 46.2], "roll, pitch, yaw");
}

/// A copy of a photo with one XMP tag renamed (same length, so the JPEG stays valid).
fn without(tag: &str, from: &Path, to: &Path) {
    let mut bytes = std::fs::read(from).unwrap();
    let needle = format!("drone-dji:{tag}=");
    let at = bytes.windows(needle.len()).position(|w| w == needle.as_bytes()).expect("tag present");
    bytes[at + "drone-dji:".len()] = b'X';
    std::fs::write(to, bytes).unwrap();
}

#[test]
fn photos_without_the_needed_tags_are_named_and_skipped_and_order_is_capture_time() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    // Names in the opposite order of capture times.
    std::fs::copy(sample().join("DJI_0032.JPG"), photos.join("a.jpg")).unwrap();
    std::fs::copy(sample().join("DJI_0030.JPG"), photos.join("c.jpg")).unwrap();
    without("GimbalYawDegree", &sample().join("DJI_0031.JPG"), &photos.join("b.jpg"));
    std::fs::write(photos.join("d.jpg"), b"not a jpeg").unwrap();
    // Cut two thirds in (a copy interrupted): its tags read, its image does not.
    let whole = std::fs::read(sample().join("DJI_0031.JPG")).unwrap();
    std::fs::write(photos.join("e.jpg"), &whole[..whole.len() * 2 / 3]).unwrap();
    // Cut inside its EXIF block (before the image's frame header).
    std::fs::write(photos.join("e2.jpg"), &whole[..30_000]).unwrap();
    // A copy of a photo beside it, and a subfolder (not searched).
    std::fs::copy(sample().join("DJI_0030.JPG"), photos.join("f.jpg")).unwrap();
    std::fs::create_dir(photos.join("sub.jpg")).unwrap();
    std::fs::copy(sample().join("DJI_0031.JPG"), photos.join("sub.jpg/g.jpg")).unwrap();
    // A header that claims 65535x65535 (its tags read; OpenCV will not decode it).
    let mut forged = std::fs::read(sample().join("DJI_0031.JPG")).unwrap();
    // The main image's frame header: walk the segments (the EXIF thumbnail and DJI's
    // appended preview have their own).
    let mut sof = 2;
    while forged[sof + 1] != 0xC0 {
        sof += 2 + u16::from_be_bytes([forged[sof + 2], forged[sof + 3]]) as usize;
    }
    forged[sof + 5..sof + 9].copy_from_slice(&[0xFF; 4]);
    std::fs::write(photos.join("h.jpg"), forged).unwrap();
    let out = dir.path().join("ds");
    let r = import_photos(&photos, &out, &ImportOptions::default()).unwrap();
    assert_eq!(r.imported, ["c.jpg", "a.jpg"], "by capture time, not by name");
    let skipped: Vec<String> = r.skipped.iter().map(|(n, why)| format!("{n}: {why}")).collect();
    assert_eq!(skipped.len(), 6, "{skipped:?}");
    assert!(skipped[0].starts_with("b.jpg") && skipped[0].contains("GimbalYawDegree"), "{skipped:?}");
    assert!(skipped[1].starts_with("d.jpg: not a JPEG"), "named once: {skipped:?}");
    assert!(skipped[2].starts_with("e.jpg") && skipped[2].contains("truncated"), "{skipped:?}");
    assert!(skipped[3].starts_with("e2.jpg: truncated or damaged JPEG (no frame header"), "{skipped:?}");
    assert!(skipped[4].starts_with("f.jpg: the same file as c.jpg"), "{skipped:?}");
    assert!(
        skipped[5].starts_with("h.jpg: not an image OpenCV can decode (its header says 65535x65535)"),
        "{skipped:?}"
    );
    let ds = mavloc_data::Dataset::open(&out).unwrap();
    assert_eq!(ds.records.len(), 2);
    assert_eq!(ds.records[1].t, 14.0, "16:33:27 to 16:33:41");
    // Local NED around the first photo; its down is minus the height above take-off.
    let p0 = ds.records[0].measured.position;
    assert!(p0[0].abs() < 1e-6 && p0[1].abs() < 1e-6 && (p0[2] + 40.10).abs() < 1e-6, "{p0:?}");
    // 14 s later, about 20 m north-east.
    let p1 = ds.records[1].measured.position;
    assert!(p1[0] > 15.0 && p1[1] > 15.0 && (p1[0].hypot(p1[1]) - 27.7).abs() < 3.0, "{p1:?}");
    // Intrinsics from the 35 mm equivalent (4:3 sensor of the same width).
    assert!((ds.camera.fx - 2311.3).abs() < 0.5, "{}", ds.camera.fx);
    assert!(ds.frame_path(&ds.records[0]).ends_with("frames/000000.jpg"));
}

#[test]
fn a_calibration_file_overrides_the_focal_length_estimate() {
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("cal.toml");
    std::fs::write(&cal, "fx = 2340.0\nfy = 2341.0\ncx = 2001.0\ncy = 1120.0\n").unwrap();
    let r = import_photos(&sample(), &dir.path().join("ds"), &with_calibration(&cal)).unwrap();
    assert_eq!(r.fx_px, 2340.0);
    let ds = mavloc_data::Dataset::open(&dir.path().join("ds")).unwrap();
    assert_eq!((ds.camera.fy, ds.camera.cx, ds.camera.cy), (2341.0, 2001.0, 1120.0));
}

/// With distortion coefficients the frames are undistorted: what the original shows at
/// the distorted position of a pixel (OpenCV's model, k1 only here) the imported frame
/// shows at the pixel itself. Patches compared by normalised cross-correlation (0.6-0.9
/// where they should match, about 0 in place), at points where k1 = -0.1 moves the image
/// by tens of pixels.
#[test]
fn a_calibration_with_distortion_undistorts_the_frames() {
    use opencv::core::{Mat, Rect};
    use opencv::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("cal.toml");
    let (fx, cx, cy, k1): (f64, f64, f64, f64) = (2311.0, 1999.5, 1124.5, -0.1);
    std::fs::write(
        &cal,
        format!("fx = {fx}\nfy = {fx}\ncx = {cx}\ncy = {cy}\ndistortion = [{k1}, 0.0, 0.0, 0.0, 0.0]\n"),
    )
    .unwrap();
    let r = import_photos(&sample(), &dir.path().join("ds"), &with_calibration(&cal)).unwrap();
    assert!(r.intrinsics_from.contains("undistorted"), "{}", r.intrinsics_from);
    let ds = mavloc_data::Dataset::open(&dir.path().join("ds")).unwrap();
    let grey = |p: &Path| opencv::imgcodecs::imread(p, opencv::imgcodecs::IMREAD_GRAYSCALE).unwrap();
    let imported = grey(&ds.frame_path(&ds.records[0]));
    let original = grey(&sample().join("DJI_0030.JPG"));
    assert_eq!((imported.cols(), imported.rows()), (4000, 2250));
    let patch = |img: &Mat, u: f64, v: f64| -> Vec<f64> {
        let roi = Mat::roi(img, Rect::new(u.round() as i32 - 20, v.round() as i32 - 20, 41, 41)).unwrap();
        let mut out = Vec::new();
        for y in 0..41 {
            for x in 0..41 {
                out.push(*roi.at_2d::<u8>(y, x).unwrap() as f64);
            }
        }
        out
    };
    let ncc = |a: &[f64], b: &[f64]| {
        let (ma, mb) = (a.iter().sum::<f64>() / a.len() as f64, b.iter().sum::<f64>() / b.len() as f64);
        let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
        for (x, y) in a.iter().zip(b) {
            ab += (x - ma) * (y - mb);
            aa += (x - ma).powi(2);
            bb += (y - mb).powi(2);
        }
        ab / (aa * bb).sqrt()
    };
    for (u, v) in [(800.0f64, 500.0f64), (3200.0, 600.0), (900.0, 1750.0), (3100.0, 1700.0), (600.0, 1100.0)]
    {
        let (x, y) = ((u - cx) / fx, (v - cy) / fx);
        let f = 1.0 + k1 * (x * x + y * y);
        let (ud, vd) = (fx * x * f + cx, fx * y * f + cy);
        assert!((ud - u).hypot(vd - v) > 15.0, "the test point ({u}, {v}) moves too little");
        let here = patch(&imported, u, v);
        let moved = ncc(&here, &patch(&original, ud, vd));
        let unmoved = ncc(&here, &patch(&original, u, v));
        assert!(
            moved > 0.5 && moved > unmoved + 0.3,
            "({u}, {v}): {moved:.2} at the distorted point, {unmoved:.2} in place"
        );
    }
    // A wrong number of coefficients is named.
    std::fs::write(
        &cal,
        "fx = 2311.0\nfy = 2311.0\ncx = 1999.5\ncy = 1124.5\ndistortion = [0.1, 0.0, 0.0]\n",
    )
    .unwrap();
    let e = import_photos(&sample(), &dir.path().join("ds2"), &with_calibration(&cal)).unwrap_err();
    assert!(e.contains("cal.toml") && e.contains("distortion has 3 coefficients"), "{e}");
    // The same k1 with the focal length of a calibration made at a sixth of the size: the
    // model turns over inside these photos (OpenCV would fold them without a word).
    std::fs::write(
        &cal,
        format!(
            "fx = {f}\nfy = {f}\ncx = 1999.5\ncy = 1124.5\ndistortion = [{k1}, 0.0, 0.0, 0.0, 0.0]\n",
            f = fx / 6.0
        ),
    )
    .unwrap();
    let e = import_photos(&sample(), &dir.path().join("ds3"), &with_calibration(&cal)).unwrap_err();
    assert!(e.contains("cal.toml") && e.contains("4000x2250") && e.contains("turns back on itself"), "{e}");
    assert!(!dir.path().join("ds3").exists());
}

#[test]
fn the_area_pipeline_runs_on_the_imported_photos_with_the_water_segmenter() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let bin = env!("CARGO_BIN_EXE_mavloc");
    let out =
        Command::new(bin).args(["import", "photos"]).arg(sample()).arg("--out").arg(&ds).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // The dataset carries the photo-survey settings: no --config needed.
    let own = std::fs::read_to_string(ds.join("mavloc.toml")).unwrap();
    assert_eq!(own, mavloc::import::PHOTO_SURVEY_SETTINGS);
    let result = dir.path().join("r");
    let stdout = area(&ds, &result, &["--debug-masks"]);
    println!("{stdout}");
    assert!(stdout.contains("settings from the dataset's") && stdout.contains("area.segmenter"), "{stdout}");
    assert!(result.join("masks.png").exists(), "contact sheet");
    assert!(result.join("views.png").exists(), "top and side view");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(result.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["frames"], 3);
    // Every photo aligned by its tie points, so the filters take a landmark from two
    // photos at SIFT's own bearing noise (`area.aligned_*`): 160 landmarks where the tags'
    // settings, three sightings at 0.7 deg, gave 19 (session 45); consistently with every photo they
    // were seen in.
    assert_eq!(summary["aligned_photos"], 3, "{summary}");
    assert_eq!(summary["aligned_min_observations"], 2, "{summary}");
    assert_eq!(summary["aligned_bearing_noise_deg"], 0.1, "{summary}");
    let n = summary["landmarks"].as_u64().unwrap();
    assert!(n >= 120, "{summary}");
    assert!(summary["residual_p90_px"].as_f64().unwrap() < 80.0, "{summary}");
    assert_eq!(summary["yaw_off_180_frames"], serde_json::json!(null), "{summary}");
    let residuals = std::fs::read_to_string(result.join("residuals.csv")).unwrap();
    assert_eq!(residuals.lines().count(), 4, "a row per photo: {residuals}");

    // Over the right place: the lake shore beside the flight line, on the lake's side.
    // Each landmark lies within the photos' footprint (69 m wide from 40 m) and south-east
    // of the line the drone flew (the photos look north-east with the water on their right;
    // Lake Superior is south-east of Duluth's shore).
    let geo: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(result.join("area.geojson")).unwrap()).unwrap();
    let photos: Vec<(f64, f64)> = ["DJI_0030.JPG", "DJI_0031.JPG", "DJI_0032.JPG"]
        .iter()
        .map(|p| {
            let t = read_tags(&sample().join(p)).unwrap();
            (t.lat_deg, t.lon_deg)
        })
        .collect();
    let metres = |(lat, lon): (f64, f64), (lat0, lon0): (f64, f64)| {
        let north = (lat - lat0).to_radians() * 6_371_000.0;
        let east = (lon - lon0).to_radians() * 6_371_000.0 * lat0.to_radians().cos();
        (north, east)
    };
    let mut landmarks = 0;
    for f in geo["features"].as_array().unwrap() {
        if f["properties"]["kind"] != "landmark" {
            continue;
        }
        landmarks += 1;
        let c = f["geometry"]["coordinates"].as_array().unwrap();
        let at = (c[1].as_f64().unwrap(), c[0].as_f64().unwrap());
        let nearest = photos.iter().map(|&p| metres(at, p)).map(|(n, e)| n.hypot(e)).fold(f64::MAX, f64::min);
        assert!(nearest < 40.0, "landmark {at:?} is {nearest:.0} m from the nearest photo");
        // Side of the flight line (first to last photo): positive = to its right.
        let (ln, le) = metres(photos[2], photos[0]);
        let (pn, pe) = metres(at, photos[0]);
        let right = (ln * pe - le * pn) / ln.hypot(le);
        assert!(right > 5.0, "landmark {at:?} is {right:.1} m right of the flight line");
    }
    assert_eq!(landmarks as u64, n);
    // A landmark from two photos has no third to show a false match: one would lie metres
    // off the shore's height. They all lie on the shore and its rocks, within 0.5 m of the
    // median height (measured: 2.84-3.75 m below the first photo's take-off, median 3.35).
    let csv = std::fs::read_to_string(result.join("landmarks.csv")).unwrap();
    let mut downs: Vec<f64> =
        csv.lines().skip(1).map(|l| l.split(',').nth(3).unwrap().parse().unwrap()).collect();
    downs.sort_by(f64::total_cmp);
    let median = downs[downs.len() / 2];
    let worst = downs.iter().map(|d| (d - median).abs()).fold(0.0, f64::max);
    assert!(worst < 1.0, "a landmark {worst:.2} m off the median height {median:.2} m");
    let kml = std::fs::read_to_string(result.join("area.kml")).unwrap();
    assert_eq!(kml.matches("<Point>").count() as u64, n, "every landmark in the KML");
    // At the lake's height above sea level: Lake Superior's surface is about 183.4 m (its
    // chart datum 183.2 m, IGLD 1985), and the shore's rocks a little above it. DJI's
    // altitudes taken as above sea level put them at 155 m (outside audit, session 39): 28 m
    // under the water in Google Earth, the geoid's undulation there.
    let mut heights: Vec<f64> = geo["features"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["properties"]["kind"] == "landmark")
        .map(|f| f["properties"]["height_amsl_m"].as_f64().unwrap())
        .collect();
    heights.sort_by(f64::total_cmp);
    let above_sea = heights[heights.len() / 2];
    assert!((above_sea - 183.4).abs() < 1.5, "the shore {above_sea:.2} m above sea level, the lake 183.4 m");
}

/// DJI's AbsoluteAltitude is a height above the WGS84 ellipsoid: the import takes it down
/// to sea level by the geoid's undulation (EGM96: -28.7 m at the sample's shore), and says
/// so; `--altitude-datum sea-level` takes the tags as they are, and `--ground-alt-m` puts
/// the take-off at a known altitude. Only the origin's height changes: the photos keep
/// their places relative to it.
#[test]
fn dji_altitudes_are_taken_from_the_ellipsoid_to_sea_level() {
    use mavloc::import::AltitudeDatum;
    let dir = tempfile::tempdir().unwrap();
    let ellipsoid = import_photos(&sample(), &dir.path().join("e"), &ImportOptions::default()).unwrap();
    let sea = ImportOptions { altitude_datum: Some(AltitudeDatum::SeaLevel), ..Default::default() };
    let sea = import_photos(&sample(), &dir.path().join("s"), &sea).unwrap();
    let (e, s) = (ellipsoid.origin.unwrap(), sea.origin.unwrap());
    // Take-off 40.10 m below the first photo's 198.61 m, as tagged.
    assert!((s.alt_m - 158.51).abs() < 1e-6, "{s:?}");
    let n = mavloc_data::geoid::undulation_m(e.lat_deg, e.lon_deg);
    assert!((-29.0..-28.4).contains(&n), "EGM96 at Duluth's shore: {n}");
    assert!((e.alt_m - (158.51 - n)).abs() < 1e-6, "{e:?}");
    assert!(
        ellipsoid.altitudes.contains("ellipsoid") && ellipsoid.altitudes.contains("-28.7"),
        "{}",
        ellipsoid.altitudes
    );
    assert!(sea.altitudes.contains("sea-level"), "{}", sea.altitudes);
    let (de, ds) = (
        mavloc_data::Dataset::open(&dir.path().join("e")).unwrap(),
        mavloc_data::Dataset::open(&dir.path().join("s")).unwrap(),
    );
    assert_eq!(de.camera.origin.alt_m, e.alt_m, "the dataset's origin");
    // A known take-off altitude stands for the tags' (a barometric DJI's drifts with the
    // weather): the origin moves there, the photos keep their places.
    let known = ImportOptions {
        ground_alt_m: Some(187.0),
        altitude_datum: Some(AltitudeDatum::SeaLevel),
        ..Default::default()
    };
    let known = import_photos(&sample(), &dir.path().join("k"), &known).unwrap().origin.unwrap();
    assert!((known.alt_m - 187.0).abs() < 1e-6, "{known:?}");
    let dk = mavloc_data::Dataset::open(&dir.path().join("k")).unwrap();
    for ((a, b), c) in de.records.iter().zip(&ds.records).zip(&dk.records) {
        for k in 0..3 {
            assert!(
                (a.measured.position[k] - c.measured.position[k]).abs() < 1e-3,
                "{:?} {:?}",
                a.measured,
                c.measured
            );
            assert!(
                (a.measured.position[k] - b.measured.position[k]).abs() < 1e-3,
                "{:?} {:?}",
                a.measured,
                b.measured
            );
        }
    }
}

/// A photo the alignment cannot reach (here a blank frame: no tie point) keeps its tag's
/// error, and a landmark from it and one other photo would have no third sighting to show
/// it: it is left out of the landmark filters and named, and the two aligned photos still
/// give landmarks from two sightings.
#[test]
fn a_photo_the_alignment_cannot_reach_is_left_out_of_the_filters() {
    use opencv::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    import_photos(&sample(), &ds, &ImportOptions::default()).unwrap();
    let frame = ds.join("frames/000002.jpg");
    let img = opencv::imgcodecs::imread(frame.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    let grey = opencv::core::Mat::new_rows_cols_with_default(
        img.rows(),
        img.cols(),
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(128.0),
    )
    .unwrap();
    opencv::imgcodecs::imwrite(frame.to_str().unwrap(), &grey, &opencv::core::Vector::new()).unwrap();
    let result = dir.path().join("r");
    println!("{}", area(&ds, &result, &[]));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(result.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["aligned_photos"], 2, "{summary}");
    assert_eq!(summary["unaligned_frames"], serde_json::json!([2]), "{summary}");
    assert_eq!(summary["aligned_min_observations"], 2, "{summary}");
    assert_eq!(summary["frames"], 2, "{summary}");
    let csv = std::fs::read_to_string(result.join("landmarks.csv")).unwrap();
    let last_frames: Vec<u64> =
        csv.lines().skip(1).map(|l| l.split(',').nth(7).unwrap().parse().unwrap()).collect();
    assert!(last_frames.len() >= 20, "{csv}");
    assert!(last_frames.iter().all(|&f| f <= 1), "no landmark seen in the left-out photo: {csv}");
}

#[test]
fn the_residual_report_names_a_frame_whose_yaw_is_half_a_turn_off() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let bin = env!("CARGO_BIN_EXE_mavloc");
    let out = Command::new(bin)
        .args([
            "sim",
            "render",
            "--scenario",
            "coastline",
            "--frames",
            "60",
            "--width",
            "480",
            "--height",
            "270",
        ])
        .arg("--out")
        .arg(&ds)
        .output()
        .unwrap();
    assert!(out.status.success());
    // Frame 30's recorded gimbal yaw turned by 180 deg, as in some real DJI logs.
    let path = ds.join("telemetry.jsonl");
    let text: Vec<String> = std::fs::read_to_string(&path)
        .unwrap()
        .lines()
        .map(|l| {
            let mut r: serde_json::Value = serde_json::from_str(l).unwrap();
            if r["frame"] == 30 {
                let y = r["measured"]["gimbal_deg"][0].as_f64().unwrap();
                r["measured"]["gimbal_deg"][0] = (y + 180.0).into();
            }
            r.to_string()
        })
        .collect();
    std::fs::write(&path, text.join("\n") + "\n").unwrap();
    let result = dir.path().join("r");
    let stdout = area(&ds, &result, &["--set", "area.downscale=1", "--set", "area.band_px=13"]);
    assert!(stdout.contains("frame 30: residuals say its recorded yaw is off by about 180 deg"), "{stdout}");
    let csv = std::fs::read_to_string(result.join("residuals.csv")).unwrap();
    let flagged: Vec<&str> = csv.lines().skip(1).filter(|l| l.ends_with(",1")).collect();
    assert_eq!(flagged.len(), 1, "only frame 30: {csv}");
    assert!(flagged[0].starts_with("30,"));
    // The others reproject within a few pixels (seed noise: 0.5 deg, 0.5 m).
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(result.join("summary.json")).unwrap()).unwrap();
    assert!(summary["residual_median_px"].as_f64().unwrap() < 15.0, "{summary}");
    assert_eq!(summary["yaw_off_180_frames"], serde_json::json!([30]));
}

/// Re-importing into a dataset: refused without --force; with it the folder is replaced
/// whole (no stale frame of the larger first import) and an edited mavloc.toml is kept,
/// the import's own settings written beside it. An output inside the photos is refused.
#[test]
fn a_reimport_replaces_the_dataset_whole_and_keeps_the_edited_settings() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for n in ["DJI_0030.JPG", "DJI_0031.JPG", "DJI_0032.JPG"] {
        std::fs::copy(sample().join(n), photos.join(n)).unwrap();
    }
    let out = dir.path().join("ds");
    import_photos(&photos, &out, &ImportOptions::default()).unwrap();
    assert!(out.join("frames/000002.jpg").exists());
    let settings = out.join("mavloc.toml");
    let edited = std::fs::read_to_string(&settings).unwrap() + "\n# mine: turnover tuned\n";
    std::fs::write(&settings, &edited).unwrap();

    std::fs::remove_file(photos.join("DJI_0032.JPG")).unwrap();
    let e = import_photos(&photos, &out, &ImportOptions::default()).unwrap_err();
    assert!(e.contains("--force"), "{e}");
    let r = import_photos(&photos, &out, &ImportOptions { replace: true, ..Default::default() }).unwrap();
    assert_eq!(r.imported.len(), 2);
    assert!(!out.join("frames/000002.jpg").exists(), "the old third frame is gone");
    assert_eq!(mavloc_data::Dataset::open(&out).unwrap().records.len(), 2);
    assert_eq!(std::fs::read_to_string(&settings).unwrap(), edited, "the user's settings are kept");
    assert!(out.join("mavloc.toml.new").exists());
    assert!(r.kept_settings.unwrap().contains("edited"));
    let siblings: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(siblings.len(), 2, "no half-written folder beside: {siblings:?}");

    let e = import_photos(&photos, &photos.join("ds"), &ImportOptions::default()).unwrap_err();
    assert!(e.contains("inside"), "{e}");
}

/// A copy of a photo with one XMP value replaced by another of the same length.
fn with_value(from: &Path, to: &Path, old: &str, new: &str) {
    replaced(from, to, old, new, 1);
}

/// A copy of a photo with its first `at_most` occurrences of `old` replaced by `new`, of
/// the same length (so the JPEG stays valid); there must be one.
fn replaced(from: &Path, to: &Path, old: impl AsRef<[u8]>, new: impl AsRef<[u8]>, at_most: usize) {
    let (old, new) = (old.as_ref(), new.as_ref());
    assert_eq!(old.len(), new.len());
    let mut bytes = std::fs::read(from).unwrap();
    let mut n = 0;
    while let Some(at) = bytes.windows(old.len()).position(|w| w == old).filter(|_| n < at_most) {
        bytes[at..at + new.len()].copy_from_slice(new);
        n += 1;
    }
    assert!(n > 0, "{old:?} not in {}", from.display());
    std::fs::write(to, bytes).unwrap();
}

/// A photo whose EXIF lost its focal length (FocalLength and FocalLengthIn35mmFilm renamed
/// to the tags after them, FlashEnergy and SceneCaptureType) takes the others': they are
/// one camera. Where no photo has one, the import asks for a calibration by name.
#[test]
fn a_photo_without_a_focal_length_takes_the_cameras_and_none_at_all_asks_for_a_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let (some, none) = (dir.path().join("some"), dir.path().join("none"));
    for d in [&some, &none] {
        std::fs::create_dir_all(d).unwrap();
    }
    // Little-endian IFD entries (the sample's TIFF header is "II"): 0x920A, 0xA405.
    let strip = |from: &Path, to: &Path| {
        replaced(from, to, [0x0A, 0x92, 0x05, 0x00], [0x0B, 0x92, 0x05, 0x00], 1);
        replaced(to, to, [0x05, 0xA4, 0x03, 0x00], [0x06, 0xA4, 0x03, 0x00], 1);
    };
    for n in ["DJI_0030.JPG", "DJI_0031.JPG", "DJI_0032.JPG"] {
        strip(&sample().join(n), &none.join(n));
        if n == "DJI_0031.JPG" {
            std::fs::copy(none.join(n), some.join(n)).unwrap();
        } else {
            std::fs::copy(sample().join(n), some.join(n)).unwrap();
        }
    }
    let t = read_tags(&some.join("DJI_0031.JPG")).unwrap();
    assert_eq!((t.focal_mm, t.focal_35mm, t.focal_px), (None, None, None), "the tags are gone");
    let whole = import_photos(&sample(), &dir.path().join("whole"), &ImportOptions::default()).unwrap();
    let r = import_photos(&some, &dir.path().join("a"), &ImportOptions::default()).unwrap();
    assert_eq!(r.imported.len(), 3, "{:?}", r.skipped);
    assert_eq!(r.fx_px, whole.fx_px);
    let e = import_photos(&none, &dir.path().join("b"), &ImportOptions::default()).unwrap_err();
    assert!(e.contains("no photo carries a focal length") && e.contains("--calibration"), "{e}");
}

/// A photo whose recorded gimbal yaw is half a turn off (as a reverse line's was on a DJI
/// survey) is found from its overlap with its neighbours and corrected at import, before
/// any landmark exists; the untouched sample is left as tagged.
#[test]
fn a_photo_recorded_half_a_turn_off_is_found_from_its_overlap_and_corrected() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    std::fs::copy(sample().join("DJI_0030.JPG"), photos.join("DJI_0030.JPG")).unwrap();
    with_value(
        &sample().join("DJI_0031.JPG"),
        &photos.join("DJI_0031.JPG"),
        "GimbalYawDegree=\"+41.40\"",
        "GimbalYawDegree=\"-138.6\"",
    );
    std::fs::copy(sample().join("DJI_0032.JPG"), photos.join("DJI_0032.JPG")).unwrap();
    let r = import_photos(&photos, &dir.path().join("ds"), &ImportOptions::default()).unwrap();
    assert_eq!(r.turned, ["DJI_0031.JPG"], "{r:?}");
    let ds = mavloc_data::Dataset::open(&dir.path().join("ds")).unwrap();
    let yaw = ds.records[1].measured.gimbal_deg[0];
    assert!((yaw - 41.4).abs() < 1e-6, "corrected back to 41.4, got {yaw}");
    assert!(r.overlap_median_m.unwrap() < 5.0, "{r:?}");

    let r = import_photos(&sample(), &dir.path().join("plain"), &ImportOptions::default()).unwrap();
    assert!(r.turned.is_empty(), "{r:?}");
}

fn seneca() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/seneca")
}

/// senseFly photos (public Seneca survey, three of line A in `tests/data/seneca`, CC0,
/// re-encoded smaller with their tags kept byte for byte): position and
/// attitude from the `sensefly:` XMP, the camera fixed to the airframe, the size from the
/// JPEG (EXIF says 4000x3000 of these 3600x2700 files), the focal length from EXIF
/// FocalLength and FocalPlaneXResolution scaled to the file. With the mount given half a
/// turn wrong, the overlap check turns every photo of the line back.
#[test]
fn sensefly_photos_import_with_a_body_fixed_camera() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    let line_a = ["IMG_0527.jpg", "IMG_0528.jpg", "IMG_0529.jpg"];
    for n in line_a {
        std::fs::copy(seneca().join(n), photos.join(n)).unwrap();
    }
    let t = read_tags(&photos.join("IMG_0527.jpg")).unwrap();
    assert_eq!((t.width, t.height, t.vendor.as_str()), (3600, 2700, "sensefly"));
    assert_eq!(t.time, "2013:06:04 17:47:49", "UTC from the XMP, not the camera clock");
    assert!((t.focal_px.unwrap() - 2497.74).abs() < 0.05, "{:?}", t.focal_px);

    let out = dir.path().join("ds");
    let r = import_photos(&photos, &out, &ImportOptions::default()).unwrap();
    assert_eq!(r.imported.len(), 3);
    assert!(r.turned.is_empty(), "{r:?}");
    let ds = mavloc_data::Dataset::open(&out).unwrap();
    assert_eq!(ds.camera.gimbal_frame, mavloc_data::dataset::GimbalFrame::Body);
    assert!(ds.records.iter().all(|r| r.measured.gimbal_deg == [0.0, -90.0, 0.0]));
    // Consecutive photos 28-36 m apart along the line (PROVENANCE.md).
    for w in ds.records.windows(2) {
        let (a, b) = (w[0].measured.position, w[1].measured.position);
        let d = (a[0] - b[0]).hypot(a[1] - b[1]);
        assert!((25.0..40.0).contains(&d), "{d} m between photos");
    }

    let mount = ImportOptions { mount_deg: Some([180.0, -90.0, 0.0]), ..Default::default() };
    let r = import_photos(&photos, &dir.path().join("turned"), &mount).unwrap();
    assert_eq!(r.turned.len(), 3, "{r:?}");
}

/// The public Seneca survey's photos (27, in `../shared/data/seneca`, CC0; or
/// `MAVLOC_SENECA_DIR`), when present.
fn seneca_survey() -> Option<PathBuf> {
    let dir = std::env::var_os("MAVLOC_SENECA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/seneca/images"));
    dir.join("IMG_0558.jpg").exists().then_some(dir)
}

/// Two overlapping lines of the Seneca survey, three photos of the return leg
/// (IMG_0559-0561) and the three beside them on the next line out (IMG_0569-0571; the eight
/// of IMG_0558-0561 and 0569-0572 gave the same figures, 40 landmark pairs 24.2 m apart
/// tagged and 0.12 m aligned, for 10.6 s of CPU against 8.4), imported with defaults: the senseFly tags put the same
/// ground tens of metres apart from the two lines (headings 10-20 deg off the track), and
/// aligning the photos by their tie points (`area::align`) brings the two lines' own
/// triangulations of the shared tie points within centimetres of each other.
#[test]
fn seneca_lines_agree_after_the_photos_are_aligned_by_their_tie_points() {
    let Some(images) = seneca_survey() else {
        eprintln!("seneca: skipped: ../shared/data/seneca/images (or MAVLOC_SENECA_DIR) is absent");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for n in ["0559", "0560", "0561", "0569", "0570", "0571"] {
        let name = format!("IMG_{n}.jpg");
        std::fs::copy(images.join(&name), photos.join(&name)).unwrap();
    }
    let ds = dir.path().join("ds");
    let r = import_photos(&photos, &ds, &ImportOptions::default()).unwrap();
    assert_eq!(r.imported.len(), 6);
    // One run: the alignment, then the landmark filters with a segmenter for its bare
    // fields (bright, colourless in near infrared) and the matching guided by each
    // landmark's prediction (rows of a field look alike).
    let fields = dir.path().join("fields");
    println!(
        "{}",
        area(
            &ds,
            &fields,
            &[
                "--set",
                "area.segmenter=hsv",
                "--set",
                "area.hsv_low=[0,0,150]",
                "--set",
                "area.hsv_high=[180,60,255]",
                "--set",
                "area.band_px=600",
                "--set",
                "area.matching=guided"
            ]
        )
    );
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fields.join("summary.json")).unwrap()).unwrap();
    let f = |k: &str| s[k].as_f64().unwrap_or_else(|| panic!("{k} missing: {s}"));
    assert_eq!(s["flight_lines"], 2, "{s}");
    assert!(f("aligned_photos") >= 5.0 && f("tie_points") >= 500.0, "{s}");
    assert!(f("align_median_before_px") > 50.0 && f("align_median_after_px") < 1.5, "{s}");
    assert!(f("cross_line_tie_pairs") >= 20.0, "{s}");
    let (tagged, aligned) = (f("cross_line_tie_median_m"), f("cross_line_tie_aligned_median_m"));
    assert!(tagged > 10.0 && aligned < 0.3, "lines {tagged:.2} m apart as tagged, {aligned:.2} m aligned");
    // Each photo's correction is in alignment.csv, with the tie points it rests on.
    let csv = std::fs::read_to_string(fields.join("alignment.csv")).unwrap();
    assert_eq!(csv.lines().count(), 7, "{csv}");
    assert!(csv.starts_with("frame,tie_sightings,correction_deg,"), "{csv}");
    // Landmarks seen from both lines: each line's own triangulation tens of metres from
    // the other's with the tags and within centimetres aligned. (Built from the matches
    // the filters refused too, the measure once put one pair 135 m apart.)
    assert!(f("landmarks") >= 100.0 && f("cross_line_pairs") >= 15.0, "{s}");
    let (tagged, aligned, refined) =
        (f("cross_line_tagged_median_m"), f("cross_line_median_m"), f("cross_line_refined_median_m"));
    assert!(tagged > 10.0 && aligned < 0.5 && refined < 0.5, "{tagged:.2} / {aligned:.2} / {refined:.2} m");
}

/// `area.segmenter = "learned"` on an imported survey: the user's mask of one photo (here
/// the water rule's, written where the dataset keeps masks) trains it, that photo keeps
/// its own mask and the others are segmented by it; with no mask at all the run stops and
/// says where to put one.
#[test]
fn the_learned_segmenter_trains_on_the_masks_the_user_made() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    mavloc::import::import_photos(&sample(), &ds, &ImportOptions::default()).unwrap();
    let learned = ["--set", "area.segmenter=learned"];
    let out = Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .env_remove("MAVLOC_CONFIG")
        .arg("area")
        .args(learned)
        .arg("--dataset")
        .arg(&ds)
        .arg("--out")
        .arg(dir.path().join("none"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("masks you make") && err.contains("none found"), "{err}");

    let d = mavloc_data::Dataset::open(&ds).unwrap();
    let r = &d.records[1];
    let frame = mavloc::imaging::read_image(&d.frame_path(r), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    let water =
        mavloc::settings::Area { segmenter: mavloc::settings::Segmenter::Water, ..Default::default() };
    let mask = mavloc::area::segment::segment(&frame, &water).unwrap().unwrap();
    std::fs::create_dir_all(d.mask_path(r).parent().unwrap()).unwrap();
    assert!(opencv::imgcodecs::imwrite_def(d.mask_path(r).to_str().unwrap(), &mask).unwrap());
    let result = dir.path().join("r");
    println!("{}", area(&ds, &result, &learned));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(result.join("summary.json")).unwrap()).unwrap();
    assert_eq!(
        (summary["frames"].as_u64(), summary["skipped_frames"].as_u64()),
        (Some(3), Some(0)),
        "{summary}"
    );
    assert!(summary["landmarks"].as_u64().unwrap() >= 10, "{summary}");
}

/// The JPEG without its XMP packet (APP1 `http://ns.adobe.com/xap/1.0/`): what a camera
/// with plain EXIF GPS writes.
fn without_xmp(jpeg: &[u8]) -> Vec<u8> {
    let mut out = jpeg[..2].to_vec();
    let mut i = 2;
    while i + 4 <= jpeg.len() {
        assert_eq!(jpeg[i], 0xFF, "a marker at {i}");
        if jpeg[i + 1] == 0xDA {
            out.extend_from_slice(&jpeg[i..]);
            break;
        }
        let len = u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]) as usize;
        let seg = &jpeg[i..i + 2 + len];
        if !(jpeg[i + 1] == 0xE1 && seg[4..].starts_with(b"http://ns.adobe.com/xap/1.0/")) {
            out.extend_from_slice(seg);
        }
        i += 2 + len;
    }
    out
}

/// Photos with plain EXIF GPS and no attitude tags (Seneca's line A with its senseFly XMP
/// removed): without the ground's altitude the import says what it needs; with it, each
/// photo is a camera fixed to a level airframe heading along the track, at its GPS
/// altitude above that ground (Seneca's: GPS 282.09 m, 72.03 m above take-off).
#[test]
fn plain_exif_photos_import_as_a_level_airframe_heading_along_its_track() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for n in ["IMG_0527.jpg", "IMG_0528.jpg", "IMG_0529.jpg"] {
        let bytes = std::fs::read(seneca().join(n)).unwrap();
        std::fs::write(photos.join(n), without_xmp(&bytes)).unwrap();
    }
    let t = read_tags(&photos.join("IMG_0527.jpg")).unwrap();
    assert_eq!(t.vendor, "exif");
    let err = import_photos(&photos, &dir.path().join("no-ground"), &ImportOptions::default()).unwrap_err();
    assert!(err.contains("--ground-alt-m") && err.contains("282.1"), "{err}");

    let out = dir.path().join("ds");
    let opts = ImportOptions { ground_alt_m: Some(282.092 - 72.030), ..Default::default() };
    let r = import_photos(&photos, &out, &opts).unwrap();
    assert_eq!(r.imported.len(), 3, "{r:?}");
    let ds = mavloc_data::Dataset::open(&out).unwrap();
    assert_eq!(ds.camera.gimbal_frame, mavloc_data::dataset::GimbalFrame::Body);
    assert!((ds.records[0].measured.position[2] + 72.03).abs() < 0.05, "{:?}", ds.records[0].measured);
    let p: Vec<[f64; 3]> = ds.records.iter().map(|r| r.measured.position).collect();
    let course = |a: [f64; 3], b: [f64; 3]| (b[1] - a[1]).atan2(b[0] - a[0]).to_degrees().rem_euclid(360.0);
    // Along the line: the middle photo's heading is between its two courses (they agree).
    let mid = (course(p[0], p[1]) + course(p[1], p[2])) / 2.0;
    let expected = [course(p[0], p[1]), mid, course(p[1], p[2])];
    for (r, want) in ds.records.iter().zip(expected) {
        let [roll, pitch, yaw] = r.measured.attitude_deg;
        assert_eq!((roll, pitch), (0.0, 0.0));
        assert!((yaw - want).abs() < 0.5, "heading {yaw} against the track's {want}");
    }
}

/// The JPEG with its XMP packet replaced by `packet` (an APP1 segment after SOI).
fn with_xmp(jpeg: &[u8], packet: &str) -> Vec<u8> {
    let plain = without_xmp(jpeg);
    let mut body = b"http://ns.adobe.com/xap/1.0/\0".to_vec();
    body.extend_from_slice(packet.as_bytes());
    let len = u16::try_from(body.len() + 2).unwrap().to_be_bytes();
    let mut out = plain[..2].to_vec();
    out.extend_from_slice(&[0xFF, 0xE1, len[0], len[1]]);
    out.extend_from_slice(&body);
    out.extend_from_slice(&plain[2..]);
    out
}

/// Parrot ANAFI photos (`drone-parrot:` XMP, element form as ANAFI writes it): the DJI
/// sample re-tagged with its own gimbal angles as Parrot's Camera{Yaw,Pitch,Roll}Degree
/// imports to the same poses as the DJI original, the ground's altitude (which Parrot's
/// XMP does not carry) given by the user and asked for when missing.
#[test]
fn parrot_photos_import_with_the_gimbal_in_the_earth_frame() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for n in ["DJI_0030.JPG", "DJI_0031.JPG", "DJI_0032.JPG"] {
        let t = read_tags(&sample().join(n)).unwrap();
        let [yaw, pitch, roll] = t.gimbal_deg;
        let [froll, fpitch, fyaw] = t.flight_deg;
        let packet = format!(
            r#"<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description xmlns:drone-parrot="http://www.parrot.com/drone-parrot/1.0/"><drone-parrot:CameraPitchDegree>{pitch}</drone-parrot:CameraPitchDegree><drone-parrot:CameraRollDegree>{roll}</drone-parrot:CameraRollDegree><drone-parrot:CameraYawDegree>{yaw}</drone-parrot:CameraYawDegree><drone-parrot:FlightRollDegree>{froll}</drone-parrot:FlightRollDegree><drone-parrot:FlightPitchDegree>{fpitch}</drone-parrot:FlightPitchDegree><drone-parrot:FlightYawDegree>{fyaw}</drone-parrot:FlightYawDegree></rdf:Description></rdf:RDF></x:xmpmeta>"#
        );
        let bytes = std::fs::read(sample().join(n)).unwrap();
        std::fs::write(photos.join(n), with_xmp(&bytes, &packet)).unwrap();
    }
    let t = read_tags(&photos.join("DJI_0030.JPG")).unwrap();
    assert_eq!(t.vendor, "parrot");
    assert_eq!(t.gimbal_deg, [44.2, -89.9, 0.0], "yaw, pitch, roll");
    assert_eq!(t.flight_deg, [2.9, 1.3, 46.2], "roll, pitch, yaw");
    let err = import_photos(&photos, &dir.path().join("no-ground"), &ImportOptions::default()).unwrap_err();
    assert!(err.contains("Parrot") && err.contains("--ground-alt-m") && err.contains("198.6"), "{err}");

    // The DJI tags put take-off 40.10 m below the first photo's 198.61 m.
    let opts = ImportOptions { ground_alt_m: Some(198.61 - 40.10), ..Default::default() };
    import_photos(&photos, &dir.path().join("parrot"), &opts).unwrap();
    import_photos(&sample(), &dir.path().join("dji"), &ImportOptions::default()).unwrap();
    let parrot = mavloc_data::Dataset::open(&dir.path().join("parrot")).unwrap();
    let dji = mavloc_data::Dataset::open(&dir.path().join("dji")).unwrap();
    assert_eq!(parrot.camera.gimbal_frame, mavloc_data::dataset::GimbalFrame::Earth);
    assert_eq!(parrot.records.len(), 3);
    for (p, d) in parrot.records.iter().zip(&dji.records) {
        assert_eq!(p.measured.gimbal_deg, d.measured.gimbal_deg);
        assert_eq!(p.measured.attitude_deg, d.measured.attitude_deg);
        for k in 0..3 {
            // EXIF's GPS altitude against DJI's XMP altitude: 198.609 against 198.61.
            assert!(
                (p.measured.position[k] - d.measured.position[k]).abs() < 0.01,
                "{:?} {:?}",
                p.measured,
                d.measured
            );
        }
    }
}

/// An import stopped by its flag (Ctrl-C in `mavloc import photos`, which sets it) fails
/// with the reason, removes its staging folder and leaves the dataset it was replacing
/// (`--force`) as it was.
#[test]
fn a_stopped_import_leaves_the_earlier_dataset_and_no_staging_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ds");
    import_photos(&seneca(), &out, &ImportOptions::default()).unwrap();
    let snapshot = |d: &Path| -> Vec<(PathBuf, Vec<u8>)> {
        let mut files: Vec<_> =
            walk(d).into_iter().map(|p| (p.clone(), std::fs::read(&p).unwrap())).collect();
        files.sort();
        files
    };
    let before = snapshot(&out);
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let opts = ImportOptions { replace: true, stop: Some(stop), ..Default::default() };
    let e = import_photos(&sample(), &out, &opts).unwrap_err();
    assert_eq!(e, mavloc::import::STOPPED);
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, ["ds"], "a staging folder is left");
    assert!(snapshot(&out) == before, "the earlier dataset changed");
}

/// Every file under `d`.
fn walk(d: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(d).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// Photos whose tags hold what no drone photo can (a gimbal pitch of 1e308 deg, an
/// altitude of 1e308 m, a yaw that is not a number, a capture time of zeros from a clock
/// never set), and an empty file, are each skipped with the reason, and the rest import.
/// They used to be imported without a word (or named as missing tags): positions 1e302 m
/// off, a dataset `mavloc area` could not read. `--force` replaces a dataset, never a folder of other
/// files, which it used to delete.
#[test]
fn photos_with_impossible_values_are_named_and_skipped_and_force_replaces_only_a_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    std::fs::copy(sample().join("DJI_0030.JPG"), photos.join("a.jpg")).unwrap();
    with_value(
        &sample().join("DJI_0031.JPG"),
        &photos.join("b.jpg"),
        "Degree=\"-89.90\"",
        "Degree=\"1e+308\"",
    );
    std::fs::copy(sample().join("DJI_0032.JPG"), photos.join("c.jpg")).unwrap();
    with_value(&sample().join("DJI_0031.JPG"), &photos.join("d.jpg"), "\"+198.71\"", "\"+1e+308\"");
    with_value(&sample().join("DJI_0030.JPG"), &photos.join("e.jpg"), "\"+44.20\"", "\"+ab.cd\"");
    // Every copy of the time (EXIF writes it more than once).
    replaced(
        &sample().join("DJI_0032.JPG"),
        &photos.join("f.jpg"),
        "2016:06:23 16:33:41",
        "0000:00:00 00:00:00",
        usize::MAX,
    );
    std::fs::write(photos.join("g.jpg"), b"").unwrap();
    let out = dir.path().join("ds");
    let r = import_photos(&photos, &out, &ImportOptions::default()).unwrap();
    assert_eq!(r.imported, ["a.jpg", "c.jpg"]);
    let skipped: Vec<String> = r.skipped.iter().map(|(n, why)| format!("{n}: {why}")).collect();
    assert_eq!(skipped.len(), 5, "{skipped:?}");
    let said = |name: &str, what: &str| skipped.iter().any(|s| s.starts_with(name) && s.contains(what));
    assert!(said("b.jpg", "gimbal angle 1e308 deg is not an angle"), "{skipped:?}");
    assert!(said("d.jpg", "altitude 1e308 m is outside"), "{skipped:?}");
    assert!(said("e.jpg", "GimbalYawDegree `+ab.cd` is not a number"), "{skipped:?}");
    assert!(said("f.jpg", "capture time `0000:00:00 00:00:00` is not a date"), "{skipped:?}");
    assert!(said("g.jpg", "empty file (0 bytes)"), "{skipped:?}");
    let ds = mavloc_data::Dataset::open(&out).unwrap();
    assert!(ds.records.iter().all(|r| r.measured.position.iter().all(|x| x.abs() < 1000.0)));

    // A folder of the user's files is not replaced, even with --force; a dataset is.
    let mine = dir.path().join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("thesis.txt"), "years of work").unwrap();
    let force = ImportOptions { replace: true, ..Default::default() };
    let e = import_photos(&photos, &mine, &force).unwrap_err();
    assert!(e.contains("not a mavloc dataset") && e.contains("--force replaces only a dataset"), "{e}");
    assert_eq!(std::fs::read_to_string(mine.join("thesis.txt")).unwrap(), "years of work");
    let e = import_photos(&photos, &mine, &ImportOptions::default()).unwrap_err();
    assert!(!e.contains("pass --force"), "no advice to delete the user's files: {e}");
    import_photos(&photos, &out, &force).unwrap();
}

/// A photo whose EXIF breaks the format after the GPS (its EXIF directory's link to a
/// next directory pointing outside the block, as piexif writes it) keeps what could be
/// read: it used to be skipped whole ("no readable EXIF (Unexpected next IFD)").
#[test]
fn a_photo_with_partly_broken_exif_imports_from_what_could_be_read() {
    let mut bytes = std::fs::read(sample().join("DJI_0031.JPG")).unwrap();
    let base = bytes.windows(6).position(|w| w == b"Exif\0\0").expect("an EXIF block") + 6;
    let le = &bytes[base..base + 2] == b"II";
    let u16_at = |b: &[u8], at: usize| {
        let v = [b[at], b[at + 1]];
        (if le { u16::from_le_bytes(v) } else { u16::from_be_bytes(v) }) as usize
    };
    let u32_at = |b: &[u8], at: usize| {
        let v = [b[at], b[at + 1], b[at + 2], b[at + 3]];
        (if le { u32::from_le_bytes(v) } else { u32::from_be_bytes(v) }) as usize
    };
    let ifd0 = base + u32_at(&bytes, base + 4);
    let exif_ifd = (0..u16_at(&bytes, ifd0))
        .map(|i| ifd0 + 2 + 12 * i)
        .find(|&e| u16_at(&bytes, e) == 0x8769)
        .map(|e| base + u32_at(&bytes, e + 8))
        .expect("an EXIF directory");
    let next = exif_ifd + 2 + 12 * u16_at(&bytes, exif_ifd);
    bytes[next..next + 4].copy_from_slice(&[0x00, 0xFF, 0xFF, 0x00]);
    let dir = tempfile::tempdir().unwrap();
    let photo = dir.path().join("DJI_0031.JPG");
    std::fs::write(&photo, &bytes).unwrap();
    assert!(exif::Reader::new().read_from_container(&mut std::io::Cursor::new(&bytes)).is_err(), "broken");
    let t = read_tags(&photo).unwrap();
    let whole = read_tags(&sample().join("DJI_0031.JPG")).unwrap();
    assert_eq!((t.lat_deg, t.lon_deg, t.time.clone()), (whole.lat_deg, whole.lon_deg, whole.time.clone()));
}

/// What is in the folder and not imported is said, once: a PNG and a link that leads
/// nowhere used to be passed over without a word, and a link to the folder itself was
/// counted as a subfolder not searched.
#[test]
fn files_that_are_not_photos_are_named_and_a_link_to_the_folder_is_no_subfolder() {
    let dir = tempfile::tempdir().unwrap();
    let photos = dir.path().join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    for n in ["DJI_0030.JPG", "DJI_0031.JPG"] {
        std::fs::copy(sample().join(n), photos.join(n)).unwrap();
    }
    std::fs::write(photos.join("map.png"), b"\x89PNG").unwrap();
    std::os::unix::fs::symlink(photos.join("gone.JPG"), photos.join("DJI_0099.JPG")).unwrap();
    std::os::unix::fs::symlink(".", photos.join("self")).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_mavloc"))
        .args(["import", "photos"])
        .arg(&photos)
        .arg("--out")
        .arg(dir.path().join("ds"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("not photos") && err.contains("map.png"), "{err}");
    assert!(err.contains("DJI_0099.JPG (a link that leads nowhere)"), "{err}");
    assert!(!err.contains("subfolder"), "{err}");
}
