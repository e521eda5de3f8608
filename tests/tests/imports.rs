//! Imports: the graph of references between the workspace's source files has no circle,
//! and the server's layers refer only downwards.
//!
//! Every crate of the workspace (each package's library, binaries, tests, benchmarks,
//! examples and build script) is walked from its root through its `mod` declarations, and
//! every reference from one file to another is an edge: a `use` (`crate::`, `super::`,
//! `self::`, a child module's name, another workspace crate's name), a `pub use`
//! re-export, a glob, and an inline path such as `crate::a::b::f()`. A path is resolved
//! through re-exports to the file that defines its item or module. Comments (doc links
//! among them) are not references.
//!
//! A module's file and its children are not a circle: the parent's `mod` declarations and
//! its `pub use` re-exports of what its descendants define are not edges. Anything else
//! the parent uses of its children is, so a parent that calls into a child which calls
//! back into the parent is a circle.
//!
//! The server's layers, lowest first, are [`SERVER_LAYERS`].

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The server's layers, lowest first: a file may refer to files of its own layer and of
/// the layers below it, never above. The library's root (`lib.rs`) only declares the
/// modules and re-exports, and belongs to none.
///
/// - `terrain`: data sets, heights, colours, the variance tree;
/// - `tessellate`: the ROAM tessellators over the terrain;
/// - `sim`: the vehicles, the world and its recordings, over the terrain;
/// - `viewer`: the per-viewer and admission decisions, over the tessellators and the world;
/// - `net` and `web`: the I/O shells (QUIC, WebTransport, NATS, the page server);
/// - `cli` and `main.rs`: the command line, over all of it.
const SERVER_LAYERS: &[&[&str]] = &[
    &["server/src/terrain/"],
    &["server/src/tessellate/"],
    &["server/src/sim/"],
    &["server/src/viewer/"],
    &["server/src/net/", "server/src/web/"],
    &["server/src/cli/", "server/src/main.rs"],
];

/// The packages walked, relative to the workspace root.
const PACKAGES: &[&str] = &["protocol", "server", "client", "link", "tests", "web"];

// ---------------------------------------------------------------------------------------
// Tokens: identifiers, `::`, string literals (for `#[path = "…"]`) and single characters,
// each with its line; comments, characters and lifetimes are dropped.

#[derive(Clone, Debug, PartialEq)]
enum Tok {
    Ident(String),
    Str(String),
    PathSep,
    Punct(char),
}

#[derive(Clone, Debug)]
struct Token {
    tok: Tok,
    line: usize,
}

