//! `serve`: the QUIC server. The colour and normal pyramids are mapped from the data set's
//! cache (`.cache/color-tiles.bin`, `.cache/normal-tiles.bin`), or built (with a progress
//! bar) and cached there. On glibc,
//! `malloc` is told to keep mapping large blocks on their own (`keep_large_blocks_mapped`:
//! what freed viewers' tables go back to the system, measured there).
//!
//! With `--web ADDR`, the browser viewer too (`net::web`): the page built into this binary
//! (refused at once if there is none) over HTTPS, WebTransport beside it. Its certificate
//! is made and renewed by the server, for `localhost`, the loopback addresses, `ADDR`'s
//! address, this machine's LAN address and host name; or `--web-cert`/`--web-key` give one
//! browsers trust. The page's address printed carries the token in its fragment
//! (`#token=`): the one printed URL with a `#`.
//!
//! The server's QUIC identity (the certificate viewers pin) is the state directory's, or
//! with `--cert`/`--key` one from files (`tls::load_files`), which the edges of one world
//! can share.

use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::served::{Served, data_hash, open_replay, open_served, record_files};
use anyhow::{Context, Result};
use clap::Args;
use roam_link::tls;
use roam_server::net::bus::BusOptions;
use roam_server::net::bus::edge::Remote;
use roam_server::net::{self, Options, Server};
use roam_server::sim::session::{self, RecordOptions};
use roam_server::viewer::ViewerLimits;
use roam_server::viewer::admission::viewer_bytes;
use roam_server::web::{Page, cert};
use std::time::Duration;

