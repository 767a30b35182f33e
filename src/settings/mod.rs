//! Configuration loading and validation.
//!
//! Layers, later wins: built-in defaults ([`Settings::default`]) < the TOML file < the
//! dataset's own settings (`DATASET/mavloc.toml`, for commands that run on a dataset) <
//! `MAVLOC_SECTION__KEY` environment variables < `--set section.key=value` on the command
//! line. A dataset's settings beat the configuration file because they describe the data
//! (an imported photo survey has no masks and needs the photo-survey tuning, whatever the
//! machine's video-tuned file says); the command says which keys they set. The `config` crate merges the layers; before it does, every layer is checked
//! against the schema (the defaults' own key tree), so an unknown key or a value of the
//! wrong type is reported with where it came from instead of surfacing as a generic
//! deserialisation error. After merging, every value is range-checked. All problems are
//! reported together and nothing starts half-configured.
//!
//! (The module is called `settings` so that it does not shadow the `config` crate.)

pub mod address;
mod schema;

pub use address::LinkAddress;
pub use schema::*;

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use ::config::{Config, Environment, File, FileFormat};

/// Environment variables with this prefix configure mavloc.
pub const ENV_PREFIX: &str = "MAVLOC_";
/// `MAVLOC_CONFIG` names the configuration file; it is not a configuration key.
pub const ENV_CONFIG_FILE: &str = "MAVLOC_CONFIG";
/// Where the systemd unit and the packaged install put the configuration.
pub const SYSTEM_CONFIG: &str = "/etc/mavloc/mavloc.toml";

impl Gimbal {
    /// The static corrections `[yaw, pitch, roll]_offset_deg`, degrees, in that order.
    pub fn offsets_deg(&self) -> [f64; 3] {
        [self.yaw_offset_deg, self.pitch_offset_deg, self.roll_offset_deg]
    }
}

/// One thing wrong with the configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Problem {
    /// Dotted key, e.g. `area.ukf_alpha`.
    pub key: String,
    /// The offending value as written, if there is one.
    pub value: Option<String>,
    /// What would have been accepted.
    pub expected: String,
    /// Where the value came from: a file path, an environment variable, the command line.
    pub origin: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.value {
            Some(v) => write!(f, "{} = {} in {}: {}", self.key, v, self.origin, self.expected),
            None => write!(f, "{} in {}: {}", self.key, self.origin, self.expected),
        }
    }
}

/// Why the configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SettingsError {
    #[error("cannot read configuration file {path}: {error}")]
    Read { path: PathBuf, error: String },
    #[error("configuration file {path} is not valid TOML: {message}")]
    Syntax { path: PathBuf, message: String },
    #[error("invalid configuration ({} problem{}):\n{}", .0.len(), if .0.len() == 1 { "" } else { "s" },
        .0.iter().map(|p| format!("  - {p}")).collect::<Vec<_>>().join("\n"))]
    Invalid(Vec<Problem>),
    #[error("configuration: {0}")]
    Merge(String),
}

/// What to load: a file, environment variables and command-line overrides.
#[derive(Clone, Debug, Default)]
pub struct Layers {
    pub file: Option<PathBuf>,
    /// Settings a dataset carries (`DATASET/mavloc.toml`), when the command runs on one.
    pub dataset: Option<PathBuf>,
    /// Environment variables (all of them; those without the prefix are ignored).
    pub env: BTreeMap<String, String>,
    /// `key=value` overrides from the command line, in order.
    pub overrides: Vec<String>,
}

impl Layers {
    /// The process environment and the given file and overrides.
    pub fn from_process(file: Option<PathBuf>, overrides: Vec<String>) -> Layers {
        Layers { file, dataset: None, env: std::env::vars().collect(), overrides }
    }
}

/// Loaded settings with a record of where each non-default value came from.
#[derive(Clone, Debug)]
pub struct Loaded {
    pub settings: Settings,
    /// Dotted key -> origin, for keys not left at their default.
    pub origins: BTreeMap<String, String>,
    pub file: Option<PathBuf>,
}

/// The kind of a leaf in the schema tree.
fn kind_name(v: &toml::Value) -> &'static str {
    match v {
        toml::Value::String(_) => "a string",
        toml::Value::Integer(_) => "an integer",
        toml::Value::Float(_) => "a number",
        toml::Value::Boolean(_) => "true or false",
        toml::Value::Array(_) => "a list of numbers",
        toml::Value::Table(_) => "a section",
        toml::Value::Datetime(_) => "a date",
    }
}

/// Whether `given` fits where the schema has `schema`.
fn type_fits(schema: &toml::Value, given: &toml::Value) -> bool {
    use toml::Value as V;
    match (schema, given) {
        (V::Float(_), V::Float(_) | V::Integer(_)) => true,
        (V::Integer(_), V::Integer(_)) => true,
        (V::String(_), V::String(_)) => true,
        (V::Boolean(_), V::Boolean(_)) => true,
        (V::Array(_), V::Array(items)) => items.iter().all(|i| matches!(i, V::Float(_) | V::Integer(_))),
        _ => false,
    }
}

fn schema() -> toml::Table {
    toml::Table::try_from(Settings::default()).expect("the defaults serialise to TOML")
}

/// Every dotted key of the schema.
pub fn all_keys() -> Vec<String> {
    let mut keys = Vec::new();
    for (section, table) in schema() {
        if let toml::Value::Table(t) = table {
            keys.extend(t.keys().map(|k| format!("{section}.{k}")));
        }
    }
    keys
}

fn lookup<'a>(schema: &'a toml::Table, key: &str) -> Option<&'a toml::Value> {
    let (section, name) = key.split_once('.')?;
    schema.get(section)?.as_table()?.get(name)
}

