//! Scenario files (`sim/scenarios/*.toml`): everything needed to rebuild a world and
//! re-render a dataset, deterministically from `seed`.

use std::path::{Path, PathBuf};

use mavloc_geometry::{Geodetic, GimbalChain};
use serde::{Deserialize, Serialize};

/// Which world generator builds the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WorldKind {
    /// Mostly flat land around a lake; the target is the water (area seed fig. 4.10-4.12).
    Coastline,
    /// An escarpment with a darker region whose border runs over the slope (fig. 4.13-4.14).
    Cliff,
    /// A flat textured floor for the texton pipeline (indoor seed sec. 3.4.2, 4.6).
    IndoorFloor,
}

/// The largest frame side the renderer takes, pixels (an 8K sensor is 7680 wide).
pub const MAX_SIDE_PX: u32 = 16384;
/// The most pixels a rendered frame may have (about 800 MB to render).
pub const MAX_PIXELS: u64 = 40_000_000;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub kind: WorldKind,
    pub seed: u64,
    pub origin: Geodetic,
    pub terrain: TerrainSpec,
    pub ground: GroundSpec,
    pub camera: CameraSpec,
    pub mission: MissionSpec,
    #[serde(default)]
    pub noise: NoiseSpec,
    /// Ranges of random views (`mavloc sim render --views N`), indoor scenarios.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<ViewSpec>,
    /// Folder relative paths in the file are resolved against (not serialised).
    #[serde(skip)]
    pub base_dir: Option<PathBuf>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainSpec {
    /// Side of the square terrain, metres.
    pub size_m: f64,
    /// Grid spacing, metres.
    pub cell_m: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundSpec {
    /// Texture image: a built-in asset name (`aukerman.png`, `caliterra.png`), a path, or
    /// empty for the procedural texture.
    #[serde(default)]
    pub texture: String,
    /// Ground size of one texel, metres.
    pub metres_per_texel: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub width: u32,
    pub height: u32,
    pub hfov_deg: f64,
    pub chain: GimbalChain,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MissionSpec {
    /// Flight altitude above the local origin, metres.
    pub altitude_m: f64,
    /// Horizontal offset of the flight path from the border, metres (positive: outside the
    /// target area).
    pub offset_m: f64,
    /// Altitude varies by this much (+-) along the path, for viewpoint diversity (seed
    /// sec. 4.2.4: "offset along all 3 axes").
    #[serde(default)]
    pub altitude_swing_m: f64,
    /// Speed limit, m/s (seed table 6.4: 3).
    pub speed_m_s: f64,
    /// Capture rate, Hz (seed sec. 6.3: about 6).
    pub frame_rate_hz: f64,
    /// Spacing of waypoints along the border, metres.
    pub waypoint_spacing_m: f64,
    /// `border` (the seed's: along the border, camera on it) or `lines` (a photo survey:
    /// parallel lines across the border, flown back and forth, camera straight down).
    #[serde(default)]
    pub pattern: MissionPattern,
    /// For `lines`: how many, how far apart (m) and how long (m). The lines run along the
    /// border where it is furthest north, centred on it.
    #[serde(default = "default_line_count")]
    pub line_count: usize,
    #[serde(default = "default_line_spacing")]
    pub line_spacing_m: f64,
    #[serde(default = "default_line_length")]
    pub line_length_m: f64,
}

fn default_line_count() -> usize {
    3
}
fn default_line_spacing() -> f64 {
    25.0
}
fn default_line_length() -> f64 {
    80.0
}

/// How the mission flies (`mission.pattern`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MissionPattern {
    /// Along the border, offset from it, the gimbal on its nearest point (area seed sec.
    /// 4.2.4).
    #[default]
    Border,
    /// A photo survey: parallel lines, every other one flown back, the camera pointing
    /// straight down with its top to the direction of flight (as a DJI survey does).
    Lines,
}

/// Sensor noise and faults added to what the simulated vehicle reports (seed table 6.2,
/// sec. 5.6.1, 6.10). The true pose is always recorded next to the noisy one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseSpec {
    pub gimbal_yaw_sd_deg: f64,
    pub gimbal_pitch_sd_deg: f64,
    /// North, east, down.
    pub position_sd_m: [f64; 3],
    /// Static offsets added to the reported gimbal yaw, pitch, roll.
    pub gimbal_offset_deg: [f64; 3],
    /// The reported gimbal attitude is the one this long before the frame.
    pub gimbal_lag_s: f64,
    /// Fraction of frames dropped, 0..1.
    pub drop_rate: f64,
    /// SD of a slowly varying error of the reported gimbal yaw, pitch, roll, degrees: an
    /// autopilot's attitude estimate wanders rather than jitters (PX4 v1.16 SIH with GPS,
    /// against its own truth over a coastline flight: heading 2.1 deg mean and 3.0 SD off,
    /// roll 1.1 SD, nearly constant over 10 s; the camera turned on the estimated body
    /// shares that error). A first-order Gauss-Markov process per angle.
    pub gimbal_drift_sd_deg: [f64; 3],
    /// Its correlation time, seconds.
    pub gimbal_drift_tau_s: f64,
}

