//! What each MAVLink parameter means, for people and for ground stations: the parameter
//! table of the README (`mavloc params doc`) and the component metadata a ground station
//! downloads over MAVLink FTP (COMPONENT_METADATA -> general.json -> parameters.json, the
//! files PX4 serves for its own parameters; schemas in mavlink/component_metadata).
//!
//! Nothing here is written twice: the meaning and unit of each key come from the
//! documented configuration (`config/mavloc.toml`, one commented line per key, compiled
//! in), the range from the very checks the configuration gets ([`settings::ranges`]), the
//! default from [`Settings::default`] and the names and types from [`PARAMS`].

use std::collections::BTreeMap;

use serde_json::json;

use super::params::{value_of, Kind, ParamDef, PARAMS};
use crate::settings::{self, Settings};

/// The documented configuration: every key with its default, meaning and unit.
const DOCUMENTED: &str = include_str!("../../config/mavloc.toml");

/// Where the files are, on mavloc's own FTP server.
pub const GENERAL_PATH: &str = "/mavloc/general.json";
pub const PARAMETERS_PATH: &str = "/mavloc/parameters.json";

/// One parameter, described.
#[derive(Clone, Debug)]
pub struct ParamDoc {
    pub def: ParamDef,
    pub meaning: String,
    pub unit: String,
    pub range: Option<(f64, f64)>,
    pub default: f64,
}

/// `key -> (meaning, unit)` from the documented configuration's comments
/// (`key = value  # meaning [unit]`).
fn key_docs() -> BTreeMap<String, (String, String)> {
    let mut section = String::new();
    let mut docs = BTreeMap::new();
    for line in DOCUMENTED.lines() {
        let t = line.trim();
        if let Some(name) = t.strip_prefix('[').and_then(|r| r.strip_suffix(']')) {
            section = name.to_string();
            continue;
        }
        if t.starts_with('#') || !t.contains('=') {
            continue;
        }
        let key = t.split('=').next().unwrap_or("").trim();
        // The comment follows the value; a `#` inside a quoted value is not one.
        let Some(comment) = comment_of(t) else { continue };
        let (meaning, unit) = match comment.rfind('[') {
            Some(at) if comment.ends_with(']') => (comment[..at].trim(), &comment[at + 1..comment.len() - 1]),
            _ => (comment, ""),
        };
        docs.insert(format!("{section}.{key}"), (meaning.to_string(), unit.to_string()));
    }
    docs
}

/// The text after the first `#` outside double quotes.
fn comment_of(line: &str) -> Option<&str> {
    let mut quoted = false;
    for (i, c) in line.char_indices() {
        match c {
            '"' => quoted = !quoted,
            '#' if !quoted => return Some(line[i + 1..].trim()),
            _ => {}
        }
    }
    None
}

/// Every parameter, described, in PARAMS order.
pub fn param_docs() -> Vec<ParamDoc> {
    let docs = key_docs();
    let ranges = settings::ranges();
    let defaults = Settings::default();
    PARAMS
        .iter()
        .map(|def| {
            let (meaning, unit) = docs.get(def.key).cloned().unwrap_or_default();
            let range = match def.kind {
                Kind::Float | Kind::Int => ranges.get(def.key).copied(),
                Kind::Bool => Some((0.0, 1.0)),
                Kind::Enum(names) => Some((0.0, (names.len() - 1) as f64)),
            };
            ParamDoc { def: *def, meaning, unit, range, default: value_of(&defaults, def) }
        })
        .collect()
}

/// A number as a person writes it (no trailing `.0` on integers).
fn num(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        format!("{}", x as i64)
    } else {
        format!("{x}")
    }
}

