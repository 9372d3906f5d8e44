//! The house without circles: every module of `src/` sits in a layer, and no module names one
//! in a layer above it (`crate::<module>` outside test modules and comments); modules of one
//! layer may use each other only without a cycle. A new module must be given its layer here.
//! Bottom to top (the README's "Layers"):

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

const LAYERS: &[&[&str]] = &[
    // files, validation, geometry, the seeded stream, the format's lights, pictures and tables,
    // the average of any module's parameters, jobs on threads of their own
    &[
        "files",
        "table",
        "threads",
        "backend",
        "scene",
        "skeleton",
        "imageio",
        "apng",
        "written",
        "photo",
        "random",
        "light",
        "geometry",
        "isosurface",
        "seen",
        "silhouette",
        "metrics",
        "plot",
        "progress",
        "averaging",
    ],
    // captures as people have them (nerfstudio cameras, BVH motion, photos) into scene/1
    &["capture"],
    // the ray integral of posed Gaussians (both paths pinned together)
    &["shadow"],
    // the bone-anchored Gaussian set, posed
    &["gaussians"],
    // bone-local encoding -> SDF, albedo
    &["field"],
    // deferred: accumulation, depth, normal, albedo, surface
    &["render"],
    // the image formation and light searches (know nothing of the network's insides)
    &["shading", "environment", "sun_search"],
    // losses, the schedule, the per-view maps of where the fit is still wrong that a batch draws
    // from; the shared vocabulary: the avatar module, what can stop a fit, the fit's messages
    &["losses", "schedule", "error_map", "avatar", "fit_error", "fit_report", "messages"],
    // step(batch, state) -> (state, stats)
    &["train"],
    // the run folder: checkpoints, restore, its lock
    &["run", "run_lock"],
    // after (and around) the fit: read a run, render, score, report
    &["fit", "scoring", "eval", "carve", "relight", "animate", "report", "basis", "export", "ablate"],
    // tools and the command line
    &["synth", "bench", "fuzzing", "cli"],
];

/// `text` without `#[cfg(test)] mod name { ... }` blocks (or `mod name;`) and without `//` comments.
fn library_code(text: &str) -> String {
    let mut out = String::new();
    let mut rest = text;
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        let after = &rest[at..];
        // A test module in a file of its own (`mod tests;`) ends at its semicolon.
        let semicolon = after.find(';').unwrap_or(after.len());
        let Some(open) = after.find('{').filter(|&open| open < semicolon) else {
            rest = &after[(semicolon + 1).min(after.len())..];
            continue;
        };
        let mut depth = 0usize;
        let mut end = after.len();
        for (i, c) in after[open..].char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = open + i + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        rest = &after[end..];
    }
    out.push_str(rest);
    out.lines().map(|l| l.split("//").next().unwrap_or("")).collect::<Vec<_>>().join("\n")
}

