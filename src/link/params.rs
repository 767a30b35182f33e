//! mavloc's MAVLink parameters: the runtime-tunable subset of the configuration under
//! names QGroundControl can list and set (at most 16 characters), with types, checks on
//! set, and a state file that keeps tuned values across restarts.
//!
//! Each parameter is a view of one configuration key, so a set is checked by exactly the
//! validation a config file gets, and a tuned value means the same thing as that key in
//! `config/mavloc.toml`. Integers, booleans and enumerations are `MAV_PARAM_TYPE_INT32`
//! sent in PX4's byte-wise encoding (the int's bytes in the float field), which is what
//! QGroundControl expects from components of a PX4 vehicle; sets are accepted in either
//! encoding. Keys that define a trained model or the hardware (texton size, camera,
//! link) are not parameters: changing them in flight could not be applied honestly.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use mavlink::dialects::common::MavParamType;
use serde_json::Value;

use crate::settings::{self, Settings};

/// How a parameter's value maps to its configuration key.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    Float,
    Int,
    Bool,
    /// Index into these names.
    Enum(&'static [&'static str]),
}

/// One parameter.
#[derive(Clone, Copy, Debug)]
pub struct ParamDef {
    pub name: &'static str,
    pub key: &'static str,
    pub kind: Kind,
}

const fn p(name: &'static str, key: &'static str, kind: Kind) -> ParamDef {
    ParamDef { name, key, kind }
}

use Kind::*;

/// Every parameter, in the order PARAM_REQUEST_LIST reports them (their index).
pub const PARAMS: &[ParamDef] = &[
    p("LOC_PIPELINE", "daemon.pipeline", Enum(&["none", "area", "indoor"])),
    p("LOC_FRAME_AGE", "daemon.max_frame_age_s", Float),
    p("GMB_AIM", "gimbal.aim", Enum(&["mission", "border"])),
    p("GMB_USE_TELEM", "gimbal.use_telemetry", Bool),
    p("GMB_MNT_YAW", "gimbal.mount_yaw_deg", Float),
    p("GMB_MNT_PITCH", "gimbal.mount_pitch_deg", Float),
    p("GMB_MNT_ROLL", "gimbal.mount_roll_deg", Float),
    p("GMB_OFF_YAW", "gimbal.yaw_offset_deg", Float),
    p("GMB_OFF_PITCH", "gimbal.pitch_offset_deg", Float),
    p("GMB_OFF_ROLL", "gimbal.roll_offset_deg", Float),
    p("AREA_METHOD", "area.method", Enum(&["ukf", "ground-plane"])),
    p("AREA_DOWNSCALE", "area.downscale", Int),
    p("AREA_BAND_PX", "area.band_px", Int),
    p("AREA_L_MAX", "area.l_max", Int),
    p("AREA_TURNOVER", "area.turnover", Int),
    p("AREA_FEAT_FACT", "area.feature_factor", Int),
    p("AREA_RATIO", "area.ratio_test", Float),
    p("AREA_MAHAL_MAX", "area.mahalanobis_max", Float),
    p("AREA_CONV_M", "area.convergence_m", Float),
    p("AREA_MIN_OBS", "area.min_observations", Int),
    p("AREA_BEAR_NOISE", "area.bearing_noise_deg", Float),
    p("AREA_UKF_ALPHA", "area.ukf_alpha", Float),
    p("AREA_UKF_BETA", "area.ukf_beta", Float),
    p("AREA_UKF_KAPPA", "area.ukf_kappa", Float),
    p("AREA_UKF_ITER", "area.ukf_iterations", Int),
    p("AREA_INIT_SIG", "area.init_sigma_m", Float),
    p("AREA_GROUND_D", "area.ground_down_m", Float),
    p("AREA_MAX_DESC", "area.max_descriptors", Int),
    p("AREA_ADJ_PRIOR", "area.attitude_prior_deg", Float),
    p("AREA_ADJ_FIRST", "area.adjust_first_frames", Int),
    p("IND_SAMPLES", "indoor.samples", Int),
    p("IND_K", "indoor.k", Int),
    p("IND_PARTICLES", "indoor.particles", Int),
    p("IND_MOTION", "indoor.motion_model", Enum(&["noise", "velocity"])),
    p("IND_PROC_SIG", "indoor.process_sigma_m", Float),
    p("IND_VEL_SIG", "indoor.velocity_sigma_m_s", Float),
    p("IND_LAND_EN", "indoor.landing_enabled", Bool),
    p("IND_LAND_X", "indoor.landing_x_m", Float),
    p("IND_LAND_Y", "indoor.landing_y_m", Float),
    p("IND_LAND_R", "indoor.landing_radius_m", Float),
    p("IND_LAND_SIG", "indoor.landing_sigma_gate_m", Float),
    p("IND_LAND_FRAMES", "indoor.landing_frames", Int),
    p("IND_LAND_PREC", "indoor.landing_precision", Bool),
];

