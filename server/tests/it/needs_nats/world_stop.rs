//! `roam-server world` stops on SIGINT even when its NATS server is gone (issue 39, defect
//! 9: its shutdown flushed the NATS connection and waited for a reconnection that never
//! came, so the process never exited). A real Debian `nats-server` on a loopback port of
//! its own, the real binary as a child process: NATS killed, then SIGINT, and the world must
//! have exited within [`LIVENESS`] — a bound on "never", not a speed threshold (the world
//! bounds its flush to 0.5 s; `net::bus::world`'s `shutdown`).

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use crate::common;

use common::{TempDir, root};

/// Time for `nats-server` and the world to say they are ready (a cold debug build).
const READY_WAIT: Duration = Duration::from_secs(60);
/// The world must have exited this long after SIGINT: it once never did.
const LIVENESS: Duration = Duration::from_secs(10);

/// A child process killed (and reaped) when dropped, so a failing test leaves none behind.
struct Killed(Option<Child>);

impl Drop for Killed {
    fn drop(&mut self) {
        if let Some(child) = &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The lines `read` gives, sent on a channel as they come (read to the end on a thread).
fn lines(read: impl std::io::Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(read).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Waits for a line holding `needle` among `rx`'s next 200, each within [`READY_WAIT`].
fn said(rx: &mpsc::Receiver<String>, what: &str, needle: &str) {
    for _ in 0..200 {
        match rx.recv_timeout(READY_WAIT) {
            Ok(line) if line.contains(needle) => return,
            Ok(_) => {}
            Err(e) => panic!("{what} did not say {needle:?}: {e}"),
        }
    }
    panic!("{what} did not say {needle:?} in 200 lines");
}

#[test]
fn world_exits_on_sigint_with_its_nats_gone() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free loopback port")
        .port();
    let mut nats = Command::new("nats-server")
        .args(["-a", "127.0.0.1", "-p", &port.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| {
            panic!("starting nats-server: {e}. This test needs Debian's `nats-server` package")
        });
    let nats_log = lines(nats.stderr.take().expect("stderr is piped"));
    let mut nats = Killed(Some(nats));
    said(&nats_log, "nats-server", "Server is ready");

    let state = TempDir::new("world-stop");
    let url = format!("nats://127.0.0.1:{port}");
    let key = state.path("bus.key");
    std::fs::write(&key, "the world-stop test's bus secret, 32 bytes or more\n")
        .expect("a secret written");
    let mut world = Command::new(env!("CARGO_BIN_EXE_roam-server"))
        .args(["world", "data/synth-65", "--nats", &url, "--world", "stop"])
        .args(["--state-dir", state.str()])
        .arg("--bus-secret")
        .arg(&key)
        .current_dir(root())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("run roam-server world");
    let pid = world.id();
    let out = lines(world.stdout.take().expect("stdout is piped"));
    let mut world = Killed(Some(world));
    said(&out, "roam-server world", "serve it with: roam-server edge");

    // NATS gone (as `kill -9` would), then Ctrl-C.
    if let Some(mut n) = nats.0.take() {
        let _ = n.kill();
        let _ = n.wait();
    }
    let sent = Command::new("kill")
        .args(["-INT", &pid.to_string()])
        .status()
        .expect("run kill");
    assert!(sent.success(), "kill -INT {pid}: {sent}");

    // Waited for on a thread of its own, so that the wait itself is bounded.
    let (tx, exited) = mpsc::channel();
    let mut child = world.0.take().expect("the world is running");
    let waiter = std::thread::spawn(move || {
        let status = child.wait();
        let _ = tx.send(status.map(|s| s.code()));
        child
    });
    match exited.recv_timeout(LIVENESS) {
        Ok(status) => {
            let code = status.expect("waiting for the world");
            assert_eq!(code, Some(0), "the world stopped, but not cleanly");
        }
        Err(_) => {
            // Still running: killed so the test ends, and failed.
            let _ = Command::new("kill")
                .args(["-KILL", &pid.to_string()])
                .status();
            let _ = waiter.join();
            panic!("roam-server world was still running {LIVENESS:?} after SIGINT with NATS gone");
        }
    }
    let _ = waiter.join();
    // Its last lines: the pipe is closed, so the reader ends.
    let rest: Vec<String> = (0..200)
        .map_while(|_| out.recv_timeout(READY_WAIT).ok())
        .collect();
    assert!(
        rest.iter().any(|l| l.starts_with("stopped at tick")),
        "the world said {rest:?}"
    );
}