#[derive(Args)]
pub(crate) struct ServeArgs {
    /// Data set directory.
    pub dir: PathBuf,
    /// Address to listen on (UDP).
    #[arg(long, default_value = "0.0.0.0:4433")]
    pub listen: SocketAddr,
    /// The join token viewers must present.
    #[command(flatten)]
    pub token: super::token::TokenArgs,
    /// Where the certificate is kept (made on first run), unless --cert and --key give it.
    #[arg(long, default_value = "roam-state")]
    pub state_dir: PathBuf,
    /// The server's certificate (with --key), instead of the state directory's: X.509, DER
    /// or PEM (its first CERTIFICATE). Viewers pin its SHA-256, so the edges of one world
    /// given the same files share one fingerprint.
    #[arg(long, value_name = "FILE", requires = "key")]
    pub cert: Option<PathBuf>,
    /// The private key of --cert: PKCS#8, DER or PEM (`BEGIN PRIVATE KEY`).
    #[arg(long, value_name = "FILE", requires = "cert")]
    pub key: Option<PathBuf>,
    /// Where sessions are recorded (default: `recordings` in the state directory).
    #[arg(long)]
    pub record_dir: Option<PathBuf>,
    /// Viewers served at once (drivers and spectators); the next is refused as full.
    #[arg(long, default_value_t = net::MAX_VIEWERS)]
    pub max_viewers: usize,
    /// Bytes the viewers' state may hold together: each viewer's seat reserves an estimate
    /// from its budget (about 6.7 MiB at 65,536 triangles: 64 bytes a triangle for its cut
    /// and 2.7 MiB for its connection); the next viewer that would not fit is refused with
    /// a reason naming this limit, and a budget raised later is served as far as it fits.
    /// A number of bytes, or with K, M, G or T (times 1024 each; `512M`, `4G`, `1.5GiB`).
    /// Default: half the memory available (MemAvailable in /proc/meminfo) when the server
    /// starts, leaving the rest to the page cache the data set is served from.
    #[arg(long, value_name = "BYTES", value_parser = max_memory)]
    pub max_memory: Option<u64>,
    /// Connections in their handshake or hello at once; past it, new ones must prove
    /// their address (QUIC Retry), and the oldest pending one is closed for a proven one.
    #[arg(long, default_value_t = net::MAX_PENDING)]
    pub max_pending: usize,
    /// Seconds a connection has for its TLS handshake and hello together.
    #[arg(long, default_value_t = net::HELLO_TIMEOUT.as_secs_f64(), value_parser = seconds)]
    pub hello_timeout: f64,
    /// Most triangles per frame a viewer is served, whatever it asks.
    #[arg(long, default_value_t = roam_protocol::messages::MAX_BUDGET)]
    pub max_budget: u32,
    /// Most frames a second a viewer is served, whatever it asks.
    #[arg(long, default_value_t = roam_server::viewer::MAX_FPS)]
    pub max_fps: u16,
    /// How the served cuts are made: --fog-priority, --guard-deg, --swap-margin.
    #[command(flatten)]
    pub cut: roam_server::viewer::CutArgs,
    /// Seconds a driver's vehicle is held after its connection drops, for it to come back.
    #[arg(long, default_value_t = net::HOLD.as_secs_f64(), value_parser = seconds)]
    pub hold: f64,
    /// Seconds between the summary lines in the log.
    #[arg(long, default_value_t = 60.0, value_parser = seconds)]
    pub log_every: f64,
    /// A recording file is closed and the next begun before it grows past this many bytes
    /// (64 KiB to 256 MiB, the most `replay` reads).
    #[arg(long, default_value_t = session::DEFAULT_MAX_BYTES,
          value_parser = clap::value_parser!(u64).range(session::MIN_MAX_BYTES..=session::MAX_MAX_BYTES))]
    pub record_max_bytes: u64,
    /// Colour tile bytes a second at most, per viewer, after the coarsest tile.
    #[arg(long, default_value_t = net::COLOR_RATE,
          value_parser = clap::value_parser!(u64).range(1_000..))]
    pub color_rate: u64,
    /// Colour tile bytes a second at most, every viewer together: shared equally by the
    /// viewers still getting tiles (each at most --color-rate), and slowed to a trickle
    /// while frames are behind.
    #[arg(long, default_value_t = net::COLOR_TOTAL,
          value_parser = clap::value_parser!(u64).range(1_000..))]
    pub color_total: u64,
    /// Colour window offered: tiles a side kept per level (1 ..= 16); a viewer asking
    /// less gets its own.
    #[arg(long, default_value_t = roam_protocol::tiles::DEFAULT_WINDOW,
          value_parser = clap::value_parser!(u8).range(1..=i64::from(roam_protocol::tiles::MAX_WINDOW)))]
    pub color_window: u8,
    /// Also serve the browser viewer on this address: its page over HTTPS (TCP) and
    /// WebTransport (UDP, the same port).
    #[arg(long, value_name = "ADDR")]
    pub web: Option<SocketAddr>,
    /// The browser viewer's certificate chain (PEM), one browsers trust (with --web-key).
    /// Without it, a certificate is made, renewed every 6 days, and pinned by the page.
    #[arg(long, value_name = "PEM", requires = "web_key", requires = "web")]
    pub web_cert: Option<PathBuf>,
    /// The private key (PEM) of --web-cert.
    #[arg(long, value_name = "PEM", requires = "web_cert", requires = "web")]
    pub web_key: Option<PathBuf>,
    /// Serve this recording instead of a live world, from its start at 1×: every viewer
    /// watches it as a spectator, the one holding the controls pauses, speeds and seeks it
    /// for all; nothing is recorded. A recording of another data set is refused.
    #[arg(long, value_name = "FILE")]
    pub replay: Option<PathBuf>,
    /// With --replay: the viewer joining with this token (instead of the join token)
    /// holds the controls (the first of them still there; nobody while none is). Without
    /// it, the first viewer to join does (then the next).
    #[arg(long, value_name = "TOKEN", requires = "replay")]
    pub control: Option<String>,
    /// With --replay: the recording is still being written (a session going on): watch it
    /// from its newest whole tick on, following it as it grows, until its end record
    /// (seek back as in any recording).
    #[arg(long, requires = "replay")]
    pub follow: bool,
}

/// A number of seconds: finite, positive and at most a day.
fn seconds(text: &str) -> Result<f64, String> {
    let s: f64 = text
        .parse()
        .map_err(|_| format!("{text:?}: expected a number of seconds"))?;
    if !(s > 0.0 && s <= 86_400.0) {
        return Err(format!(
            "{text}: expected more than 0 and at most 86400 seconds"
        ));
    }
    Ok(s)
}

