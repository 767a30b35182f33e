//! WGS84 geodetic coordinates and the local NED frame around a geodetic origin.
//!
//! The conversion goes through ECEF with the `map_3d` crate (a port of pymap3d), which
//! keeps the WGS84 constants and the iterative ECEF -> geodetic inversion out of this
//! code base.

use map_3d::{geodetic2ned, ned2geodetic, Ellipsoid};
use serde::{Deserialize, Serialize};

use crate::Vec3;

/// A WGS84 position: latitude and longitude in degrees, height above the ellipsoid in
/// metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Geodetic {
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub alt_m: f64,
}

/// A number for a message: in exponent form when huge or tiny (`{}` writes 1e308 with
/// all its 309 digits).
pub fn readable(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-3..1e6).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

impl Geodetic {
    pub fn new(lat_deg: f64, lon_deg: f64, alt_m: f64) -> Self {
        Geodetic { lat_deg, lon_deg, alt_m }
    }

    /// Checks the coordinates are on the globe; the message names the bad one.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.lat_deg.is_finite() && (-90.0..=90.0).contains(&self.lat_deg)) {
            return Err(format!("latitude {} deg is outside [-90, 90]", readable(self.lat_deg)));
        }
        if !(self.lon_deg.is_finite() && (-180.0..=180.0).contains(&self.lon_deg)) {
            return Err(format!("longitude {} deg is outside [-180, 180]", readable(self.lon_deg)));
        }
        if !(self.alt_m.is_finite() && (-12_000.0..=100_000.0).contains(&self.alt_m)) {
            return Err(format!("altitude {} m is outside [-12000, 100000]", readable(self.alt_m)));
        }
        Ok(())
    }
}

/// A local North-East-Down frame tangent to the WGS84 ellipsoid at `origin`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LocalFrame {
    pub origin: Geodetic,
}

impl LocalFrame {
    pub fn new(origin: Geodetic) -> Self {
        LocalFrame { origin }
    }

    /// Local NED coordinates of a geodetic position.
    pub fn to_ned(&self, p: &Geodetic) -> Vec3 {
        let o = &self.origin;
        let (n, e, d) = geodetic2ned(
            p.lat_deg.to_radians(),
            p.lon_deg.to_radians(),
            p.alt_m,
            o.lat_deg.to_radians(),
            o.lon_deg.to_radians(),
            o.alt_m,
            Ellipsoid::WGS84,
        );
        Vec3::new(n, e, d)
    }

    /// Geodetic position of a local NED point.
    pub fn to_geodetic(&self, ned: &Vec3) -> Geodetic {
        let o = &self.origin;
        let (lat, lon, alt) = ned2geodetic(
            ned.x,
            ned.y,
            ned.z,
            o.lat_deg.to_radians(),
            o.lon_deg.to_radians(),
            o.alt_m,
            Ellipsoid::WGS84,
        );
        Geodetic { lat_deg: lat.to_degrees(), lon_deg: lon.to_degrees(), alt_m: alt }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn origin_is_zero_and_north_is_north() {
        let f = LocalFrame::new(Geodetic::new(57.0134748, 9.9742011, 10.0));
        assert!(f.to_ned(&f.origin).norm() < 1e-6);
        // Seed table 6.7, marker "Center" relative to the RTK mast; expected values from the
        // meridian and prime-vertical radii of curvature of WGS84 at 57.01 deg (the seed's
        // own table rounds through the drone's GPS and is 0.6 m off).
        let m = f.to_ned(&Geodetic::new(57.0131517, 9.9740606, 10.0));
        assert!((m.x + 35.980).abs() < 0.01 && (m.y + 8.535).abs() < 0.01, "{m:?}");
        // Going up is negative down.
        let up = f.to_ned(&Geodetic::new(57.0134748, 9.9742011, 40.0));
        assert!((up.z + 30.0).abs() < 1e-6);
    }

    #[test]
    fn validate_rejects_off_globe() {
        assert!(Geodetic::new(91.0, 0.0, 0.0).validate().unwrap_err().contains("latitude"));
        assert!(Geodetic::new(0.0, 181.0, 0.0).validate().unwrap_err().contains("longitude"));
        assert!(Geodetic::new(45.0, 7.0, 300.0).validate().is_ok());
    }

    proptest! {
        /// WGS84 -> NED -> WGS84 round trip under 1 mm within 10 km of the origin.
        #[test]
        fn ned_round_trip_under_a_millimetre(
            lat0 in -85.0f64..85.0,
            lon0 in -180.0f64..180.0,
            alt0 in -100.0f64..3000.0,
            n in -10_000.0f64..10_000.0,
            e in -10_000.0f64..10_000.0,
            d in -2_000.0f64..500.0,
        ) {
            let f = LocalFrame::new(Geodetic::new(lat0, lon0, alt0));
            let ned = Vec3::new(n, e, d);
            prop_assume!(ned.norm() <= 10_000.0);
            let back = f.to_ned(&f.to_geodetic(&ned));
            prop_assert!((back - ned).norm() < 1e-3, "{back:?} vs {ned:?}");
        }

        /// And from the geodetic side: a position near the origin survives the trip.
        #[test]
        fn geodetic_round_trip(
            lat0 in -80.0f64..80.0, lon0 in -179.0f64..179.0,
            dlat in -0.05f64..0.05, dlon in -0.05f64..0.05, alt in -50.0f64..500.0,
        ) {
            let f = LocalFrame::new(Geodetic::new(lat0, lon0, 0.0));
            let p = Geodetic::new(lat0 + dlat, lon0 + dlon, alt);
            let back = f.to_geodetic(&f.to_ned(&p));
            // 1e-8 deg is about 1 mm.
            prop_assert!((back.lat_deg - p.lat_deg).abs() < 1e-8);
            prop_assert!((back.lon_deg - p.lon_deg).abs() < 1e-8);
            prop_assert!((back.alt_m - p.alt_m).abs() < 1e-3);
        }
    }
}
