//! `serve`: the QUIC server.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use roam_link::tls;
use roam_server::net::{self, Options, Server};

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
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let record = record_dir.join(format!("session-{stamp}.rec"));
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let server = Server::start(
            Arc::new(terrain),
            Arc::new(vt),
            &identity,
            Options {
                record: Some(record.clone()),
                ..Options::new(args.listen, token.clone())
            },
        )?;
        say!("listening on {} (UDP)", server.addr);
        say!("fingerprint {}", identity.fingerprint());
        say!("token {token}");
        say!("recording to {}", record.display());
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
        say!(
            "stopped at tick {}; the session replays with: roam-server replay {} --data {}",
            world.tick(),
            record.display(),
            args.dir.display()
        );
        Ok(())
    })
}
