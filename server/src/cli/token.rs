//! The join token `serve` asks of viewers: where it comes from and what it must look like.
//!
//! Sources, first found wins: `--token T`, `--token-file PATH`, the environment variable
//! `ROAM_TOKEN`, else a random one (128 bits, 32 hex digits, from the system's random
//! source). `--token` is visible to every user of the machine in `ps`, so it draws a
//! warning; a file or the environment keep the token off the command line. A token file
//! loses its trailing newline and spaces (what `echo` and editors add), and draws a
//! warning if other users may read it (it is not changed: it is the operator's file).
//!
//! A token is refused at start, with the reason and how to make a good one, when it is:
//! empty (it would let anyone in), shorter than 16 characters (guessable), longer than the
//! 128 bytes a viewer may send ([`MAX_TOKEN`]), or not printable ASCII without spaces (it is
//! pasted into command lines and URLs). Error messages name the source and never repeat
//! the token. The environment is read by [`TokenArgs::resolve`] and handed to
//! [`TokenArgs::resolve_with`], so the tests never touch the process's environment.

use std::ffi::OsString;
use std::fmt;
use std::io::Read;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use clap::Args;
use roam_protocol::messages::MAX_TOKEN;

/// The environment variable a token may come from.
pub(crate) const TOKEN_ENV: &str = "ROAM_TOKEN";
/// The fewest characters a token may have.
pub(crate) const MIN_TOKEN: usize = 16;
/// What a token file may weigh: a token and some trailing white space.
const MAX_TOKEN_FILE: u64 = 1024;
/// How to make a good token, for the refusals.
const HOW: &str = "leave out --token, --token-file and ROAM_TOKEN for a random one, or make \
                   one with `openssl rand -hex 16`";

/// Where the join token comes from (flattened into `serve`'s arguments).
#[derive(Args, Clone, Default)]
pub(crate) struct TokenArgs {
    /// The join token viewers must present. Other users of this machine can read it (`ps`):
    /// prefer --token-file or ROAM_TOKEN. With none of the three, a random one.
    #[arg(long, value_name = "TOKEN")]
    pub token: Option<String>,
    /// A file holding the join token (trailing newline and spaces ignored); used when
    /// --token is not given. Then the environment variable ROAM_TOKEN.
    #[arg(long, value_name = "PATH")]
    pub token_file: Option<PathBuf>,
}

/// Where a [`Token`] came from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) enum Source {
    Flag,
    File(PathBuf),
    Env,
    Random,
}

impl fmt::Display for Source {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        match self {
            Source::Flag => write!(f, "--token"),
            Source::File(path) => write!(f, "--token-file {}", path.display()),
            Source::Env => write!(f, "{TOKEN_ENV}"),
            Source::Random => write!(f, "made at random"),
        }
    }
}

/// A join token that passed the checks. Its `Debug` hides it, so logging one by mistake
/// does not leak it.
pub(crate) struct Token {
    secret: String,
    pub source: Source,
}

impl Token {
    /// The token itself: for the server's options and the connect line people copy.
    pub(crate) fn as_str(&self) -> &str {
        &self.secret
    }
}

impl fmt::Debug for Token {
    fn fmt(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "Token(<{} bytes, {}>)", self.secret.len(), self.source)
    }
}

impl TokenArgs {
    /// The token, from the first of `--token`, `--token-file`, `ROAM_TOKEN`, or a random
    /// one; an error says why a given one is refused.
    pub(crate) fn resolve(&self) -> Result<Token> {
        self.resolve_with(std::env::var_os(TOKEN_ENV))
    }

