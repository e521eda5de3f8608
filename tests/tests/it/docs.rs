//! The documents kept true: what ARCHITECTURE.md, README.md and `docs/*.md` write in
//! backticks is checked against the repository on every `cargo test`. Each rule fails
//! listing every offender as `FILE:LINE: token: why`.
//!
//! - **Paths** (ARCHITECTURE.md): a code span that is a path (ASCII letters, digits and
//!   `_.-/*`, not a URL) — one with a `/` whose last part has an extension, that ends in
//!   `/` or starts with one of the repository's top-level entries, or a bare file name
//!   with a source extension (`SOURCE_EXTENSIONS` in `roam_tests::docs::markdown`) —
//!   names a file or directory that exists (a `*` in its last part matching at least
//!   one). It is tried against, in turn: the repository's root; the directories the
//!   headings above it name (under a heading naming `tessellate/coherent/` or
//!   `roam-client`, `eval.rs` or `core.rs` means a file there, a package's `src/`
//!   included); every package's directory and its `src/`, `tests/`, `benches/` and
//!   `examples/`. A path with `..` is outside the repository: it fails. Not checked:
//!   absolute paths (URL paths, system files), a path with an upper-case placeholder
//!   part (`DIR/.cache/…`), and the run-time and build outputs [`NOT_IN_THE_REPOSITORY`]
//!   names.
//! - **Rust paths** (ARCHITECTURE.md): `a::b::c` in backticks (the span, or its start up
//!   to a `(`) resolves. Its first part is a workspace crate (`roam_server`, …), `crate`
//!   (the crates the headings above name, else any), a module of the workspace (any
//!   module of that name: `sim::world_core`), or a type (`Type::member`). Each further
//!   part is a child module, an item the module defines (`struct`, `enum`, `trait`,
//!   `type`, `union`, `fn`, `const`, `static`, `mod`, `macro_rules!`) or re-exports (`pub
//!   use`, `pub(crate) use`, followed), or, after a type, a member of it (a method,
//!   constant, field or variant in a file that defines or implements the type). A first
//!   part that is none of these (`std`, `tokio`) starts another crate's path: not checked.
//! - **Type names** (ARCHITECTURE.md): a single CamelCase identifier in backticks
//!   (`ViewerCore`) is a type, trait or enum variant defined in the workspace's sources,
//!   or one [`ELSEWHERE`] names with where it comes from (else write it with its path:
//!   `wgpu::TextureView`).
//! - **Files outside** (every document): no Markdown link or word climbs out of the
//!   repository, and every relative link, and every other word with `../`, names a file
//!   that exists (read from the document's folder).
//! - **Commands** (README.md, ARCHITECTURE.md, `docs/*.md`): every line of a ```` ```sh ````
//!   block and every code span that is a command — a workspace binary (`roam-server`,
//!   `roam-client`, …, or `target/PROFILE/roam-…`), `cargo …`, or a script under
//!   `scripts/` (no extension, or `.sh`), after any `NAME=value` — parses: a binary's
//!   subcommand exists and every `--flag` is among the options its `--help` lists for that
//!   subcommand (for a binary whose `--help` lists none, among the flags its answer
//!   mentions); `cargo`'s `-p` names a package, its `--bin`, `--test` and `--bench` that
//!   package's targets, and `cargo run`'s arguments after `--` are its binary's; a script
//!   exists and is executable; an argument naming a path under one of the repository's
//!   top-level directories (`data/kossou`) exists. Placeholders (`[--hold S]`, `…`) are
//!   words like any other: flags in brackets are checked too. The binaries are those
//!   beside this test (`target/PROFILE/`), built first by cargo when missing or older
//!   than their package's sources.

use std::collections::BTreeSet;

use roam_tests::docs::binaries::Binaries;
use roam_tests::docs::code::{Code, Package, bases, exists, heading_crates, read, root};
use roam_tests::docs::markdown::{
    Cmd, PathToken, camel, commands, path_token, rust_path, shell_lines, spans,
};

