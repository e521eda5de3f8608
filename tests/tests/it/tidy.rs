//! Tidy: rules about the source tree itself, checked on every `cargo test` (in the spirit of
//! rust-analyzer's tidy test). The sources are the `.rs` files of the packages in [`ROOTS`]
//! (`target/` and hidden directories aside); a line counts unless it starts with `//`.
//! Each rule fails naming the files or lines that break it:
//!
//! - every source file starts with a `//!` comment;
//! - no test is switched off (`#[ignore]`) or made to expect a panic (`#[should_panic]`);
//! - `roam-protocol` is pure: `protocol/src` names no clock (`std::time`, `Instant`,
//!   `SystemTime`), socket (`std::net`, `UdpSocket`, `TcpStream`), async runtime (`tokio`,
//!   `quinn`, `async`), thread (`std::thread`) or file system (`std::fs`), and
//!   `protocol/Cargo.toml` no `tokio`, `quinn`, `async` or `mio`;
//! - a clock is read or waited on ([`CLOCK_WORDS`]: `Instant::now`, `.elapsed()`,
//!   `SystemTime::now`, anything of `tokio::time`, a thread's sleep, the browser's clock and
//!   timers) only in the files [`CLOCK_READERS`] names, each with why; and every entry
//!   there still exempts a file that reads one;
//! - the workspace's lints are set once, in the root `Cargo.toml`
//!   (`[workspace.lints.rust]` and `[workspace.lints.clippy]`), and every package's
//!   manifest takes them (`[lints] workspace = true`).

use std::path::{Path, PathBuf};

/// The workspace's packages, whose sources the rules read.
const ROOTS: &[&str] = &["protocol", "server", "client", "tests", "link", "web"];

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
    let mut dirs: Vec<PathBuf> = ROOTS
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

/// The words that read or wait on a clock: std's and `web_time`'s `Instant::now` and
/// `.elapsed()`, `SystemTime::now`, anything of `tokio::time` (its `sleep`, `interval`,
/// `timeout`, `Instant`), a thread's sleep, and the browser's clock and timers.
const CLOCK_WORDS: &[&str] = &[
    "Instant::now",
    "SystemTime::now",
    ".elapsed()",
    "tokio::time",
    "time::sleep",
    "time::timeout",
    "time::interval",
    "sleep_until",
    "thread::sleep",
    "performance()",
    "Date::now",
    "set_timeout",
    "set_interval",
    "request_animation_frame",
];