impl Default for NoiseSpec {
    fn default() -> Self {
        NoiseSpec {
            gimbal_yaw_sd_deg: 0.5,
            gimbal_pitch_sd_deg: 0.5,
            position_sd_m: [0.5, 0.5, 2.0],
            gimbal_offset_deg: [0.0; 3],
            gimbal_lag_s: 0.0,
            drop_rate: 0.0,
            gimbal_drift_sd_deg: [0.0; 3],
            gimbal_drift_tau_s: 20.0,
        }
    }
}

impl NoiseSpec {
    /// No noise at all.
    pub fn none() -> Self {
        NoiseSpec {
            gimbal_yaw_sd_deg: 0.0,
            gimbal_pitch_sd_deg: 0.0,
            position_sd_m: [0.0; 3],
            gimbal_offset_deg: [0.0; 3],
            gimbal_lag_s: 0.0,
            drop_rate: 0.0,
            gimbal_drift_sd_deg: [0.0; 3],
            gimbal_drift_tau_s: 20.0,
        }
    }
}

/// Ranges of the random views (uniform within each range).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ViewSpec {
    /// Largest |roll| and |pitch| of the vehicle, degrees.
    pub max_tilt_deg: f64,
    /// Height range above the floor, metres.
    pub height_m: [f64; 2],
    /// Half side of the square the view centres are drawn from, metres.
    pub half_extent_m: f64,
    /// Brightness offset range, grey levels.
    pub brightness: [f64; 2],
    /// Contrast factor range.
    pub contrast: [f64; 2],
    /// Largest box-blur kernel (odd sizes from 1 up to this).
    pub max_blur_px: u32,
}

impl Default for ViewSpec {
    fn default() -> Self {
        ViewSpec {
            max_tilt_deg: 8.0,
            height_m: [0.8, 1.2],
            half_extent_m: 3.6,
            brightness: [-25.0, 25.0],
            contrast: [0.8, 1.2],
            max_blur_px: 5,
        }
    }
}

/// The built-in scenarios, by name.
pub const BUILT_IN: &[(&str, &str)] = &[
    ("coastline", include_str!("../scenarios/coastline.toml")),
    ("coastline-survey", include_str!("../scenarios/coastline-survey.toml")),
    ("cliff", include_str!("../scenarios/cliff.toml")),
    ("indoor-floor", include_str!("../scenarios/indoor-floor.toml")),
];

impl Scenario {
    /// Parses a scenario from TOML text.
    pub fn parse(text: &str, origin: &str) -> Result<Scenario, String> {
        let s: Scenario = toml::from_str(text).map_err(|e| format!("scenario {origin}: {e}"))?;
        s.validate().map_err(|e| format!("scenario {origin}: {e}"))?;
        Ok(s)
    }

    /// A built-in scenario by name, or a scenario file by path.
    pub fn load(name_or_path: &str) -> Result<Scenario, String> {
        if let Some((_, text)) = BUILT_IN.iter().find(|(n, _)| *n == name_or_path) {
            return Scenario::parse(text, name_or_path);
        }
        let path = Path::new(name_or_path);
        if !path.exists() {
            let names: Vec<_> = BUILT_IN.iter().map(|(n, _)| *n).collect();
            return Err(format!(
                "no scenario `{name_or_path}`: give one of {} or a scenario file",
                names.join(", ")
            ));
        }
        let text =
            std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        let mut s = Scenario::parse(&text, &path.display().to_string())?;
        s.base_dir = path.parent().map(Path::to_path_buf);
        Ok(s)
    }

