//! The layering rules, checked on the sources (issue 17): pipelines and the data crate
//! import neither the simulator, tokio, MAVLink nor the daemon's link and core; only the
//! sim-facing layer imports the simulator; settings, camera and link do not import the
//! layers above them; the data crate depends on no heavy crate; and neither the
//! simulator's modules nor the top-level modules of `mavloc` form a circle. Beside them:
//! no test outside `tests/it/realtime` has `realtime::` in its name, which `make test`
//! skips in its main test process.
//!
//! The check reads `use` paths and qualified names in code (comments are skipped), so a
//! new import that breaks a rule fails here with the file and line that has it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every `.rs` file under `dir`, sorted.
fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|e| e == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Code lines (1-based number, text) with `//` comments removed.
fn code_lines(path: &Path) -> Vec<(usize, String)> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.split("//").next().unwrap_or("").to_string()))
        .filter(|(_, l)| !l.trim().is_empty())
        .collect()
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// The modules of this crate a line refers to: `crate::a::...` and `crate::{a, b::c}`.
fn crate_modules(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (at, _) in line.match_indices("crate::") {
        if line[..at].chars().next_back().is_some_and(is_ident) {
            continue; // `mavloc_crate::`, not `crate::`
        }
        let rest = &line[at + "crate::".len()..];
        let parts: Vec<&str> = match rest.strip_prefix('{') {
            Some(group) => group.split('}').next().unwrap_or("").split(',').collect(),
            None => vec![rest],
        };
        for part in parts {
            let m: String = part.trim().chars().take_while(|&c| is_ident(c)).collect();
            if !m.is_empty() && m != "self" {
                out.push(m);
            }
        }
    }
    out
}

/// Whether `line` refers to `name`: an external crate (`tokio`, as a whole word not
/// preceded by `::`) or a module of this crate (`crate::link`).
fn names(line: &str, name: &str) -> bool {
    if let Some(module) = name.strip_prefix("crate::") {
        return crate_modules(line).iter().any(|m| m == module);
    }
    line.match_indices(name).any(|(at, _)| {
        let before = line[..at].chars().next_back();
        let after = line[at + name.len()..].chars().next();
        before.is_none_or(|c| !is_ident(c) && c != ':') && after.is_none_or(|c| !is_ident(c))
    })
}

/// `path:line: text` for each line of the files that names one of `forbidden`.
fn violations(files: &[PathBuf], forbidden: &[&str]) -> Vec<String> {
    let mut out = Vec::new();
    for f in files {
        for (n, line) in code_lines(f) {
            for name in forbidden {
                if names(&line, name) {
                    let rel = f.strip_prefix(root()).unwrap_or(f);
                    out.push(format!("{}:{n}: imports {name}: {}", rel.display(), line.trim()));
                }
            }
        }
    }
    out
}

const PIPELINE_DIRS: &[&str] = &["src/area", "src/indoor", "src/filter", "src/geometry", "data/src"];
const NOT_IN_PIPELINES: &[&str] = &[
    "mavloc_sim",
    "tokio",
    "mavlink",
    "crate::link",
    "crate::daemon",
    "crate::camera",
    "crate::demo",
    "crate::simulated",
];

#[test]
fn pipelines_and_data_import_no_simulator_tokio_mavlink_or_daemon() {
    let files: Vec<PathBuf> = PIPELINE_DIRS.iter().flat_map(|d| sources(&root().join(d))).collect();
    assert!(files.len() > 30, "the pipeline sources were found ({} files)", files.len());
    let bad = violations(&files, NOT_IN_PIPELINES);
    assert!(bad.is_empty(), "pipelines must stay plain libraries:\n{}", bad.join("\n"));
}

/// The sim-facing layer: the only files of `src/` that may use the simulator.
const SIM_FACING: &[&str] = &[
    "src/demo.rs",
    "src/simulated/",
    "src/camera/sim.rs",
    // The `sim` subcommands.
    "src/commands/sim.rs",
];

#[test]
fn only_the_sim_facing_layer_imports_the_simulator() {
    let files: Vec<PathBuf> = sources(&root().join("src"))
        .into_iter()
        .filter(|f| {
            let rel = f.strip_prefix(root()).unwrap().to_string_lossy().into_owned();
            !SIM_FACING.iter().any(|allowed| rel.starts_with(allowed))
        })
        .collect();
    let bad = violations(&files, &["mavloc_sim"]);
    assert!(bad.is_empty(), "read datasets through mavloc_data, not the simulator:\n{}", bad.join("\n"));
}