/// The closest known key, for "did you mean" hints.
fn suggest(key: &str) -> Option<String> {
    all_keys()
        .into_iter()
        .map(|k| (strsim::damerau_levenshtein(key, &k), k))
        .filter(|(d, k)| *d <= 3.max(k.len() / 4))
        .min()
        .map(|(_, k)| k)
}

fn unknown_key(key: &str, value: Option<String>, origin: &str) -> Problem {
    let expected = match suggest(key) {
        Some(s) => format!("unknown key; did you mean `{s}`?"),
        None => "unknown key; `mavloc config show` lists every key".to_string(),
    };
    Problem { key: key.to_string(), value, expected, origin: origin.to_string() }
}

/// Reads a value written on the command line or in the environment: TOML syntax if it
/// parses (`3`, `0.5`, `true`, `[0.1, 0]`), otherwise a bare string.
fn parse_loose(raw: &str) -> toml::Value {
    let doc = format!("v = {raw}");
    match doc.parse::<toml::Table>() {
        Ok(mut t) => t.remove("v").unwrap_or_else(|| toml::Value::String(raw.to_string())),
        Err(_) => {
            // Environment lists may be written without brackets: `0.1,0,0,0,0`.
            let items: Option<Vec<toml::Value>> =
                raw.split(',').map(|s| s.trim().parse::<f64>().ok().map(toml::Value::Float)).collect();
            match items {
                Some(v) if raw.contains(',') => toml::Value::Array(v),
                _ => toml::Value::String(raw.to_string()),
            }
        }
    }
}

/// Keys whose values are names from a fixed set, with the names accepted. A test checks
/// each name deserialises, so this list cannot drift from the schema's enums.
pub const ENUM_KEYS: &[(&str, &[&str])] = &[
    ("daemon.pipeline", &["area", "indoor", "none"]),
    ("daemon.record_format", &["jpg", "png"]),
    ("camera.source", &["v4l2", "file", "dataset", "sim", "none"]),
    ("gimbal.chain", &["yaw-pitch-roll", "yaw-roll-pitch"]),
    ("gimbal.aim", &["mission", "border"]),
    ("area.method", &["ukf", "ground-plane"]),
    ("area.matching", &["global", "guided"]),
    ("area.segmenter", &["masks", "water", "hsv", "learned"]),
    ("indoor.dictionary", &["competitive", "k-means"]),
    ("indoor.motion_model", &["velocity", "noise"]),
];

/// Checks one layer's key/value pairs against the schema.
fn check_layer(schema: &toml::Table, pairs: &[(String, toml::Value, String)], problems: &mut Vec<Problem>) {
    for (key, value, origin) in pairs {
        match lookup(schema, key) {
            None => problems.push(unknown_key(key, Some(render(value)), origin)),
            Some(s) if !type_fits(s, value) => problems.push(Problem {
                key: key.clone(),
                value: Some(render(value)),
                expected: format!("expected {}", kind_name(s)),
                origin: origin.clone(),
            }),
            Some(_) => {
                if let (Some((_, names)), toml::Value::String(given)) =
                    (ENUM_KEYS.iter().find(|(k, _)| k == key), value)
                {
                    if !names.contains(&given.as_str()) {
                        problems.push(Problem {
                            key: key.clone(),
                            value: Some(render(value)),
                            expected: format!("expected one of {}", names.join(", ")),
                            origin: origin.clone(),
                        });
                    }
                }
            }
        }
    }
}

fn render(v: &toml::Value) -> String {
    v.to_string()
}

/// Flattens a parsed file into (key, value, origin) triples; sections that are not
/// tables and unknown sections are problems of their own.
fn flatten_file(
    schema: &toml::Table,
    path: &Path,
    doc: &toml::Table,
    problems: &mut Vec<Problem>,
) -> Vec<(String, toml::Value, String)> {
    let origin = path.display().to_string();
    let mut pairs = Vec::new();
    for (section, value) in doc {
        match (schema.get(section), value) {
            (Some(_), toml::Value::Table(t)) => {
                for (k, v) in t {
                    pairs.push((format!("{section}.{k}"), v.clone(), origin.clone()));
                }
            }
            (Some(_), other) => problems.push(Problem {
                key: section.clone(),
                value: Some(render(other)),
                expected: format!("`{section}` is a section: write `[{section}]` and its keys below it"),
                origin: origin.clone(),
            }),
            // `foo = 1` above every section header: a key, not a section (it was called an
            // unknown section).
            (None, other) if !matches!(other, toml::Value::Table(_)) => {
                let homes: Vec<_> = schema
                    .iter()
                    .filter(|(_, t)| t.as_table().is_some_and(|t| t.contains_key(section)))
                    .map(|(name, _)| format!("[{name}]"))
                    .collect();
                let expected = if homes.is_empty() {
                    let sections: Vec<_> = schema.keys().map(String::as_str).collect();
                    format!(
                        "a key outside any section, and no section has it; sections are {}",
                        sections.join(", ")
                    )
                } else {
                    format!("a key outside any section: write it below {}", homes.join(" or "))
                };
                problems.push(Problem {
                    key: section.clone(),
                    value: Some(render(other)),
                    expected,
                    origin: origin.clone(),
                })
            }
            (None, _) => {
                let sections: Vec<_> = schema.keys().map(String::as_str).collect();
                problems.push(Problem {
                    key: section.clone(),
                    value: None,
                    expected: format!("unknown section; sections are {}", sections.join(", ")),
                    origin: origin.clone(),
                })
            }
        }
    }
    pairs
}

