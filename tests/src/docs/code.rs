//! The workspace as the document checks see it: its packages (binaries, tests, benches)
//! from their manifests, its Rust sources, the items each defines or re-exports, and the
//! resolution of a path like `roam_server::net::Server` or `sim::world_core` through
//! them; and where a path written in a document may be relative to. Text-based (no
//! compiler): a name counts as defined where a declaration of it is written.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::markdown::{PathToken, camel, path_token};

/// The workspace's root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate sits in the workspace root")
        .to_path_buf()
}

/// `path`'s text (a panic naming it if it cannot be read).
pub fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

// ---- The workspace -------------------------------------------------------------------

/// A package of the workspace.
#[derive(Debug)]
pub struct Package {
    pub name: String,
    pub dir: PathBuf,
    /// Its library's crate name, if it has one.
    pub lib: Option<String>,
    pub bins: Vec<String>,
    pub tests: Vec<String>,
    pub benches: Vec<String>,
}

/// The workspace's packages, from its manifests.
pub fn packages() -> Vec<Package> {
    let root = root();
    let manifest = read(&root.join("Cargo.toml"));
    let members = manifest
        .split("members")
        .nth(1)
        .and_then(|m| m.split(']').next())
        .expect("the root Cargo.toml lists its members");
    let stems = |dir: &Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .filter_map(|e| {
                let p = e.ok()?.path();
                let stem = p.file_stem()?.to_str()?.to_owned();
                (p.extension().is_some_and(|e| e == "rs") || p.join("main.rs").exists())
                    .then_some(stem)
            })
            .collect();
        v.sort();
        v
    };
    members
        .split('"')
        .skip(1)
        .step_by(2)
        .map(|m| {
            let dir = root.join(m);
            let toml = read(&dir.join("Cargo.toml"));
            let value = |line: &str| line.split('"').nth(1).map(str::to_owned);
            let mut section = String::new();
            let (mut name, mut lib, mut bins) = (String::new(), None, Vec::new());
            for line in toml.lines().map(str::trim) {
                if line.starts_with('[') {
                    section = line.to_owned();
                } else if line.starts_with("name") {
                    match section.as_str() {
                        "[package]" => name = value(line).unwrap_or_default(),
                        "[lib]" => lib = value(line),
                        "[[bin]]" => bins.extend(value(line)),
                        _ => {}
                    }
                }
            }
            if dir.join("src/lib.rs").exists() && lib.is_none() {
                lib = Some(name.replace('-', "_"));
            }
            if dir.join("src/main.rs").exists() && bins.is_empty() {
                bins.push(name.clone());
            }
            bins.extend(stems(&dir.join("src/bin")));
            Package {
                lib,
                bins,
                tests: stems(&dir.join("tests")),
                benches: stems(&dir.join("benches")),
                name,
                dir,
            }
        })
        .collect()
}

/// Every `.rs` file under `dir` (no `target`, no hidden directories).
pub fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if p.is_dir() && name != "target" && !name.starts_with('.') {
            rust_files(&p, out);
        } else if name.ends_with(".rs") {
            out.push(p);
        }
    }
}

/// Whether `text` has `kw name` with `name` a whole word (`fn take`, not `fn taken`).
pub fn declares(text: &str, kw: &str, name: &str) -> bool {
    let pat = format!("{kw} {name}");
    text.match_indices(&pat).any(|(i, _)| {
        let before = text[..i].chars().next_back();
        let after = text[i + pat.len()..].chars().next();
        !before.is_some_and(|c| c.is_alphanumeric() || c == '_')
            && !after.is_some_and(|c| c.is_alphanumeric() || c == '_')
    })
}

/// Whether `text` defines an item `name` at some level.
pub fn defines(text: &str, name: &str) -> bool {
    [
        "struct", "enum", "trait", "type", "union", "fn", "const", "static", "mod",
    ]
    .iter()
    .any(|kw| declares(text, kw, name))
        || declares(text, "macro_rules!", name)
}

/// The variants of every `enum` in `text`.
pub fn variants(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut depth: Option<i32> = None;
    for line in text.lines() {
        let t = line.trim();
        match depth {
            None => {
                if (t.starts_with("enum ") || t.contains(" enum ")) && t.ends_with('{') {
                    depth = Some(1);
                }
            }
            Some(d) => {
                if d == 1 && !t.starts_with("//") && !t.starts_with('#') {
                    let end = t
                        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                        .unwrap_or(t.len());
                    let next = t[end..].trim_start().chars().next();
                    if end > 0 && matches!(next, None | Some(',' | '(' | '{' | '=')) {
                        out.push(t[..end].to_owned());
                    }
                }
                let d = d + t.matches('{').count() as i32 - t.matches('}').count() as i32;
                depth = (d > 0).then_some(d);
            }
        }
    }
    out
}