/// Arrows that once ran the wrong way (issue 17), each with where the shared part went.
const ONE_WAY: &[(&str, &[&str], &str)] = &[
    (
        "src/settings",
        &["crate::link", "crate::daemon"],
        "the link depends on the settings: addresses are parsed in settings::address",
    ),
    (
        "src/camera",
        &["crate::area", "crate::indoor", "crate::simulated", "crate::daemon"],
        "frame sources feed the pipelines: shared helpers go in crate::imaging or mavloc-data",
    ),
    (
        "src/link",
        &["crate::output", "crate::daemon"],
        "the link writes its state files with mavloc_data::write_atomic",
    ),
];

/// The line with `super::` chains that climb from `file` (under `src/`) to the crate root
/// spelt as `crate::`, so `super::link` in `src/settings/mod.rs` counts as `crate::link`.
fn rooted(file: &Path, line: &str) -> String {
    let rel = file.strip_prefix(root().join("src")).unwrap();
    let mut depth = rel.components().count();
    if rel.ends_with("mod.rs") {
        depth -= 1;
    }
    line.replace(&"super::".repeat(depth), "crate::")
}

#[test]
fn lower_layers_do_not_import_higher_ones() {
    let mut bad = Vec::new();
    for (dir, forbidden, why) in ONE_WAY {
        let files = sources(&root().join(dir));
        assert!(files.len() >= 3, "the sources of {dir} were found ({} files)", files.len());
        for f in &files {
            // An inline test module is one level deeper, so `super::` means less there
            // (`#[cfg(test)] mod tests;` in another file is not inline).
            let (mut cfg_test, mut in_tests) = (false, false);
            for (n, line) in code_lines(f) {
                in_tests |= cfg_test && line.contains("mod ") && line.contains('{');
                cfg_test = line.contains("#[cfg(test)]");
                let line = if in_tests { line } else { rooted(f, &line) };
                for name in forbidden.iter().filter(|name| names(&line, name)) {
                    let rel = f.strip_prefix(root()).unwrap_or(f);
                    bad.push(format!("{}:{n}: imports {name}: {} ({why})", rel.display(), line.trim()));
                }
            }
        }
    }
    assert!(bad.is_empty(), "dependencies must run one way:\n{}", bad.join("\n"));
}

#[test]
fn the_data_crate_depends_on_no_heavy_crate() {
    let manifest = std::fs::read_to_string(root().join("data/Cargo.toml")).unwrap();
    let deps = manifest.split("[dependencies]").nth(1).expect("data/Cargo.toml has [dependencies]");
    let deps = deps.split("\n[").next().unwrap();
    for name in ["mavloc-sim", "mavloc_sim", "opencv", "tokio", "mavlink", "plotters"] {
        assert!(
            !deps.lines().any(|l| l.trim_start().starts_with(name)),
            "mavloc-data must stay plain data; it depends on {name}"
        );
    }
}

/// `crate::<module>` references of each module of a crate's `src/` (test modules left
/// out: a test may use any module).
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mut graph = BTreeMap::new();
    for f in sources(src) {
        let name = f.file_stem().unwrap().to_string_lossy().into_owned();
        if name == "lib" || name == "main" {
            continue;
        }
        let mut deps = BTreeSet::new();
        for (_, line) in code_lines(&f) {
            if line.contains("#[cfg(test)]") {
                break;
            }
            deps.extend(crate_modules(&line).into_iter().filter(|m| *m != name));
        }
        graph.insert(name, deps);
    }
    graph
}

/// A cycle in the graph, if there is one (as the list of modules around it).
fn find_cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(i) = path.iter().position(|p| p == n) {
            let mut cycle = path[i..].to_vec();
            cycle.push(n.to_string());
            return Some(cycle);
        }
        if done.contains(n) {
            return None;
        }
        path.push(n.to_string());
        for d in graph.get(n).into_iter().flatten() {
            if let Some(c) = visit(d, graph, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n.to_string());
        None
    }
    let mut done = BTreeSet::new();
    graph.keys().find_map(|n| visit(n, graph, &mut Vec::new(), &mut done))
}

#[test]
fn the_simulator_modules_form_no_circle() {
    let graph = module_graph(&root().join("sim/src"));
    assert!(graph.len() >= 8 && graph["mission"].contains("world"), "the graph was read: {graph:?}");
    if let Some(cycle) = find_cycle(&graph) {
        panic!("sim modules import each other in a circle: {}", cycle.join(" -> "));
    }
    let data = module_graph(&root().join("data/src"));
    assert_eq!(find_cycle(&data), None, "mavloc-data modules: {data:?}");
}

/// `crate::<module>` references between the top-level modules of `mavloc` (`src/`, less
/// the geometry crate that lives there), test modules left out.
fn crate_graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = root().join("src");
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in sources(&src) {
        let rel = f.strip_prefix(&src).unwrap();
        let top = rel.components().next().unwrap().as_os_str().to_string_lossy();
        let top = top.trim_end_matches(".rs").to_string();
        if ["lib", "main", "geometry"].contains(&top.as_str()) {
            continue;
        }
        let deps = graph.entry(top.clone()).or_default();
        for (_, line) in code_lines(&f) {
            if line.contains("#[cfg(test)]") {
                break;
            }
            deps.extend(crate_modules(&rooted(&f, &line)).into_iter().filter(|m| *m != top));
        }
    }
    graph
}

