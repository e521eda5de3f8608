//! `serve`: the QUIC server.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use roam_link::tls;
use roam_server::net::{self, Options, Server};
use roam_server::sim::record_files::RecordDir;
use roam_server::sim::session::{self, RecordOptions};

#[derive(Args)]
pub struct ServeArgs {
    /// Data set directory.
    pub dir: PathBuf,
    /// Address to listen on (UDP).
    #[arg(long, default_value = "0.0.0.0:4433")]
    pub listen: SocketAddr,
    /// The join token viewers must present (default: a random one, printed at start).
    #[arg(long)]
    pub token: Option<String>,
    /// Where the certificate is kept (made on first run).
    #[arg(long, default_value = "roam-state")]
    pub state_dir: PathBuf,
    /// Where sessions are recorded (default: `recordings` in the state directory).
    #[arg(long)]
    pub record_dir: Option<PathBuf>,
    /// A recording file is closed and the next begun before it grows past this many bytes
    /// (64 KiB to 256 MiB, the most `replay` reads).
    #[arg(long, default_value_t = session::DEFAULT_MAX_BYTES,
          value_parser = clap::value_parser!(u64).range(session::MIN_MAX_BYTES..=session::MAX_MAX_BYTES))]
    pub record_max_bytes: u64,
}

pub fn serve(args: ServeArgs) -> Result<()> {
    let (terrain, vt, _) = super::tess::load(&args.dir)?;
    let identity = tls::load_or_create(&args.state_dir)
        .with_context(|| format!("the certificate in {}", args.state_dir.display()))?;
    let token = args.token.unwrap_or_else(net::random_token);
    let record_dir = args
        .record_dir
        .unwrap_or_else(|| args.state_dir.join("recordings"));
    std::fs::create_dir_all(&record_dir)
        .with_context(|| format!("creating {}", record_dir.display()))?;
    let files = RecordDir::new(&record_dir, net::world_loop::unix_seconds);
    let made = files.made();
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let server = Server::start(
            Arc::new(terrain),
            Arc::new(vt),
            &identity,
            Options {
                record: Some(RecordOptions::new(files, args.record_max_bytes)),
                ..Options::new(args.listen, token.clone())
            },
        )?;
        say!("listening on {} (UDP)", server.addr);
        say!("fingerprint {}", identity.fingerprint());
        say!("token {token}");
        let first = made.list().first().map(|p| p.display().to_string());
        say!("recording to {}", first.as_deref().unwrap_or("nothing"));
        let host = if server.addr.ip().is_unspecified() {
            format!("<this machine's address>:{}", server.addr.port())
        } else {
            server.addr.to_string()
        };
        say!(
            "connect with: roam-client --connect {host} --token {token} --fingerprint {} --headless",
            identity.fingerprint()
        );
        tokio::signal::ctrl_c()
            .await
            .context("waiting for Ctrl-C")?;
        say!("shutting down");
        let world = server.shutdown().await?;
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