fn lex(text: &str) -> Vec<Token> {
    let c: Vec<char> = text.chars().collect();
    let (mut i, mut line, mut out) = (0, 1, Vec::new());
    let at = |i: usize| c.get(i).copied().unwrap_or('\0');
    while i < c.len() {
        let ch = c[i];
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch.is_whitespace() {
            i += 1;
        } else if ch == '/' && at(i + 1) == '/' {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if ch == '/' && at(i + 1) == '*' {
            let mut depth = 0;
            loop {
                if i >= c.len() {
                    break;
                } else if c[i] == '/' && at(i + 1) == '*' {
                    depth += 1;
                    i += 2;
                } else if c[i] == '*' && at(i + 1) == '/' {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    line += usize::from(c[i] == '\n');
                    i += 1;
                }
            }
        } else if ch == '"' {
            let start_line = line;
            let mut s = String::new();
            i += 1;
            while i < c.len() && c[i] != '"' {
                if c[i] == '\\' {
                    s.push(c[i]);
                    i += 1;
                }
                line += usize::from(at(i) == '\n');
                s.push(at(i));
                i += 1;
            }
            i += 1;
            out.push(Token {
                tok: Tok::Str(s),
                line: start_line,
            });
        } else if ch == '\'' {
            if at(i + 1) == '\\' {
                // An escaped character: up to the closing quote.
                i += 2;
                while i < c.len() && c[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if at(i + 2) == '\'' {
                i += 3;
            } else {
                // A lifetime or label: the quote and its name.
                i += 1;
                while at(i).is_alphanumeric() || at(i) == '_' {
                    i += 1;
                }
            }
        } else if ch.is_alphabetic() || ch == '_' {
            let start = i;
            while at(i).is_alphanumeric() || at(i) == '_' {
                i += 1;
            }
            let word: String = c[start..i].iter().collect();
            let raw = matches!(word.as_str(), "r" | "br" | "cr");
            let prefix = raw || matches!(word.as_str(), "b" | "c");
            if raw && (at(i) == '#' || at(i) == '"') {
                let mut hashes = 0;
                while at(i + hashes) == '#' {
                    hashes += 1;
                }
                if at(i + hashes) == '"' {
                    // A raw string: up to the quote followed by as many hashes.
                    let start_line = line;
                    i += hashes + 1;
                    let from = i;
                    while i < c.len() && !(c[i] == '"' && (1..=hashes).all(|h| at(i + h) == '#')) {
                        line += usize::from(c[i] == '\n');
                        i += 1;
                    }
                    let s: String = c[from..i.min(c.len())].iter().collect();
                    i += hashes + 1;
                    out.push(Token {
                        tok: Tok::Str(s),
                        line: start_line,
                    });
                    continue;
                }
                // A raw identifier: `r#name`.
                i += 1;
                continue;
            }
            if prefix && (at(i) == '"' || at(i) == '\'') {
                continue; // the literal that follows is lexed as one.
            }
            out.push(Token {
                tok: Tok::Ident(word),
                line,
            });
        } else if ch.is_ascii_digit() {
            while at(i).is_alphanumeric() || at(i) == '_' {
                i += 1;
            }
        } else if ch == ':' && at(i + 1) == ':' {
            out.push(Token {
                tok: Tok::PathSep,
                line,
            });
            i += 2;
        } else {
            out.push(Token {
                tok: Tok::Punct(ch),
                line,
            });
            i += 1;
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// Modules: each crate's tree, the names each module defines, declares and imports.

type ModId = usize;

/// A `use` (or an inline path): its segments, what it binds, where it is.
#[derive(Clone, Debug)]
struct Use {
    segs: Vec<String>,
    /// `None` for a glob or an inline path; `Some("_")` binds nothing.
    name: Option<String>,
    inline: bool,
    public: bool,
    line: usize,
}

#[derive(Debug, Default)]
struct Module {
    file: PathBuf,
    parent: Option<ModId>,
    /// The crate's root module.
    root: ModId,
    children: BTreeMap<String, ModId>,
    items: BTreeSet<String>,
    uses: Vec<Use>,
}

/// One reference from a file to another.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Edge {
    from: PathBuf,
    line: usize,
    to: PathBuf,
    path: String,
}

/// Where a path leads: a module, or an item defined in a file.
#[derive(Clone, Copy, Debug)]
enum Res {
    Module(ModId),
    Item(ModId),
}

#[derive(Default)]
struct Workspace {
    modules: Vec<Module>,
    /// The workspace's libraries by crate name (`roam_protocol`), to their root modules.
    libs: BTreeMap<String, ModId>,
    /// References found while reading, resolved once every crate is read: the module they
    /// are written in and the reference.
    pending: Vec<(ModId, Use)>,
    /// Files a `mod` declaration names that do not exist.
    missing: Vec<String>,
}

const ITEM_KEYWORDS: &[&str] = &[
    "fn", "struct", "enum", "trait", "type", "const", "static", "union",
];

impl Workspace {
    fn new_module(&mut self, file: &Path, parent: Option<ModId>) -> ModId {
        let id = self.modules.len();
        let root = parent.map_or(id, |p| self.modules[p].root);
        self.modules.push(Module {
            file: file.to_path_buf(),
            parent,
            root,
            ..Module::default()
        });
        id
    }

    /// Reads a crate from its root file; `lib` names it if it is a library.
    fn add_crate(&mut self, files: &BTreeMap<PathBuf, String>, root: &Path, lib: Option<&str>) {
        let id = self.new_module(root, None);
        if let Some(name) = lib {
            self.libs.insert(name.to_string(), id);
        }
        self.read_file(files, id, true);
    }

    /// Reads module `m`'s file: its items, `mod`s (reading their files in turn), `use`s and
    /// inline paths. `owns_dir`: whether its children's files sit beside it (a crate root,
    /// `mod.rs` or a file loaded by `#[path]`) rather than in a folder named after it.
    fn read_file(&mut self, files: &BTreeMap<PathBuf, String>, m: ModId, owns_dir: bool) {
        let file = self.modules[m].file.clone();
        let Some(text) = files.get(&file) else {
            self.missing.push(file.display().to_string());
            return;
        };
        let toks = lex(text);
        let dir = file.parent().unwrap_or(Path::new("")).to_path_buf();
        let base = if owns_dir {
            dir.clone()
        } else {
            dir.join(file.file_stem().expect("a source file has a name"))
        };
        // The inline modules open: the module, the brace depth its items sit at, and the
        // folder its file children sit in.
        let mut scopes: Vec<(ModId, usize, PathBuf)> = vec![(m, 0, base)];
        let mut depth = 0;
        let mut path_attr: Option<String> = None;
        let mut i = 0;
        let ident = |i: usize| match toks.get(i) {
            Some(Token {
                tok: Tok::Ident(s), ..
            }) => Some(s.as_str()),
            _ => None,
        };
        let punct = |i: usize, p: char| matches!(toks.get(i), Some(t) if t.tok == Tok::Punct(p));
        let sep = |i: usize| matches!(toks.get(i), Some(t) if t.tok == Tok::PathSep);
        while i < toks.len() {
            let (cur, item_depth, cur_dir) = scopes.last().expect("the file's scope").clone();
            let top = depth == item_depth;
            match &toks[i].tok {
                Tok::Punct('{') => depth += 1,
                Tok::Punct('}') => {
                    depth -= 1;
                    if depth < item_depth {
                        scopes.pop();
                    }
                    path_attr = None;
                }
                Tok::Punct(';') => path_attr = None,
                Tok::Punct('#') if punct(i + 1, '[') && ident(i + 2) == Some("path") => {
                    if let Some(Token {
                        tok: Tok::Str(s), ..
                    }) = toks.get(i + 4)
                    {
                        path_attr = Some(s.clone());
                    }
                }
                Tok::Ident(w) if w == "mod" && top => {
                    if let Some(name) = ident(i + 1) {
                        let name = name.to_string();
                        if punct(i + 2, ';') {
                            let (path, owns) = match path_attr.take() {
                                Some(p) => (cur_dir_of(&dir, &scopes, &p), true),
                                None => {
                                    let flat = cur_dir.join(format!("{name}.rs"));
                                    if files.contains_key(&flat) {
                                        (flat, false)
                                    } else {
                                        (cur_dir.join(&name).join("mod.rs"), true)
                                    }
                                }
                            };
                            let child = self.new_module(&path, Some(cur));
                            self.modules[cur].children.insert(name, child);
                            self.read_file(files, child, owns);
                            i += 3;
                            continue;
                        } else if punct(i + 2, '{') {
                            let child = self.new_module(&file, Some(cur));
                            self.modules[cur].children.insert(name.clone(), child);
                            depth += 1;
                            scopes.push((child, depth, cur_dir.join(&name)));
                            i += 3;
                            continue;
                        }
                    }
                }
                Tok::Ident(w) if w == "use" && !sep(i.wrapping_sub(1)) => {
                    // `pub use` or `pub(…) use`.
                    let mut k = i.wrapping_sub(1);
                    if punct(k, ')') {
                        while k < toks.len() && !punct(k, '(') {
                            k = k.wrapping_sub(1);
                        }
                        k = k.wrapping_sub(1);
                    }
                    let public = ident(k) == Some("pub");
                    let mut leaves = Vec::new();
                    let end = use_tree(&toks, i + 1, Vec::new(), &mut leaves);
                    for mut u in leaves {
                        u.public = public && top;
                        if top {
                            self.modules[cur].uses.push(u.clone());
                        }
                        self.pending.push((cur, u));
                    }
                    i = end;
                    continue;
                }
                Tok::Ident(w) if w == "macro_rules" && top && punct(i + 1, '!') => {
                    if let Some(name) = ident(i + 2) {
                        self.modules[cur].items.insert(name.to_string());
                    }
                }
                Tok::Ident(w) if top && ITEM_KEYWORDS.contains(&w.as_str()) => {
                    let mut k = i + 1;
                    while matches!(ident(k), Some("fn" | "unsafe" | "async" | "extern")) {
                        k += 1;
                    }
                    if let Some(name) = ident(k) {
                        self.modules[cur].items.insert(name.to_string());
                    }
                }
                Tok::Ident(w)
                    if sep(i + 1)
                        && !sep(i.wrapping_sub(1))
                        && ident(i.wrapping_sub(1)) != Some("in") =>
                {
                    // An inline path: its identifiers joined by `::`.
                    let mut segs = vec![w.clone()];
                    let mut k = i + 1;
                    while sep(k) {
                        match ident(k + 1) {
                            Some(s) => segs.push(s.to_string()),
                            None => break,
                        }
                        k += 2;
                    }
                    if segs.len() > 1 {
                        let line = toks[i].line;
                        let u = Use {
                            segs,
                            name: None,
                            inline: true,
                            public: false,
                            line,
                        };
                        self.pending.push((cur, u));
                    }
                    i = k;
                    continue;
                }
                _ => {}
            }
            i += 1;
        }
    }

    /// The module a path's first segment names, from module `m`.
    fn first(&self, m: ModId, seg: &str, guard: usize) -> Option<Res> {
        match seg {
            "crate" => Some(Res::Module(self.modules[m].root)),
            "self" => Some(Res::Module(m)),
            "super" => self.modules[m].parent.map(Res::Module),
            _ => self
                .lookup(m, seg, guard)
                .or_else(|| self.libs.get(seg).map(|&r| Res::Module(r))),
        }
    }

    /// What `name` means in module `m`: a child module, an item it defines, or what it
    /// imports under that name (by name or by glob).
    fn lookup(&self, m: ModId, name: &str, guard: usize) -> Option<Res> {
        if guard > 32 {
            return None;
        }
        let module = &self.modules[m];
        if let Some(&c) = module.children.get(name) {
            return Some(Res::Module(c));
        }
        if module.items.contains(name) {
            return Some(Res::Item(m));
        }
        for u in &module.uses {
            if u.name.as_deref() == Some(name) {
                if let Some(r) = self.resolve(m, &u.segs, guard + 1) {
                    return Some(r);
                }
            }
        }
        for u in module.uses.iter().filter(|u| u.name.is_none() && !u.inline) {
            if let Some(Res::Module(g)) = self.resolve(m, &u.segs, guard + 1) {
                if g != m {
                    if let Some(r) = self.lookup(g, name, guard + 1) {
                        return Some(r);
                    }
                }
            }
        }
        None
    }

    /// Where `segs`, written in module `m`, leads; `None` outside the workspace.
    fn resolve(&self, m: ModId, segs: &[String], guard: usize) -> Option<Res> {
        let mut at = self.first(m, segs.first()?, guard)?;
        for seg in &segs[1..] {
            at = match at {
                Res::Item(_) => return Some(at),
                Res::Module(here) if seg == "super" => Res::Module(self.modules[here].parent?),
                // A name not found (made by a macro, say) is taken to live in the module.
                Res::Module(here) => self.lookup(here, seg, guard).unwrap_or(Res::Item(here)),
            };
        }
        Some(at)
    }

    /// Whether module `d` is `a` or below it.
    fn descends(&self, mut d: ModId, a: ModId) -> bool {
        loop {
            if d == a {
                return true;
            }
            match self.modules[d].parent {
                Some(p) => d = p,
                None => return false,
            }
        }
    }

    /// Every reference from one file to another, but a module's `pub use` of what its own
    /// descendants define.
    fn edges(&self) -> BTreeSet<Edge> {
        let mut out = BTreeSet::new();
        for (m, u) in &self.pending {
            // An inline path counts from the crate, a module or a library: one from a name a
            // `use` binds is that `use`'s reference, already counted.
            let first = u.segs[0].as_str();
            if u.inline
                && !matches!(first, "crate" | "super" | "self")
                && !self.modules[*m].children.contains_key(first)
                && !self.libs.contains_key(first)
            {
                continue;
            }
            let Some(res) = self.resolve(*m, &u.segs, 0) else {
                continue;
            };
            let (Res::Module(t) | Res::Item(t)) = res;
            let from = &self.modules[*m].file;
            let to = &self.modules[t].file;
            if from == to || (u.public && self.descends(t, *m)) {
                continue;
            }
            out.insert(Edge {
                from: from.clone(),
                line: u.line,
                to: to.clone(),
                path: u.segs.join("::")
                    + if u.name.is_none() && !u.inline {
                        "::*"
                    } else {
                        ""
                    },
            });
        }
        out
    }

    /// The files read, every crate's.
    fn files(&self) -> BTreeSet<PathBuf> {
        self.modules.iter().map(|m| m.file.clone()).collect()
    }
}

/// The file `#[path = "p"]` names, from a file in `dir` with inline modules `scopes` open.
fn cur_dir_of(dir: &Path, scopes: &[(ModId, usize, PathBuf)], p: &str) -> PathBuf {
    if scopes.len() > 1 {
        scopes.last().expect("an inline module").2.join(p)
    } else {
        dir.join(p)
    }
}

/// Parses the use tree starting at token `i` (after `use`) under `prefix`, pushing its
/// leaves; returns the token after the tree (after the `;` for a whole declaration).
fn use_tree(toks: &[Token], mut i: usize, prefix: Vec<String>, out: &mut Vec<Use>) -> usize {
    let mut segs = prefix;
    let line = toks.get(i).map_or(0, |t| t.line);
    loop {
        match toks.get(i).map(|t| &t.tok) {
            Some(Tok::PathSep) => i += 1,
            Some(Tok::Ident(s)) if s == "as" => {
                if segs.last().is_some_and(|s| s == "self") {
                    segs.pop();
                }
                let name = match toks.get(i + 1).map(|t| &t.tok) {
                    Some(Tok::Ident(n)) => n.clone(),
                    _ => "_".into(),
                };
                out.push(leaf(segs, Some(name), line));
                return skip_to_end(toks, i + 2);
            }
            Some(Tok::Ident(s)) => {
                segs.push(s.clone());
                i += 1;
            }
            Some(Tok::Punct('*')) => {
                out.push(leaf(segs, None, line));
                return skip_to_end(toks, i + 1);
            }
            Some(Tok::Punct('{')) => {
                i += 1;
                loop {
                    match toks.get(i).map(|t| &t.tok) {
                        Some(Tok::Punct('}')) => return skip_to_end(toks, i + 1),
                        Some(Tok::Punct(',')) => i += 1,
                        None => return i,
                        _ => i = use_tree(toks, i, segs.clone(), out),
                    }
                }
            }
            _ => {
                if segs.last().is_some_and(|s| s == "self") {
                    segs.pop();
                }
                let name = segs.last().cloned();
                if name.is_some() {
                    out.push(leaf(segs, name, line));
                }
                return skip_to_end(toks, i);
            }
        }
    }
}

fn leaf(segs: Vec<String>, name: Option<String>, line: usize) -> Use {
    Use {
        segs,
        name,
        inline: false,
        public: false,
        line,
    }
}

/// Past a tree's end: a `;` is consumed, a `,` or `}` left to the enclosing group.
fn skip_to_end(toks: &[Token], i: usize) -> usize {
    match toks.get(i).map(|t| &t.tok) {
        Some(Tok::Punct(';')) => i + 1,
        _ => i,
    }
}

// ---------------------------------------------------------------------------------------
// Circles: the strongly connected components of more than one file.

/// The graph's strongly connected components of more than one file (Tarjan's), each
/// sorted, in order.
fn circles(edges: &BTreeSet<Edge>) -> Vec<Vec<PathBuf>> {
    let mut next: BTreeMap<&Path, BTreeSet<&Path>> = BTreeMap::new();
    for e in edges {
        next.entry(&e.from).or_default().insert(&e.to);
        next.entry(&e.to).or_default();
    }
    struct State<'a> {
        next: &'a BTreeMap<&'a Path, BTreeSet<&'a Path>>,
        index: BTreeMap<&'a Path, usize>,
        low: BTreeMap<&'a Path, usize>,
        stack: Vec<&'a Path>,
        on_stack: BTreeSet<&'a Path>,
        out: Vec<Vec<PathBuf>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a Path) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on_stack.insert(v);
        for &w in &s.next[v] {
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(lw);
            } else if s.on_stack.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).expect("visited");
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().expect("v is on the stack");
                s.on_stack.remove(w);
                component.push(w.to_path_buf());
                if w == v {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.out.push(component);
            }
        }
    }
    let mut s = State {
        next: &next,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for &v in next.keys() {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out.sort();
    s.out
}

/// Each circle with the references that close it: for each pair of its files, every line
/// of the first that refers to the second, with the path written there.
fn describe(circles: &[Vec<PathBuf>], edges: &BTreeSet<Edge>) -> Vec<String> {
    circles
        .iter()
        .map(|c| {
            let names: Vec<String> = c.iter().map(|f| f.display().to_string()).collect();
            let mut pairs: BTreeMap<(&Path, &Path), Vec<String>> = BTreeMap::new();
            for e in edges
                .iter()
                .filter(|e| c.contains(&e.from) && c.contains(&e.to))
            {
                pairs
                    .entry((&e.from, &e.to))
                    .or_default()
                    .push(format!("{} {}", e.line, e.path));
            }
            let refs: Vec<String> = pairs
                .iter()
                .map(|((from, to), lines)| {
                    format!(
                        "{} -> {}: {}",
                        from.display(),
                        to.display(),
                        lines.join(", ")
                    )
                })
                .collect();
            format!("{}\n      {}", names.join(" <-> "), refs.join("\n      "))
        })
        .collect()
}

fn show(e: &Edge) -> String {
    format!(
        "{}:{}: {} -> {}",
        e.from.display(),
        e.line,
        e.path,
        e.to.display()
    )
}

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
    // Libraries first, so the others' references to them resolve... (resolution happens
    // after every crate is read, so the order only matters for the map of names).
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
                    .filter(|f| f.parent() == Some(dir.as_path()))
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
#[test]
fn zz_dump() {
    let (ws, _) = workspace();
    let mut out = String::new();
    for e in ws.edges() {
        out += &format!("{}\n", show(&e));
    }
    std::fs::write("/tmp/i26-edges.txt", out).unwrap();
}
