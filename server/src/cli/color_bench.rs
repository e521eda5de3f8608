//! `color-bench DIR`: what starting a server and streaming the colour by view cost, as one
//! JSON line. Opens the data set as `serve` does ([`super::served::open_served`]: heights,
//! variance tree and colour tiles mapped from the cache, or built and cached), serves it in
//! process on loopback, reports the start to listening time and the whole process's peak
//! RSS, joins as a driver speaking the protocol directly, and measures:
//! connect (QUIC handshake started) to the first frame, the UDP bytes received before it,
//! then the colour bytes a second while the vehicle drives (Up held, key datagrams at
//! 100 Hz) for `--seconds`, and the normal tiles and bytes that came with them (one normal
//! tile per colour tile; the coarsest's comes after the first frame, so while driving the
//! normal tiles are the colour tiles, or one more).
//!
//! Figures (measure profile, loopback, 2 shared cores, default rate 2 MB/s, W = 8,
//! T = 256), from `scripts/color_stream.sh`:
//!
//! | data set | connect → first frame | UDP bytes before it | colour while driving | pyramid |
//! |---|---|---|---|---|
//! | kossou, 1024² | 30–48 ms | 125–132 KB | 0.23 MB/s (the whole pyramid, 3 levels, in 8 s) | 1.9 MB coded, built in 0.06 s |
//! | g4097 | 40–52 ms | 145 KB | 1.23 MB/s (148 tiles in 10 s) | 28.6 MB coded, built in 0.68 s |
//! | g16385 | 65 ms | 210 KB | 2.00 MB/s (the rate cap; 254 tiles in 10 s) | 454 MB coded, built in 15.4 s, then mapped |
//!
//! Those were taken before the heights and variance tree were cached, and before each
//! colour tile's normals came with it (issue 24: since, the coarsest tile's normals wait
//! for the first frame, and the normals share the rate, so at the cap the colour comes
//! slower: g4097, 121 colour and 122 normal tiles in 10 s; kossou unchanged, 20 and 21 in
//! 8 s, the normal pyramid 1.39 MB); the figures with the cache are in the README ("Large
//! terrain").

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_link::{tls, wire};
use roam_protocol::Keys;
use roam_protocol::messages::{
    self, ClientMessage, Hello, KeyDatagram, KeyState, MAX_MESSAGE, Role, ServerMessage, VERSION,
};
use roam_server::net::{self, Options, Server};

#[derive(Args)]
pub(crate) struct ColorBenchArgs {
    /// Data set directory.
    pub dir: PathBuf,
    /// Seconds to drive after the first frame.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Colour bytes a second per viewer.
    #[arg(long, default_value_t = net::COLOR_RATE)]
    pub color_rate: u64,
    /// Colour window (tiles a side per level).
    #[arg(long, default_value_t = roam_protocol::tiles::DEFAULT_WINDOW)]
    pub color_window: u8,
}

pub(crate) fn color_bench(args: ColorBenchArgs) -> Result<()> {
    // Opened as `serve` opens it: the cached heights, variance tree and colour tiles.
    let started = Instant::now();
    let cached = super::served::open_served(&args.dir)?;
    let open_s = started.elapsed().as_secs_f64();
    let (terrain, vt, pyramid, normals) = (
        cached.terrain,
        cached.variance,
        cached.pyramid,
        cached.normals,
    );
    let (cells, levels, coded, normals_coded) = (
        terrain.heights.size(),
        pyramid.levels(),
        pyramid.coded_bytes(),
        normals.coded_bytes(),
    );
    let identity = tls::generate()?;
    let fingerprint = tls::parse_fingerprint(&identity.fingerprint())?;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let (listening_s, m) = runtime.block_on(async {
        let server = Server::start(
            Arc::new(terrain),
            Arc::new(vt),
            Arc::new(pyramid),
            &identity,
            Options {
                color_rate: args.color_rate,
                color_window: args.color_window,
                normals: Some(Arc::new(normals)),
                ..Options::new(
                    "127.0.0.1:0".parse().expect("a valid address"),
                    "bench".into(),
                )
            },
        )?;
        let listening_s = started.elapsed().as_secs_f64();
        let m = drive(server.addr, fingerprint, args.color_window, args.seconds).await;
        server.shutdown().await?;
        anyhow::Ok((listening_s, m?))
    })?;
    let report = serde_json::json!({
        "data_set": args.dir.display().to_string(),
        "cells": cells,
        "levels": levels,
        "coded_bytes": coded,
        "normal_coded_bytes": normals_coded,
        "open_s": open_s,
        "start_to_listening_s": listening_s,
        "color_rate": args.color_rate,
        "color_window": args.color_window,
        "connect_to_first_frame_ms": m.first_frame_ms,
        "bytes_before_first_frame": m.bytes_before,
        "control_bytes_before_first_frame": m.control_before,
        "drive_s": m.drive_s,
        "color_bytes_driving": m.color_bytes,
        "color_tiles_driving": m.color_tiles,
        "color_bytes_per_s_driving": m.color_bytes as f64 / m.drive_s.max(1e-9),
        "normal_bytes_driving": m.normal_bytes,
        "normal_tiles_driving": m.normal_tiles,
        "max_rss_kb": max_rss_kb(),
    });
    say!("{report}");
    Ok(())
}