    /// [`TokenArgs::resolve`] with `env` as the value of `ROAM_TOKEN`.
    pub(crate) fn resolve_with(&self, env: Option<OsString>) -> Result<Token> {
        let (secret, source) = if let Some(token) = &self.token {
            tracing::warn!(
                "--token is visible to other users of this machine (`ps`): --token-file or \
                 {TOKEN_ENV} keep it off the command line"
            );
            (token.clone(), Source::Flag)
        } else if let Some(path) = &self.token_file {
            (read_token_file(path)?, Source::File(path.clone()))
        } else if let Some(value) = env {
            let value = value
                .into_string()
                .map_err(|_| anyhow!("{TOKEN_ENV} is not UTF-8 text; {HOW}"))?;
            (value, Source::Env)
        } else {
            return Ok(Token {
                secret: random_token()?,
                source: Source::Random,
            });
        };
        check(&secret).map_err(|why| anyhow!("the join token from {source} {why}; {HOW}"))?;
        Ok(Token { secret, source })
    }
}

/// Why `token` is refused, if it is (the reason completes "the join token from X …").
pub(crate) fn check(token: &str) -> Result<(), String> {
    if token.is_empty() {
        return Err("is empty, which would let anyone join".to_owned());
    }
    if let Some((at, c)) = token
        .chars()
        .enumerate()
        .find(|(_, c)| !c.is_ascii_graphic())
    {
        let what = match c {
            ' ' => "a space",
            c if c.is_ascii_control() => "a control character",
            c if c.is_ascii() => "a character that is not printable",
            _ => "a non-ASCII character",
        };
        return Err(format!(
            "has {what} at character {}: it must be printable ASCII without spaces, as it is \
             pasted into command lines and URLs",
            at + 1
        ));
    }
    // Printable ASCII from here: characters and bytes are the same count.
    if token.len() < MIN_TOKEN {
        return Err(format!(
            "is {} characters long: at least {MIN_TOKEN} are needed, so that it cannot be \
             guessed",
            token.len()
        ));
    }
    if token.len() > MAX_TOKEN {
        return Err(format!(
            "is {} bytes long: a viewer may send at most {MAX_TOKEN}",
            token.len()
        ));
    }
    Ok(())
}

/// The token in `path`, its trailing white space removed (not yet checked).
fn read_token_file(path: &Path) -> Result<String> {
    let context = || format!("reading the token file {}", path.display());
    let file = std::fs::File::open(path).with_context(context)?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = file.metadata().with_context(context)?.permissions().mode() & 0o777;
        if mode & 0o044 != 0 {
            tracing::warn!(
                "the token file {} can be read by other users (mode {mode:03o}): `chmod 600 {}`",
                path.display(),
                path.display()
            );
        }
    }
    let mut bytes = Vec::new();
    file.take(MAX_TOKEN_FILE + 1)
        .read_to_end(&mut bytes)
        .with_context(context)?;
    if bytes.len() as u64 > MAX_TOKEN_FILE {
        bail!(
            "the token file {} is over {MAX_TOKEN_FILE} bytes: it should hold the token alone",
            path.display()
        );
    }
    let text = String::from_utf8(bytes)
        .map_err(|_| anyhow!("the token file {} is not UTF-8 text; {HOW}", path.display()))?;
    Ok(text.trim_end().to_owned())
}