/// Loads and validates the configuration from all layers.
pub fn load(layers: &Layers) -> Result<Loaded, SettingsError> {
    let (loaded, problems) = load_lenient(layers)?;
    if !problems.is_empty() {
        return Err(SettingsError::Invalid(problems));
    }
    Ok(loaded)
}

/// What `mavloc run` would refuse, all in one pass: every problem of every layer (unknown
/// keys, wrong types, values out of range) and the files the values name, together.
/// `config check` and `run` both call it.
///
/// `files` looks inside the files the settings name as the modules that use them would.
pub fn check(layers: &Layers, files: &FileChecks) -> Result<Loaded, SettingsError> {
    let (loaded, mut problems) = load_lenient(layers)?;
    // The files are checked on what is valid, so a missing model is named beside a
    // misspelt key rather than after it is fixed.
    let bad: std::collections::BTreeSet<&str> = problems.iter().map(|p| p.key.as_str()).collect();
    let more: Vec<Problem> =
        preflight(&loaded, files).into_iter().filter(|p| !bad.contains(p.key.as_str())).collect();
    problems.extend(more);
    if !problems.is_empty() {
        return Err(SettingsError::Invalid(problems));
    }
    Ok(loaded)
}

/// Loads every layer, leaving out (and reporting) each value that is wrong, so one run
/// names every problem: the settings returned are the defaults plus the valid values.
/// Only an unreadable file or broken TOML stops it early (nothing in it can be trusted).
fn load_lenient(layers: &Layers) -> Result<(Loaded, Vec<Problem>), SettingsError> {
    let schema = schema();
    let mut problems = Vec::new();
    let mut origins = BTreeMap::new();

    // Layers 1 and 2: the configuration file, then the dataset's settings.
    let mut file_pairs = Vec::new();
    for path in layers.file.iter().chain(&layers.dataset) {
        // The OS error is the message's cause; it is not repeated as a source.
        let text = std::fs::read_to_string(path)
            .map_err(|e| SettingsError::Read { path: path.clone(), error: e.to_string() })?;
        let doc: toml::Table = text.parse().map_err(|e: toml::de::Error| SettingsError::Syntax {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let pairs = flatten_file(&schema, path, &doc, &mut problems);
        check_layer(&schema, &pairs, &mut problems);
        for (k, _, o) in &pairs {
            origins.insert(k.clone(), o.clone());
        }
        file_pairs.push(pairs);
    }

    // Layer 3: the environment.
    let mut env_pairs = Vec::new();
    let mut env_vars = Vec::new();
    for (var, raw) in &layers.env {
        let Some(rest) = var.strip_prefix(ENV_PREFIX) else {
            continue;
        };
        // Only MAVLOC_<SECTION>__<KEY> is configuration; other MAVLOC_* variables
        // (MAVLOC_CONFIG, the test tools' MAVLOC_PYTHON, a user's own) are not ours to
        // refuse, and refusing them would stop every command.
        if var == ENV_CONFIG_FILE || !rest.contains("__") {
            continue;
        }
        let key = rest.to_lowercase().replacen("__", ".", 1);
        let origin = format!("environment variable {var}");
        env_pairs.push((key.clone(), parse_loose(raw), origin.clone()));
        origins.insert(key.clone(), origin);
        env_vars.push((key, var.clone(), raw.clone()));
    }
    check_layer(&schema, &env_pairs, &mut problems);

    // Layer 4: the command line.
    let mut cli_pairs = Vec::new();
    for item in &layers.overrides {
        let origin = format!("command line ({item})");
        match item.split_once('=') {
            Some((k, v)) if !k.trim().is_empty() => {
                let key = k.trim().to_string();
                cli_pairs.push((key.clone(), parse_loose(v.trim()), origin.clone()));
                origins.insert(key, origin);
            }
            _ => problems.push(Problem {
                key: item.clone(),
                value: None,
                expected: "expected `section.key=value`".into(),
                origin,
            }),
        }
    }
    check_layer(&schema, &cli_pairs, &mut problems);

    // Merge with the `config` crate what passed; a value the merge still refuses (an
    // integer beyond its type) is reported and left out, and the merge tried again.
    let mut excluded: std::collections::BTreeSet<(String, String)> =
        problems.iter().map(|p| (p.key.clone(), p.origin.clone())).collect();
    let mut settings = loop {
        match merge_layers(&file_pairs, &env_vars, &cli_pairs, &excluded, &origins) {
            Ok(s) => break s,
            Err(MergeFailure::Key(problem)) => {
                if !excluded.insert((problem.key.clone(), "*".into())) {
                    return Err(SettingsError::Invalid(vec![problem]));
                }
                problems.push(problem);
            }
            Err(MergeFailure::Other(e)) => return Err(e),
        }
    };
    // A left-out value is not in force: its origin would mislead `config show` (unless a
    // later layer set the key validly, whose origin stays).
    for (k, o) in &excluded {
        if o == "*" || origins.get(k) == Some(o) {
            origins.remove(k);
        }
    }
    for path in layers.file.iter().chain(&layers.dataset) {
        resolve_relative_paths(&mut settings, &origins, path);
    }
    let range_problems = validate(&settings, &origins);
    problems.extend(range_problems);
    Ok((Loaded { settings, origins, file: layers.file.clone() }, problems))
}

/// Why one merge attempt failed.
enum MergeFailure {
    /// One value, named with its origin.
    Key(Problem),
    Other(SettingsError),
}

/// Defaults < files < environment < command line, leaving out the (key, origin) pairs in
/// `excluded`.
fn merge_layers(
    files: &[Vec<(String, toml::Value, String)>],
    env: &[(String, String, String)],
    cli: &[(String, toml::Value, String)],
    excluded: &std::collections::BTreeSet<(String, String)>,
    origins: &BTreeMap<String, String>,
) -> Result<Settings, MergeFailure> {
    let merge = |e: ::config::ConfigError| MergeFailure::Other(SettingsError::Merge(e.to_string()));
    // (key, origin) leaves out one layer's value; (key, "*") the key in every layer.
    let keep = |key: &String, origin: &String| {
        !excluded.contains(&(key.clone(), origin.clone())) && !excluded.contains(&(key.clone(), "*".into()))
    };
    let table = |pairs: &[(String, toml::Value, String)]| {
        let mut doc = toml::Table::new();
        for (key, value, _) in pairs.iter().filter(|(k, _, o)| keep(k, o)) {
            let Some((section, name)) = key.split_once('.') else { continue };
            if let Some(t) = doc
                .entry(section.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
            {
                t.insert(name.to_string(), value.clone());
            }
        }
        doc.to_string()
    };
    let defaults = Config::try_from(&Settings::default()).map_err(merge)?;
    let mut builder = Config::builder().add_source(defaults);
    for pairs in files {
        builder = builder.add_source(File::from_str(&table(pairs), FileFormat::Toml));
    }
    let env_map: ::config::Map<String, String> = env
        .iter()
        .filter(|(key, var, _)| keep(key, &format!("environment variable {var}")))
        .map(|(_, var, raw)| (var.clone(), raw.clone()))
        .collect();
    builder = builder.add_source(
        Environment::with_prefix("MAVLOC")
            .prefix_separator("_")
            .separator("__")
            .try_parsing(true)
            .list_separator(",")
            .with_list_parse_key("camera.distortion")
            .with_list_parse_key("area.hsv_low")
            .with_list_parse_key("area.position_noise_m")
            .with_list_parse_key("area.hsv_high")
            .source(Some(env_map)),
    );
    builder = builder.add_source(File::from_str(&table(cli), FileFormat::Toml));
    let merged = builder.build().map_err(merge)?;
    merged.try_deserialize().map_err(|e| match merge_error(e, origins) {
        SettingsError::Invalid(mut v) if v.len() == 1 => MergeFailure::Key(v.remove(0)),
        other => MergeFailure::Other(other),
    })
}

/// A relative path written in a configuration file means "beside this file", not "in
/// whatever folder the process started in": under systemd that is `/`, so
/// `indoor.model = "floor.model"` in /etc/mavloc/mavloc.toml must mean
/// /etc/mavloc/floor.model. Paths from the environment or the command line keep the
/// working directory, as a shell user expects.
fn resolve_relative_paths(s: &mut Settings, origins: &BTreeMap<String, String>, file: &Path) {
    let origin = file.display().to_string();
    let Some(dir) = file.parent() else { return };
    let from_file = |key: &str| origins.get(key).is_some_and(|o| *o == origin);
    let resolve = |key: &str, value: &mut String| {
        if from_file(key) && !value.is_empty() && Path::new(value.as_str()).is_relative() {
            *value = dir.join(value.as_str()).display().to_string();
        }
    };
    resolve("daemon.state_dir", &mut s.daemon.state_dir);
    resolve("camera.path", &mut s.camera.path);
    resolve("camera.device", &mut s.camera.device);
    resolve("indoor.model", &mut s.indoor.model);
    resolve("mavlink.px4_events", &mut s.mavlink.px4_events);
    if !s.mavlink.signing_key.starts_with("credential:") {
        resolve("mavlink.signing_key", &mut s.mavlink.signing_key);
    }
}

/// Turns a deserialisation error (an enum value that is not one of the variants, an
/// integer out of its type's range) into a problem naming the key, its origin and, for an
/// integer, the range its type holds.
fn merge_error(e: ::config::ConfigError, origins: &BTreeMap<String, String>) -> SettingsError {
    let msg = e.to_string();
    // The config crate quotes the key and the value in backticks, in either order
    // ("invalid value: integer `300`, expected u8 for key `mavlink.system_id`").
    let quoted: Vec<&str> = msg.split('`').skip(1).step_by(2).collect();
    let keys = all_keys();
    let key = quoted.iter().find(|q| keys.iter().any(|k| k == *q)).map(|k| k.to_string());
    let value = quoted.iter().find(|q| q.parse::<i128>().is_ok()).map(|v| v.to_string());
    // Serde names the integer type as `u8` or as "an unsigned 8 bit integer".
    let ranges = [
        (["u8", "unsigned 8 bit"], "0 to 255"),
        (["u16", "unsigned 16 bit"], "0 to 65535"),
        (["u32", "unsigned 32 bit"], "0 to 4294967295"),
        (["u64", "unsigned 64 bit"], "0 to 18446744073709551615"),
        (["i32", "signed 32 bit"], "-2147483648 to 2147483647"),
    ];
    let tail = msg.split("expected").nth(1).unwrap_or("");
    let expected = ranges
        .iter()
        .find(|(names, _)| {
            names.iter().any(|n| {
                tail.trim_start().trim_start_matches(['`', ' ']).starts_with(n)
                    || tail.contains(&format!("an {n} integer"))
            })
        })
        .map(|(_, r)| format!("expected an integer from {r}"))
        .unwrap_or(msg.clone());
    // A key with a documented range says that range, not the type's ("expected an
    // unsigned 64 bit or less integer" for `area.l_max = -5`).
    // (Not for a key whose range depends on another, e.g. `area.turnover` below `l_max`:
    // the table holds the default's bound.)
    let expected =
        match key.as_ref().filter(|k| *k != "area.turnover").and_then(|k| self::ranges().get(k).copied()) {
            Some((lo, hi)) if value.is_some() => format!("out of range; allowed {lo} ..= {hi}"),
            _ => expected,
        };
    match key {
        Some(key) => {
            let origin = origins.get(&key).cloned().unwrap_or_else(|| "the merged configuration".into());
            SettingsError::Invalid(vec![Problem { key, value, expected, origin }])
        }
        None => SettingsError::Merge(msg),
    }
}

/// How [`preflight`] looks inside what the settings name, as the modules that use it would.
/// Given by the caller, since the settings cannot depend on the modules they configure
/// (`commands::FILE_CHECKS` is mavloc's).
pub struct FileChecks<'a> {
    /// Reads a floor model as the indoor pipeline would (`indoor::model::Model::check_file`).
    pub model: &'a dyn Fn(&Path) -> Result<(), String>,
    /// Loads a signing key file as the link would, contents, owner and mode
    /// (`link::signing::load_key`).
    pub signing_key: &'a dyn Fn(&Path) -> Result<(), String>,
    /// The state directory `run` would use for these settings (`daemon::state_dir`:
    /// systemd's `$STATE_DIRECTORY` wins over `daemon.state_dir`).
    pub state_dir: &'a dyn Fn(&Settings) -> PathBuf,
    /// Loads the simulated camera's scenario as it would (`camera::sim::check_scenario`).
    pub scenario: &'a dyn Fn(&str) -> Result<(), String>,
}

/// What `mavloc run` needs beyond valid values: the files the settings name, readable and
/// usable, and a state directory it can make and write. `config check` and `run` both
/// call it, so `check` passes only what `run` starts on (before, `check` passed a missing
/// model, a signing key others could read and a state directory under a file, and `run`
/// then refused them or ran without a pipeline).
pub fn preflight(loaded: &Loaded, files: &FileChecks) -> Vec<Problem> {
    let s = &loaded.settings;
    let origin =
        |key: &str| loaded.origins.get(key).cloned().unwrap_or_else(|| "the built-in default".into());
    let mut problems = Vec::new();
    // `usable` looks inside what exists: a path to the wrong kind of file passed the check
    // and `run` then stayed up without a pipeline.
    let mut need_file = |key: &str, path: &str, what: &str, usable: &dyn Fn(&Path) -> Result<(), String>| {
        let p = Path::new(path);
        let why = if path.is_empty() {
            Some(format!("{what} is needed and none is set"))
        } else {
            match std::fs::metadata(p) {
                Ok(_) => usable(p).err().map(|e| format!("{what}: {e}")),
                Err(e) => Some(format!("{what}: cannot read {}: {e}", p.display())),
            }
        };
        if let Some(expected) = why {
            problems.push(Problem {
                key: key.into(),
                value: Some(quote(path)),
                expected,
                origin: origin(key),
            });
        }
    };
    if s.daemon.pipeline == PipelineKind::Indoor {
        need_file(
            "indoor.model",
            &s.indoor.model,
            "a floor model (mavloc indoor train) for daemon.pipeline = \"indoor\"",
            files.model,
        );
    }
    match s.camera.source {
        CameraSource::Dataset => {
            need_file("camera.path", &s.camera.path, "a dataset for this camera source", &|p| {
                mavloc_data::Dataset::open(p).map(|_| ())
            })
        }
        CameraSource::File => {
            need_file("camera.path", &s.camera.path, "a video or image folder for this camera source", &|p| {
                use std::os::unix::fs::FileTypeExt;
                let m = std::fs::metadata(p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
                let kind = m.file_type();
                if m.is_dir() {
                    // An empty folder (or one of other files) passed, and `run` then idled
                    // with no camera.
                    let n = crate::imaging::image_files(p)
                        .map_err(|e| format!("cannot list {}: {e}", p.display()))?
                        .len();
                    if n == 0 {
                        return Err(format!(
                            "{} holds no images (.png, .jpg, .jpeg, .bmp, .tif, .tiff)",
                            p.display()
                        ));
                    }
                } else if kind.is_char_device() || kind.is_block_device() {
                    return Err(format!(
                        "{} is a device, not a video file: for a camera set camera.source = \"v4l2\" and camera.device",
                        p.display()
                    ));
                } else if m.is_file() && m.len() == 0 {
                    return Err(format!("{} is empty", p.display()));
                } else if m.is_file() {
                    crate::imaging::probe_video(p)?;
                }
                Ok(())
            })
        }
        _ => {}
    }
    let key = &s.mavlink.signing_key;
    if !key.is_empty() && !key.starts_with("credential:") {
        need_file("mavlink.signing_key", key, "the signing key file", files.signing_key);
    }
    // A simulated camera on a scenario that does not load passed, and `run` then idled
    // with its camera failed (outside audit).
    if matches!(s.camera.source, CameraSource::Sim) {
        if let Err(e) = (files.scenario)(&s.camera.scenario) {
            problems.push(Problem {
                key: "camera.scenario".into(),
                value: Some(quote(&s.camera.scenario)),
                expected: format!("a scenario the simulated camera can render: {e}"),
                origin: origin("camera.scenario"),
            });
        }
    }
    let dir = (files.state_dir)(s);
    if let Some(why) = unmakeable_dir(&dir) {
        // Another directory than the setting's is systemd's ($STATE_DIRECTORY wins).
        let from_systemd = dir != Path::new(&s.daemon.state_dir);
        problems.push(Problem {
            key: "daemon.state_dir".into(),
            value: Some(quote(&dir.to_string_lossy())),
            expected: format!("a state directory mavloc can make and write: {why}"),
            origin: if from_systemd {
                "the environment (STATE_DIRECTORY, set by systemd's StateDirectory=)".into()
            } else {
                origin("daemon.state_dir")
            },
        });
    }
    // A live camera gives frames only: with `masks` or `learned` (which trains on a
    // dataset's masks, `mavloc area` only) the area pipeline would skip every frame.
    if s.daemon.pipeline == PipelineKind::Area
        && matches!(s.camera.source, CameraSource::V4l2 | CameraSource::File)
        && matches!(s.area.segmenter, Segmenter::Masks | Segmenter::Learned)
    {
        let value = if s.area.segmenter == Segmenter::Masks { "\"masks\"" } else { "\"learned\"" };
        problems.push(Problem {
            key: "area.segmenter".into(),
            value: Some(value.into()),
            expected: format!(
                "\"water\" or \"hsv\" with camera.source = \"{}\": that camera gives no masks (\"learned\" trains on a dataset's masks, for mavloc area), so every frame would be skipped",
                if s.camera.source == CameraSource::V4l2 { "v4l2" } else { "file" }
            ),
            origin: origin("area.segmenter"),
        });
    }
    problems
}

/// Why `run` could not make `dir` (with its missing parents) and write in it, without
/// making anything: the nearest part of the path that exists must be a directory this
/// process may write in (`access(2)`, which also says so for a read-only file system).
fn unmakeable_dir(dir: &Path) -> Option<String> {
    let mut p = dir;
    loop {
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() => {
                use std::os::unix::ffi::OsStrExt;
                let c = std::ffi::CString::new(p.as_os_str().as_bytes()).ok()?;
                // SAFETY: `c` is a NUL-terminated path that outlives the call.
                if unsafe { libc::access(c.as_ptr(), libc::W_OK | libc::X_OK) } != 0 {
                    let e = std::io::Error::last_os_error();
                    // Who may write depends on who runs: the check is for this user.
                    // SAFETY: getuid has no preconditions and cannot fail.
                    let uid = unsafe { libc::getuid() };
                    return Some(format!("{} is not writable by uid {uid} ({e})", p.display()));
                }
                // access() says yes to root on the kernel's own file systems, where no
                // directory can be made: `config check` passed /proc/x and `run` refused it.
                return kernel_fs(p).map(|fs| {
                    format!(
                        "{} is on {fs}, a kernel file system where mavloc cannot keep its state",
                        p.display()
                    )
                });
            }
            Ok(_) => return Some(format!("{} is not a directory", p.display())),
            Err(e)
                if matches!(e.kind(), std::io::ErrorKind::NotFound | std::io::ErrorKind::NotADirectory) =>
            {
                // Made by `run`, with the parents that are missing; a relative path's
                // first part is made in the working folder.
                p = match p.parent() {
                    Some(q) if q.as_os_str().is_empty() => Path::new("."),
                    Some(q) => q,
                    None => return None,
                };
            }
            Err(e) => return Some(format!("cannot read {}: {e}", p.display())),
        }
    }
}

/// The name of the kernel file system `p` is on, if it is one of those that hold no
/// directories of ours (proc, sysfs, cgroup, ...).
fn kernel_fs(p: &Path) -> Option<&'static str> {
    let kind = rustix::fs::statfs(p).ok()?.f_type as u64;
    // linux/magic.h's numbers, as libc has them (their type differs by target).
    [
        (libc::PROC_SUPER_MAGIC as u64, "proc"),
        (libc::SYSFS_MAGIC as u64, "sysfs"),
        (libc::CGROUP2_SUPER_MAGIC as u64, "cgroup"),
        (libc::CGROUP_SUPER_MAGIC as u64, "cgroup"),
        (libc::DEBUGFS_MAGIC as u64, "debugfs"),
        (libc::TRACEFS_MAGIC as u64, "tracefs"),
        (libc::SECURITYFS_MAGIC as u64, "securityfs"),
    ]
    .into_iter()
    .find_map(|(magic, name)| (magic == kind).then_some(name))
}

/// Range and consistency checks on merged settings.
pub fn validate(s: &Settings, origins: &BTreeMap<String, String>) -> Vec<Problem> {
    checked(s, origins).problems
}

/// The allowed range of every key that has one (for the defaults: a bound that depends on
/// another key, such as `area.turnover` below `area.l_max`, is the default's).
pub fn ranges() -> BTreeMap<String, (f64, f64)> {
    checked(&Settings::default(), &BTreeMap::new()).ranges
}

fn checked<'a>(s: &Settings, origins: &'a BTreeMap<String, String>) -> Validator<'a> {
    let mut v = Validator { origins, problems: Vec::new(), ranges: BTreeMap::new() };

    // [daemon]
    v.range("daemon.max_frame_age_s", s.daemon.max_frame_age_s, 0.01, 60.0);
    v.range("daemon.record_reserve_mb", s.daemon.record_reserve_mb, 0.0, 1e7);
    v.nonempty("daemon.state_dir", &s.daemon.state_dir);
    if let Err(e) = tracing_subscriber::EnvFilter::try_new(&s.daemon.log) {
        v.problem(
            "daemon.log",
            quote(&s.daemon.log),
            format!("not a tracing filter ({e}); e.g. \"info\" or \"mavloc=debug\""),
        );
    }

    // [mavlink]
    if let Err(e) = LinkAddress::parse(&s.mavlink.connection) {
        v.problem("mavlink.connection", quote(&s.mavlink.connection), e);
    }
    v.range_int("mavlink.component_id", s.mavlink.component_id.into(), 1, 255);
    v.range_int("mavlink.autopilot_system_id", s.mavlink.autopilot_system_id.into(), 1, 255);
    v.range_int("mavlink.gcs_system_id", s.mavlink.gcs_system_id.into(), 1, 255);
    v.range("mavlink.heartbeat_hz", s.mavlink.heartbeat_hz, 0.2, 10.0);
    v.range("mavlink.autopilot_timeout_s", s.mavlink.autopilot_timeout_s, 0.5, 60.0);

    // [camera]
    v.range_int("camera.width", s.camera.width.into(), 16, 8192);
    v.range_int("camera.height", s.camera.height.into(), 16, 8192);
    v.range("camera.fps", s.camera.fps, 0.1, 240.0);
    v.range("camera.hfov_deg", s.camera.hfov_deg, 1.0, 179.0);
    if s.camera.pixel_format.len() != 4 || !s.camera.pixel_format.is_ascii() {
        v.problem(
            "camera.pixel_format",
            quote(&s.camera.pixel_format),
            "a four-character V4L2 code such as \"MJPG\" or \"YUYV\"",
        );
    }
    for (key, val) in [("camera.fx", s.camera.fx), ("camera.fy", s.camera.fy)] {
        if val != 0.0 {
            v.range(key, val, 1.0, 100_000.0);
        }
    }
    for (key, val, size) in
        [("camera.cx", s.camera.cx, s.camera.width), ("camera.cy", s.camera.cy, s.camera.height)]
    {
        // On the image, as `Intrinsics::validate` wants it when the pipeline is built.
        if val != -1.0 {
            v.range(key, val, -0.5, size as f64 - 0.5);
        }
    }
    if ![0, 4, 5, 8].contains(&s.camera.distortion.len()) {
        v.problem(
            "camera.distortion",
            format!("{:?}", s.camera.distortion),
            "0, 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]])",
        );
    }
    let bounded = s.camera.distortion.iter().all(|c| c.is_finite() && c.abs() <= 100.0);
    if !bounded {
        v.problem(
            "camera.distortion",
            format!("{:?}", s.camera.distortion),
            "coefficients within -100 ..= 100",
        );
    }
    // The model must hold out to the image's corners at this size (`lens`).
    let k = s.camera.intrinsics();
    if bounded && k.fx >= 1.0 && k.fy >= 1.0 {
        if let Some(problem) = crate::lens::fold_problem(&k, &s.camera.distortion) {
            v.problem(
                "camera.distortion",
                format!("{:?} at {}x{}", s.camera.distortion, s.camera.width, s.camera.height),
                problem,
            );
        }
    }

    // [gimbal]
    v.range("gimbal.mount_yaw_deg", s.gimbal.mount_yaw_deg, -180.0, 180.0);
    v.range("gimbal.mount_pitch_deg", s.gimbal.mount_pitch_deg, -90.0, 90.0);
    v.range("gimbal.mount_roll_deg", s.gimbal.mount_roll_deg, -180.0, 180.0);
    v.range("gimbal.yaw_offset_deg", s.gimbal.yaw_offset_deg, -20.0, 20.0);
    v.range("gimbal.pitch_offset_deg", s.gimbal.pitch_offset_deg, -20.0, 20.0);
    v.range("gimbal.roll_offset_deg", s.gimbal.roll_offset_deg, -20.0, 20.0);

    // [area]
    let a = &s.area;
    v.range_int("area.downscale", a.downscale.into(), 1, 8);
    v.range_int("area.band_px", a.band_px.into(), 1, 2000);
    v.range_int("area.l_max", a.l_max.into(), 1, 20_000);
    // Bounded by l_max: when l_max itself is out of range that is the one problem (an
    // unchanged turnover was blamed beside it).
    let l_max = if (1..=20_000).contains(&a.l_max) { a.l_max } else { Settings::default().area.l_max };
    v.range_int("area.turnover", a.turnover.into(), 0, l_max.saturating_sub(1).into());
    v.range_int("area.feature_factor", a.feature_factor.into(), 1, 100);
    v.range("area.ratio_test", a.ratio_test, 0.05, 1.0);
    v.range("area.mahalanobis_max", a.mahalanobis_max, 0.5, 1e6);
    v.range("area.convergence_m", a.convergence_m, 0.01, 100.0);
    v.range_int("area.min_observations", a.min_observations.into(), 1, 10_000);
    v.range("area.bearing_noise_deg", a.bearing_noise_deg, 0.001, 20.0);
    v.range("area.ukf_alpha", a.ukf_alpha, 0.001, 1.0);
    v.range("area.ukf_beta", a.ukf_beta, 0.0, 10.0);
    v.range("area.ukf_kappa", a.ukf_kappa, -2.9, 10.0); // n + kappa > 0 for n = 3
    v.range_int("area.ukf_iterations", a.ukf_iterations.into(), 1, 20);
    v.range("area.init_sigma_m", a.init_sigma_m, 0.1, 1000.0);
    v.range("area.ground_down_m", a.ground_down_m, -10_000.0, 10_000.0);
    v.range_int("area.max_descriptors", a.max_descriptors.into(), 1, 1000);
    v.range("area.attitude_prior_deg", a.attitude_prior_deg, 0.0, 30.0);
    v.range_int("area.adjust_first_frames", a.adjust_first_frames.into(), 0, 10_000_000);
    v.range("area.align_prior_deg", a.align_prior_deg, 0.0, 45.0);
    v.range("area.align_shift_m", a.align_shift_m, 0.0, 1000.0);
    v.range("area.aligned_bearing_noise_deg", a.aligned_bearing_noise_deg, 0.0, 20.0);
    v.range_int("area.aligned_min_observations", a.aligned_min_observations.into(), 0, 10_000);
    if !(a.position_noise_m.len() == 3
        && a.position_noise_m.iter().all(|c| c.is_finite() && (0.0..=100.0).contains(c)))
    {
        v.problem(
            "area.position_noise_m",
            format!("{:?}", a.position_noise_m),
            "three values, north, east, down, each 0..=100 m",
        );
    }
    for (key, hsv) in [("area.hsv_low", &a.hsv_low), ("area.hsv_high", &a.hsv_high)] {
        let ok = hsv.len() == 3
            && hsv.iter().all(|c| c.is_finite() && *c >= 0.0)
            && hsv[0] <= 180.0
            && hsv[1] <= 255.0
            && hsv[2] <= 255.0;
        if !ok {
            v.problem(
                key,
                format!("{hsv:?}"),
                "three values: H 0..=180, S 0..=255, V 0..=255 (OpenCV ranges)",
            );
        }
    }

    // [indoor]
    let i = &s.indoor;
    v.range_int("indoor.textons", i.textons.into(), 2, 256);
    v.range_int("indoor.patch_w", i.patch_w.into(), 1, 64);
    v.range_int("indoor.patch_h", i.patch_h.into(), 1, 64);
    v.range("indoor.learning_rate", i.learning_rate, 1e-5, 1.0);
    v.range_int("indoor.samples", i.samples.into(), 1, 1_000_000);
    v.range_int("indoor.work_width", i.work_width.into(), 16, 8192);
    v.range_int("indoor.k", i.k.into(), 1, 100);
    v.range_int("indoor.particles", i.particles.into(), 1, 100_000);
    v.range("indoor.process_sigma_m", i.process_sigma_m, 0.0, 10.0);
    v.range("indoor.velocity_sigma_m_s", i.velocity_sigma_m_s, 0.001, 100.0);
    v.range("indoor.landing_x_m", i.landing_x_m, -1000.0, 1000.0);
    v.range("indoor.landing_y_m", i.landing_y_m, -1000.0, 1000.0);
    v.range("indoor.landing_radius_m", i.landing_radius_m, 0.05, 100.0);
    v.range("indoor.landing_sigma_gate_m", i.landing_sigma_gate_m, 0.01, 100.0);
    // At least two frames: the trigger never fires on a single frame.
    v.range_int("indoor.landing_frames", i.landing_frames.into(), 2, 1000);
    v.range("indoor.min_height_m", i.min_height_m, 0.0, 1000.0);
    v.range("indoor.max_height_m", i.max_height_m, i.min_height_m, 1000.0);
    v.range("indoor.height_ref_m", i.height_ref_m, -1.0, 100.0);
    v.range("indoor.pad_x_m", i.pad_x_m, -1000.0, 1000.0);
    v.range("indoor.pad_y_m", i.pad_y_m, -1000.0, 1000.0);
    // Without an origin PX4 refuses to arm on vision alone (../shared/data/px4-sitl).
    let ok = match i.origin.as_slice() {
        [] => !i.gps_denied,
        [lat, lon, alt] => {
            (-90.0..=90.0).contains(lat)
                && (-180.0..=180.0).contains(lon)
                && (-1000.0..=10000.0).contains(alt)
        }
        _ => false,
    };
    if !ok {
        v.problem(
            "indoor.origin",
            format!("{:?}", i.origin),
            "[latitude, longitude, altitude]: the WGS84 point of the floor's (0, 0) (degrees -90..=90, -180..=180, metres -1000..=10000); needed when indoor.gps_denied = true",
        );
    }

    v
}