struct Measured {
    first_frame_ms: f64,
    bytes_before: u64,
    control_before: u64,
    drive_s: f64,
    color_bytes: u64,
    color_tiles: u64,
    normal_bytes: u64,
    normal_tiles: u64,
}

/// Joins as a driver, waits for the first frame, then drives for `seconds`.
async fn drive(
    addr: std::net::SocketAddr,
    fingerprint: [u8; 32],
    window: u8,
    seconds: f64,
) -> Result<Measured> {
    let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().expect("a valid address"))?;
    endpoint.set_default_client_config(tls::client_config(fingerprint)?);
    let t0 = Instant::now();
    let conn = endpoint.connect(addr, "roam")?.await?;
    let (mut send, mut recv) = conn.open_bi().await?;
    let hello = Hello {
        version: VERSION,
        role: Role::Driver,
        token: "bench".into(),
        viewport: [1280, 720],
        fov_y_deg: 60.0,
        budget: 65_536,
        frame_rate: 60,
        resume: None,
        color_window: window,
    };
    wire::write(&mut send, &ClientMessage::Hello(hello)).await?;
    // The control stream, read on: colour bytes counted as they come.
    // Control bytes, colour bytes and tiles, normal bytes and tiles.
    let counting = Arc::new(std::array::from_fn::<AtomicU64, 5, _>(|_| {
        AtomicU64::new(0)
    }));
    let reader = tokio::spawn({
        let counting = counting.clone();
        async move {
            while let Ok(msg) = wire::read::<ServerMessage>(&mut recv, MAX_MESSAGE).await {
                let mut bytes = Vec::new();
                let _ = messages::encode(&msg, &mut bytes);
                counting[0].fetch_add(bytes.len() as u64 + 4, Ordering::Relaxed);
                match msg {
                    ServerMessage::ColorTile { data, .. } => {
                        counting[1].fetch_add(data.len() as u64, Ordering::Relaxed);
                        counting[2].fetch_add(1, Ordering::Relaxed);
                    }
                    ServerMessage::NormalTile { data, .. } => {
                        counting[3].fetch_add(data.len() as u64, Ordering::Relaxed);
                        counting[4].fetch_add(1, Ordering::Relaxed);
                    }
                    ServerMessage::Refused(r) | ServerMessage::Bye(r) => return Some(r),
                    _ => {}
                }
            }
            None
        }
    });
    let first = tokio::time::timeout(Duration::from_secs(60), async {
        tokio::select! {
            d = conn.read_datagram() => d.is_ok(),
            s = conn.accept_uni() => s.is_ok(),
        }
    })
    .await;
    if first != Ok(true) {
        bail!("no first frame within 60 s");
    }
    let first_frame_ms = t0.elapsed().as_secs_f64() * 1e3;
    let bytes_before = conn.stats().udp_rx.bytes;
    let control_before = counting[0].load(Ordering::Relaxed);
    let [bytes0, tiles0, normal_bytes0, normal_tiles0] =
        [1, 2, 3, 4].map(|k| counting[k].load(Ordering::Relaxed));
    // Drive: Up held, a key datagram every 10 ms; frames read and dropped.
    let drain = tokio::spawn({
        let conn = conn.clone();
        async move {
            loop {
                tokio::select! {
                    d = conn.read_datagram() => if d.is_err() { return },
                    s = conn.accept_uni() => match s {
                        Ok(mut s) => { let _ = s.read_to_end(MAX_MESSAGE).await; }
                        Err(_) => return,
                    },
                }
            }
        }
    });
    let t1 = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let mut seq = 0u32;
    while t1.elapsed().as_secs_f64() < seconds {
        tick.tick().await;
        seq += 1;
        let d = KeyDatagram {
            states: vec![KeyState {
                seq,
                held: Keys::UP.bits(),
                pressed: 0,
            }],
            acked: None,
        };
        let mut bytes = Vec::new();
        messages::encode(&d, &mut bytes)?;
        let _ = conn.send_datagram(bytes.into());
    }
    let drive_s = t1.elapsed().as_secs_f64();
    let color_bytes = counting[1].load(Ordering::Relaxed) - bytes0;
    let color_tiles = counting[2].load(Ordering::Relaxed) - tiles0;
    let normal_bytes = counting[3].load(Ordering::Relaxed) - normal_bytes0;
    let normal_tiles = counting[4].load(Ordering::Relaxed) - normal_tiles0;
    let _ = wire::write(&mut send, &ClientMessage::Bye(messages::Reason::Quit)).await;
    conn.close(messages::close::BYE.into(), b"bye");
    reader.abort();
    drain.abort();
    endpoint.wait_idle().await;
    Ok(Measured {
        first_frame_ms,
        bytes_before,
        control_before,
        drive_s,
        color_bytes,
        color_tiles,
        normal_bytes,
        normal_tiles,
    })
}

/// The process's peak resident set, KiB (Linux), or 0.
fn max_rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}
