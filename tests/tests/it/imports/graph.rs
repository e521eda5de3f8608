//! The import test's graph: each crate's module tree read from its root through its `mod`
//! declarations, the names each module defines, declares and imports, every reference
//! from one file to another resolved (through re-exports) to the file that defines what
//! it names, and the graph's circles (strongly connected components of more than one
//! file).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::lex::{Tok, Token, lex};

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

impl Use {
    /// A path written inline (`crate::a::f()`, `wire::read()`) at `line`: it binds nothing.
    fn inline(segs: Vec<String>, line: usize) -> Use {
        Use {
            segs,
            name: None,
            inline: true,
            public: false,
            line,
        }
    }
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
pub struct Edge {
    pub from: PathBuf,
    pub line: usize,
    pub to: PathBuf,
    pub path: String,
}

/// Where a path leads: a module, or an item defined in a file.
#[derive(Clone, Copy, Debug)]
enum Res {
    Module(ModId),
    Item(ModId),
}

#[derive(Default)]
pub struct Workspace {
    modules: Vec<Module>,
    /// The workspace's libraries by crate name (`roam_protocol`), to their root modules.
    libs: BTreeMap<String, ModId>,
    /// References found while reading, resolved once every crate is read: the module they
    /// are written in and the reference.
    pending: Vec<(ModId, Use)>,
    /// Files a `mod` declaration names that do not exist.
    pub missing: Vec<String>,
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
    pub fn add_crate(&mut self, files: &BTreeMap<PathBuf, String>, root: &Path, lib: Option<&str>) {
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
                // A path in an attribute's string (`deserialize_with = "crate::a::f"`).
                Tok::Str(text) if punct(i.wrapping_sub(1), '=') => {
                    let segs: Vec<String> = text.split("::").map(str::to_string).collect();
                    let idents = segs.iter().all(|s| {
                        !s.is_empty() && s.chars().all(|c| c.is_alphanumeric() || c == '_')
                    });
                    if segs.len() > 1
                        && idents
                        && matches!(segs[0].as_str(), "crate" | "super" | "self")
                    {
                        self.pending.push((cur, Use::inline(segs, toks[i].line)));
                    }
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
                        self.pending.push((cur, Use::inline(segs, toks[i].line)));
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
            if u.name.as_deref() == Some(name)
                && let Some(r) = self.resolve(m, &u.segs, guard + 1)
            {
                return Some(r);
            }
        }
        for u in module.uses.iter().filter(|u| u.name.is_none() && !u.inline) {
            if let Some(Res::Module(g)) = self.resolve(m, &u.segs, guard + 1)
                && g != m
                && let Some(r) = self.lookup(g, name, guard + 1)
            {
                return Some(r);
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

    /// Every reference from one file to another, but those between a module and its own
    /// descendants (either way: a module's file and its children are not a circle).
    pub fn edges(&self) -> BTreeSet<Edge> {
        let mut out = BTreeSet::new();
        for (m, u) in &self.pending {
            // An inline path counts from a module (the crate, a module a `use` names, a
            // library): one from an item a `use` binds is that `use`'s reference, already
            // counted; one from a local name is none.
            if u.inline && !matches!(self.first(*m, &u.segs[0], 0), Some(Res::Module(_))) {
                continue;
            }
            let Some(res) = self.resolve(*m, &u.segs, 0) else {
                continue;
            };
            let (Res::Module(t) | Res::Item(t)) = res;
            let from = &self.modules[*m].file;
            let to = &self.modules[t].file;
            if from == to || self.descends(t, *m) || self.descends(*m, t) {
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
    pub fn files(&self) -> BTreeSet<PathBuf> {
        self.modules.iter().map(|m| m.file.clone()).collect()
    }
}

/// The file `#[path = "p"]` names, from a file in `dir` with inline modules `scopes` open.
fn cur_dir_of(dir: &Path, scopes: &[(ModId, usize, PathBuf)], p: &str) -> PathBuf {
    let joined = if scopes.len() > 1 {
        scopes.last().expect("an inline module").2.join(p)
    } else {
        dir.join(p)
    };
    lexical(&joined)
}

/// `p` with its `.` and `dir/..` steps taken (`protocol/benches/../tests/it/common/mod.rs` is
/// `protocol/tests/it/common/mod.rs`), as the files are named when walked.
fn lexical(p: &Path) -> PathBuf {
    use std::path::Component;
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir if out.file_name().is_some() => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    out
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
pub fn circles(edges: &BTreeSet<Edge>) -> Vec<Vec<PathBuf>> {
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
pub fn describe(circles: &[Vec<PathBuf>], edges: &BTreeSet<Edge>) -> Vec<String> {
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

pub fn show(e: &Edge) -> String {
    format!(
        "{}:{}: {} -> {}",
        e.from.display(),
        e.line,
        e.path,
        e.to.display()
    )
}