/// A number of bytes: digits (a decimal point allowed with a suffix), then optionally K,
/// M, G or T (times 1024 each), then optionally `B` or `iB`; case and a space before the
/// suffix do not matter.
pub(crate) fn byte_size(text: &str) -> Result<u64, String> {
    let expected =
        || format!("{text:?}: expected a number of bytes, such as 536870912, 512M, 4G or 1.5GiB");
    let t = text.trim();
    let split = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, suffix) = t.split_at(split);
    let suffix = suffix.trim_start().to_ascii_lowercase();
    let unit = suffix
        .strip_suffix("ib")
        .or_else(|| suffix.strip_suffix('b'))
        .unwrap_or(&suffix);
    let shift = match unit {
        "" if !suffix.is_empty() => 0, // a plain `B`
        "" => {
            // Digits only: a whole number of bytes.
            return number.parse().map_err(|_| expected());
        }
        "k" => 10,
        "m" => 20,
        "g" => 30,
        "t" => 40,
        _ => return Err(expected()),
    };
    let value: f64 = number.parse().map_err(|_| expected())?;
    let bytes = (value * (1u64 << shift) as f64).round();
    if !(bytes.is_finite() && bytes >= 0.0 && bytes < 2f64.powi(64)) {
        return Err(expected());
    }
    Ok(bytes as u64)
}

/// `--max-memory`: a [`byte_size`] with room for one viewer at the fewest triangles.
fn max_memory(text: &str) -> Result<u64, String> {
    let bytes = byte_size(text)?;
    let least = viewer_bytes(roam_protocol::messages::MIN_BUDGET);
    if bytes < least {
        return Err(format!(
            "{text:?}: expected at least {least} bytes (one viewer at the fewest triangles)"
        ));
    }
    Ok(bytes)
}

impl ServeArgs {
    /// The serving options these flags give, or why they are wrong.
    fn options(&self, token: String, record: Option<RecordOptions>) -> Result<Options> {
        let limits = self.cut.limits(ViewerLimits {
            max_budget: self.max_budget,
            max_fps: self.max_fps,
            ..ViewerLimits::default()
        });
        anyhow::ensure!(
            limits.clamped() == limits,
            "--max-budget {} / --max-fps {}: expected {} ..= {} triangles and 1 ..= {} frames a second",
            self.max_budget,
            self.max_fps,
            roam_protocol::messages::MIN_BUDGET,
            roam_protocol::messages::MAX_BUDGET,
            roam_server::viewer::MAX_FPS
        );
        anyhow::ensure!(self.max_viewers >= 1, "--max-viewers: expected at least 1");
        anyhow::ensure!(self.max_pending >= 1, "--max-pending: expected at least 1");
        Ok(Options {
            record,
            limits,
            max_viewers: self.max_viewers,
            max_memory: self.max_memory,
            max_pending: self.max_pending,
            hello_timeout: Duration::from_secs_f64(self.hello_timeout),
            hold: Duration::from_secs_f64(self.hold),
            summary_every: Duration::from_secs_f64(self.log_every),
            color_rate: self.color_rate,
            color_total: self.color_total,
            color_window: self.color_window,
            ..Options::new(self.listen, token)
        })
    }
}

/// The browser viewer's options for `--web ADDR`, `--web-cert` and `--web-key`, and the
/// host its page's address names.
fn web_options(args: &ServeArgs, listen: SocketAddr) -> Result<(net::web::WebOptions, String)> {
    let page = Page::embedded();
    anyhow::ensure!(page.is_built(), "{}", roam_server::web::NOT_BUILT);
    if page.is_quick() {
        tracing::warn!(
            "the page is the tests' quick build (scripts/build-web --quick): larger and slower \
             to load; to publish it, run scripts/build-web, then build roam-server again"
        );
    }
    let lan = listen
        .ip()
        .is_unspecified()
        .then(|| lan_address(listen.ip()))
        .flatten();
    let hostname = hostname();
    let cert = match (&args.web_cert, &args.web_key) {
        (Some(cert), Some(key)) => load_pem(cert, key)?,
        _ => net::web::WebCert::Made {
            names: cert::subject_names(listen.ip(), lan, hostname.as_deref()),
        },
    };
    let host = if !listen.ip().is_unspecified() {
        listen.ip().to_string()
    } else if let Some(ip) = lan {
        ip.to_string()
    } else {
        hostname.unwrap_or_else(|| "localhost".into())
    };
    let options = net::web::WebOptions {
        listen,
        page: Arc::new(page),
        cert,
    };
    Ok((options, host))
}