/// Paths the documents may name that a checkout does not hold: `(prefix, why)`.
const NOT_IN_THE_REPOSITORY: &[(&str, &str)] = &[
    (
        ".cache/",
        "a data set's cache, written beside it when it is first served",
    ),
    ("web/dist/", "the built page: scripts/build-web makes it"),
    ("target/", "cargo's build output"),
];

/// Type names ARCHITECTURE.md may write bare that are defined outside the workspace:
/// `(name, where)`.
const ELSEWHERE: &[(&str, &str)] = &[
    ("Arc", "std::sync"),
    ("Vec", "std::vec"),
    ("Instant", "std::time, and web_time in the browser"),
    ("Display", "std::fmt"),
    ("ResolvesServerCert", "rustls::server"),
    ("ApplicationHandler", "winit::application"),
    ("TextureView", "wgpu"),
    ("Rg8Unorm", "wgpu::TextureFormat"),
    ("DeTable", "toml::de"),
];

/// Fails listing `offenders` under `rule`, if there are any.
fn check(rule: &str, offenders: Vec<String>) {
    assert!(
        offenders.is_empty(),
        "{rule} ({}):\n  {}",
        offenders.len(),
        offenders.join("\n  ")
    );
}

/// What `target`, written in the document at `doc` (relative to the root), names: the
/// path from the root with its `.` and `..` steps taken, or `None` when it climbs out of
/// the repository.
fn inside(doc: &str, target: &str) -> Option<std::path::PathBuf> {
    use std::path::{Component, Path, PathBuf};
    let dir = Path::new(doc).parent().unwrap_or(Path::new(""));
    let mut out = PathBuf::new();
    for c in dir.join(target).components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                if !out.pop() {
                    return None;
                }
            }
            Component::Normal(n) => out.push(n),
            Component::RootDir | Component::Prefix(_) => return None,
        }
    }
    Some(out)
}

/// The relative targets of `text`'s Markdown links (`[words](target)`, an anchor cut
/// off; web addresses and links within the page left out), with their lines.
fn link_targets(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            let end = rest.find(')').unwrap_or(rest.len());
            let target = rest[..end].split('#').next().unwrap_or("").trim();
            if !target.is_empty() && !target.contains("://") && !target.starts_with("mailto:") {
                out.push((n + 1, target.to_owned()));
            }
            rest = &rest[end..];
        }
    }
    out
}

#[test]
fn every_document_names_only_files_in_the_repository() {
    let root = root();
    let mut bad = Vec::new();
    let mut links = 0;
    for (file, text) in documents() {
        for (line, target) in link_targets(&text) {
            links += 1;
            match inside(&file, &target) {
                None => bad.push(format!("{file}:{line}: {target}: outside the repository")),
                Some(p) if !root.join(&p).exists() => bad.push(format!(
                    "{file}:{line}: {target}: no such file ({})",
                    p.display()
                )),
                Some(_) => {}
            }
        }
        // A `..` path anywhere else (a code span, prose): it must name a file here.
        for (n, l) in text.lines().enumerate() {
            for word in l.split_whitespace().filter(|w| w.contains("../")) {
                let word = word
                    .trim_start_matches(|c: char| "`*_\"'(".contains(c))
                    .trim_end_matches(|c: char| "`*_\"'),.;:".contains(c));
                let target = word.rsplit("](").next().unwrap_or(word);
                let target = target.trim_end_matches(')').split('#').next().unwrap_or("");
                // Read from the document's folder, it must land on a file here.
                if !inside(&file, target).is_some_and(|p| root.join(p).exists()) {
                    bad.push(format!(
                        "{file}:{}: {word}: outside the repository (or no such file)",
                        n + 1
                    ));
                }
            }
        }
    }
    assert!(
        links > 0,
        "no link found in the documents: the reading is broken"
    );
    bad.sort();
    bad.dedup();
    check(
        "documents naming files outside the repository or not in it",
        bad,
    );
}

