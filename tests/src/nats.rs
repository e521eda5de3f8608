//! A real NATS server for the tests of the world and its edges: Debian's `nats-server`, on
//! a loopback port of its own, stopped when dropped. A machine without it fails the test
//! with a message naming the package. And an edge as a process of its own
//! ([`EdgeProcess`], the `roam-test-edge` binary), for a test to kill.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// The cluster secret of test world `world` (the same in every test process, so an edge in
/// a process of its own, `roam-test-edge`, holds its world's).
pub fn test_secret(world: &str) -> roam_server::net::bus::BusSecret {
    roam_server::net::bus::BusSecret::from_bytes(
        format!("the roam tests' bus secret for world {world}").as_bytes(),
    )
    .expect("longer than the shortest secret")
}

/// How long `nats-server` has to say it is ready.
const READY_WAIT: Duration = Duration::from_secs(20);

/// A running `nats-server`.
pub struct Nats {
    child: Child,
    pub port: u16,
    /// Its log's lines after "Server is ready", as they come.
    log: std::sync::Mutex<std::sync::mpsc::Receiver<String>>,
}

impl Nats {
    /// Starts `nats-server` on a free loopback port and waits until it is ready.
    pub fn start() -> Nats {
        // A port the kernel picked, freed for nats-server (which reports if it is taken).
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free loopback port")
            .port();
        Nats::on(port)
    }

    /// Starts `nats-server` on `port` (a restart: the same port as before).
    pub fn on(port: u16) -> Nats {
        Nats::with_args(port, &[])
    }

    /// Starts `nats-server` on a free loopback port, admitting only clients with `token`.
    pub fn with_token(token: &str) -> Nats {
        let port = Nats::start().kill();
        Nats::with_args(port, &["--auth", token])
    }

    /// Starts `nats-server` on a free loopback port with TLS (`--tls`: clients must speak
    /// it; their certificates are not asked for), presenting the certificate in the PEM
    /// file `cert` with its key in `key`.
    pub fn with_tls(cert: &std::path::Path, key: &std::path::Path) -> Nats {
        let port = Nats::start().kill();
        let (cert, key) = (cert.display().to_string(), key.display().to_string());
        Nats::with_args(port, &["--tls", "--tlscert", &cert, "--tlskey", &key])
    }

    fn with_args(port: u16, more: &[&str]) -> Nats {
        let mut child = Command::new("nats-server")
            .args(["-a", "127.0.0.1", "-p", &port.to_string()])
            .args(more)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "starting nats-server: {e}. The world/edge tests need Debian's \
                     `nats-server` package: apt-get install nats-server"
                )
            });
        let stderr = child.stderr.take().expect("stderr is piped");
        let (tx, rx) = std::sync::mpsc::channel();
        // Reads the log to its end (nats-server keeps writing to it), telling when ready.
        let (log_tx, log) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut said = false;
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if said {
                    let _ = log_tx.send(line);
                } else if line.contains("Server is ready") {
                    said = true;
                    let _ = tx.send(Ok(()));
                } else if line.contains("[FTL]") {
                    let _ = tx.send(Err(line));
                }
            }
        });
        match rx.recv_timeout(READY_WAIT) {
            Ok(Ok(())) => Nats {
                child,
                port,
                log: std::sync::Mutex::new(log),
            },
            Ok(Err(line)) => {
                let _ = child.kill();
                panic!("nats-server on port {port} failed: {line}")
            }
            Err(_) => {
                let _ = child.kill();
                panic!("nats-server on port {port} was not ready in {READY_WAIT:?}")
            }
        }
    }

    /// Starts `nats-server` on a free loopback port with `config` (the server's
    /// configuration file's text, e.g. `max_pending` or `write_deadline`).
    pub fn with_config(config: &str) -> Nats {
        let port = Nats::start().kill();
        let file =
            std::env::temp_dir().join(format!("roam-nats-{}-{port}.conf", std::process::id()));
        std::fs::write(&file, config).expect("a temporary nats-server configuration");
        Nats::with_args(port, &["-c", &file.display().to_string()])
    }

    /// The first line of its log from now on that holds `needle`, within `within`.
    pub fn logged(&self, needle: &str, within: Duration) -> Option<String> {
        let log = self.log.lock().unwrap_or_else(|e| e.into_inner());
        let mut left = within;
        loop {
            let started = std::time::Instant::now();
            let line = log.recv_timeout(left).ok()?;
            if line.contains(needle) {
                return Some(line);
            }
            left = left.checked_sub(started.elapsed())?;
        }
    }

    /// The URL clients connect to.
    pub fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    /// The URL clients connect to requiring TLS.
    pub fn tls_url(&self) -> String {
        format!("tls://127.0.0.1:{}", self.port)
    }

    /// Stops it (as `kill -9` would) and waits for it to be gone.
    pub fn kill(mut self) -> u16 {
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.port
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An edge of a test world in a process of its own (`roam-test-edge`), killed when dropped.
pub struct EdgeProcess {
    child: Child,
    pub addr: std::net::SocketAddr,
    pub fingerprint: [u8; 32],
    /// Its page's HTTPS address (and WebTransport's UDP one), when started with the page.
    pub web: Option<std::net::SocketAddr>,
}

impl EdgeProcess {
    /// Starts `exe` (the `roam-test-edge` binary) for `world` on `nats`, with the identity
    /// in `state`, and waits until it listens.
    pub fn start(exe: &str, nats: &Nats, world: &str, state: &std::path::Path) -> EdgeProcess {
        EdgeProcess::spawn(exe, nats, world, state, false)
    }

    /// As [`EdgeProcess::start`], serving the page too (`--web`).
    pub fn start_web(exe: &str, nats: &Nats, world: &str, state: &std::path::Path) -> EdgeProcess {
        EdgeProcess::spawn(exe, nats, world, state, true)
    }

    fn spawn(
        exe: &str,
        nats: &Nats,
        world: &str,
        state: &std::path::Path,
        web: bool,
    ) -> EdgeProcess {
        let mut child = Command::new(exe)
            .args([&nats.url(), world, &state.display().to_string()])
            .args(web.then_some("--web"))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {exe}: {e}"));
        let stdout = child.stdout.take().expect("stdout is piped");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        // Each line within READY_WAIT, and the one wanted within 100 lines.
        let said = |what: &str| {
            for _ in 0..100 {
                match rx.recv_timeout(READY_WAIT) {
                    Ok(line) => {
                        if let Some(rest) = line.strip_prefix(what) {
                            return rest.trim().to_owned();
                        }
                    }
                    Err(_) => panic!("{exe} did not say {what:?} in {READY_WAIT:?}"),
                }
            }
            panic!("{exe} did not say {what:?} in 100 lines");
        };
        let addr = said("listening on").parse().expect("an address");
        let fingerprint =
            roam_link::tls::parse_fingerprint(&said("fingerprint")).expect("a fingerprint");
        let web = web.then(|| said("web on").parse().expect("an address"));
        EdgeProcess {
            child,
            addr,
            fingerprint,
            web,
        }
    }

    /// Kills it (`kill -9`: no goodbye to its viewers or its world) and waits for it to go.
    pub fn kill(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for EdgeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
