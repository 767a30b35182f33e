//! Heights above mean sea level and above the WGS84 ellipsoid. mavloc's altitudes are
//! above mean sea level, as MAVLink (HOME_POSITION, GLOBAL_POSITION_INT), DJI's and
//! senseFly's tags give them; KML wants the same, but GeoJSON (RFC 7946) wants heights
//! above the ellipsoid, tens of metres away (-35.8 m at the Seneca survey, +45.5 m at
//! Munich). The difference is the geoid undulation N (h = H + N), here from EGM96 on a
//! 15-minute grid embedded in the binary (`data/geoid/`, 0.7 MB; bilinear, within 0.86 m
//! of the 5-minute grid everywhere, 0.14 m at the 99th percentile; EGM96's own error is
//! about 0.5-1 m). No crate on crates.io ships the grid without downloading it at build
//! time, hence the table here.

use std::io::Read;
use std::sync::OnceLock;

const GRID: &[u8] = include_bytes!("../geoid/egm96-15.bin");
const ROWS: usize = 721;
const COLS: usize = 1441;
const STEP_DEG: f64 = 0.25;

/// The decoded grid, centimetres; decoded once (a constant table, like the bytes it comes
/// from).
fn grid() -> &'static [i32] {
    static DECODED: OnceLock<Vec<i32>> = OnceLock::new();
    DECODED.get_or_init(|| {
        let mut raw = Vec::with_capacity(ROWS * COLS * 2);
        flate2::read::ZlibDecoder::new(GRID).read_to_end(&mut raw).expect("the embedded geoid grid inflates");
        assert_eq!(raw.len(), ROWS * COLS * 2, "embedded geoid grid size");
        let d2: Vec<i32> = raw.chunks_exact(2).map(|b| i16::from_le_bytes([b[0], b[1]]) as i32).collect();
        // Undo the latitude differences, then the longitude ones.
        let mut v = d2;
        for r in 1..ROWS {
            for c in 0..COLS {
                v[r * COLS + c] += v[(r - 1) * COLS + c];
            }
        }
        for r in 0..ROWS {
            for c in 1..COLS {
                v[r * COLS + c] += v[r * COLS + c - 1];
            }
        }
        v
    })
}

/// EGM96 geoid undulation N at a point, metres (mean sea level above the ellipsoid).
pub fn undulation_m(lat_deg: f64, lon_deg: f64) -> f64 {
    let g = grid();
    let lat = lat_deg.clamp(-90.0, 90.0);
    let lon = (lon_deg + 180.0).rem_euclid(360.0) - 180.0;
    let fi = (lat + 90.0) / STEP_DEG;
    let fj = (lon + 180.0) / STEP_DEG;
    let i0 = (fi.floor() as usize).min(ROWS - 2);
    let j0 = (fj.floor() as usize).min(COLS - 2);
    let (di, dj) = (fi - i0 as f64, fj - j0 as f64);
    let at = |i: usize, j: usize| g[i * COLS + j] as f64 / 100.0;
    at(i0, j0) * (1.0 - di) * (1.0 - dj)
        + at(i0, j0 + 1) * (1.0 - di) * dj
        + at(i0 + 1, j0) * di * (1.0 - dj)
        + at(i0 + 1, j0 + 1) * di * dj
}

/// Height above the WGS84 ellipsoid of a point `amsl_m` above mean sea level.
pub fn ellipsoid_height_m(lat_deg: f64, lon_deg: f64, amsl_m: f64) -> f64 {
    amsl_m + undulation_m(lat_deg, lon_deg)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Golden values: the PyPI `egm96` package's 5-minute grid at these points (Munich
    /// 45.48 m in its documentation), within this grid's interpolation difference.
    #[test]
    fn undulations_match_the_five_minute_grid() {
        for (lat, lon, n) in [(48.14, 11.58, 45.476), (46.84, -91.99, -28.725), (41.04, -83.31, -35.84)] {
            let got = undulation_m(lat, lon);
            assert!((got - n).abs() < 0.3, "({lat}, {lon}): {got} m, 5-minute grid {n} m");
        }
        // The extremes of the field: the Indian Ocean low, New Guinea's high.
        assert!(undulation_m(4.7, 78.8) < -100.0);
        assert!(undulation_m(-8.2, 147.3) > 75.0);
        // Longitude wraps; the poles are single values.
        assert!((undulation_m(10.0, 190.0) - undulation_m(10.0, -170.0)).abs() < 1e-9);
        assert!((undulation_m(90.0, 0.0) - undulation_m(90.0, 120.0)).abs() < 1e-9);
    }

    /// The Seneca survey's own tags carry both heights: AltitudeWGS84 - AltitudeAMSL is
    /// -31.1 to -40.1 m over its photos, -35.0 m on average (their PROVENANCE.md).
    #[test]
    fn the_seneca_tags_agree_with_the_geoid() {
        let h = ellipsoid_height_m(41.036704, -83.3053526, 312.975);
        assert!((h - (312.975 - 35.0)).abs() < 5.0, "{h}");
    }
}