/// Every module `crate::<name>` named in `code`.
fn named_modules(code: &str) -> BTreeSet<String> {
    code.match_indices("crate::")
        .map(|(at, _)| code[at + 7..].chars().take_while(|c| c.is_ascii_lowercase() || *c == '_').collect::<String>())
        .filter(|m| !m.is_empty())
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn no_module_names_one_in_a_layer_above_it_and_no_layer_holds_a_cycle() {
    let layer: BTreeMap<&str, usize> = LAYERS.iter().enumerate().flat_map(|(k, names)| names.iter().map(move |n| (*n, k))).collect();
    let mut files = Vec::new();
    rust_files(Path::new("src"), &mut files);
    let mut uses: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut problems = Vec::new();
    for file in &files {
        let relative = file.strip_prefix("src").unwrap();
        let module = relative.components().next().unwrap().as_os_str().to_string_lossy().trim_end_matches(".rs").to_string();
        if module == "lib" || module == "main" {
            continue;
        }
        let Some(&own) = layer.get(module.as_str()) else {
            problems.push(format!("{}: module {module} has no layer in tests/layers.rs", file.display()));
            continue;
        };
        for named in named_modules(&library_code(&std::fs::read_to_string(file).unwrap())) {
            match layer.get(named.as_str()) {
                Some(&other) if other > own => problems.push(format!("{}: {module} (layer {own}) names crate::{named} (layer {other})", file.display())),
                Some(_) if named != module => {
                    uses.entry(module.clone()).or_default().insert(named);
                }
                _ => {}
            }
        }
    }
    // Within a layer: no cycle (depth-first search over same-layer edges).
    fn cycle(from: &str, at: &str, uses: &BTreeMap<String, BTreeSet<String>>, layer: &BTreeMap<&str, usize>, seen: &mut BTreeSet<String>) -> bool {
        for next in uses.get(at).into_iter().flatten().filter(|n| layer.get(n.as_str()) == layer.get(from)) {
            if next == from || (seen.insert(next.clone()) && cycle(from, next, uses, layer, seen)) {
                return true;
            }
        }
        false
    }
    for module in uses.keys() {
        if cycle(module, module, &uses, &layer, &mut BTreeSet::new()) {
            problems.push(format!("{module} is in a cycle within its layer"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    // The parse must see the imports at all: the trainer names the field, scoring names eval.
    assert!(uses["train"].contains("field") && uses["scoring"].contains("eval"), "{uses:?}");
}

#[test]
fn the_parse_drops_test_modules_and_comments() {
    let code = "use crate::a;\n// crate::b\n#[cfg(test)]\nmod tests {\n    fn f() { let _ = \"{}\"; crate::c::x(); }\n}\nfn g() { crate::d::y() }\n";
    assert_eq!(named_modules(&library_code(code)), ["a", "d"].iter().map(|s| s.to_string()).collect());
}

/// The sibling files of a folder module (`super::name` or `crate::folder::name`) named in `code`.
fn named_siblings(code: &str, folder: &str, siblings: &BTreeSet<String>) -> BTreeSet<String> {
    let mut named = BTreeSet::new();
    for prefix in ["super::".to_string(), format!("crate::{folder}::")] {
        for (at, _) in code.match_indices(prefix.as_str()) {
            let name: String = code[at + prefix.len()..].chars().take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_').collect();
            if siblings.contains(&name) {
                named.insert(name);
            }
        }
    }
    named
}

#[test]
fn no_folder_holds_a_circle_between_its_files() {
    let mut problems = Vec::new();
    for entry in std::fs::read_dir("src").unwrap() {
        let folder = entry.unwrap().path();
        if !folder.is_dir() {
            continue;
        }
        let name = folder.file_name().unwrap().to_string_lossy().into_owned();
        let mut files = Vec::new();
        rust_files(&folder, &mut files);
        let stem = |p: &Path| p.file_stem().unwrap().to_string_lossy().into_owned();
        let siblings: BTreeSet<String> = files.iter().map(|f| stem(f)).filter(|s| s != "mod").collect();
        let uses: BTreeMap<String, BTreeSet<String>> = files
            .iter()
            .filter(|f| stem(f) != "mod")
            .map(|f| {
                (stem(f), named_siblings(&library_code(&std::fs::read_to_string(f).unwrap()), &name, &siblings).into_iter().filter(|n| *n != stem(f)).collect())
            })
            .collect();
        fn reaches(from: &str, to: &str, uses: &BTreeMap<String, BTreeSet<String>>, seen: &mut BTreeSet<String>) -> bool {
            uses.get(from).into_iter().flatten().any(|next| next == to || (seen.insert(next.clone()) && reaches(next, to, uses, seen)))
        }
        for file in uses.keys() {
            if reaches(file, file, &uses, &mut BTreeSet::new()) {
                problems.push(format!("src/{name}/{file}.rs is in a circle of files within src/{name}/"));
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}
