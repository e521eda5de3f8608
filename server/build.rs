//! Embeds the browser viewer's page in release builds: when `web/dist/index.html` exists
//! (what `scripts/build-web` writes), every file under `web/dist/` goes into a table in
//! `OUT_DIR/page.rs` (`FILES: &[(name, bytes)]`, names relative to `web/dist/` with `/`
//! between folders, each file through `include_bytes!`); otherwise the table is empty and
//! `serve --web` says how to build the page.
//!
//! Other builds (the tests', the edit-test loop's: Cargo's `PROFILE` is `debug`) embed
//! nothing and name `web/dist/` instead (`DIST`), read when `serve --web` starts: the page
//! can be built while the tests compile, or after, and the server is not rebuilt for it
//! (it was, with the whole workspace above it: docs/testing.md#times).
//!
//! What makes it run again: in release builds `web/dist/` and each of its files when it
//! exists, else `web/` (where `web/dist/` will appear); in others only this file. A path
//! that does not exist would make Cargo run this script at every build, and rebuild the
//! crate each time, so none is named.

use std::path::{Path, PathBuf};

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by Cargo"));
    let root = manifest
        .parent()
        .expect("the server crate sits in the workspace root")
        .to_path_buf();
    let web = root.join("web");
    let dist = web.join("dist");
    let mut files = Vec::new();
    let release = std::env::var("PROFILE").as_deref() == Ok("release");
    if !release {
        // Read at run time (`Page::embedded`).
    } else if dist.join("index.html").is_file() {
        println!("cargo:rerun-if-changed={}", dist.display());
        walk(&dist, &mut files);
        files.sort();
        for f in &files {
            println!("cargo:rerun-if-changed={}", f.display());
        }
    } else if web.is_dir() {
        println!("cargo:rerun-if-changed={}", web.display());
    }
    println!("cargo:rerun-if-changed=build.rs");
    let mut out = String::from("pub(super) static FILES: &[(&str, &[u8])] = &[\n");
    for f in &files {
        let name = f
            .strip_prefix(&dist)
            .expect("walked under dist")
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect::<Vec<_>>()
            .join("/");
        let path = f.to_str().unwrap_or_else(|| {
            panic!("{}: a file name that is not UTF-8", f.display());
        });
        out.push_str(&format!("    ({name:?}, include_bytes!({path:?})),\n"));
    }
    out.push_str("];\n");
    let dist_path = dist.to_str().unwrap_or_else(|| {
        panic!("{}: a path that is not UTF-8", dist.display());
    });
    let named = if release {
        "None".to_owned()
    } else {
        format!("Some({dist_path:?})")
    };
    out.push_str(&format!("pub(super) const DIST: Option<&str> = {named};\n"));
    let target = PathBuf::from(std::env::var_os("OUT_DIR").expect("set by Cargo")).join("page.rs");
    // Written only when it changes: an unchanged table leaves the file's time alone.
    if std::fs::read_to_string(&target).ok().as_deref() != Some(out.as_str()) {
        std::fs::write(&target, out)
            .unwrap_or_else(|e| panic!("writing {}: {e}", target.display()));
    }
}

/// Every regular file under `dir`, in folders too (hidden ones left out).
fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
    let entries =
        std::fs::read_dir(dir).unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()));
    for entry in entries {
        let entry = entry.unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()));
        let path = entry.path();
        if entry.file_name().to_string_lossy().starts_with('.') {
            continue;
        }
        if path.is_dir() {
            walk(&path, out);
        } else if path.is_file() {
            out.push(path);
        }
    }
}
