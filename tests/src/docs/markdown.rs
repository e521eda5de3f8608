//! Reading the documents: the code spans of a Markdown text (with the headings above
//! each), the lines of its shell blocks, and what a token in them is — a path, a Rust
//! path, a type name, a command with its flags. Pure: text in, tokens out (the checks
//! against the repository are `tests/tests/it/docs.rs`'s, the workspace's model [`super::code`]).

use std::collections::BTreeSet;

/// Bare file names with these extensions are paths (with a `/`, any extension is).
pub const SOURCE_EXTENSIONS: &[&str] = &["rs", "md", "toml", "sh", "wgsl", "html", "js", "lock"];

// ---- Reading Markdown ----------------------------------------------------------------

/// A code span: the line it starts on, its text (a line break in it read as a space), and
/// the headings above it (level, the heading's own code spans).
#[derive(Clone, Debug, PartialEq)]
pub struct Span {
    pub line: usize,
    pub text: String,
    pub headings: Vec<(usize, Vec<String>)>,
}

/// The code spans outside fenced blocks. A span may run over a line break within a
/// paragraph; a backtick left open at a paragraph's end was a literal one.
pub fn spans(md: &str) -> Vec<Span> {
    let mut out = Vec::new();
    let mut fence = false;
    let mut headings: Vec<(usize, Vec<String>)> = Vec::new();
    // The run of backticks that opened the span, its line and text so far.
    let mut open: Option<(usize, usize, String)> = None;
    for (i, line) in md.lines().enumerate() {
        if line.trim_start().starts_with("```") {
            fence = !fence;
            open = None;
            continue;
        }
        if fence || line.trim().is_empty() {
            open = None;
            continue;
        }
        let level = line.chars().take_while(|&c| c == '#').count();
        let heading = (1..=6).contains(&level) && line[level..].starts_with(' ');
        let mut found = Vec::new();
        if let Some((_, _, text)) = &mut open {
            text.push(' ');
        }
        let chars: Vec<char> = line.chars().collect();
        let mut at = 0;
        while at < chars.len() {
            if chars[at] != '`' {
                if let Some((_, _, text)) = &mut open {
                    text.push(chars[at]);
                }
                at += 1;
                continue;
            }
            let run = chars[at..].iter().take_while(|&&c| c == '`').count();
            at += run;
            match open.take() {
                None => open = Some((run, i + 1, String::new())),
                Some((k, start, text)) if k == run => found.push((start, text.trim().to_owned())),
                Some((k, start, mut text)) => {
                    text.extend(std::iter::repeat_n('`', run));
                    open = Some((k, start, text));
                }
            }
        }
        if heading {
            headings.retain(|(l, _)| *l < level);
            let names = found.iter().map(|(_, t)| t.clone()).collect();
            headings.push((level, names));
        }
        out.extend(found.into_iter().map(|(line, text)| Span {
            line,
            text,
            headings: headings.clone(),
        }));
    }
    out
}

/// The command lines of ```` ```sh ```` (or `bash`, `shell`) blocks: each with its line,
/// continuation lines (`\`) joined, comments dropped.
pub fn shell_lines(md: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut shell: Option<bool> = None;
    let mut pending: Option<(usize, String)> = None;
    for (i, line) in md.lines().enumerate() {
        let t = line.trim();
        if let Some(lang) = t.strip_prefix("```") {
            shell = match shell {
                Some(_) => None,
                None => Some(matches!(lang.trim(), "sh" | "bash" | "shell")),
            };
            continue;
        }
        if shell != Some(true) {
            continue;
        }
        let code = match t.find(" #") {
            Some(c) => &t[..c],
            None if t.starts_with('#') => "",
            None => t,
        };
        let (start, mut text) = pending.take().unwrap_or((i + 1, String::new()));
        match code.trim_end().strip_suffix('\\') {
            Some(part) => {
                text.push_str(part);
                text.push(' ');
                pending = Some((start, text));
            }
            None => {
                text.push_str(code);
                if !text.trim().is_empty() {
                    out.push((start, text.trim().to_owned()));
                }
            }
        }
    }
    out
}

// ---- What a token is -------------------------------------------------------------------

/// What a path-like token asks to be checked as.
#[derive(Debug, PartialEq)]
pub enum PathToken {
    /// A path to look for.
    Check,
    /// A path outside the repository (`../`).
    Outside,
    /// A path, but not one the repository holds (absolute, a placeholder, a run-time
    /// output).
    Skip,
}

/// Whether `t` is a path and how to check it: `top` is the repository's top-level
/// entries, `outputs` the `(prefix, why)` of paths made at run time or by a build.
pub fn path_token(t: &str, top: &BTreeSet<String>, outputs: &[(&str, &str)]) -> Option<PathToken> {
    let allowed = |c: char| c.is_ascii_alphanumeric() || "_.-/*".contains(c);
    if t.is_empty()
        || !t.chars().all(allowed)
        || t.starts_with('-')
        || !t.contains(char::is_alphabetic)
    {
        return None;
    }
    let last = t.trim_end_matches('/').rsplit('/').next().unwrap_or("");
    let extension = last
        .rsplit_once('.')
        .filter(|(stem, ext)| !stem.is_empty() && ext.chars().any(|c| c.is_ascii_alphabetic()))
        .map(|(_, ext)| ext);
    let first = t.trim_start_matches("./").split('/').next().unwrap_or("");
    let is_path = if t.contains('/') {
        t.ends_with('/') || extension.is_some() || top.contains(first) || first == ".."
    } else {
        extension.is_some_and(|e| SOURCE_EXTENSIONS.contains(&e))
    };
    if !is_path {
        return None;
    }
    let placeholder = |part: &str| {
        !part.is_empty()
            && part
                .chars()
                .all(|c| c.is_ascii_uppercase() || c == '_' || c == '-')
    };
    Some(if t.split('/').any(|p| p == "..") {
        PathToken::Outside
    } else if t.starts_with('/')
        || t.split('/').any(placeholder)
        || outputs
            .iter()
            .any(|(p, _)| t.starts_with(p) || t == p.trim_end_matches('/'))
    {
        PathToken::Skip
    } else {
        PathToken::Check
    })
}

