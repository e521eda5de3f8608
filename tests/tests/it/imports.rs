//! Imports: the graph of references between the workspace's source files has no circle,
//! and the server's layers refer only downwards.
//!
//! Every crate of the workspace (each package's library, binaries, tests, benchmarks,
//! examples and build script) is walked from its root through its `mod` declarations
//! (`#[path]` ones too; every `.rs` file must be reached), and every reference from one
//! file to another is an edge, with its line: a `use` (`crate::`, `super::`, `self::`, a
//! child module's name, another workspace crate's name), a `pub use` re-export, a glob
//! (to the module's file), an inline path such as `crate::a::b::f()` or `wire::read()`
//! through a module a `use` names, and a path in an attribute's string
//! (`deserialize_with = "crate::a::f"`). A path is resolved through re-exports to the
//! file that defines its item or module. Comments (doc links among them) are not
//! references; what a macro expands to is not seen (the paths written in its definition
//! are).
//!
//! The detector is `imports/lex.rs` (tokens) and `imports/graph.rs` (module trees, paths
//! resolved, circles); the tests at the end of this file check it on files in memory.
//!
//! A module's file and its children are not a circle: references between a module and
//! its own descendants (its `mod` declarations, its re-exports, its calls into a child,
//! a child's `super::`) are not edges. Siblings that refer to each other are a circle, and
//! so is any loop through modules that are not one inside the other.
//!
//! The server's layers, lowest first, are [`SERVER_LAYERS`].

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The server's layers, lowest first: a file may refer to files of its own layer and of
/// the layers below it, never above. The library's root (`lib.rs`) only declares the
/// modules and re-exports, and belongs to none.
///
/// - `terrain`: data sets, heights, colours, the variance tree (the bintree's geometry is
///   below it, in `roam_protocol::bintree`);
/// - `tessellate`: the ROAM tessellators over the terrain;
/// - `sim`: the vehicles, the world and its recordings, over the terrain (the fly-over
///   cameras are the tessellator's);
/// - `viewer`: the per-viewer and admission decisions, over the tessellators and the world;
/// - `web`: the browser viewer's page and certificate (it refers to nothing else here);
/// - `net`: the network shell (QUIC, WebTransport, NATS, the clock), which serves the
///   page with `web`;
/// - `cli` and `main.rs` (the binary, through the library's paths): the command line.
const SERVER_LAYERS: &[&[&str]] = &[
    &["server/src/terrain/"],
    &["server/src/tessellate/"],
    &["server/src/sim/"],
    &["server/src/viewer/"],
    &["server/src/web/"],
    &["server/src/net/"],
    &["server/src/cli/", "server/src/main.rs"],
];

/// The packages walked, relative to the workspace root.
const PACKAGES: &[&str] = &["protocol", "server", "client", "link", "tests", "web"];

#[path = "imports/graph.rs"]
mod graph;
#[path = "imports/lex.rs"]
mod lex;

use graph::{Edge, Workspace, circles, describe, show};

// ---------------------------------------------------------------------------------------
// The workspace on disk.

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace root")
        .to_path_buf()
}

/// Every `.rs` file under `dir` (relative to the root), but build outputs'.
fn walk(dir: &Path, out: &mut BTreeMap<PathBuf, String>) {
    let root = root();
    let entries =
        std::fs::read_dir(root.join(dir)).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for entry in entries {
        let path = entry.expect("a readable directory entry").path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        let rel = path
            .strip_prefix(&root)
            .expect("under the root")
            .to_path_buf();
        if path.is_dir() {
            if name != "target" && !name.starts_with('.') {
                walk(&rel, out);
            }
        } else if name.ends_with(".rs") {
            let text =
                std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", rel.display()));
            out.insert(rel, text);
        }
    }
}

/// The library's crate name in a package's manifest: `[lib] name`, or the package's name
/// with `_` for `-`.
fn lib_name(manifest: &str) -> String {
    let mut section = "";
    let (mut package, mut lib) = (None, None);
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            section = line;
        } else if let Some(v) = line.strip_prefix("name = ") {
            let v = v.trim_matches('"').replace('-', "_");
            match section {
                "[package]" => package = Some(v),
                "[lib]" => lib = Some(v),
                _ => {}
            }
        }
    }
    lib.or(package).expect("a package has a name")
}