#[test]
fn the_link_reader_sees_targets_and_what_leaves_the_repository() {
    let md = "See [the spec](docs/spec.md#keys), [web](https://x.org/a.md), [here](#top)\n\
              and [up](../README.md) or [out](../../shared/SPEC.md).\n";
    assert_eq!(
        link_targets(md),
        [
            (1, "docs/spec.md".to_owned()),
            (2, "../README.md".to_owned()),
            (2, "../../shared/SPEC.md".to_owned()),
        ]
    );
    assert_eq!(
        inside("docs/cluster.md", "../README.md"),
        Some("README.md".into())
    );
    assert_eq!(inside("docs/cluster.md", "../../shared/SPEC.md"), None);
    assert_eq!(inside("README.md", "../shared/SPEC.md"), None);
    assert_eq!(
        inside("README.md", "docs/./spec.md"),
        Some("docs/spec.md".into())
    );
}

fn architecture() -> (String, String) {
    let name = "ARCHITECTURE.md".to_owned();
    let text = read(&root().join(&name));
    (name, text)
}

#[test]
fn every_path_in_the_architecture_exists() {
    let code = Code::load();
    let top = code.top();
    let (file, text) = architecture();
    let mut bad = Vec::new();
    for s in spans(&text) {
        let why = match path_token(&s.text, &top, NOT_IN_THE_REPOSITORY) {
            Some(PathToken::Check) => {
                let tries = std::iter::once(code.root.clone()).chain(bases(
                    &code,
                    &s.headings,
                    NOT_IN_THE_REPOSITORY,
                ));
                if tries.into_iter().any(|b| exists(&b, &s.text)) {
                    continue;
                }
                "no such file or directory (from the root, the headings' directories or a package's)"
            }
            Some(PathToken::Outside) => "outside the repository",
            _ => continue,
        };
        bad.push(format!("{file}:{}: {}: {why}", s.line, s.text));
    }
    bad.dedup();
    check(
        "paths in ARCHITECTURE.md that are not in the repository",
        bad,
    );
}

#[test]
fn every_rust_path_in_the_architecture_resolves() {
    let code = Code::load();
    let (file, text) = architecture();
    let mut bad = Vec::new();
    for s in spans(&text) {
        let Some(parts) = rust_path(&s.text) else {
            continue;
        };
        let crates = heading_crates(&code, &s.headings);
        if let Some(why) = code.unresolved(&parts, &crates) {
            bad.push(format!("{file}:{}: {}: {why}", s.line, s.text));
        }
    }
    check("Rust paths in ARCHITECTURE.md that do not resolve", bad);
}

#[test]
fn every_type_name_in_the_architecture_is_defined() {
    let code = Code::load();
    let (file, text) = architecture();
    let bad = spans(&text)
        .into_iter()
        .filter(|s| camel(&s.text) && !code.types.contains(&s.text))
        .filter(|s| !ELSEWHERE.iter().any(|(n, _)| *n == s.text))
        .map(|s| {
            format!(
                "{file}:{}: {}: defined nowhere in the workspace",
                s.line, s.text
            )
        })
        .collect();
    check(
        "type names in ARCHITECTURE.md that the code does not define",
        bad,
    );
}

// ---- Commands, checked ---------------------------------------------------------------

/// README.md, ARCHITECTURE.md and `docs/*.md`: `(name, text)`.
fn documents() -> Vec<(String, String)> {
    let root = root();
    let mut names = vec!["README.md".to_owned(), "ARCHITECTURE.md".to_owned()];
    let mut docs: Vec<String> = std::fs::read_dir(root.join("docs"))
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".md"))
        .map(|n| format!("docs/{n}"))
        .collect();
    docs.sort();
    names.extend(docs);
    names
        .into_iter()
        .map(|n| {
            let text = read(&root.join(&n));
            (n, text)
        })
        .collect()
}

/// Arguments naming a path under one of the repository's top-level directories that is
/// not there.
fn missing_paths(code: &Code, args: &[String]) -> Vec<String> {
    let top = code.top();
    args.iter()
        .filter(|a| !a.starts_with('-') && a.contains('/'))
        .filter(|a| path_token(a, &top, NOT_IN_THE_REPOSITORY) == Some(PathToken::Check))
        .filter(|a| top.contains(a.trim_start_matches("./").split('/').next().unwrap_or("")))
        .filter(|a| !exists(&code.root, a))
        .map(|a| format!("{a}: no such file or directory"))
        .collect()
}