/// Every file (or, for tests, directory: a path ending in `/`) that may read a clock, and
/// why. Everything else is a core that takes time as a parameter.
const CLOCK_READERS: &[(&str, &str)] = &[
    // The server's network shell.
    (
        "server/src/net/server.rs",
        "the server's shell: the accept loop's pauses, shutdown's waits, the summaries' ticker",
    ),
    (
        "server/src/net/world_loop.rs",
        "the world thread: paces the world core every 10 ms by its own clock",
    ),
    (
        "server/src/net/handshake.rs",
        "admission: one deadline for a connection's handshake and hello",
    ),
    (
        "server/src/net/viewer.rs",
        "a viewer's connection: its silence watched, its last words waited for",
    ),
    (
        "server/src/net/clock.rs",
        "the frame clock's grid: where its phases begin, read once",
    ),
    (
        "server/src/net/frames.rs",
        "the frame clock: its passes, each viewer's frames when due by the clock",
    ),
    (
        "server/src/viewer/conversation/tests.rs",
        "the conversation takes `now`; its tests start it from a real `Instant`",
    ),
    (
        "server/src/net/control.rs",
        "a viewer's control stream: the colour stream's ticks",
    ),
    (
        "server/src/net/color_budget.rs",
        "the budget takes `now`; its tests start it from a real `Instant`",
    ),
    (
        "server/src/net/web.rs",
        "the page's server: TLS and connection time limits, waits between retries",
    ),
    (
        "server/src/net/bus/world.rs",
        "the world process: edges not heard from for a while",
    ),
    (
        "server/src/net/bus/edge.rs",
        "an edge's connection to the world: when it was last heard, reconnection deadlines",
    ),
    (
        "server/src/net/bus/asker.rs",
        "an edge's requests to the world: each waits for its answer so long",
    ),
    // The server's command line.
    (
        "server/src/cli/net.rs",
        "`serve`: times loading the data set",
    ),
    (
        "server/src/cli/served.rs",
        "opening what is served: times the data set's load, the tiles and the hash",
    ),
    (
        "server/src/cli/progress.rs",
        "progress bars, shown once a load takes a second",
    ),
    (
        "server/src/cli/sim.rs",
        "`simulate` and `replay`: how long they took",
    ),
    ("server/src/cli/tess.rs", "`bench`: times the tessellator"),
    (
        "server/src/cli/color_bench.rs",
        "`color-bench`: times a colour stream",
    ),
    (
        "server/src/cli/bus_load.rs",
        "`bus-load`: a load generator pacing its keys and timing the replies",
    ),
    // The native viewer's I/O.
    (
        "client/src/session.rs",
        "the session: frames and keys stamped as they arrive, for the clock-free core",
    ),
    (
        "client/src/connection.rs",
        "a connection's tasks, carrying out the reconnection supervisor's timers: tokio timers bound the \
         handshake, the join and control writes, pace the key sender, watch the silence and \
         back off between attempts",
    ),
    (
        "client/src/live.rs",
        "the window's network task: the costs and latencies it shows",
    ),
    (
        "client/src/window.rs",
        "the window: the display clock each frame is drawn at",
    ),
    (
        "client/src/headless.rs",
        "the headless viewer: its run's length and time to the first frame",
    ),
    ("client/src/main.rs", "the command line: the run's length"),
    (
        "client/src/bench/mod.rs",
        "`--bench`: times decoding, uploads and drawing",
    ),
    (
        "client/src/bench/watch.rs",
        "`--replay --bench`: times opening, playing and seeking a recording",
    ),
    // The browser viewer's I/O.
    (
        "web/src/app.rs",
        "the page's display loop: its frame clock and the costs it shows",
    ),
    (
        "web/src/net.rs",
        "the page's WebTransport session: arrivals stamped, the silence watched, the \
         reconnection's deadline",
    ),
    (
        "web/src/page.rs",
        "the browser's clock and timers (`performance.now`, `setTimeout`)",
    ),
    // Tests and benchmarks, which measure or bound real time.
    (
        "tests/tests/",
        "end-to-end tests over loopback: every wait bounded by a timeout",
    ),
    (
        "tests/src/fixtures.rs",
        "`bounded`: a session test's waits fail after `BOUND`",
    ),
    ("tests/src/relay.rs", "the lossy relay delays datagrams"),
    (
        "tests/src/flood.rs",
        "junk connections: how long the server takes to close them",
    ),
    (
        "tests/src/nats.rs",
        "nats-server's log, an edge process's lines, a world's snapshots and captured \
         messages awaited within a bound",
    ),
    (
        "tests/src/browser.rs",
        "the page's report awaited within a bound",
    ),
    ("tests/src/web.rs", "a WebTransport client's reads bounded"),
    (
        "tests/src/simnet/sim.rs",
        "virtual time counts from one real `Instant`, its epoch; nothing waits on it",
    ),
    ("tests/src/bin/roam-flood.rs", "the flood's pace and length"),
    ("tests/benches/fuzz.rs", "a benchmark: times itself"),
    ("server/benches/bus_seal.rs", "a benchmark: times itself"),
    (
        "protocol/benches/colormap.rs",
        "a benchmark: times the codec",
    ),
    (
        "server/tests/it/world_loop.rs",
        "the real world thread, awaited within a bound",
    ),
    (
        "client/tests/it/needs_display/window.rs",
        "a real window under Xvfb, awaited within a deadline",
    ),
];

/// Whether `f` is `entry` or, for an entry ending in `/`, under it.
fn names(entry: &str, f: &Path) -> bool {
    let f = f.to_string_lossy();
    if entry.ends_with('/') {
        f.starts_with(entry)
    } else {
        f == entry
    }
}

#[test]
fn only_the_files_named_read_a_clock() {
    let mut bad = Vec::new();
    let mut used = vec![false; CLOCK_READERS.len()];
    for f in sources() {
        let found = uses(&f, &read(&f), CLOCK_WORDS);
        if found.is_empty() {
            continue;
        }
        match CLOCK_READERS.iter().position(|(e, _)| names(e, &f)) {
            Some(i) => used[i] = true,
            None => bad.extend(found),
        }
    }
    check("a clock read outside the files CLOCK_READERS names", bad);
    let stale = CLOCK_READERS
        .iter()
        .zip(used)
        .filter(|(_, used)| !used)
        .map(|((e, _), _)| format!("{e}: reads no clock (or is gone)"))
        .collect();
    check("CLOCK_READERS entries that exempt nothing", stale);
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
    for pkg in ROOTS {
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