/// Where viewers reach an edge, as the world tells the other edges' viewers: its QUIC
/// `host:port` and, with `--web`, its WebTransport URL with the certificate hashes to pin.
fn edge_addresses(server: &Server, advertise: Option<&str>, web_host: Option<&str>) -> Vec<String> {
    let ip = server.addr.ip();
    let host = match advertise {
        Some(host) => host.to_owned(),
        None if !ip.is_unspecified() => ip.to_string(),
        None => lan_address(ip).map_or_else(|| "127.0.0.1".into(), |ip| ip.to_string()),
    };
    let native = match host.parse::<std::net::Ipv6Addr>() {
        Ok(_) => format!("[{host}]:{}", server.addr.port()),
        Err(_) => format!("{host}:{}", server.addr.port()),
    };
    let mut out = vec![native];
    if let (Some(addr), Some(web_host)) = (server.web_addr(), web_host) {
        let web_host = advertise.unwrap_or(web_host);
        out.push(roam_server::web::transport_url(
            web_host,
            addr.port(),
            &server.web_hashes(),
        ));
    }
    out
}

/// This machine's address on its LAN for `listen`'s family (IPv4 first for `[::]`): the
/// source address of a route out, found by connecting a UDP socket (no packet is sent).
fn lan_address(listen: IpAddr) -> Option<IpAddr> {
    let routes: &[(&str, &str)] = match listen {
        IpAddr::V4(_) => &[("0.0.0.0:0", "192.0.2.1:9")],
        IpAddr::V6(_) => &[("0.0.0.0:0", "192.0.2.1:9"), ("[::]:0", "[2001:db8::1]:9")],
    };
    routes.iter().find_map(|(bind, to)| {
        let socket = std::net::UdpSocket::bind(bind).ok()?;
        socket.connect(to).ok()?;
        let ip = socket.local_addr().ok()?.ip();
        (!ip.is_unspecified() && !ip.is_loopback()).then_some(ip)
    })
}

/// This machine's host name, if the kernel says one.
fn hostname() -> Option<String> {
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname").ok()?;
    let name = name.trim();
    (!name.is_empty() && name != "(none)").then(|| name.to_owned())
}

/// A certificate chain and its key from PEM files, checked to match.
fn load_pem(cert: &Path, key: &Path) -> Result<net::web::WebCert> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let read = |flag: &str, path: &Path| {
        std::fs::read(path).with_context(|| format!("{flag} {}: reading it", path.display()))
    };
    let bytes = read("--web-cert", cert)?;
    let chain = CertificateDer::pem_slice_iter(&bytes)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| {
            anyhow::anyhow!(
                "--web-cert {}: not a PEM certificate chain: {e}",
                cert.display()
            )
        })?;
    anyhow::ensure!(
        !chain.is_empty(),
        "--web-cert {}: no CERTIFICATE in it",
        cert.display()
    );
    let bytes = read("--web-key", key)?;
    let key_der = PrivateKeyDer::from_pem_slice(&bytes)
        .map_err(|e| anyhow::anyhow!("--web-key {}: not a PEM private key: {e}", key.display()))?;
    cert::CertStore::given(chain.clone(), key_der.clone_key()).with_context(|| {
        format!(
            "--web-cert {} with --web-key {}",
            cert.display(),
            key.display()
        )
    })?;
    Ok(net::web::WebCert::Given {
        chain,
        key: key_der,
    })
}

/// The allocation size from which glibc's `malloc` maps each block of its own (and unmaps
/// it when freed), kept fixed: twice glibc's starting value.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: libc::c_int = 256 << 10;