/// A value as MAVLink carries it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wire {
    pub value: f32,
    pub ty: MavParamType,
}

/// Why a set was refused.
#[derive(Clone, Debug, PartialEq)]
pub enum SetError {
    Unknown(String),
    Refused { name: &'static str, why: String },
}

impl std::fmt::Display for SetError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SetError::Unknown(n) => write!(f, "no parameter {n}"),
            SetError::Refused { name, why } => write!(f, "{name}: {why}"),
        }
    }
}

pub fn find(name: &str) -> Option<(usize, &'static ParamDef)> {
    PARAMS.iter().enumerate().find(|(_, d)| d.name == name)
}

fn get_key<'a>(v: &'a Value, key: &str) -> &'a Value {
    let (section, field) = key.split_once('.').expect("dotted key");
    &v[section][field]
}

/// A parameter's current numeric value from the settings.
pub fn value_of(settings: &Settings, def: &ParamDef) -> f64 {
    let v = serde_json::to_value(settings).expect("settings serialise");
    let x = get_key(&v, def.key);
    match def.kind {
        Float | Int => x.as_f64().expect("numeric key"),
        Bool => x.as_bool().expect("bool key") as u8 as f64,
        Enum(names) => names.iter().position(|n| Some(*n) == x.as_str()).expect("known enum name") as f64,
    }
}

/// The wire form of a parameter's value.
pub fn encode(settings: &Settings, def: &ParamDef) -> Wire {
    let x = value_of(settings, def);
    match def.kind {
        Float => Wire { value: x as f32, ty: MavParamType::MAV_PARAM_TYPE_REAL32 },
        _ => Wire { value: f32::from_bits(x as i32 as u32), ty: MavParamType::MAV_PARAM_TYPE_INT32 },
    }
}

/// Reads a set's value as a number, in either integer encoding.
fn decode(def: &ParamDef, w: Wire) -> Result<f64, String> {
    let x = match w.ty {
        // The shortest decimal that is this f32: a 0.7 typed in QGroundControl is 0.7 in
        // the configuration, not 0.699999988.
        MavParamType::MAV_PARAM_TYPE_REAL32 => w.value.to_string().parse::<f64>().unwrap_or(f64::NAN),
        MavParamType::MAV_PARAM_TYPE_INT32
        | MavParamType::MAV_PARAM_TYPE_UINT32
        | MavParamType::MAV_PARAM_TYPE_INT16
        | MavParamType::MAV_PARAM_TYPE_UINT16
        | MavParamType::MAV_PARAM_TYPE_INT8
        | MavParamType::MAV_PARAM_TYPE_UINT8 => {
            // Byte-wise (PX4) if the bits read as a small integer, else a C cast (ArduPilot
            // style): a real float of an integer never has a tiny bit pattern. For an
            // integer parameter every pattern below 1.0f's is byte-wise: as a float it is a
            // fraction, never a C-cast integer (AREA_ADJ_FIRST's 9000000 is 2^23 and more).
            let bits = w.value.to_bits() as i32;
            let below_one = (0..0x3F80_0000).contains(&bits);
            if (-(1 << 23)..(1 << 23)).contains(&bits) || (def.kind != Float && below_one) {
                bits as f64
            } else {
                // The shortest decimal here too: a float sent under an integer type was
                // kept as 0.6000000238418579.
                w.value.to_string().parse::<f64>().unwrap_or(f64::NAN)
            }
        }
        other => return Err(format!("type {other:?} is not supported; use REAL32 or INT32")),
    };
    if !x.is_finite() {
        return Err("value is not a finite number".into());
    }
    if def.kind != Float && x.fract() != 0.0 {
        return Err(format!("{x} is not an integer"));
    }
    Ok(x)
}