    /// Checks values a world cannot be built from.
    pub fn validate(&self) -> Result<(), String> {
        self.origin.validate()?;
        let t = &self.terrain;
        if !(t.cell_m > 0.0 && t.size_m >= 2.0 * t.cell_m && t.size_m / t.cell_m <= 4000.0) {
            return Err(format!("terrain: size_m {} / cell_m {} is not a usable grid", t.size_m, t.cell_m));
        }
        if !self.ground.metres_per_texel.is_finite() || self.ground.metres_per_texel <= 0.0 {
            return Err("ground.metres_per_texel must be positive".into());
        }
        let c = &self.camera;
        if c.width < 16 || c.height < 16 || !(1.0..=179.0).contains(&c.hfov_deg) {
            return Err(format!(
                "camera: {}x{} px, hfov {} deg is not a usable camera",
                c.width, c.height, c.hfov_deg
            ));
        }
        // A frame takes about 20 bytes a pixel to render (depth buffer, colour, mask): a
        // size the machine cannot hold is refused here, not by an allocation abort.
        if c.width > MAX_SIDE_PX || c.height > MAX_SIDE_PX || c.width as u64 * c.height as u64 > MAX_PIXELS {
            return Err(format!(
                "camera: {}x{} px is larger than the renderer takes (at most {MAX_SIDE_PX} px a side and {} megapixels)",
                c.width,
                c.height,
                MAX_PIXELS / 1_000_000
            ));
        }
        let m = &self.mission;
        if !(m.speed_m_s > 0.0 && m.frame_rate_hz > 0.0 && m.waypoint_spacing_m > 0.0 && m.altitude_m > 0.0) {
            return Err("mission: speed, frame rate, waypoint spacing and altitude must be positive".into());
        }
        if m.pattern == MissionPattern::Lines
            && !(m.line_count >= 1 && m.line_spacing_m > 0.0 && m.line_length_m > 0.0)
        {
            return Err(
                "mission: a survey needs line_count >= 1 and positive line_spacing_m and line_length_m"
                    .into(),
            );
        }
        if !(0.0..1.0).contains(&self.noise.drop_rate) {
            return Err(format!("noise.drop_rate {} must be in [0, 1)", self.noise.drop_rate));
        }
        Ok(())
    }

    /// The camera intrinsics at the scenario's resolution.
    pub fn intrinsics(&self) -> mavloc_geometry::Intrinsics {
        mavloc_geometry::Intrinsics::from_hfov(
            self.camera.width,
            self.camera.height,
            self.camera.hfov_deg.to_radians(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_scenarios_parse() {
        for (name, _) in BUILT_IN {
            let s = Scenario::load(name).unwrap();
            assert_eq!(&s.name, name);
        }
    }

    #[test]
    fn unknown_scenario_lists_the_built_in_ones() {
        let e = Scenario::load("moon").unwrap_err();
        assert!(e.contains("coastline") && e.contains("indoor-floor"), "{e}");
    }

    /// Sizes the renderer cannot hold are refused by name (100000x100000 aborted the
    /// process allocating 160 GB); an 8K frame and the small ones pass.
    #[test]
    fn camera_sizes_are_checked_both_ways() {
        let mut s = Scenario::load("coastline").unwrap();
        for (w, h, ok) in [
            (16, 16, true),
            (7680, 4320, true),
            (8, 90, false),
            (100_000, 100_000, false),
            (16384, 4096, false),
        ] {
            (s.camera.width, s.camera.height) = (w, h);
            let r = s.validate();
            assert_eq!(r.is_ok(), ok, "{w}x{h}: {r:?}");
            if let Err(e) = r {
                assert!(e.contains(&format!("{w}x{h} px")), "{e}");
            }
        }
    }

    #[test]
    fn unknown_key_is_refused() {
        let text = BUILT_IN[0].1.replace("[mission]", "[mission]\nspeeed = 3.0");
        assert!(Scenario::parse(&text, "x").unwrap_err().contains("speeed"));
    }
}