/// What is wrong with `cargo sub args…` (its package and targets; a `run`'s binary and
/// arguments).
fn check_cargo(code: &Code, bins: &mut Binaries, sub: &str, args: &[String]) -> Vec<String> {
    let (own, rest) = match args.iter().position(|a| a == "--") {
        Some(i) => (&args[..i], &args[i + 1..]),
        None => (args, &args[..0]),
    };
    let value = |names: &[&str]| -> Vec<String> {
        let mut out = Vec::new();
        for (i, a) in own.iter().enumerate() {
            for n in names {
                if a == n {
                    out.extend(own.get(i + 1).cloned());
                } else if let Some(v) = a.strip_prefix(&format!("{n}=")) {
                    out.push(v.to_owned());
                }
            }
        }
        out
    };
    let mut bad = Vec::new();
    let named = value(&["-p", "--package"]);
    let mut pkgs: Vec<&Package> = Vec::new();
    for n in &named {
        match code.packages.iter().find(|p| p.name == *n) {
            Some(p) => pkgs.push(p),
            None => bad.push(format!("-p {n}: no such package")),
        }
    }
    let scope: Vec<&Package> = if named.is_empty() {
        code.packages.iter().collect()
    } else {
        pkgs
    };
    for (flag, targets) in [
        (
            "--bin",
            &(|p: &Package| p.bins.clone()) as &dyn Fn(&Package) -> Vec<String>,
        ),
        ("--test", &|p: &Package| p.tests.clone()),
        ("--bench", &|p: &Package| p.benches.clone()),
    ] {
        for t in value(&[flag]) {
            if !scope.iter().any(|p| targets(p).contains(&t)) {
                bad.push(format!("{flag} {t}: no such target"));
            }
        }
    }
    if sub == "run" && bad.is_empty() {
        let bin = value(&["--bin"]).pop().or_else(|| match scope.as_slice() {
            [p] if p.bins.len() == 1 => Some(p.bins[0].clone()),
            _ => None,
        });
        match bin {
            Some(b) => {
                bad.extend(bins.check(&b, rest));
                bad.extend(missing_paths(code, rest));
            }
            None => bad.push("which binary `cargo run` runs is not said".to_owned()),
        }
    }
    bad
}

#[test]
fn every_command_in_the_documents_parses() {
    let code = Code::load();
    let mut bins = Binaries::new(&code);
    let binaries: BTreeSet<String> = code.packages.iter().flat_map(|p| p.bins.clone()).collect();
    let (mut bad, mut checked) = (Vec::new(), 0);
    for (file, text) in documents() {
        let written = shell_lines(&text)
            .into_iter()
            .chain(spans(&text).into_iter().map(|s| (s.line, s.text)));
        for (line, written) in written {
            for cmd in commands(&written, &binaries) {
                checked += 1;
                let why = match &cmd {
                    Cmd::Binary(b, args) => {
                        let mut w = bins.check(b, args);
                        w.extend(missing_paths(&code, args));
                        w
                    }
                    Cmd::Cargo(sub, args) => check_cargo(&code, &mut bins, sub, args),
                    Cmd::Script(s, args) => {
                        let mut w = missing_paths(&code, args);
                        let mode = std::fs::metadata(code.root.join(s))
                            .map(|m| std::os::unix::fs::PermissionsExt::mode(&m.permissions()));
                        match mode {
                            Err(_) => w.push("no such script".to_owned()),
                            Ok(m) if m & 0o111 == 0 => {
                                w.push("the script is not executable".to_owned())
                            }
                            Ok(_) => {}
                        }
                        // A script's flags are its own words: each written must be in it.
                        let text = std::fs::read_to_string(code.root.join(s)).unwrap_or_default();
                        w.extend(
                            args.iter()
                                .filter(|a| a.starts_with("--") && a.len() > 2)
                                .map(|a| a.split('=').next().unwrap_or(a))
                                .filter(|flag| !text.contains(flag))
                                .map(|flag| format!("{flag}: the script has no such flag")),
                        );
                        w
                    }
                };
                bad.extend(
                    why.into_iter()
                        .map(|w| (file.clone(), line, written.clone(), w)),
                );
            }
        }
    }
    assert!(
        checked > 0,
        "no command found in the documents: the reading is broken"
    );
    bad.sort();
    bad.dedup();
    let bad = bad
        .into_iter()
        .map(|(file, line, written, why)| format!("{file}:{line}: {written}: {why}"))
        .collect();
    check("commands in the documents that do not parse", bad);
}