/// Sets a parameter on a copy of the settings and validates the result like a config
/// file. Returns the new settings; the caller applies and persists them.
pub fn set(settings: &Settings, name: &str, w: Wire) -> Result<(Settings, f64), SetError> {
    let (_, def) = find(name).ok_or_else(|| SetError::Unknown(name.to_string()))?;
    let refuse = |why: String| SetError::Refused { name: def.name, why };
    let x = decode(def, w).map_err(refuse)?;
    let new_value = match def.kind {
        Float => serde_json::json!(x),
        Int if x < 0.0 => return Err(refuse(format!("{x} is negative"))),
        Int => serde_json::json!(x as u64),
        Bool if x == 0.0 || x == 1.0 => serde_json::json!(x == 1.0),
        Bool => return Err(refuse(format!("{x} is not 0 or 1"))),
        Enum(names) => match names.get(x as usize).filter(|_| x >= 0.0) {
            Some(n) => serde_json::json!(n),
            None => {
                let opts: Vec<_> = names.iter().enumerate().map(|(i, n)| format!("{i}={n}")).collect();
                return Err(refuse(format!("{x} is not one of {}", opts.join(", "))));
            }
        },
    };
    let mut v = serde_json::to_value(settings).expect("settings serialise");
    let (section, field) = def.key.split_once('.').expect("dotted key");
    v[section][field] = new_value;
    let new: Settings = serde_json::from_value(v).map_err(|e| refuse(e.to_string()))?;
    let mut origins = BTreeMap::new();
    origins.insert(def.key.to_string(), "PARAM_SET".to_string());
    let problems = settings::validate(&new, &origins);
    if let Some(p) = problems.first() {
        // A value can break another key's bound (AREA_L_MAX below AREA_TURNOVER): that
        // key is named, with the parameter it is, or its range would read as this one's.
        if p.key != def.key {
            let other =
                PARAMS.iter().find(|d| d.key == p.key).map(|d| format!(" ({})", d.name)).unwrap_or_default();
            return Err(refuse(format!(
                "{x} would leave {}{other} = {} {}",
                p.key,
                p.value.as_deref().unwrap_or("?"),
                p.expected
            )));
        }
        return Err(refuse(p.expected.clone()));
    }
    // A pipeline that cannot start is refused here, not taken and then failed: taken, it
    // stopped the running one, was saved, and left the next start with no pipeline.
    if def.key == "daemon.pipeline"
        && new.daemon.pipeline == settings::PipelineKind::Indoor
        && new.indoor.model.is_empty()
    {
        return Err(refuse(format!(
            "{x} (indoor) needs a floor model and indoor.model is not set (`mavloc indoor train`)"
        )));
    }
    Ok((new, x))
}

/// Why `params.json` could not be read.
#[derive(Debug)]
pub enum Unreadable {
    /// Not a parameter file (not text, not JSON, not a map of numbers).
    Corrupt(String),
    Io(std::io::Error),
}

/// The largest `params.json` read: every parameter tuned takes a few kB, so anything
/// larger is not one (a link to `/dev/zero` was read until the kernel killed mavloc).
const MAX_PARAMS_FILE: u64 = 1 << 20;

