//! The workspace's binaries as the document checks run them: found beside the running
//! test (`target/PROFILE/`), built first with cargo when missing or older than their
//! package's sources, and asked for their `--help` (once each): whether a subcommand
//! exists, and which `--flag`s it takes.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use super::code::{Code, rust_files};
use super::markdown::{flags, help_flags};

/// What `BIN [SUB] --help` said.
#[derive(Clone, Debug)]
pub struct Help {
    /// It exited successfully (clap: the subcommand exists).
    pub ok: bool,
    /// Its output, standard output then standard error.
    pub text: String,
}

impl Help {
    /// The long options it lists: its option lines; when it has none (a binary without
    /// clap, answering with a usage line), every `--flag` it mentions.
    pub fn flags(&self) -> BTreeSet<String> {
        let listed = help_flags(&self.text);
        if !listed.is_empty() {
            return listed;
        }
        let words: Vec<String> = self.text.split_whitespace().map(str::to_owned).collect();
        flags(&words).into_iter().collect()
    }
}

/// Why a binary could not be asked for its `--help`. `Clone` (an error is kept as each
/// answer is, and given again): the operating system's errors are shared.
#[derive(Clone, Debug, thiserror::Error)]
pub enum BinaryError {
    #[error("no package has a binary `{name}`")]
    NoPackage { name: String },
    /// The running test is not in `target/PROFILE/deps`.
    #[error("no target directory")]
    NoTarget,
    #[error("running cargo: {0}")]
    Cargo(Arc<std::io::Error>),
    /// `cargo build` failed (`stderr`: what it said).
    #[error("cargo build -p {package} --bin {name} failed: {stderr}")]
    Build {
        package: String,
        name: String,
        stderr: String,
    },
    #[error("running {}: {error}", bin.display())]
    Run {
        bin: PathBuf,
        error: Arc<std::io::Error>,
    },
}

/// The workspace's binaries, run for their `--help`.
pub struct Binaries<'a> {
    code: &'a Code,
    /// `target/PROFILE`, where the running test and the binaries are.
    dir: PathBuf,
    helps: HashMap<(String, String), Result<Help, BinaryError>>,
}

fn modified(p: &Path) -> Option<std::time::SystemTime> {
    std::fs::metadata(p).and_then(|m| m.modified()).ok()
}

impl Binaries<'_> {
    pub fn new(code: &Code) -> Binaries<'_> {
        let exe = std::env::current_exe().expect("a running program has a path");
        // target/PROFILE/deps/TEST-HASH
        let dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("cargo runs tests from target/PROFILE/deps")
            .to_path_buf();
        Binaries {
            code,
            dir,
            helps: HashMap::new(),
        }
    }

    /// The path of binary `name`, built first when missing or older than its package's
    /// sources or manifest.
    fn path(&self, name: &str) -> Result<PathBuf, BinaryError> {
        let pkg = (self.code.packages.iter())
            .find(|p| p.bins.iter().any(|b| b == name))
            .ok_or_else(|| BinaryError::NoPackage {
                name: name.to_owned(),
            })?;
        let bin = self.dir.join(name);
        let mut sources = Vec::new();
        rust_files(&pkg.dir.join("src"), &mut sources);
        sources.push(pkg.dir.join("Cargo.toml"));
        let newest = sources.iter().filter_map(|s| modified(s)).max();
        if modified(&bin).is_some_and(|b| newest.is_none_or(|n| b >= n)) {
            return Ok(bin);
        }
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| env!("CARGO").into());
        let target = self.dir.parent().ok_or(BinaryError::NoTarget)?;
        let mut cmd = Command::new(cargo);
        cmd.current_dir(&self.code.root)
            .args(["build", "--quiet", "-p", &pkg.name, "--bin", name])
            .arg("--target-dir")
            .arg(target);
        match self.dir.file_name().and_then(|p| p.to_str()) {
            Some("debug") | None => {}
            Some("release") => {
                cmd.arg("--release");
            }
            Some(other) => {
                cmd.args(["--profile", other]);
            }
        }
        let out = cmd.output().map_err(|e| BinaryError::Cargo(Arc::new(e)))?;
        if !out.status.success() {
            return Err(BinaryError::Build {
                package: pkg.name.clone(),
                name: name.to_owned(),
                stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
            });
        }
        Ok(bin)
    }

    /// What `name [sub] --help` says, or why it could not be run.
    pub fn help(&mut self, name: &str, sub: &str) -> Result<Help, BinaryError> {
        let key = (name.to_owned(), sub.to_owned());
        if let Some(h) = self.helps.get(&key) {
            return h.clone();
        }
        let help = self.path(name).and_then(|bin| {
            let out = Command::new(&bin)
                .args(sub.split_whitespace())
                .arg("--help")
                .output()
                .map_err(|error| BinaryError::Run {
                    bin: bin.clone(),
                    error: Arc::new(error),
                })?;
            let mut text = String::from_utf8_lossy(&out.stdout).into_owned();
            text.push_str(&String::from_utf8_lossy(&out.stderr));
            Ok(Help {
                ok: out.status.success(),
                text,
            })
        });
        self.helps.insert(key, help.clone());
        help
    }

    /// What is wrong with the command `name args…`: its subcommand (the first word not a
    /// flag, when the binary lists commands) and each `--flag` before it (the binary's)
    /// and after it (the subcommand's).
    pub fn check(&mut self, name: &str, args: &[String]) -> Vec<String> {
        let top = match self.help(name, "") {
            Ok(h) => h,
            Err(e) => return vec![e.to_string()],
        };
        let words: Vec<String> = args.iter().take_while(|w| *w != "--").cloned().collect();
        let at = (top.ok && top.text.contains("\nCommands:"))
            .then(|| {
                words
                    .iter()
                    .position(|w| !w.starts_with('-') && !w.starts_with('['))
            })
            .flatten()
            .filter(|&i| !matches!(words[i].as_str(), "…" | "..."));
        let (before, sub, after) = match at {
            Some(i) => (&words[..i], words[i].as_str(), &words[i + 1..]),
            None => (&words[..], "", &words[..0]),
        };
        let sub_help = match sub {
            "" => top.clone(),
            s => match self.help(name, s) {
                Ok(h) if h.ok => h,
                Ok(_) => return vec![format!("`{name} {s}`: no such subcommand")],
                Err(e) => return vec![e.to_string()],
            },
        };
        let mut bad = Vec::new();
        for (words, help, what) in [
            (before, &top, name.to_owned()),
            (after, &sub_help, format!("{name} {sub}")),
        ] {
            let known = help.flags();
            for f in flags(words) {
                if !known.contains(&f) && f != "help" && f != "version" {
                    bad.push(format!("--{f}: not an option of `{what}`"));
                }
            }
        }
        bad
    }
}