/// The workspace read from disk: every package's crates, and every file walked.
fn workspace() -> (Workspace, BTreeMap<PathBuf, String>) {
    let mut files = BTreeMap::new();
    for pkg in PACKAGES {
        walk(Path::new(pkg), &mut files);
    }
    let mut ws = Workspace::default();
    // The libraries, by their crate names, then every other crate root (references are
    // resolved once all are read).
    for pkg in PACKAGES {
        let lib = Path::new(pkg).join("src/lib.rs");
        if files.contains_key(&lib) {
            let manifest = std::fs::read_to_string(root().join(pkg).join("Cargo.toml"))
                .unwrap_or_else(|e| panic!("{pkg}/Cargo.toml: {e}"));
            ws.add_crate(&files, &lib, Some(&lib_name(&manifest)));
        }
    }
    for pkg in PACKAGES {
        let pkg = Path::new(pkg);
        let mut roots = vec![pkg.join("src/main.rs"), pkg.join("build.rs")];
        for dir in ["src/bin", "tests", "benches", "examples"] {
            let dir = pkg.join(dir);
            roots.extend(
                files
                    .keys()
                    .filter(|f| {
                        // `dir/x.rs`, or a target of several files: `dir/x/main.rs`.
                        f.parent() == Some(dir.as_path())
                            || (f.file_name().is_some_and(|n| n == "main.rs")
                                && f.parent().and_then(Path::parent) == Some(dir.as_path()))
                    })
                    .cloned(),
            );
        }
        for r in roots.iter().filter(|r| files.contains_key(*r)) {
            ws.add_crate(&files, r, None);
        }
    }
    (ws, files)
}

#[test]
fn every_file_is_read_and_no_files_refer_to_each_other_in_a_circle() {
    let (ws, files) = workspace();
    assert!(
        ws.missing.is_empty(),
        "`mod` declarations of no file: {:?}",
        ws.missing
    );
    let read = ws.files();
    let unread: Vec<String> = files
        .keys()
        .filter(|f| !read.contains(*f))
        .map(|f| f.display().to_string())
        .collect();
    assert!(
        unread.is_empty(),
        "files no crate's module tree reaches (this walk would not check them):\n  {}",
        unread.join("\n  ")
    );
    let edges = ws.edges();
    assert!(edges.len() > 300, "only {} references found", edges.len());
    let found = circles(&edges);
    assert!(
        found.is_empty(),
        "files that refer to each other in a circle (each with the references between \
         them):\n  {}",
        describe(&found, &edges).join("\n  ")
    );
}

/// The server's layer of a file, `None` for the library's root and files outside it.
fn server_layer(f: &Path) -> Option<usize> {
    let s = f.to_string_lossy();
    SERVER_LAYERS
        .iter()
        .position(|layer| layer.iter().any(|p| s.starts_with(p)))
}

#[test]
fn the_server_refers_only_to_its_own_layer_and_those_below() {
    let (ws, _) = workspace();
    let edges = ws.edges();
    let upward: Vec<String> = edges
        .iter()
        .filter(|e| match (server_layer(&e.from), server_layer(&e.to)) {
            (Some(a), Some(b)) => a < b,
            _ => false,
        })
        .map(show)
        .collect();
    assert!(
        upward.is_empty(),
        "references from a lower layer of the server to a higher one (layers, lowest \
         first: {SERVER_LAYERS:?}):\n  {}",
        upward.join("\n  ")
    );
}

// ---------------------------------------------------------------------------------------
// The detector itself, on files in memory.

/// The references between `files` (path, text), read as one crate from the first.
fn edges_of(files: &[(&str, &str)]) -> BTreeSet<Edge> {
    let map: BTreeMap<PathBuf, String> = files
        .iter()
        .map(|(p, t)| (PathBuf::from(p), t.to_string()))
        .collect();
    let mut ws = Workspace::default();
    ws.add_crate(&map, Path::new(files[0].0), Some("a"));
    assert!(ws.missing.is_empty(), "{:?}", ws.missing);
    ws.edges()
}

fn names(circles: &[Vec<PathBuf>]) -> Vec<Vec<String>> {
    circles
        .iter()
        .map(|c| c.iter().map(|f| f.display().to_string()).collect())
        .collect()
}