/// The readers on a small document: what they find, and the prose they pass over.
mod reading {
    use std::collections::BTreeSet;

    use roam_tests::docs::code::{declares, reexports, variants};
    use roam_tests::docs::markdown::{
        Cmd, PathToken, camel, commands, flags, help_flags, path_token, rust_path, shell_lines,
        spans,
    };

    const DOC: &str = "\
# Title

Prose with `server/src/net/mod.rs`, `core.rs`, a word `budget`, a unit `B/tri`,
`roam_server::net::Server`, `Type::method(a, b)`, `ViewerCore`, `HTTP`, `tick()`,
`../shared/SPEC.md`, `DIR/.cache/x.bin`, `/proc/meminfo`, `web/dist/index.html`,
`https://example.com/a.rs`, ``a `tick` inside``, and an open ` backtick.

### `client/` (`roam-client`)

A command across a line break: `roam-server serve
data/kossou --web ADDR`.

```sh
roam-server check data/kossou   # a comment
PROFILE=measure scripts/lossy.sh 40/0 \\
  --json
cargo run --release -p roam-server -- serve data/kossou --hold 5
sudo apt-get install -y x && scripts/build-web
```

```text
roam-server not-a-command --nope
```
";

    fn top() -> BTreeSet<String> {
        ["server", "client", "data", "scripts", "web"]
            .map(str::to_owned)
            .into()
    }

    const OUTPUTS: &[(&str, &str)] = &[("web/dist/", "built")];

    fn texts() -> Vec<String> {
        spans(DOC).into_iter().map(|s| s.text).collect()
    }

    #[test]
    fn finds_code_spans_with_their_lines_and_headings() {
        let s = spans(DOC);
        assert_eq!(s[0].text, "server/src/net/mod.rs");
        assert_eq!(s[0].line, 3);
        assert!(texts().contains(&"a `tick` inside".to_owned()));
        assert!(
            !texts().iter().any(|t| t.contains("backtick")),
            "{:?}",
            texts()
        );
        let across = s
            .iter()
            .find(|s| s.text.starts_with("roam-server serve"))
            .expect("the span across the line break");
        assert_eq!(across.text, "roam-server serve data/kossou --web ADDR");
        assert_eq!(across.line, 10);
        let names: Vec<&String> = across.headings.iter().flat_map(|(_, n)| n).collect();
        assert_eq!(names, ["client/", "roam-client"]);
        assert!(s[0].headings.iter().all(|(_, n)| n.is_empty()));
        // Nothing from inside the fenced blocks.
        assert!(!texts().iter().any(|t| t.contains("not-a-command")));
    }

    #[test]
    fn finds_paths_and_passes_over_prose() {
        let kinds: Vec<(String, Option<PathToken>)> = texts()
            .into_iter()
            .map(|t| {
                let k = path_token(&t, &top(), OUTPUTS);
                (t, k)
            })
            .collect();
        let kind = |t: &str| {
            let found = kinds.iter().find(|(s, _)| s == t);
            found.unwrap_or_else(|| panic!("no span {t}")).1.as_ref()
        };
        assert_eq!(kind("server/src/net/mod.rs"), Some(&PathToken::Check));
        assert_eq!(kind("core.rs"), Some(&PathToken::Check));
        assert_eq!(kind("client/"), Some(&PathToken::Check));
        assert_eq!(kind("../shared/SPEC.md"), Some(&PathToken::Outside));
        assert_eq!(kind("DIR/.cache/x.bin"), Some(&PathToken::Skip));
        assert_eq!(kind("web/dist/index.html"), Some(&PathToken::Skip));
        for prose in [
            "budget",
            "B/tri",
            "https://example.com/a.rs",
            "roam-client",
            "ViewerCore",
            "tick()",
            "/proc/meminfo",
        ] {
            assert_eq!(kind(prose), None, "{prose}");
        }
    }

    #[test]
    fn finds_rust_paths_and_type_names() {
        let paths: Vec<Vec<&str>> = ["roam_server::net::Server", "Type::method(a, b)"]
            .iter()
            .filter_map(|t| rust_path(t))
            .collect();
        assert_eq!(
            paths,
            [vec!["roam_server", "net", "Server"], vec!["Type", "method"]]
        );
        for not in [
            "ViewerCore",
            "tick()",
            "a::b c",
            "Mapped { x: a::B }",
            "B/tri",
        ] {
            assert_eq!(rust_path(not), None, "{not}");
        }
        let camels: Vec<String> = texts().into_iter().filter(|t| camel(t)).collect();
        assert_eq!(camels, ["ViewerCore"]);
    }

    #[test]
    fn finds_commands_and_their_flags() {
        let lines = shell_lines(DOC);
        let starts: Vec<usize> = lines.iter().map(|(l, _)| *l).collect();
        assert_eq!(starts, [14, 15, 17, 18]);
        assert_eq!(lines[0].1, "roam-server check data/kossou");
        let bins: BTreeSet<String> = ["roam-server", "roam-client"].map(str::to_owned).into();
        let words = |w: &[&str]| w.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let found: Vec<Cmd> = lines.iter().flat_map(|(_, l)| commands(l, &bins)).collect();
        assert_eq!(
            found,
            [
                Cmd::Binary("roam-server".into(), words(&["check", "data/kossou"])),
                Cmd::Script("scripts/lossy.sh".into(), words(&["40/0", "--json"])),
                Cmd::Cargo(
                    "run".into(),
                    words(&[
                        "--release",
                        "-p",
                        "roam-server",
                        "--",
                        "serve",
                        "data/kossou",
                        "--hold",
                        "5"
                    ])
                ),
                Cmd::Script("scripts/build-web".into(), vec![]),
            ]
        );
        // A binary by its build path; prose is no command.
        assert_eq!(
            commands("target/release/roam-client --local data/kossou", &bins),
            [Cmd::Binary(
                "roam-client".into(),
                words(&["--local", "data/kossou"])
            )]
        );
        assert_eq!(commands("the roam-server binary", &bins), []);
        assert_eq!(commands("scripts/capacity-drive.txt", &bins), []);
        assert_eq!(commands("scripts/", &bins), []);
        assert_eq!(
            flags(&words(&[
                "serve",
                "--web",
                "ADDR",
                "[--hold",
                "S]",
                "--token-file=F",
                "--"
            ])),
            ["web", "hold", "token-file"]
        );
    }

    #[test]
    fn reads_the_options_a_help_lists() {
        let help = "\
Usage: roam-client [OPTIONS]

Options:
      --connect <CONNECT>
          The server's address (see `--token-file`)
  -h, --help
          Print help
      --frames <FRAMES>  Frames to receive [default: 300]
";
        let got: Vec<String> = help_flags(help).into_iter().collect();
        assert_eq!(got, ["connect", "frames", "help"]);
    }

    #[test]
    fn reads_definitions_and_re_exports() {
        let text = "\
pub use a::{b, c::D as E};
pub(crate) use crate::x::{
    Y,
};
use private::Z;
pub enum K {
    /// A doc line.
    A,
    B(u8),
    #[default]
    C { x: u8 },
    D = 3,
}
fn taken() {}
";
        let names: Vec<(String, Vec<String>)> = reexports(text);
        let want = |n: &str, p: &[&str]| (n.to_owned(), p.iter().map(|s| s.to_string()).collect());
        assert_eq!(
            names,
            [
                want("b", &["a", "b"]),
                want("E", &["a", "c", "D"]),
                want("Y", &["crate", "x", "Y"])
            ]
        );
        assert_eq!(variants(text), ["A", "B", "C", "D"]);
        assert!(declares(text, "fn", "taken") && !declares(text, "fn", "take"));
        assert!(declares(text, "enum", "K"));
    }
}