#[test]
fn the_crate_modules_form_no_circle() {
    let graph = crate_graph();
    assert!(graph.len() >= 15 && graph["link"].contains("settings"), "the graph was read: {graph:?}");
    if let Some(cycle) = find_cycle(&graph) {
        panic!("modules of mavloc import each other in a circle: {}", cycle.join(" -> "));
    }
}

#[test]
fn the_checks_see_violations() {
    assert!(names("use mavloc_sim::World;", "mavloc_sim"));
    assert!(names("    let w = mavloc_sim::World::build(&s);", "mavloc_sim"));
    assert!(names("use crate::link::Address;", "crate::link"));
    assert!(names("use crate::{daemon, link::Address};", "crate::link"));
    assert!(!names("use crate::linking;", "crate::link") && !names("use mavloc_crate::link;", "crate::link"));
    assert_eq!(crate_modules("use crate::{a, b::c, self};"), ["a", "b"]);
    assert!(!names("let my_tokio = 1;", "tokio") && names("tokio::spawn(f);", "tokio"));
    let settings = root().join("src/settings/mod.rs");
    assert!(names(&rooted(&settings, "use super::link::LinkAddress;"), "crate::link"));
    let address = root().join("src/settings/address.rs");
    assert!(names(&rooted(&address, "use super::super::{daemon, link};"), "crate::link"));
    assert!(!names(&rooted(&address, "use super::link::X;"), "crate::link"), "that is settings::link");
    let g = BTreeMap::from([
        ("a".to_string(), BTreeSet::from(["b".to_string()])),
        ("b".to_string(), BTreeSet::from(["c".to_string()])),
        ("c".to_string(), BTreeSet::from(["a".to_string()])),
    ]);
    assert_eq!(find_cycle(&g).unwrap(), ["a", "b", "c", "a"]);
}

/// Files and `mod` lines under `root` that would put `realtime::` into a test's name outside
/// `tests/it/realtime` (whose declaration in `tests/it/main.rs` is the one allowed): a
/// module whose name ends in `realtime` (`non_realtime::x` holds it too), declared on a
/// line of its own or after attributes. This file is left out: it spells such lines in
/// its own test.
fn realtime_elsewhere(root: &Path) -> Vec<String> {
    let mut found = Vec::new();
    for dir in ["src", "data", "sim", "tests", "benches", "examples"] {
        let d = root.join(dir);
        if !d.is_dir() {
            continue;
        }
        for f in sources(&d) {
            let rel = f.strip_prefix(root).unwrap();
            if rel.starts_with("tests/it/realtime")
                || rel == Path::new("tests/it/main.rs")
                || rel == Path::new("tests/it/layers.rs")
            {
                continue;
            }
            let named = |c: &std::ffi::OsStr| {
                let c = c.to_string_lossy();
                c.trim_end_matches(".rs").ends_with("realtime")
            };
            if rel.components().any(|c| named(c.as_os_str())) {
                found.push(rel.display().to_string());
            }
            for (n, line) in code_lines(&f) {
                let words: Vec<&str> = line.split(|c: char| !is_ident(c)).filter(|w| !w.is_empty()).collect();
                if words.windows(2).any(|w| w[0] == "mod" && w[1].ends_with("realtime")) {
                    found.push(format!("{}:{n}", rel.display()));
                }
            }
        }
    }
    found
}

/// `make test` runs `tests/it/realtime` in a test process of its own and everything else
/// with `--skip realtime::`, which leaves out every test whose name holds that text: a
/// module of that name anywhere else would have its tests run by neither.
#[test]
fn no_other_test_path_holds_the_realtime_filter() {
    assert_eq!(realtime_elsewhere(&root()), Vec::<String>::new());
    // The check sees both kinds.
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(dir.path().join("src/daemon")).unwrap();
    std::fs::write(
        dir.path().join("src/daemon/mod.rs"),
        "pub mod realtime;\n#[cfg(test)] mod non_realtime;\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("src/daemon/realtime.rs"), "fn f() {}\n").unwrap();
    std::fs::write(dir.path().join("src/daemon/soft_realtime.rs"), "fn f() {}\n").unwrap();
    assert_eq!(
        realtime_elsewhere(dir.path()),
        [
            "src/daemon/mod.rs:1",
            "src/daemon/mod.rs:2",
            "src/daemon/realtime.rs",
            "src/daemon/soft_realtime.rs"
        ]
    );
}