pub fn ident(s: &str) -> bool {
    let mut c = s.chars();
    c.next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && c.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// The `a::b::c` a token starts with (up to a `(`), if it is one of two parts or more.
pub fn rust_path(t: &str) -> Option<Vec<&str>> {
    let head = t.split('(').next().unwrap_or("");
    if head.len() != t.len() && !t.ends_with(')') && !t.contains(") ->") {
        return None;
    }
    let parts: Vec<&str> = head.split("::").collect();
    (parts.len() >= 2 && parts.iter().all(|p| ident(p))).then_some(parts)
}

/// Whether `t` is one CamelCase identifier (an upper-case letter first, a lower-case one
/// in it).
pub fn camel(t: &str) -> bool {
    t.starts_with(|c: char| c.is_ascii_uppercase())
        && t.contains(|c: char| c.is_ascii_lowercase())
        && t.chars().all(|c| c.is_ascii_alphanumeric())
}

// ---- Commands ------------------------------------------------------------------------

/// A command as written: what runs it and its words after that.
#[derive(Debug, PartialEq)]
pub enum Cmd {
    /// A workspace binary, by name, with its arguments.
    Binary(String, Vec<String>),
    /// `cargo SUB …`.
    Cargo(String, Vec<String>),
    /// A script of the repository (its path), with its arguments.
    Script(String, Vec<String>),
}

/// The commands in one line of shell (split at `&&`, `||`, `;` and `|` outside
/// brackets; `NAME=value` and `sudo` before a command dropped; redirections ended): a
/// workspace binary (one of `binaries`, or `target/PROFILE/` and its name), `cargo`, or a
/// script under `scripts/` (no extension, or `.sh`). Anything else is not ours to check.
pub fn commands(line: &str, binaries: &BTreeSet<String>) -> Vec<Cmd> {
    let mut pieces = vec![Vec::new()];
    let mut depth = 0i32;
    for w in line.split_whitespace() {
        depth += w.matches('[').count() as i32 - w.matches(']').count() as i32;
        if matches!(w, "&&" | "||" | ";") || (w == "|" && depth <= 0) {
            pieces.push(Vec::new());
        } else if let Some(p) = pieces.last_mut() {
            p.push(w.trim_end_matches(';').to_owned());
        }
    }
    let mut out = Vec::new();
    for piece in pieces {
        let mut words = piece.into_iter().skip_while(|w| {
            w == "sudo"
                || w.split_once('=')
                    .is_some_and(|(k, _)| ident(k) && !w.starts_with('-'))
        });
        let Some(head) = words.next() else { continue };
        let args: Vec<String> = words
            .take_while(|w| !w.starts_with('>') && !w.starts_with("2>") && !w.starts_with('<'))
            .collect();
        let head = head.trim_start_matches("./");
        let bin = head
            .strip_prefix("target/")
            .and_then(|h| h.split_once('/'))
            .map_or(head, |(_, b)| b);
        if binaries.contains(bin) {
            out.push(Cmd::Binary(bin.to_owned(), args));
        } else if head == "cargo" {
            if let Some((sub, rest)) = args.split_first() {
                out.push(Cmd::Cargo(sub.clone(), rest.to_vec()));
            }
        } else if let Some(name) = head.strip_prefix("scripts/") {
            // A script has no extension or a shell's; `scripts/capacity-drive.txt` is data.
            let ext = name.rsplit_once('.').map(|(_, e)| e);
            if !name.is_empty() && !name.ends_with('/') && ext.is_none_or(|e| e == "sh") {
                out.push(Cmd::Script(head.to_owned(), args));
            }
        }
    }
    out
}

/// The long options a `--help` text lists (its option lines, not its prose).
pub fn help_flags(help: &str) -> BTreeSet<String> {
    help.lines()
        .filter_map(|l| {
            let indent = l.len() - l.trim_start().len();
            let t = l.trim_start();
            let t = match t.strip_prefix('-') {
                Some(short) if !short.starts_with('-') => short.get(3..)?,
                _ => t,
            };
            let name = t.strip_prefix("--")?;
            let end = name
                .find(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
                .unwrap_or(name.len());
            ((2..=6).contains(&indent) && end > 0).then(|| name[..end].to_owned())
        })
        .collect()
}

/// The `--flag`s among `words` (a value after `=` and closing brackets dropped).
pub fn flags(words: &[String]) -> Vec<String> {
    words
        .iter()
        .filter_map(|w| {
            let w = w.trim_start_matches('[').trim_start_matches('(');
            let name = w.strip_prefix("--")?;
            let name = name.split('=').next().unwrap_or("");
            let name = name.trim_end_matches([']', ')', ',', '.', '…']);
            (!name.is_empty()).then(|| name.to_owned())
        })
        .collect()
}
