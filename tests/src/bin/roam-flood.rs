//! `roam-flood`: what junk connections cost a running server, as JSON. Opens `--idle`
//! connections that finish the handshake and send nothing and `--stalled` that stall inside
//! their hello ([`roam_tests::flood`]); once `--after` of them are open, a real viewer joins
//! and takes `--frames` frames. Prints one JSON object: the junk's fate (and how long after
//! its handshake the server closed it: the median, the slowest, and the slowest by how it
//! ended, since a close lost in the flood is heard late, by a reset or an idle timeout),
//! the viewer's time to its first frame and its frames per second, and the server's
//! resident memory before, at its peak and after (sampled from `/proc/PID/status` every
//! 50 ms when `--pid` is given).
//!
//! ```sh
//! roam-server serve data/kossou --listen 127.0.0.1:4433 --token-file T &
//! roam-flood --connect 127.0.0.1:4433 --fingerprint HEX --token "$(cat T)" --pid $!
//! ```
// A tool whose output is its figures or its addresses, on stdout.
#![allow(clippy::print_stdout)]

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Parser;
use roam_client::headless::{self, ViewerOptions};
use roam_protocol::messages::Role;
use roam_protocol::stats::quantile;
use roam_protocol::sync::lock;
use roam_tests::flood::{self, Flood};

#[derive(Parser)]
#[command(
    name = "roam-flood",
    about = "Junk connections at a server, and a viewer through them"
)]
struct Cli {
    /// The server, `HOST:PORT`.
    #[arg(long)]
    connect: SocketAddr,
    /// The server's certificate fingerprint (64 hex digits).
    #[arg(long)]
    fingerprint: String,
    /// The join token, for the real viewer.
    #[arg(long)]
    token: String,
    /// The server's process id, to sample its memory.
    #[arg(long)]
    pid: Option<u32>,
    #[arg(long, default_value_t = 2_000)]
    idle: usize,
    #[arg(long, default_value_t = 2_000)]
    stalled: usize,
    /// Handshakes in flight at once.
    #[arg(long, default_value_t = 256)]
    in_flight: usize,
    /// Junk connections opened before the viewer joins.
    #[arg(long, default_value_t = 1_000)]
    after: usize,
    /// Frames the viewer takes.
    #[arg(long, default_value_t = 300)]
    frames: u64,
}

#[tokio::main]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let fp = roam_link::tls::parse_fingerprint(&cli.fingerprint)?;
    let pid = cli.pid.map(|p| p.to_string());
    let rss = |pid: &Option<String>| {
        pid.as_deref()
            .and_then(|p| flood::memory(p, "VmRSS"))
            .map(|b| b as f64 / 1e6)
    };
    let before = rss(&pid);
    let peak = std::sync::Arc::new(std::sync::Mutex::new(before.unwrap_or(0.0)));
    let sampler = {
        let (peak, pid) = (peak.clone(), pid.clone());
        tokio::spawn(async move {
            let mut every = tokio::time::interval(Duration::from_millis(50));
            loop {
                every.tick().await;
                if let Some(now) = rss(&pid) {
                    let mut p = lock(&peak);
                    *p = p.max(now);
                }
            }
        })
    };
    let started = Instant::now();
    let (opened_tx, mut opened) = tokio::sync::watch::channel(0usize);
    let plan = Flood {
        idle: cli.idle,
        stalled: cli.stalled,
        in_flight: cli.in_flight,
        patience: Duration::from_secs(60),
    };
    let addr = cli.connect;
    let junk = tokio::spawn(async move { flood::run(addr, fp, plan, Some(&opened_tx)).await });
    let _ = opened.wait_for(|&n| n >= cli.after).await;
    let viewer = headless::measure(
        addr,
        fp,
        ViewerOptions {
            token: cli.token.clone(),
            role: Role::Driver,
            budget: 32_768,
            frames: cli.frames,
            ..ViewerOptions::default()
        },
    )
    .await
    .context("the viewer")?;
    let out = junk.await.context("the flood")??;
    let seconds = started.elapsed().as_secs_f64();
    sampler.abort();
    let peak = *lock(&peak);
    let mut close_ms: Vec<f64> = out.closed_after_ms.iter().map(|&(_, m)| m as f64).collect();
    close_ms.sort_by(f64::total_cmp);
    // The slowest close by how it ended: a late one that ended by a timeout is a close
    // this side never heard, not one the server made late.
    let mut slowest = std::collections::BTreeMap::new();
    for &(end, ms) in &out.closed_after_ms {
        let m = slowest.entry(end.name()).or_insert(0u64);
        *m = (*m).max(ms);
    }
    let report = serde_json::json!({
        "junk": out,
        "junk_close_ms_median": quantile(&close_ms, 0.5),
        "junk_close_ms_max": close_ms.last(),
        "junk_close_ms_max_by_end": slowest,
        "junk_per_second": (cli.idle + cli.stalled) as f64 / seconds,
        "viewer_first_frame_ms": viewer.first_frame_s * 1e3,
        "viewer_fps": viewer.frames as f64 / viewer.streaming_s.max(1e-9),
        "viewer_frames": viewer.frames,
        "viewer_decode_errors": viewer.decode_errors,
        "viewer_error": viewer.error,
        "server_rss_mb_before": before,
        "server_rss_mb_peak": pid.as_ref().map(|_| peak),
        "server_rss_mb_after": rss(&pid),
        "seconds": seconds,
    });
    println!("{report}");
    Ok(())
}