/// What the `pub use` (or `pub(crate) use`, …) statements in `text` re-export: `(name,
/// path)`, braces expanded.
pub fn reexports(text: &str) -> Vec<(String, Vec<String>)> {
    fn expand(prefix: &str, body: &str, out: &mut Vec<(String, Vec<String>)>) {
        let body = body.trim();
        if let Some(open) = body.find('{') {
            let head = format!("{prefix}{}", &body[..open]);
            let inner = &body[open + 1..body.rfind('}').unwrap_or(body.len())];
            let mut depth = 0;
            let mut start = 0;
            for (i, c) in inner.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(&head, &inner[start..i], out);
                        start = i + 1;
                    }
                    _ => {}
                }
            }
            expand(&head, &inner[start..], out);
        } else if !body.is_empty() {
            let full = format!("{prefix}{body}");
            let (path, name) = match full.split_once(" as ") {
                Some((p, n)) => (p.trim().to_owned(), n.trim().to_owned()),
                None => (
                    full.clone(),
                    full.rsplit("::").next().unwrap_or("").to_owned(),
                ),
            };
            let path = path.split("::").map(|s| s.trim().to_owned()).collect();
            out.push((name, path));
        }
    }
    let mut out = Vec::new();
    for (i, _) in text.match_indices("use ") {
        let line = text[..i].rsplit('\n').next().unwrap_or("").trim();
        if !(line == "pub" || line.starts_with("pub(") && line.ends_with(')')) {
            continue;
        }
        let rest = &text[i + "use ".len()..];
        if let Some(end) = rest.find(';') {
            let stmt: String = rest[..end].split_whitespace().collect::<Vec<_>>().join(" ");
            expand("", &stmt.replace(":: {", "::{"), &mut out);
        }
    }
    out
}

/// The workspace's sources, for resolving the names the documents write.
pub struct Code {
    pub root: PathBuf,
    pub packages: Vec<Package>,
    pub files: BTreeMap<PathBuf, String>,
    /// Types, traits and enum variants defined anywhere.
    pub types: BTreeSet<String>,
}

impl Code {
    pub fn load() -> Code {
        let root = root();
        let packages = packages();
        let mut paths = Vec::new();
        for p in &packages {
            rust_files(&p.dir, &mut paths);
        }
        let files: BTreeMap<PathBuf, String> = paths
            .into_iter()
            .map(|p| {
                let text = read(&p);
                (p, text)
            })
            .collect();
        let mut types = BTreeSet::new();
        for text in files.values() {
            for kw in ["struct", "enum", "trait", "type", "union"] {
                let pat = format!("{kw} ");
                for (i, _) in text.match_indices(&pat) {
                    let name: String = text[i + pat.len()..]
                        .chars()
                        .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                        .collect();
                    types.insert(name);
                }
            }
            types.extend(variants(text));
        }
        Code {
            root,
            packages,
            files,
            types,
        }
    }

    /// The repository's top-level entries.
    pub fn top(&self) -> BTreeSet<String> {
        std::fs::read_dir(&self.root)
            .expect("the repository's root")
            .filter_map(|e| Some(e.ok()?.file_name().to_str()?.to_owned()))
            .collect()
    }

    /// The root file of library crate `name` (`roam_server`), if it is the workspace's.
    pub fn crate_root(&self, name: &str) -> Option<PathBuf> {
        let p = self
            .packages
            .iter()
            .find(|p| p.lib.as_deref() == Some(name))?;
        Some(p.dir.join("src/lib.rs")).filter(|f| self.files.contains_key(f))
    }

    /// The directory a module's children are in.
    fn module_dir(file: &Path) -> PathBuf {
        let dir = file.parent().expect("a file in a directory");
        match file.file_name().and_then(|n| n.to_str()) {
            Some("mod.rs" | "lib.rs" | "main.rs") => dir.to_path_buf(),
            _ => dir.join(file.file_stem().expect("a file name")),
        }
    }

    fn child(&self, file: &Path, name: &str) -> Option<PathBuf> {
        let dir = Code::module_dir(file);
        [
            dir.join(format!("{name}.rs")),
            dir.join(name).join("mod.rs"),
        ]
        .into_iter()
        .find(|f| self.files.contains_key(f))
    }