/// The README's parameter table (Markdown).
pub fn markdown_table() -> String {
    let mut out = String::from(
        "| parameter | configuration key | type | unit | range | default | meaning |\n|---|---|---|---|---|---|---|\n",
    );
    for d in param_docs() {
        let ty = match d.def.kind {
            Kind::Float => "float".to_string(),
            Kind::Int => "int".to_string(),
            Kind::Bool => "0/1".to_string(),
            Kind::Enum(names) => {
                names.iter().enumerate().map(|(i, n)| format!("{i} {n}")).collect::<Vec<_>>().join(", ")
            }
        };
        let range = d.range.map(|(a, b)| format!("{} ..= {}", num(a), num(b))).unwrap_or_default();
        // The type column already says what an enum or a flag holds.
        let unit = match d.def.kind {
            Kind::Bool | Kind::Enum(_) => "",
            _ if d.unit == "-" => "",
            _ => d.unit.as_str(),
        };
        out.push_str(&format!(
            "| `{}` | `{}` | {ty} | {unit} | {range} | {} | {} |\n",
            d.def.name,
            d.def.key,
            num(d.default),
            d.meaning.replace('|', "\\|")
        ));
    }
    out
}

/// `parameters.json` (COMP_METADATA_TYPE_PARAMETER).
pub fn parameters_json() -> String {
    let params: Vec<serde_json::Value> = param_docs()
        .iter()
        .map(|d| {
            let mut p = json!({
                "name": d.def.name,
                "type": if d.def.kind == Kind::Float { "Float" } else { "Int32" },
                "shortDesc": short(&d.meaning),
                "longDesc": format!("{} (configuration key {})", d.meaning, d.def.key),
                "default": d.default,
                "group": d.def.key.split('.').next().unwrap_or(""),
            });
            // QGroundControl converts the units it knows; ours are written as the README's.
            if !d.unit.is_empty() && d.unit != "-" && !matches!(d.def.kind, Kind::Bool | Kind::Enum(_)) {
                p["units"] = json!(d.unit);
            }
            if let Some((a, b)) = d.range {
                p["min"] = json!(a);
                p["max"] = json!(b);
            }
            match d.def.kind {
                Kind::Enum(names) => {
                    p["values"] = names
                        .iter()
                        .enumerate()
                        .map(|(i, n)| json!({"value": i, "description": n}))
                        .collect();
                }
                Kind::Bool => {
                    p["values"] =
                        json!([{"value": 0, "description": "off"}, {"value": 1, "description": "on"}]);
                }
                Kind::Int => p["decimalPlaces"] = json!(0),
                Kind::Float => {}
            }
            p
        })
        .collect();
    serde_json::to_string_pretty(&json!({"version": 1, "parameters": params})).expect("serialises")
}

/// The first clause of a meaning, for a ground station's one-line label.
fn short(meaning: &str) -> String {
    let cut = meaning.find([';', '(']).unwrap_or(meaning.len());
    let s = meaning[..cut].trim();
    if s.chars().count() <= 60 {
        s.to_string()
    } else {
        format!("{}…", s.chars().take(59).collect::<String>())
    }
}

/// `general.json` (COMP_METADATA_TYPE_GENERAL), naming the parameter file on component
/// `component_id`'s FTP server with its CRC.
pub fn general_json(component_id: u8, parameters: &[u8]) -> String {
    let version = env!("CARGO_PKG_VERSION");
    serde_json::to_string_pretty(&json!({
        "version": 1,
        "vendorName": "mavloc",
        "modelName": "mavloc companion daemon",
        "firmwareVersion": version,
        "metadataTypes": [{
            "type": 1,
            "uri": format!("mftp://[;comp={component_id}]{PARAMETERS_PATH}"),
            "fileCrc": crc32(parameters),
        }],
    }))
    .expect("serialises")
}

/// MAVLink's CRC32 of `bytes`, as FTP's CalcFileCRC32 and COMPONENT_METADATA's `file_crc`
/// carry it (mavlink.io/en/guide/crc.html): the CRC-32 polynomial of zlib and Ethernet,
/// but started at 0 with no final inversion (NuttX's `crc32part`, which PX4 uses), so
/// zlib's value is not it. crc32fast computes the standard one: its state is the
/// inverted register, hence the two inversions.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new_with_initial(!0);
    h.update(bytes);
    !h.finalize()
}