/// A fresh random join token: 128 bits as 32 hex digits.
pub(crate) fn random_token() -> Result<String> {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 16];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .map_err(|_| {
            anyhow!("the system's random source failed; give a token with --token-file")
        })?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    /// A directory for one test's token files, removed at the end.
    struct Scratch(PathBuf);

    impl Scratch {
        fn new(name: &str) -> Scratch {
            let path =
                std::env::temp_dir().join(format!("roam-token-{}-{name}", std::process::id()));
            let _absent = std::fs::remove_dir_all(&path);
            std::fs::create_dir_all(&path).expect("the temporary directory is writable");
            Scratch(path)
        }

        /// A token file holding `text`, private to its owner.
        fn file(&self, name: &str, text: &[u8]) -> PathBuf {
            let path = self.0.join(name);
            std::fs::write(&path, text).expect("a writable directory");
            path
        }
    }

    impl Drop for Scratch {
        fn drop(&mut self) {
            let _best_effort = std::fs::remove_dir_all(&self.0);
        }
    }

    fn flag(token: &str) -> TokenArgs {
        TokenArgs {
            token: Some(token.to_owned()),
            token_file: None,
        }
    }

    fn file(path: &Path) -> TokenArgs {
        TokenArgs {
            token: None,
            token_file: Some(path.to_owned()),
        }
    }

    /// Resolves `args` with `env` as `ROAM_TOKEN`: `Ok((token, source))` or `Err(words the
    /// message must contain)`. A refusal never repeats the token.
    fn check(
        case: &str,
        args: &TokenArgs,
        env: Option<OsString>,
        expected: Result<(&str, Source), &[&str]>,
    ) {
        let given: Vec<String> = args
            .token
            .iter()
            .cloned()
            .chain(env.iter().filter_map(|e| e.to_str().map(str::to_owned)))
            .filter(|t| t.len() >= 4)
            .collect();
        match (args.resolve_with(env), expected) {
            (Ok(token), Ok((want, source))) => {
                assert_eq!(token.as_str(), want, "{case}");
                assert_eq!(token.source, source, "{case}");
            }
            (Err(err), Err(words)) => {
                let text = format!("{err:#}");
                for w in words {
                    assert!(text.contains(w), "{case}: {w:?} not in {text:?}");
                }
                for t in given {
                    assert!(!text.contains(&t), "{case}: the token is in {text:?}");
                }
            }
            (Ok(token), Err(_)) => panic!("{case}: accepted {:?}", token.as_str()),
            (Err(err), Ok(_)) => panic!("{case}: refused: {err:#}"),
        }
    }

    const GOOD: &str = "0123456789abcdef";

    /// What a case expects: the token accepted, or words of the refusal.
    type Expected<'a> = Result<&'a str, &'a [&'a str]>;

    #[test]
    fn tokens_given_on_the_command_line() {
        let long = "x".repeat(MAX_TOKEN);
        let too_long = "x".repeat(MAX_TOKEN + 1);
        let cases: [(&str, &str, Expected); 10] = [
            (
                "empty",
                "",
                Err(&["--token", "is empty", "anyone", "openssl rand"]),
            ),
            (
                "15 characters",
                "0123456789abcde",
                Err(&[
                    "--token",
                    "is 15 characters",
                    "at least 16",
                    "openssl rand -hex 16",
                ]),
            ),
            ("16 characters", GOOD, Ok(GOOD)),
            ("128 bytes", &long, Ok(&long)),
            (
                "129 bytes",
                &too_long,
                Err(&["is 129 bytes", "at most 128"]),
            ),
            (
                "a space",
                "01234567 89abcdef",
                Err(&["a space at character 9", "printable ASCII"]),
            ),
            (
                "non-ASCII",
                "0123456789abcdéf",
                Err(&["a non-ASCII character at character 15"]),
            ),
            ("a tab", "01234567\t89abcdef", Err(&["a control character"])),
            (
                "a newline at the end",
                "0123456789abcdef\n",
                Err(&["a control character at character 17"]),
            ),
            (
                "punctuation",
                "a-b_c.d~e!f@g#h$i%",
                Ok("a-b_c.d~e!f@g#h$i%"),
            ),
        ];
        for (case, token, expected) in cases {
            check(
                case,
                &flag(token),
                None,
                expected.map(|t| (t, Source::Flag)),
            );
        }
    }

    #[test]
    fn tokens_from_a_file() {
        let scratch = Scratch::new("file");
        let cases: [(&str, &[u8], Expected); 7] = [
            ("a trailing newline", b"0123456789abcdef\n", Ok(GOOD)),
            ("CRLF and spaces", b"0123456789abcdef \r\n\n", Ok(GOOD)),
            ("no newline", b"0123456789abcdef", Ok(GOOD)),
            ("empty", b"\n", Err(&["is empty"])),
            ("short", b"short\n", Err(&["is 5 characters"])),
            (
                "two lines",
                b"01234567\n89abcdef\n",
                Err(&["a control character"]),
            ),
            ("not UTF-8", b"0123456789abcdef\xff\n", Err(&["not UTF-8"])),
        ];
        for (i, (case, text, expected)) in cases.into_iter().enumerate() {
            let path = scratch.file(&format!("token-{i}"), text);
            let expected = expected.map(|t| (t, Source::File(path.clone())));
            check(case, &file(&path), None, expected);
            // Refusals name the file.
            if let Err(err) = file(&path).resolve_with(None) {
                assert!(
                    format!("{err:#}").contains(&path.display().to_string()),
                    "{case}: {err:#}"
                );
            }
        }
        let big = scratch.file("big", &[b'x'; 2000]);
        check(
            "over 1 KiB",
            &file(&big),
            None,
            Err(&["is over 1024 bytes"]),
        );
        let missing = scratch.0.join("missing");
        check(
            "a missing file",
            &file(&missing),
            None,
            Err(&[&format!("reading the token file {}", missing.display())]),
        );
    }

    #[test]
    fn tokens_from_the_environment() {
        let env = |s: &str| Some(OsString::from(s));
        let none = TokenArgs::default();
        check("set", &none, env(GOOD), Ok((GOOD, Source::Env)));
        check("empty", &none, env(""), Err(&["ROAM_TOKEN is empty"]));
        check(
            "short",
            &none,
            env("abc"),
            Err(&["ROAM_TOKEN is 3 characters"]),
        );
        #[cfg(unix)]
        {
            use std::os::unix::ffi::OsStringExt;
            let bad = Some(OsString::from_vec(b"0123456789abcdef\xff".to_vec()));
            check("not UTF-8", &none, bad, Err(&["ROAM_TOKEN is not UTF-8"]));
        }
    }

    #[test]
    fn the_first_source_given_wins() {
        let scratch = Scratch::new("precedence");
        let in_file = "fromthefile-0123456789";
        let path = scratch.file("token", format!("{in_file}\n").as_bytes());
        let in_env = Some(OsString::from("fromtheenvironment-0123"));
        let all = TokenArgs {
            token: Some(GOOD.to_owned()),
            token_file: Some(path.clone()),
        };
        check("all three", &all, in_env.clone(), Ok((GOOD, Source::Flag)));
        check(
            "file and environment",
            &file(&path),
            in_env.clone(),
            Ok((in_file, Source::File(path.clone()))),
        );
        check(
            "environment",
            &TokenArgs::default(),
            in_env,
            Ok(("fromtheenvironment-0123", Source::Env)),
        );
        // A source not used is not read: a missing file behind --token is no error.
        let shadowed = TokenArgs {
            token: Some(GOOD.to_owned()),
            token_file: Some(scratch.0.join("missing")),
        };
        check(
            "--token over a missing file",
            &shadowed,
            None,
            Ok((GOOD, Source::Flag)),
        );
        // But a bad token given is refused, not replaced by the next source.
        check(
            "a short --token over a good file",
            &TokenArgs {
                token: Some("short".to_owned()),
                token_file: Some(path),
            },
            None,
            Err(&["--token is 5 characters"]),
        );
    }

    #[test]
    fn with_no_source_the_token_is_128_random_bits() {
        let a = TokenArgs::default()
            .resolve_with(None)
            .expect("a random token");
        let b = TokenArgs::default()
            .resolve_with(None)
            .expect("a random token");
        assert_eq!(a.source, Source::Random);
        assert_eq!(a.as_str().len(), 32);
        assert!(a.as_str().chars().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(a.as_str(), b.as_str());
        assert!(
            super::check(a.as_str()).is_ok(),
            "a random token passes the checks"
        );
        assert!(!format!("{a:?}").contains(a.as_str()), "Debug hides it");
    }

    #[test]
    fn the_flags_parse_as_a_flattened_group() {
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            token: TokenArgs,
        }
        let cli =
            Cli::try_parse_from(["serve", "--token-file", "/run/roam/token"]).expect("valid flags");
        assert_eq!(cli.token.token_file, Some(PathBuf::from("/run/roam/token")));
        assert_eq!(cli.token.token, None);
        let cli = Cli::try_parse_from(["serve", "--token", GOOD]).expect("valid flags");
        assert_eq!(cli.token.token.as_deref(), Some(GOOD));
    }
}
