//! `roam-relay`: a seeded lossy UDP relay ([`roam_tests::relay`]) for measuring a server
//! and viewers over a bad network on one machine. The same settings apply each way. Its first
//! line on stdout is `listening on ADDR`; it runs until Ctrl-C or SIGTERM, then prints what
//! it forwarded and dropped to stderr. SIGUSR1 cuts the relay (every datagram dropped, both
//! ways, as a dropped Wi-Fi connection) or restores it, and says which on stderr: to watch a
//! viewer reconnect by hand.
//!
//! ```sh
//! roam-relay --to 127.0.0.1:4433 --delay-ms 40 --loss 0.05 --seed 1
//! kill -USR1 $(pidof roam-relay)   # cut; again to restore
//! ```
// A tool whose output is its figures or its addresses, on stdout.
#![allow(clippy::print_stdout)]

use std::io::Write;
use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;
use roam_tests::relay::{Direction, Relay, RelayConfig};

#[derive(Parser)]
#[command(
    name = "roam-relay",
    about = "Relay UDP to a server with delay, jitter and seeded loss"
)]
struct Cli {
    /// Where to relay to (the server), `HOST:PORT`.
    #[arg(long)]
    to: SocketAddr,
    /// Where to listen for clients.
    #[arg(long, default_value = "127.0.0.1:0")]
    listen: SocketAddr,
    /// One-way delay, milliseconds (each way).
    #[arg(long, default_value_t = 40.0)]
    delay_ms: f64,
    /// Uniform extra delay in [0, jitter), milliseconds (datagrams may be reordered).
    #[arg(long, default_value_t = 0.0)]
    jitter_ms: f64,
    /// Probability that a datagram is dropped (each way).
    #[arg(long, default_value_t = 0.05)]
    loss: f64,
    /// A bottleneck rate each way, bytes a second (none by default).
    #[arg(long)]
    rate: Option<u64>,
    /// Seed of the drops and the jitter.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn millis(name: &str, ms: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(ms / 1e3)
        .with_context(|| format!("--{name} {ms}: expected milliseconds >= 0"))
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let direction = Direction {
        delay: millis("delay-ms", cli.delay_ms)?,
        jitter: millis("jitter-ms", cli.jitter_ms)?,
        loss: cli.loss,
        rate_bytes_per_s: cli.rate,
    };
    let relay = Relay::start_on(
        cli.listen,
        cli.to,
        RelayConfig::symmetric(direction, cli.seed),
    )
    .await?;
    {
        let mut out = std::io::stdout().lock();
        writeln!(out, "listening on {}", relay.addr()).context("writing to stdout")?;
        out.flush().context("writing to stdout")?;
    }
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = signal(SignalKind::terminate()).context("listening for SIGTERM")?;
    let mut toggle = signal(SignalKind::user_defined1()).context("listening for SIGUSR1")?;
    let ctrl_c = tokio::signal::ctrl_c();
    tokio::pin!(ctrl_c);
    loop {
        tokio::select! {
            r = &mut ctrl_c => {
                r.context("listening for Ctrl-C")?;
                break;
            }
            _ = term.recv() => break,
            Some(()) = toggle.recv() => {
                if relay.is_cut() {
                    relay.restore();
                    eprintln!("roam-relay: restored");
                } else {
                    relay.cut();
                    eprintln!("roam-relay: cut");
                }
            }
        }
    }
    eprintln!("roam-relay: {}", relay.stats());
    Ok(())
}