/// The files served over MAVLink FTP: path -> bytes.
pub fn files(component_id: u8) -> BTreeMap<String, Vec<u8>> {
    let parameters = parameters_json().into_bytes();
    let general = general_json(component_id, &parameters).into_bytes();
    BTreeMap::from([(GENERAL_PATH.to_string(), general), (PARAMETERS_PATH.to_string(), parameters)])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_parameter_has_a_meaning_a_range_and_its_real_default() {
        let docs = param_docs();
        assert_eq!(docs.len(), PARAMS.len());
        for d in &docs {
            assert!(!d.meaning.is_empty(), "{} has no meaning in config/mavloc.toml", d.def.key);
            let (a, b) = d.range.unwrap_or_else(|| panic!("{} has no range", d.def.key));
            assert!(
                a <= d.default && d.default <= b,
                "{}: default {} outside {a}..={b}",
                d.def.key,
                d.default
            );
        }
        let r = docs.iter().find(|d| d.def.name == "IND_LAND_R").unwrap();
        assert_eq!((r.unit.as_str(), r.range, r.default), ("m", Some((0.05, 100.0)), 0.6));
        let method = docs.iter().find(|d| d.def.name == "AREA_METHOD").unwrap();
        assert!(method.meaning.contains("ukf"), "{}", method.meaning);
    }

    #[test]
    fn the_range_is_the_one_the_configuration_check_applies() {
        // Just past the table's bound the configuration refuses the value; at it, accepts.
        for d in param_docs().iter().filter(|d| d.def.kind == Kind::Float) {
            let (_, max) = d.range.unwrap();
            let mut v = serde_json::to_value(Settings::default()).unwrap();
            let (section, field) = d.def.key.split_once('.').unwrap();
            v[section][field] = json!(max + 1.0);
            let s: Settings = serde_json::from_value(v).unwrap();
            let problems = settings::validate(&s, &BTreeMap::new());
            assert!(problems.iter().any(|p| p.key == d.def.key), "{} accepts {}", d.def.key, max + 1.0);
        }
    }

    #[test]
    fn metadata_files_follow_the_component_metadata_schemas() {
        let files = files(191);
        let general: serde_json::Value = serde_json::from_slice(&files[GENERAL_PATH]).unwrap();
        let t = &general["metadataTypes"][0];
        assert_eq!(t["type"], 1);
        assert_eq!(t["uri"], "mftp://[;comp=191]/mavloc/parameters.json");
        assert_eq!(t["fileCrc"], crc32(&files[PARAMETERS_PATH]));
        let p: serde_json::Value = serde_json::from_slice(&files[PARAMETERS_PATH]).unwrap();
        let list = p["parameters"].as_array().unwrap();
        assert_eq!(list.len(), PARAMS.len());
        for item in list {
            let name = item["name"].as_str().unwrap();
            assert!(name.len() <= 16 && !item["shortDesc"].as_str().unwrap().is_empty(), "{item}");
            assert!(["Float", "Int32"].contains(&item["type"].as_str().unwrap()));
        }
        let pipe = list.iter().find(|i| i["name"] == "LOC_PIPELINE").unwrap();
        assert_eq!(pipe["values"][2]["description"], "indoor");
    }

    #[test]
    fn crc32_is_mavlinks_not_zlibs() {
        // "123456789" through NuttX's table-driven crc32part from 0 (worked out apart from
        // crc32fast); zlib's CRC-32 of it is the check value 0xCBF43926.
        assert_eq!(crc32(b"123456789"), 0x2DFD_2D88);
        assert_eq!(crc32fast::hash(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn comments_are_found_outside_quotes() {
        assert_eq!(comment_of(r##"a = "x#y"  # the meaning [m]"##), Some("the meaning [m]"));
        assert_eq!(comment_of("a = 1"), None);
    }
}