#[test]
fn the_detector_finds_a_two_file_circle_and_names_its_lines() {
    let edges = edges_of(&[
        ("a/src/lib.rs", "//! A crate.\nmod x;\nmod y;\n"),
        ("a/src/x.rs", "//! x.\nuse crate::y::Y;\npub struct X(Y);\n"),
        (
            "a/src/y.rs",
            "//! y: `crate::x` in a comment and \"crate::x::X\" in a string are not references.\n\
             pub struct Y;\nfn f() -> usize {\n    let _ = ('\\'', '\"', r#\"\"#, 'y');\n    \
             std::mem::size_of::<crate::x::X>()\n}\n",
        ),
    ]);
    let found = circles(&edges);
    assert_eq!(names(&found), [["a/src/x.rs", "a/src/y.rs"]]);
    let message = describe(&found, &edges).join("\n");
    assert!(
        message.contains("a/src/x.rs -> a/src/y.rs: 2 crate::y::Y")
            && message.contains("a/src/y.rs -> a/src/x.rs: 5 crate::x::X"),
        "{message}"
    );
}

#[test]
fn the_detector_finds_a_circle_through_a_re_export() {
    // `y` re-exports what `x` defines, and `x` uses `y`: a circle (the recorder's once).
    let edges = edges_of(&[
        ("a/src/lib.rs", "mod x;\nmod y;\n"),
        (
            "a/src/x.rs",
            "use crate::y::Header;\npub struct Writer(Header);\n",
        ),
        (
            "a/src/y.rs",
            "pub struct Header;\npub use crate::x::Writer;\n",
        ),
    ]);
    assert_eq!(names(&circles(&edges)), [["a/src/x.rs", "a/src/y.rs"]]);
}

#[test]
fn the_detector_does_not_flag_a_parent_and_its_children() {
    // `p` declares `q` and re-exports what `q` defines; `q` uses `p`'s own item (between a
    // module and its child: no edge); `z` uses `p::Q`, which resolves to `q`, where it is
    // defined.
    let edges = edges_of(&[
        ("a/src/lib.rs", "mod p;\nmod z;\n"),
        ("a/src/p/mod.rs", "mod q;\npub use q::Q;\npub struct P;\n"),
        ("a/src/p/q.rs", "use super::P;\npub struct Q(pub P);\n"),
        ("a/src/z.rs", "use crate::p::Q;\nfn f(_: Q) {}\n"),
    ]);
    assert!(circles(&edges).is_empty(), "{edges:?}");
    let pairs: Vec<(String, String)> = edges
        .iter()
        .map(|e| (e.from.display().to_string(), e.to.display().to_string()))
        .collect();
    assert_eq!(
        pairs,
        [("a/src/z.rs".to_string(), "a/src/p/q.rs".to_string())]
    );
    // A parent whose own code calls into a child that refers back to it is no circle;
    // two of its children that refer to each other are.
    let edges = edges_of(&[
        ("a/src/lib.rs", "mod p;\n"),
        (
            "a/src/p/mod.rs",
            "mod q;\nmod r;\npub struct P;\nfn f() { q::g(); }\n",
        ),
        ("a/src/p/q.rs", "use super::P;\npub fn g() {}\n"),
        ("a/src/p/r.rs", "use super::q::g;\npub fn h() { g() }\n"),
    ]);
    assert!(circles(&edges).is_empty(), "{edges:?}");
    let edges = edges_of(&[
        ("a/src/lib.rs", "mod p;\n"),
        ("a/src/p/mod.rs", "mod q;\nmod r;\n"),
        ("a/src/p/q.rs", "use super::r::h;\npub fn g() { h() }\n"),
        ("a/src/p/r.rs", "use super::q::g;\npub fn h() { g() }\n"),
    ]);
    assert_eq!(names(&circles(&edges)), [["a/src/p/q.rs", "a/src/p/r.rs"]]);
}

#[test]
fn the_server_layers_name_every_module_of_the_server() {
    let (ws, _) = workspace();
    let unlayered: Vec<String> = ws
        .files()
        .into_iter()
        .filter(|f| f.starts_with("server/src") && f != Path::new("server/src/lib.rs"))
        .filter(|f| server_layer(f).is_none())
        .map(|f| f.display().to_string())
        .collect();
    assert!(
        unlayered.is_empty(),
        "server files in no layer of SERVER_LAYERS: {unlayered:?}"
    );
}