    /// The module above `file`'s (a crate's root has none).
    fn parent(&self, file: &Path) -> Option<PathBuf> {
        let dir = match file.file_name().and_then(|n| n.to_str()) {
            Some("lib.rs" | "main.rs") => return None,
            Some("mod.rs") => file.parent()?.parent()?.to_path_buf(),
            _ => file.parent()?.to_path_buf(),
        };
        let up = dir.with_extension("rs");
        ["mod.rs", "lib.rs", "main.rs"]
            .iter()
            .map(|f| dir.join(f))
            .chain([up])
            .find(|f| self.files.contains_key(f))
    }

    /// The crate roots `file` may belong to.
    fn roots_of(&self, file: &Path) -> Vec<PathBuf> {
        self.packages
            .iter()
            .filter(|p| file.starts_with(&p.dir))
            .flat_map(|p| [p.dir.join("src/lib.rs"), p.dir.join("src/main.rs")])
            .filter(|f| self.files.contains_key(f))
            .collect()
    }

    /// Modules named `name` anywhere in the workspace (their files).
    pub fn modules_named(&self, name: &str) -> Vec<PathBuf> {
        self.files
            .keys()
            .filter(|f| {
                let stem = f.file_stem().and_then(|s| s.to_str());
                stem == Some(name)
                    || (stem == Some("mod")
                        && f.parent()
                            .and_then(|d| d.file_name())
                            .and_then(|n| n.to_str())
                            == Some(name))
            })
            .cloned()
            .collect()
    }

    /// Whether `ty` has a member `m`: a method, constant, field or variant in a file that
    /// defines or implements it.
    pub fn member(&self, ty: &str, m: &str) -> bool {
        let implements = |text: &str| {
            text.lines().any(|l| {
                let l = l.trim_start();
                l.starts_with("impl")
                    && l.split(|c: char| !(c.is_alphanumeric() || c == '_'))
                        .any(|w| w == ty)
            })
        };
        self.files
            .values()
            .filter(|t| defines(t, ty) || implements(t))
            .any(|t| {
                ["fn", "const", "static", "type"]
                    .iter()
                    .any(|kw| declares(t, kw, m))
                    || t.lines().any(|l| {
                        let l = l.trim_start();
                        let l = l.strip_prefix("pub ").unwrap_or(l);
                        // A field (`m: T`) or a variant (`M`, `M(T)`, `M { … }`, `M = 1`).
                        l.strip_prefix(m).is_some_and(|rest| {
                            rest.is_empty()
                                || rest.starts_with([':', ',', '(', '{'])
                                || [" {", " (", " ="].iter().any(|p| rest.starts_with(p))
                        })
                    })
            })
    }

    /// Whether `parts` resolves from the module in `file`.
    pub fn resolve_in(&self, file: &Path, parts: &[&str], depth: usize) -> bool {
        let Some((&first, rest)) = parts.split_first() else {
            return true;
        };
        if depth > 12 {
            return false;
        }
        match first {
            "self" => return self.resolve_in(file, rest, depth + 1),
            "super" => {
                return self
                    .parent(file)
                    .is_some_and(|p| self.resolve_in(&p, rest, depth + 1));
            }
            "crate" => {
                return self
                    .roots_of(file)
                    .iter()
                    .any(|r| self.resolve_in(r, rest, depth + 1));
            }
            _ => {}
        }
        if let Some(child) = self.child(file, first) {
            return self.resolve_in(&child, rest, depth + 1);
        }
        let text = &self.files[file];
        if defines(text, first) {
            return match rest {
                [] => true,
                [m] => self.member(first, m),
                // Past an inline module: taken as it stands.
                _ => declares(text, "mod", first),
            };
        }
        reexports(text)
            .into_iter()
            .filter(|(name, _)| name == first)
            .any(|(_, path)| {
                let mut full: Vec<&str> = path.iter().map(String::as_str).collect();
                full.extend_from_slice(rest);
                self.resolve_use(file, &full, depth + 1)
            })
    }

    /// Whether a `use` path from `file` resolves (another crate's: taken as it stands).
    fn resolve_use(&self, file: &Path, parts: &[&str], depth: usize) -> bool {
        let Some(&first) = parts.first() else {
            return true;
        };
        if matches!(first, "crate" | "self" | "super") || self.child(file, first).is_some() {
            return self.resolve_in(file, parts, depth);
        }
        self.crate_root(first)
            .is_none_or(|r| self.resolve_in(&r, &parts[1..], depth))
    }

