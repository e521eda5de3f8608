//! A real window under a virtual X display (Xvfb): it opens, draws the terrain, and quits
//! on `q`, pressed through the X server's test extension (xdotool) as a person would.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// What CI installs for this test.
const PACKAGES: &str = "apt-get install -y --no-install-recommends xvfb xauth xdotool";

fn require(tool: &str) {
    let found = std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(tool).is_file()));
    assert!(found, "the window test needs `{tool}`: {PACKAGES}");
}

/// Kills a child process when dropped (the test fails without leaving it behind).
struct Reaped(Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Sends each line `from` writes, until it closes.
fn lines(from: impl Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(from).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                return;
            }
        }
    });
    rx
}

/// The first line from `rx` containing `want`, within `limit`.
fn expect_line(rx: &mpsc::Receiver<String>, want: &str, limit: Duration) -> Result<String, String> {
    let deadline = Instant::now() + limit;
    let mut seen = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) if line.contains(want) => return Ok(line),
            Ok(line) => seen.push(line),
            Err(e) => return Err(format!("no line with {want:?} ({e}); saw {seen:?}")),
        }
    }
}

#[test]
fn a_window_opens_draws_and_quits_on_q() {
    require("Xvfb");
    require("xdotool");
    // A display of its own: Xvfb picks a free number and writes it to stdout.
    let mut xvfb = Command::new("Xvfb")
        .args([
            "-displayfd",
            "1",
            "-screen",
            "0",
            "640x480x24",
            "-nolisten",
            "tcp",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting Xvfb");
    let xvfb_out = lines(xvfb.stdout.take().expect("piped"));
    let xvfb = Reaped(xvfb);
    let number = xvfb_out
        .recv_timeout(Duration::from_secs(30))
        .expect("Xvfb names its display");
    let display = format!(":{}", number.trim());

    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let xdg = std::env::temp_dir().join(format!("roam-window-test-{}", std::process::id()));
    std::fs::create_dir_all(&xdg).expect("a runtime directory");
    let mut client = Command::new(env!("CARGO_BIN_EXE_roam-client"))
        .args([
            "--local",
            "data/synth-65",
            "--size",
            "320x240",
            "--budget",
            "2000",
        ])
        .current_dir(&root)
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .env("XDG_RUNTIME_DIR", &xdg)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("starting roam-client");
    let out = lines(client.stdout.take().expect("piped"));
    let err = lines(client.stderr.take().expect("piped"));
    let mut client = Reaped(client);
    let stderr = |err: &mpsc::Receiver<String>| err.try_iter().collect::<Vec<_>>().join("\n");

    let drawn = expect_line(&out, "window drawn", Duration::from_secs(180))
        .unwrap_or_else(|e| panic!("{e}\nstderr:\n{}", stderr(&err)));
    assert!(drawn.contains("triangles"), "{drawn}");

    // Focus the window and press q, as a person would.
    let status = Command::new("xdotool")
        .args([
            "search",
            "--name",
            "^roam",
            "windowfocus",
            "--sync",
            "key",
            "q",
        ])
        .env("DISPLAY", &display)
        .status()
        .expect("running xdotool");
    assert!(status.success(), "xdotool found and focused the window");

    let bye = expect_line(&out, "roam-client:", Duration::from_secs(60))
        .unwrap_or_else(|e| panic!("{e}\nstderr:\n{}", stderr(&err)));
    assert!(bye.contains("the server heard the goodbye"), "{bye}");
    // It exits, and with success (bounded: the stdout reader ends when the process does).
    let closed = out.recv_timeout(Duration::from_secs(60));
    assert!(
        matches!(closed, Err(mpsc::RecvTimeoutError::Disconnected)),
        "the client's output ends: {closed:?}"
    );
    let code = client.0.wait().expect("the client exits");
    assert!(code.success(), "{code}\nstderr:\n{}", stderr(&err));
    drop(xvfb);
    let _ = std::fs::remove_dir_all(xdg);
}