fn quote(s: &str) -> String {
    format!("{s:?}")
}

struct Validator<'a> {
    origins: &'a BTreeMap<String, String>,
    problems: Vec<Problem>,
    /// Every range checked, so the parameter table and metadata state the very bounds
    /// the check applies ([`ranges`]).
    ranges: BTreeMap<String, (f64, f64)>,
}

impl Validator<'_> {
    fn origin(&self, key: &str) -> String {
        self.origins.get(key).cloned().unwrap_or_else(|| "the built-in defaults".into())
    }

    fn problem(&mut self, key: &str, value: String, expected: impl Into<String>) {
        let origin = self.origin(key);
        self.problems.push(Problem {
            key: key.into(),
            value: Some(value),
            expected: expected.into(),
            origin,
        });
    }

    fn range(&mut self, key: &str, value: f64, min: f64, max: f64) {
        self.ranges.insert(key.into(), (min, max));
        if !(value.is_finite() && value >= min && value <= max) {
            self.problem(key, value.to_string(), format!("out of range; allowed {min} ..= {max}"));
        }
    }

    fn range_int(&mut self, key: &str, value: i64, min: i64, max: i64) {
        self.ranges.insert(key.into(), (min as f64, max as f64));
        if value < min || value > max {
            self.problem(key, value.to_string(), format!("out of range; allowed {min} ..= {max}"));
        }
    }

    fn nonempty(&mut self, key: &str, value: &str) {
        if value.trim().is_empty() {
            self.problem(key, quote(value), "must not be empty");
        }
    }
}

/// The effective configuration as TOML, each non-default value annotated with its origin.
pub fn render_effective(loaded: &Loaded) -> String {
    let table = toml::Table::try_from(&loaded.settings).expect("settings serialise to TOML");
    let mut out = String::new();
    out.push_str("# Effective mavloc configuration: built-in defaults");
    if let Some(f) = &loaded.file {
        out.push_str(&format!(" < {}", f.display()));
    }
    out.push_str(
        " < MAVLOC_* environment < tuned over MAVLink (params.json in the state directory) < --set\n",
    );
    for (section, value) in &table {
        out.push_str(&format!("\n[{section}]\n"));
        if let toml::Value::Table(t) = value {
            for (k, v) in t {
                let key = format!("{section}.{k}");
                match loaded.origins.get(&key) {
                    Some(o) => out.push_str(&format!("{k} = {v}  # from {o}\n")),
                    None => out.push_str(&format!("{k} = {v}\n")),
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests;