/// Reads `params.json` without changing anything: `None` when there is none.
pub fn read_tuned(path: &Path) -> Result<Option<BTreeMap<String, f64>>, Unreadable> {
    let bytes = match mavloc_data::state::read_capped(path, MAX_PARAMS_FILE) {
        Ok(Some(b)) => b,
        Ok(None) => return Err(Unreadable::Corrupt(format!("larger than {MAX_PARAMS_FILE} bytes"))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Unreadable::Io(e)),
    };
    let text = String::from_utf8(bytes).map_err(|e| Unreadable::Corrupt(format!("not text: {e}")))?;
    serde_json::from_str(&text).map(Some).map_err(|e| Unreadable::Corrupt(e.to_string()))
}

/// What became of one tuned value.
#[derive(Clone, Debug, PartialEq)]
pub enum Tuned {
    /// In force.
    Applied { name: String, key: &'static str, value: f64 },
    /// Kept, but the command line set the same key, and the command line wins.
    Pinned { name: String, key: &'static str, value: f64 },
    /// No longer a parameter, or no longer valid.
    Dropped { name: String, why: String },
}

/// Applies tuned values over `settings`, except keys in `pinned`.
pub fn apply_tuned(
    settings: &mut Settings,
    tuned: &BTreeMap<String, f64>,
    pinned: &BTreeSet<String>,
) -> Vec<Tuned> {
    let mut out = Vec::new();
    for (name, &x) in tuned {
        let Some((_, def)) = find(name) else {
            out.push(Tuned::Dropped { name: name.clone(), why: "no longer a parameter".into() });
            continue;
        };
        if pinned.contains(def.key) {
            out.push(Tuned::Pinned { name: name.clone(), key: def.key, value: x });
            continue;
        }
        // The file holds any JSON number; what goes further must fit the parameter's
        // wire type, or `as` would make 1e300 infinite (then called "not a finite
        // number") and 1e12 the largest INT32, a value nobody set.
        let fits = match def.kind {
            Float => x.is_finite() && x.abs() <= f32::MAX as f64,
            _ => x.is_finite() && x >= i32::MIN as f64 && x <= i32::MAX as f64,
        };
        if !fits {
            let ty = if def.kind == Float { "REAL32" } else { "INT32" };
            out.push(Tuned::Dropped {
                name: name.clone(),
                why: format!("{x:e} is beyond the range of {ty}, the parameter's type"),
            });
            continue;
        }
        let w = match def.kind {
            Float => Wire { value: x as f32, ty: MavParamType::MAV_PARAM_TYPE_REAL32 },
            _ => Wire { value: f32::from_bits(x as i32 as u32), ty: MavParamType::MAV_PARAM_TYPE_INT32 },
        };
        match set(settings, name, w) {
            Ok((s, v)) => {
                *settings = s;
                out.push(Tuned::Applied { name: name.clone(), key: def.key, value: v });
            }
            Err(e) => out.push(Tuned::Dropped { name: name.clone(), why: e.to_string() }),
        }
    }
    out
}

/// Configuration keys set on the command line (`--set`), which win over tuned values.
pub fn pinned_keys(origins: &BTreeMap<String, String>) -> BTreeSet<String> {
    origins.iter().filter(|(_, o)| o.starts_with("command line")).map(|(k, _)| k.clone()).collect()
}

/// Tuned values, kept in the state directory as `params.json` ({"NAME": value}).
pub struct ParamStore {
    path: Option<PathBuf>,
    tuned: BTreeMap<String, f64>,
}

impl ParamStore {
    pub fn in_memory() -> ParamStore {
        ParamStore { path: None, tuned: BTreeMap::new() }
    }

    /// Opens the store and applies what it holds to `settings`, except keys in `pinned`
    /// (set on the command line, which wins over tuned values: the precedence is
    /// defaults < file < environment < tuned over MAVLink < `--set`). Entries that no
    /// longer name a parameter or no longer validate are reported and dropped, not fatal:
    /// a config change must not stop a drone's companion from starting. A pinned entry
    /// stays in the file for later runs.
    pub fn open(
        path: &Path,
        settings: &mut Settings,
        pinned: &BTreeSet<String>,
    ) -> (ParamStore, Vec<(tracing::Level, String)>) {
        let mut notes = Vec::new();
        let mut store = ParamStore { path: Some(path.to_path_buf()), tuned: BTreeMap::new() };
        let map = match read_tuned(path) {
            Ok(Some(m)) => m,
            Ok(None) => return (store, notes),
            Err(Unreadable::Corrupt(why)) => {
                move_aside(path, &why);
                return (store, notes);
            }
            Err(Unreadable::Io(e)) => {
                notes.push((
                    tracing::Level::WARN,
                    format!(
                        "{}: cannot read tuned parameters ({e}); using the configuration",
                        path.display()
                    ),
                ));
                return (store, notes);
            }
        };
        for t in apply_tuned(settings, &map, pinned) {
            match t {
                Tuned::Applied { name, value, .. } => {
                    notes.push((
                        tracing::Level::INFO,
                        format!("{name} = {value} (tuned over MAVLink, from {})", path.display()),
                    ));
                    store.tuned.insert(name, value);
                }
                Tuned::Pinned { name, key, value } => {
                    notes.push((
                        tracing::Level::INFO,
                        format!(
                            "{name} = {value} tuned over MAVLink is not used this run: --set {key} wins (kept in {})",
                            path.display()
                        ),
                    ));
                    store.tuned.insert(name, value);
                }
                // Said as a warning: a value the ground set is not in force.
                Tuned::Dropped { name, why } => {
                    notes.push((tracing::Level::WARN, format!("{}: {name}: {why}; dropped", path.display())))
                }
            }
        }
        (store, notes)
    }

    /// The tuned values, for the daemon's core (which then owns them).
    pub fn into_tuned(self) -> BTreeMap<String, f64> {
        self.tuned
    }

    /// Records a tuned value and writes the file atomically.
    pub fn record(&mut self, name: &str, value: f64) -> std::io::Result<()> {
        self.tuned.insert(name.to_string(), value);
        match &self.path {
            Some(p) => {
                let json = serde_json::to_string_pretty(&self.tuned).expect("map serialises");
                mavloc_data::write_atomic(p, json.as_bytes())
            }
            None => Ok(()),
        }
    }
}

/// A parameter file that does not parse is moved aside, not ignored: the next PARAM_SET
/// would overwrite it and the tuned values it still holds would be lost unseen. mavloc
/// starts with the configuration's values.
fn move_aside(path: &Path, why: &str) {
    let said = mavloc_data::state::set_aside(path, None, "parameter file", why);
    tracing::warn!("{said}; starting with the configuration's values");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_mavlink_legal_unique_and_keys_exist() {
        let s = Settings::default();
        let mut seen = std::collections::HashSet::new();
        for d in PARAMS {
            assert!(
                d.name.len() <= 16
                    && d.name.chars().all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'),
                "{}",
                d.name
            );
            assert!(seen.insert(d.name), "duplicate {}", d.name);
            assert!(settings::all_keys().contains(&d.key.to_string()), "{} -> {}", d.name, d.key);
            value_of(&s, d); // panics on a kind mismatch
            if let Enum(names) = d.kind {
                let listed = settings::ENUM_KEYS.iter().find(|(k, _)| *k == d.key).unwrap().1;
                let mut a = names.to_vec();
                let mut b = listed.to_vec();
                a.sort();
                b.sort();
                assert_eq!(a, b, "{}", d.name);
            }
        }
    }

    #[test]
    fn every_parameter_round_trips_its_own_value() {
        let s = Settings::default();
        for d in PARAMS {
            let w = encode(&s, d);
            let (s2, _) = set(&s, d.name, w).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(s2, s, "{}", d.name);
        }
    }

    #[test]
    fn sets_are_checked_like_the_config() {
        let s = Settings::default();
        let real = |x: f32| Wire { value: x, ty: MavParamType::MAV_PARAM_TYPE_REAL32 };
        let int = |x: i32| Wire { value: f32::from_bits(x as u32), ty: MavParamType::MAV_PARAM_TYPE_INT32 };
        let (s2, _) = set(&s, "AREA_RATIO", real(0.7)).unwrap();
        assert!((s2.area.ratio_test - 0.7).abs() < 1e-6);
        assert!(matches!(set(&s, "AREA_RATIO", real(3.0)), Err(SetError::Refused { .. })));
        // A value that breaks another key's bound names that key, not its range as this one's.
        let mut low = s.clone();
        low.area.turnover = 20;
        let ten = Wire { value: f32::from_bits(10), ty: MavParamType::MAV_PARAM_TYPE_INT32 };
        let e = set(&low, "AREA_L_MAX", ten).unwrap_err().to_string();
        assert!(e.starts_with("AREA_L_MAX: 10 would leave area.turnover (AREA_TURNOVER) = 20"), "{e}");
        assert!(matches!(set(&s, "NOPE", real(1.0)), Err(SetError::Unknown(_))));
        // The indoor pipeline with no floor model would not start: refused, not taken.
        let e = set(&s, "LOC_PIPELINE", int(2)).unwrap_err().to_string();
        assert!(e.contains("indoor.model is not set"), "{e}");
        let mut with_model = s.clone();
        with_model.indoor.model = "floor.model".into();
        let (s3, _) = set(&with_model, "LOC_PIPELINE", int(2)).unwrap();
        assert_eq!(s3.daemon.pipeline, settings::PipelineKind::Indoor);
        assert!(set(&s, "LOC_PIPELINE", int(7)).unwrap_err().to_string().contains("0=none"));
        // Byte-wise integers of 2^23 and more (AREA_ADJ_FIRST's range reaches 10^7).
        for n in [9_000_000, 10_000_000] {
            let (big, x) = set(&s, "AREA_ADJ_FIRST", int(n)).unwrap();
            assert_eq!((big.area.adjust_first_frames, x), (n as u32, n as f64));
        }
        // A C-cast integer (ArduPilot style) is read too.
        let (s4, _) =
            set(&s, "AREA_BAND_PX", Wire { value: 80.0, ty: MavParamType::MAV_PARAM_TYPE_INT32 }).unwrap();
        assert_eq!(s4.area.band_px, 80);
        // A float under an integer type, as its shortest decimal.
        let (s5, _) =
            set(&s, "AREA_RATIO", Wire { value: 0.6, ty: MavParamType::MAV_PARAM_TYPE_INT32 }).unwrap();
        assert_eq!(s5.area.ratio_test, 0.6);
        assert!(set(&s, "AREA_BAND_PX", real(80.5)).is_err());
        assert!(set(&s, "IND_LAND_EN", int(2)).is_err());
    }

    /// A tuned value the wire type cannot hold is dropped as such: 1e300 was called "not
    /// a finite number", and an integer beyond INT32 became INT32's largest.
    #[test]
    fn a_tuned_value_beyond_its_wire_type_is_dropped_as_out_of_range() {
        let mut s = Settings::default();
        let tuned: BTreeMap<String, f64> =
            [("AREA_RATIO".to_string(), 1e300), ("AREA_L_MAX".to_string(), 1e12)].into_iter().collect();
        let out = apply_tuned(&mut s, &tuned, &BTreeSet::new());
        let why = |n: &str| match out.iter().find(|t| matches!(t, Tuned::Dropped { name, .. } if name == n)) {
            Some(Tuned::Dropped { why, .. }) => why.clone(),
            _ => panic!("{n} not dropped: {out:?}"),
        };
        assert_eq!(why("AREA_RATIO"), "1e300 is beyond the range of REAL32, the parameter's type");
        assert_eq!(why("AREA_L_MAX"), "1e12 is beyond the range of INT32, the parameter's type");
        assert_eq!(s, Settings::default());
    }

    #[test]
    fn the_store_survives_a_restart_and_drops_stale_entries() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("params.json");
        let mut s = Settings::default();
        let (mut store, _) = ParamStore::open(&path, &mut s, &BTreeSet::new());
        store.record("AREA_BAND_PX", 77.0).unwrap();
        let mut text: BTreeMap<String, f64> =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        text.insert("GONE_PARAM".into(), 1.0);
        text.insert("AREA_RATIO".into(), 9.0); // out of range
        std::fs::write(&path, serde_json::to_string(&text).unwrap()).unwrap();
        let mut s = Settings::default();
        let (_, notes) = ParamStore::open(&path, &mut s, &BTreeSet::new());
        assert_eq!(s.area.band_px, 77);
        assert_eq!(s.area.ratio_test, Settings::default().area.ratio_test);
        let warned = |p: &str| notes.iter().any(|(l, n)| *l == tracing::Level::WARN && n.contains(p));
        assert!(warned("GONE_PARAM") && warned("AREA_RATIO"), "{notes:?}");
    }

    #[test]
    fn a_corrupt_parameter_file_is_moved_aside_and_mavloc_starts() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("params.json");
        std::fs::write(&path, b"{\"AREA_BAND_PX\": 77, \"AREA_RA").unwrap(); // torn by a power cut
        let mut s = Settings::default();
        let (mut store, _) = ParamStore::open(&path, &mut s, &BTreeSet::new());
        assert_eq!(s.area.band_px, Settings::default().area.band_px, "the configuration's values");
        assert!(store.tuned.is_empty());
        assert!(!path.exists());
        let aside: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("params.json.corrupt-"))
            .collect();
        assert_eq!(aside.len(), 1, "kept, not overwritten by the next set");
        store.record("AREA_RATIO", 0.7).unwrap();
        let aside = std::fs::read(dir.path().join(&aside[0])).unwrap();
        assert!(aside.starts_with(b"{\"AREA_BAND_PX\": 77"));
        // Bytes that are not even text go the same way.
        std::fs::write(&path, [0xff, 0xfe, 0x00]).unwrap();
        ParamStore::open(&path, &mut Settings::default(), &BTreeSet::new());
        assert!(!path.exists());
        // And one without end (a link to /dev/zero was read until memory ran out).
        std::os::unix::fs::symlink("/dev/zero", &path).unwrap();
        ParamStore::open(&path, &mut Settings::default(), &BTreeSet::new());
        assert!(std::fs::symlink_metadata(&path).is_err(), "moved aside");
    }

    #[test]
    fn the_command_line_wins_over_a_tuned_value_which_wins_over_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("params.json");
        std::fs::write(&path, r#"{"IND_LAND_R": 1.0, "AREA_RATIO": 0.7}"#).unwrap();
        let mut s = Settings::default();
        s.indoor.landing_radius_m = 2.0; // as if --set indoor.landing_radius_m=2
        let pinned: BTreeSet<String> = ["indoor.landing_radius_m".to_string()].into();
        let (store, notes) = ParamStore::open(&path, &mut s, &pinned);
        assert_eq!(s.indoor.landing_radius_m, 2.0, "--set wins");
        assert!((s.area.ratio_test - 0.7).abs() < 1e-6, "the tuned value beats the file's");
        assert!(notes.iter().any(|(_, n)| n.contains("--set indoor.landing_radius_m wins")), "{notes:?}");
        // The pinned value stays in the store, so the next save does not lose it.
        assert_eq!(store.into_tuned().get("IND_LAND_R"), Some(&1.0));
    }
}
