//! A real NATS server for the tests of the world and its edges: Debian's `nats-server`, on
//! a loopback port of its own, stopped when dropped. A machine without it fails the test
//! with a message naming the package. And an edge as a process of its own
//! ([`EdgeProcess`], the `roam-test-edge` binary), for a test to kill.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use roam_protocol::sync::lock;

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
        let log = lock(&self.log);
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

/// The cluster tests' common ground: a world and its edges on one [`Nats`], sealing with
/// [`test_secret`].
pub mod cluster {
    use std::sync::Arc;
    use std::time::Duration;

    use futures_util::StreamExt;
    use roam_protocol::bus::{Answer, Ask};
    use roam_server::Terrain;
    use roam_server::net::Options;
    use roam_server::net::bus::BusOptions;
    use roam_server::net::bus::asker::Asker;
    use roam_server::net::bus::edge::Remote;
    use roam_server::net::bus::seal::RefusedCounts;
    use roam_server::net::bus::world::{WorldOptions, WorldServer};
    use roam_server::sim::session::RecordOptions;
    use roam_server::sim::world_core::Snapshot;

    use super::{Nats, test_secret};
    use crate::fixtures::{self, Running};

    /// World `world` on `nats`, sealed with its test secret.
    pub fn bus(nats: &Nats, world: &str) -> BusOptions {
        BusOptions {
            url: nats.url(),
            world: world.into(),
            creds: None,
            ca: None,
            name: "roam-test".into(),
            secret: Some(test_secret(world)),
        }
    }

    /// A world of `terrain` on `bus`: `hold` for a dropped driver's vehicle, at most
    /// `max_vehicles`, recording to `record` if given.
    pub async fn start_world(
        terrain: &Arc<Terrain>,
        bus: &BusOptions,
        (hold, max_vehicles): (Duration, usize),
        record: Option<RecordOptions>,
    ) -> WorldServer {
        let options = WorldOptions {
            record,
            hold,
            max_vehicles,
            replay: None,
        };
        WorldServer::start(terrain.clone(), terrain.content_hash(), options, bus)
            .await
            .expect("the world starts")
    }

    /// An edge of `bus`'s world on loopback, serving viewers, and its way to the world.
    pub async fn edge_and_remote(
        terrain: Arc<Terrain>,
        bus: &BusOptions,
    ) -> (Running, Arc<Remote>) {
        let remote = Remote::connect(
            bus,
            terrain.content_hash(),
            "the test terrain",
            vec![],
            Duration::from_secs(10),
        )
        .await
        .expect("the edge reaches the world");
        let running = fixtures::serve(terrain, |o| Options {
            remote: Some(remote.clone()),
            ..o
        });
        remote.set_addresses(vec![running.server.addr.to_string()]);
        (running, remote)
    }

    /// The world's snapshot once `f` holds of it, within `secs` seconds (else a panic
    /// naming `what`).
    pub async fn when(
        snaps: &mut tokio::sync::watch::Receiver<Arc<Snapshot>>,
        secs: u64,
        what: &str,
        f: impl FnMut(&Arc<Snapshot>) -> bool,
    ) -> Arc<Snapshot> {
        tokio::time::timeout(Duration::from_secs(secs), snaps.wait_for(f))
            .await
            .unwrap_or_else(|_| panic!("{what}: not within {secs} s"))
            .expect("the world runs")
            .clone()
    }

    /// The next `n` messages on `subject`, as a NATS client of no standing hears them
    /// (each within 5 s), and that client.
    pub async fn capture(
        nats: &Nats,
        subject: &str,
        n: usize,
    ) -> (async_nats::Client, Vec<bytes::Bytes>) {
        let client = async_nats::connect(nats.url()).await.expect("reaches NATS");
        let mut sub = client
            .subscribe(subject.to_owned())
            .await
            .expect("subscribes");
        let mut captured = Vec::with_capacity(n);
        while captured.len() < n {
            let msg = tokio::time::timeout(Duration::from_secs(5), sub.next())
                .await
                .unwrap_or_else(|_| panic!("a message on {subject} within 5 s"))
                .expect("subscribed");
            captured.push(msg.payload);
        }
        (client, captured)
    }

    /// An edge of the test's making, named `name`, sealing with `bus`'s secret, its
    /// requests for the world process that answered its first hello.
    pub async fn hand_made_edge(bus: &BusOptions, terrain: &Terrain, name: u64) -> Arc<Asker> {
        let client = bus.connect().await.expect("reaches NATS");
        let subjects = bus.subjects().expect("a valid name");
        let asker = Asker::start(
            client,
            &subjects,
            bus.key().as_ref(),
            name,
            Arc::new(RefusedCounts::default()),
        )
        .await
        .expect("subscribes to its answers");
        match asker.ask(&hello(terrain, name, vec![])).await {
            Ok(Answer::Hello { world, .. }) => asker.set_world(world),
            other => panic!("{other:?}"),
        }
        Arc::new(asker)
    }

    /// Edge `edge`'s hello naming `vehicles` (with their claims), with no address.
    pub fn hello(terrain: &Terrain, edge: u64, vehicles: Vec<(u16, u64)>) -> Ask {
        Ask::Hello {
            data: terrain.content_hash(),
            edge,
            addresses: vec![],
            vehicles,
        }
    }
}