/// Keeps glibc's `malloc` mapping every block of [`MMAP_THRESHOLD`] or more on its own.
/// By default the threshold rises to the largest mapped block freed (up to 32 MiB): a
/// viewer's cut grows its tables by doubling, every freed table raises it, and from then on
/// the tables come from the allocator's arenas, which keep what is freed and spread it over
/// a heap per thread (frames are made on any worker or blocking thread). Measured with
/// `scripts/viewer_memory.sh` (4097², 65,536 triangles, driving), anonymous memory a
/// viewer: 17.7–20.2 MB with the rising threshold (four runs), 14.0–14.4 with it fixed at
/// 256 KiB, 12.3–12.9 at 128 KiB, 16.2 at 1 MiB; the cut's heap is 13.3–14.5 MB (a mapped
/// table is resident only where it is written), and heaptrack put everything else a viewer
/// holds at about 0.2 MB. A mapped block costs an `mmap` when it is made and a `munmap`
/// when freed: 10 viewers at 32,768 triangles on `data/kossou`, 6,000 frames, made 436 +
/// 466 + 298 (`mremap`) such calls at 256 KiB, 965 + 959 + 1,174 at 128 KiB (the cut's
/// schedule buckets growing and shrinking; 20 viewers' CPU per frame 368–372 µs against
/// 361–364 with the rising threshold), 24 + 45 + 15 with the rising threshold.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_large_blocks_mapped() {
    // SAFETY: `mallopt` sets one of glibc's allocator settings; any value is safe to set,
    // at any time, from any thread.
    if unsafe { libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD) } != 1 {
        tracing::warn!("malloc's mmap threshold could not be fixed: viewers may hold more memory");
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_large_blocks_mapped() {}

pub(crate) fn serve(args: ServeArgs) -> Result<()> {
    serve_on(args, None)
}

/// An edge's way to its world (`roam-server edge`, [`super::cluster`]), for [`serve_on`].
pub(crate) struct Edge {
    pub(super) bus: BusOptions,
    pub(super) wait: Duration,
    /// The host its viewers reach it at, if given.
    pub advertise: Option<String>,
}

impl Edge {
    /// Reaches the world and checks it serves this data set (`hash`).
    pub(crate) async fn reach(&self, args: &ServeArgs, hash: [u8; 32]) -> Result<Arc<Remote>> {
        let dir = args.dir.display().to_string();
        // The addresses follow once the edge listens (its ports may be chosen then).
        let remote = Remote::connect(&self.bus, hash, &dir, Vec::new(), self.wait).await?;
        tracing::info!(
            world = remote.world(),
            "the world answered: the same data set"
        );
        Ok(remote)
    }
}

/// `serve`, or with `bus` an edge of that world (`roam-server edge`): the world's
/// snapshots served, its tickets handed out, nothing recorded here (the world records).
pub(crate) fn serve_on(args: ServeArgs, bus: Option<Edge>) -> Result<()> {
    keep_large_blocks_mapped();
    // The page and the certificate files (the browser's, and the server's identity when
    // given) first, then the token: each fails before anything is loaded.
    let web = args
        .web
        .map(|listen| web_options(&args, listen))
        .transpose()?;
    let given = match (&args.cert, &args.key) {
        (Some(cert), Some(key)) => {
            Some(tls::load_files(cert, key).context("the server's identity (--cert, --key)")?)
        }
        (None, None) => None,
        _ => anyhow::bail!("--cert and --key go together"),
    };
    let token = args.token.resolve()?;
    tracing::info!("join token from {}", token.source);
    let token = token.as_str().to_owned();
    let Served {
        terrain,
        variance: vt,
        pyramid,
        normals,
        report,
    } = open_served(&args.dir)?;
    let hash = data_hash(&args.dir, &terrain, &report)?;
    let identity = match given {
        Some(identity) => identity,
        None => tls::load_or_create(&args.state_dir)?,
    };
    let terrain = Arc::new(terrain);
    let replay = match (&args.replay, &bus) {
        (Some(file), None) => Some(open_replay(
            file,
            (&args.control, args.follow),
            &terrain,
            &hash,
        )?),
        (Some(_), Some(_)) => anyhow::bail!("an edge serves its world's recording, not --replay"),
        (None, _) => None,
    };
    // An edge records nothing: its world does; nor does a replay.
    let recording = match (&bus, &replay) {
        (None, None) => Some(record_files(&args.state_dir, args.record_dir.as_deref())?),
        _ => None,
    };
    let made = recording
        .as_ref()
        .map(|(dir, files)| (dir.clone(), files.made()));
    let web_host = web.as_ref().map(|(_, host)| host.clone());
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let remote = match &bus {
            Some(edge) => Some(edge.reach(&args, hash).await?),
            None => None,
        };
        // Timed apart: `Server::start` scans every height for the codec's height step
        // (`roam_protocol::height_step`), most of a warm start at 16385² and more.
        let started = std::time::Instant::now();
        let server = Server::start(
            terrain,
            Arc::new(vt),
            Arc::new(pyramid),
            &identity,
            Options {
                web: web.map(|(options, _)| options),
                record: recording.map(|(_, files)| {
                    RecordOptions::new(files, args.record_max_bytes).with_terrain_hash(hash)
                }),
                remote: remote.clone(),
                normals: Some(Arc::new(normals)),
                replay,
                ..args.options(token.clone(), None)?
            },
        )?;
        tracing::info!(
            "server started in {:.0} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
        say!("listening on {} (UDP)", server.addr);
        say!("fingerprint {}", identity.fingerprint());
        if let (Some(r), Some(edge)) = (&remote, &bus) {
            let addresses = edge_addresses(&server, edge.advertise.as_deref(), web_host.as_deref());
            say!(
                "edge of the world {:?}: it records the session; this edge is {}",
                r.world(),
                addresses.join(" and ")
            );
            r.set_addresses(addresses);
            let others: Vec<String> = r.edges();
            if !others.is_empty() {
                say!("the world's other edges: {}", others.join(", "));
            }
        }
        if let Some((_, made)) = &made {
            let first = made.list().first().map(|p| p.display().to_string());
            say!("recording to {}", first.as_deref().unwrap_or("nothing"));
        }
        let host = if server.addr.ip().is_unspecified() {
            format!("<this machine's address>:{}", server.addr.port())
        } else {
            server.addr.to_string()
        };
        say!(
            "connect with: roam-client --connect {host} --token {token} --fingerprint {} --headless",
            identity.fingerprint()
        );
        if let (Some(addr), Some(host)) = (server.web_addr(), &web_host) {
            say!("browser viewer on {addr} (HTTPS over TCP, WebTransport over UDP)");
            if let Some(sha) = server.web_certificate() {
                let how = if args.web_cert.is_some() {
                    "given"
                } else {
                    "made here, renewed every 6 days; browsers warn about it once, \
                     and the page pins it by this hash"
                };
                say!("browser certificate SHA-256 {} ({how})", tls::hex(&sha));
            }
            say!(
                "or open in a browser: {}",
                roam_server::web::page_url(host, addr.port(), &token)
            );
        }
        // An edge says its addresses again each minute: a made browser certificate is
        // renewed every few days, and the pages of the other edges pin it by its hash.
        let mut renew = tokio::time::interval(Duration::from_secs(60));
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        loop {
            tokio::select! {
                r = &mut ctrl_c => break r.context("waiting for Ctrl-C")?,
                _ = renew.tick() => {
                    if let (Some(r), Some(edge)) = (&remote, &bus) {
                        let advertise = edge.advertise.as_deref();
                        r.set_addresses(edge_addresses(&server, advertise, web_host.as_deref()));
                    }
                }
            }
        }
        say!("shutting down");
        let world = server.shutdown().await?;
        if let Some(r) = &remote {
            r.settle(Duration::from_secs(5)).await;
        }
        let Some((record_dir, made)) = &made else {
            say!("stopped (the world was at tick {})", world.tick());
            return Ok(());
        };
        match made.list().as_slice() {
            [] => say!("stopped at tick {}", world.tick()),
            [one] => say!(
                "stopped at tick {}; the session replays with: roam-server replay {} --data {}",
                world.tick(),
                one.display(),
                args.dir.display()
            ),
            [first, .., last] => say!(
                "stopped at tick {}; the session is in {} files in {}, {} to {}; each replays \
                 with: roam-server replay FILE --data {}",
                world.tick(),
                made.list().len(),
                record_dir.display(),
                first.display(),
                last.display(),
                args.dir.display()
            ),
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::{byte_size, max_memory};

    #[test]
    fn byte_sizes_take_suffixes_and_refuse_anything_else() {
        let cases = [
            ("536870912", 536_870_912),
            ("512M", 512 << 20),
            ("512m", 512 << 20),
            ("512MiB", 512 << 20),
            ("512 MB", 512 << 20),
            ("4G", 4 << 30),
            ("1.5GiB", 3 << 29),
            ("2t", 2 << 40),
            ("64K", 64 << 10),
            ("100B", 100),
        ];
        for (text, bytes) in cases {
            assert_eq!(byte_size(text), Ok(bytes), "{text}");
        }
        for bad in [
            "",
            "G",
            "lots",
            "4X",
            "4GG",
            "-1G",
            "1.5",
            "1e3",
            "99999999999T",
            "4 G B",
        ] {
            let e = byte_size(bad).expect_err(bad);
            assert!(e.contains("expected a number of bytes"), "{bad}: {e}");
        }
        assert_eq!(max_memory("4G"), Ok(4 << 30));
        let e = max_memory("1K").expect_err("too small for one viewer");
        assert!(e.contains("expected at least"), "{e}");
    }
}