    /// Why `parts` (written under headings naming `crates`) does not resolve, if it does
    /// not; `None` too when it is another crate's path.
    pub fn unresolved(&self, parts: &[&str], crates: &[PathBuf]) -> Option<String> {
        let first = parts[0];
        let starts: Vec<PathBuf> = if first == "crate" {
            if crates.is_empty() {
                self.packages
                    .iter()
                    .flat_map(|p| self.crate_root(p.lib.as_deref()?))
                    .collect()
            } else {
                crates.to_vec()
            }
        } else if let Some(r) = self.crate_root(first) {
            vec![r]
        } else if camel(first) {
            if !self.types.contains(first) {
                return Some(format!("no type `{first}` in the workspace"));
            }
            return (!parts[1..].iter().all(|m| self.member(first, m)))
                .then(|| format!("`{first}` has no member `{}`", parts[1..].join("::")));
        } else {
            let modules = self.modules_named(first);
            if modules.is_empty() {
                return None;
            }
            return (!modules.iter().any(|m| self.resolve_in(m, &parts[1..], 0)))
                .then(|| format!("no module `{first}` has `{}`", parts[1..].join("::")));
        };
        let rest = if first == "crate" || self.crate_root(first).is_some() {
            &parts[1..]
        } else {
            parts
        };
        (!starts.iter().any(|s| self.resolve_in(s, rest, 0)))
            .then(|| format!("`{}` is not in `{first}`", rest.join("::")))
    }
}

// ---- Paths ---------------------------------------------------------------------------

/// Whether `rel` (a `*` allowed in its last part) names something under `base`.
pub fn exists(base: &Path, rel: &str) -> bool {
    let rel = rel.trim_start_matches("./");
    let (dir, last) = match rel.trim_end_matches('/').rsplit_once('/') {
        Some((d, l)) => (base.join(d), l),
        None => (base.to_path_buf(), rel.trim_end_matches('/')),
    };
    if !last.contains('*') {
        return base.join(rel).exists();
    }
    let (pre, post) = last.split_once('*').unwrap_or((last, ""));
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .any(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.len() >= pre.len() + post.len() && n.starts_with(pre) && n.ends_with(post)
        })
}

/// The directories a path written under `headings` may be relative to, after the root:
/// those the headings name (a package's `src/` too), then every package's.
pub fn bases(
    code: &Code,
    headings: &[(usize, Vec<String>)],
    outputs: &[(&str, &str)],
) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let package_dirs =
        |p: &Package| ["", "src", "tests", "benches", "examples"].map(|s| p.dir.join(s));
    let top = code.top();
    for (_, names) in headings {
        for name in names {
            if let Some(p) = code
                .packages
                .iter()
                .find(|p| p.name == *name || p.lib.as_deref() == Some(name))
            {
                out.extend([p.dir.clone(), p.dir.join("src")]);
                continue;
            }
            if path_token(name, &top, outputs) != Some(PathToken::Check) {
                continue;
            }
            let tries = std::iter::once(code.root.clone())
                .chain(code.packages.iter().flat_map(package_dirs));
            for base in tries.collect::<Vec<_>>() {
                let at = base.join(name.trim_end_matches('/'));
                if at.is_dir() {
                    if at.join("Cargo.toml").exists() {
                        out.push(at.join("src"));
                    }
                    out.push(at);
                } else if at.is_file() {
                    out.extend(at.parent().map(Path::to_path_buf));
                }
            }
        }
    }
    out.extend(code.packages.iter().flat_map(package_dirs));
    out
}

/// The library crate roots the headings name (by package, path or crate).
pub fn heading_crates(code: &Code, headings: &[(usize, Vec<String>)]) -> Vec<PathBuf> {
    let named: Vec<&Package> = code
        .packages
        .iter()
        .filter(|p| {
            headings.iter().flat_map(|(_, n)| n).any(|n| {
                *n == p.name
                    || p.lib.as_deref() == Some(n.as_str())
                    || n.trim_end_matches('/')
                        == p.dir
                            .strip_prefix(&code.root)
                            .unwrap_or(&p.dir)
                            .to_string_lossy()
            })
        })
        .collect();
    named
        .iter()
        .filter_map(|p| code.crate_root(p.lib.as_deref()?))
        .collect()
}
