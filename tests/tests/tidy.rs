//! Tidy: rules about the source tree itself, checked on every `cargo test` (in the spirit of
//! rust-analyzer's tidy test). Each rule names the files that break it.
//!
//! - every source file starts with a `//!` comment saying what it is;
//! - no test is switched off or made to expect a panic;
//! - `roam-protocol` is pure: no clock, socket or async runtime, in its code or its
//!   dependencies;
//! - only the I/O shells read a clock: the cores (terrain, tessellation, simulation, the
//!   per-viewer and world cores, the viewer's connection core, camera, HUD, renderer)
//!   take time as a parameter;
//! - the workspace's lints are set once, in the root `Cargo.toml`, and every package
//!   takes them.

use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace root")
        .to_path_buf()
}

/// Every `.rs` file of the workspace's packages, relative to the root, sorted.
fn sources() -> Vec<PathBuf> {
    let root = root();
    let mut out = Vec::new();
    let mut dirs: Vec<PathBuf> = ["protocol", "server", "client", "tests", "link"]
        .iter()
        .map(|d| root.join(d))
        .filter(|d| d.is_dir())
        .collect();
    while let Some(dir) = dirs.pop() {
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for entry in entries {
            let path = entry.expect("a readable directory entry").path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if path.is_dir() {
                if name != "target" && !name.starts_with('.') {
                    dirs.push(path);
                }
            } else if name.ends_with(".rs") {
                out.push(
                    path.strip_prefix(&root)
                        .expect("under the root")
                        .to_path_buf(),
                );
            }
        }
    }
    out.sort();
    out
}

fn read(rel: &Path) -> String {
    std::fs::read_to_string(root().join(rel)).unwrap_or_else(|e| panic!("{}: {e}", rel.display()))
}

/// Fails listing `offenders` under `rule`, if there are any.
fn check(rule: &str, offenders: Vec<String>) {
    assert!(
        offenders.is_empty(),
        "{rule}:\n  {}",
        offenders.join("\n  ")
    );
}

/// The lines of `text` outside comments that contain one of `words`, as `file:line: text`.
fn uses(rel: &Path, text: &str, words: &[&str]) -> Vec<String> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim_start().starts_with("//"))
        .filter(|(_, l)| words.iter().any(|w| l.contains(w)))
        .map(|(n, l)| format!("{}:{}: {}", rel.display(), n + 1, l.trim()))
        .collect()
}

#[test]
fn every_source_file_starts_with_a_module_comment() {
    let files = sources();
    assert!(
        files.len() > 50,
        "the walk found only {} files",
        files.len()
    );
    check(
        "files that do not start with `//!`",
        files
            .iter()
            .filter(|f| !read(f).starts_with("//!"))
            .map(|f| f.display().to_string())
            .collect(),
    );
}

#[test]
fn no_test_is_ignored_or_expects_a_panic() {
    // Spelled in two pieces so this file does not match itself.
    let words = [concat!("#[", "ignore"), concat!("#[", "should_panic")];
    let mut bad = Vec::new();
    for f in sources() {
        bad.extend(uses(&f, &read(&f), &words));
    }
    check("switched-off or panic-expecting tests", bad);
}

#[test]
fn the_protocol_crate_is_pure() {
    let words = [
        "std::time",
        "Instant",
        "SystemTime",
        "std::net",
        "UdpSocket",
        "TcpStream",
        "tokio",
        "quinn",
        "async ",
        "std::thread",
        "std::fs",
    ];
    let mut bad = Vec::new();
    for f in sources().iter().filter(|f| f.starts_with("protocol/src")) {
        bad.extend(uses(f, &read(f), &words));
    }
    let manifest = Path::new("protocol/Cargo.toml");
    bad.extend(uses(
        manifest,
        &read(manifest),
        &["tokio", "quinn", "async", "mio"],
    ));
    check("clocks, sockets or async in roam-protocol", bad);
}

/// Where a clock may be read: the I/O shells (the server's network shell and command
/// line, the viewer's connection I/O, window and measuring front ends, the shared QUIC
/// crate), benchmarks and the end-to-end tests, which measure real time.
fn may_read_a_clock(f: &Path) -> bool {
    let shells = [
        "server/src/net/",
        "server/src/cli/",
        "server/src/main.rs",
        "client/src/session.rs",
        "client/src/connection.rs",
        "client/src/live.rs",
        "client/src/window.rs",
        "client/src/headless.rs",
        "client/src/bench/mod.rs",
        "client/src/bench/watch.rs",
        "client/src/main.rs",
        "link/src/",
        "tests/",
        "client/tests/window.rs",
    ];
    let s = f.to_string_lossy();
    shells.iter().any(|p| s.starts_with(p)) || s.contains("/benches/")
}

#[test]
fn only_the_io_shells_read_a_clock() {
    let words = [
        "Instant::now",
        "SystemTime::now",
        ".elapsed()",
        "time::sleep",
    ];
    let mut bad = Vec::new();
    for f in sources().iter().filter(|f| !may_read_a_clock(f)) {
        bad.extend(uses(f, &read(f), &words));
    }
    check("a clock read outside the I/O shells", bad);
}

#[test]
fn lints_are_set_once_for_the_workspace() {
    let root_manifest = read(Path::new("Cargo.toml"));
    assert!(
        root_manifest.contains("[workspace.lints.rust]")
            && root_manifest.contains("[workspace.lints.clippy]"),
        "Cargo.toml: expected [workspace.lints.rust] and [workspace.lints.clippy]"
    );
    let mut bad = Vec::new();
    for pkg in ["protocol", "server", "client", "tests", "link"] {
        let manifest = Path::new(pkg).join("Cargo.toml");
        if !root().join(&manifest).exists() {
            continue;
        }
        let text = read(&manifest);
        if !text.contains("[lints]\nworkspace = true") {
            bad.push(format!(
                "{}: no `[lints] workspace = true`",
                manifest.display()
            ));
        }
    }
    check("packages that do not take the workspace's lints", bad);
}
