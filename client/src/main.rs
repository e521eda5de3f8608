//! `roam-client`: the viewer's command line. With no arguments it opens a window on the
//! bundled data set, served in-process; `--headless` measures, and renders offscreen.
// The binary: its reports go to stdout.
#![allow(clippy::print_stdout)]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use clap::Parser;
use roam_client::headless::{self, ViewerOptions};
use roam_client::session::{KeySource, Session};
use roam_link::tls;
use roam_protocol::messages::Role;
use roam_server::net::{self, Options, Server};

#[derive(Parser)]
#[command(
    name = "roam-client",
    version,
    about = "View a roam server's terrain stream"
)]
struct Cli {
    /// The server's address, `HOST:PORT`; or several, comma-separated (the edges of one
    /// world, behind the one --fingerprint and token): tried in turn, and after losing one
    /// the next, wrapping around.
    #[arg(long, conflicts_with = "local", requires = "fingerprint", value_parser = addresses)]
    connect: Option<Addresses>,
    /// The join token the server printed (visible to other users in `ps`: prefer
    /// `--token-file` or the environment variable `ROAM_TOKEN`).
    #[arg(long, requires = "connect", conflicts_with = "token_file")]
    token: Option<String>,
    /// A file holding the join token (trailing whitespace ignored).
    #[arg(long, requires = "connect")]
    token_file: Option<PathBuf>,
    /// The SHA-256 fingerprint of the server's certificate, as it printed it.
    #[arg(long, requires = "connect")]
    fingerprint: Option<String>,
    /// Start a server for this data set in this process, on loopback, instead of --connect
    /// (the default: the bundled data/kossou).
    #[arg(long)]
    local: Option<PathBuf>,
    /// Watch this recording (a session a server recorded, or `roam-server simulate
    /// --record`), served in this process as `--local` serves a live world: pause, speed
    /// and seek it, follow any vehicle. Spectating is implied.
    #[arg(long, value_name = "FILE", conflicts_with = "connect")]
    replay: Option<PathBuf>,
    /// With --replay: the recording is still being written: follow it as it grows.
    #[arg(long, requires = "replay")]
    follow: bool,
    /// The data set --replay was recorded on (default: the bundled data/kossou).
    #[arg(
        long,
        value_name = "DIR",
        requires = "replay",
        conflicts_with = "local"
    )]
    data: Option<PathBuf>,
    /// Run without a window: decode and check every frame, then write stats.
    #[arg(long)]
    headless: bool,
    /// Input script to drive with (the format of `roam-server simulate`).
    #[arg(long)]
    inputs: Option<PathBuf>,
    /// Play --inputs again each time it ends, each viewer of --viewers from another of its
    /// lines (so they do not all turn at once), for 20 times the run's length at
    /// --frame-rate: a load generator keeps driving the whole run.
    #[arg(long, requires = "inputs")]
    loop_inputs: bool,
    /// Every viewer of --viewers plays --inputs in step: from its first line, each step at
    /// the same instant for all (on the process's 10 ms grid), so a viewer that joins later
    /// starts where the others are: a group turning together.
    #[arg(long, requires = "inputs")]
    in_step: bool,
    /// Frames to receive per viewer.
    #[arg(long, default_value_t = 300)]
    frames: u64,
    /// Triangle budget.
    #[arg(long, default_value_t = 65_536)]
    budget: u32,
    /// Headless viewers to run in this process (a load generator), each driving its own
    /// vehicle (all with the same script). Their key clocks are spread evenly over the
    /// 10 ms step (viewer i of N at i × 10 / N ms on one grid), so a latency pooled over
    /// them samples every phase of the server's tick.
    #[arg(long, default_value_t = 1)]
    viewers: u32,
    /// Watch instead of drive.
    #[arg(long)]
    spectate: bool,
    /// Measure the viewer's own costs per frame (decode, vertex build, upload, drawing at
    /// --size offscreen) on a drive and print them as JSON (with --headless). With
    /// --replay: what watching costs (open to the first frame, frames a second at 8×,
    /// seeks).
    #[arg(long)]
    bench: bool,
    /// Geomorphs' length in world ticks (100 a second): a vertex a split adds rises from
    /// its edge's midpoint, and one a merge removes sinks back, over this many ticks. 0
    /// draws every change at once (the viewer before geomorphs). The window and --bench
    /// draw with them; other headless viewers draw nothing.
    #[arg(long, default_value_t = roam_client::render::MORPH_TICKS)]
    morph_ticks: u16,
    /// Acknowledge frames without decoding them, and let colour and normal tiles go
    /// undecoded, the join's too (counted in the colour bytes): a load generator that
    /// measures the server, not its own decoding (the wire and decode figures are then
    /// empty).
    #[arg(long)]
    skip_decode: bool,
    /// Frames a second each headless viewer asks for (the server serves at most its
    /// `--max-fps`).
    #[arg(long, default_value_t = 60, value_parser = clap::value_parser!(u16).range(1..))]
    frame_rate: u16,
    /// Seconds without a frame or message from the server before a headless viewer calls
    /// the connection lost (and reconnects): 10, or 0.8 when there are other addresses to
    /// go to (a shorter one given stands).
    #[arg(long, default_value_t = 10.0, value_parser = seconds)]
    silence: f64,
    /// Seconds a headless viewer keeps trying to reconnect after a loss.
    #[arg(long, default_value_t = 35.0, value_parser = seconds)]
    reconnect_for: f64,
    /// Write the stats as JSON here (else to stdout).
    #[arg(long)]
    stats: Option<PathBuf>,
    /// After the last frame, render it offscreen (any adapter, a software one included)
    /// and write it as a PNG.
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Window or screenshot size, `WIDTHxHEIGHT`.
    #[arg(long, default_value = "1280x720", value_parser = parse_size)]
    size: (u32, u32),
    /// Start with fog off.
    #[arg(long)]
    no_fog: bool,
    /// Start with lighting off (flat colours).
    #[arg(long)]
    no_lighting: bool,
    /// Start with the wireframe drawn over.
    #[arg(long)]
    wireframe: bool,
    /// Start without the water surface.
    #[arg(long)]
    no_water: bool,
    /// Start without the other vehicles' markers.
    #[arg(long)]
    no_vehicles: bool,
    /// Start without the ground's detail texture.
    #[arg(long)]
    no_detail: bool,
    /// Light with the vertex normals alone, not per pixel from the normal tiles (the
    /// viewer before issue 24, for comparisons).
    #[arg(long)]
    no_normal_tiles: bool,
    /// Vertical field of view, degrees.
    #[arg(long, default_value_t = 60.0)]
    fov: f32,
    /// The in-process server's cuts (`--local`, `--replay` or no `--connect`), as
    /// `roam-server serve` makes them; last, as its heading holds for what follows.
    #[command(
        flatten,
        next_help_heading = "In-process server (as `roam-server serve`)"
    )]
    cut: roam_server::viewer::CutArgs,
}

impl Cli {
    fn toggles(&self) -> roam_client::render::Toggles {
        roam_client::render::Toggles {
            fog: !self.no_fog,
            lighting: !self.no_lighting,
            wireframe: self.wireframe,
            water: !self.no_water,
            vehicles: !self.no_vehicles,
            detail: !self.no_detail,
            normals: !self.no_normal_tiles,
        }
    }

    fn role(&self) -> Role {
        if self.spectate || self.replay.is_some() {
            Role::Spectator { follow: None }
        } else {
            Role::Driver
        }
    }
}

/// The addresses `--connect` names.
#[derive(Clone, Debug)]
struct Addresses(Vec<SocketAddr>);

/// `HOST:PORT[,HOST:PORT…]`: socket addresses, at least one.
fn addresses(text: &str) -> Result<Addresses, String> {
    let list = text
        .split(',')
        .map(|a| {
            a.trim()
                .parse::<SocketAddr>()
                .map_err(|e| format!("{a:?}: {e} (expected HOST:PORT, e.g. 192.0.2.1:4433)"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Addresses(list))
}

/// The bundled data set: `data/kossou` from the current directory (the repository root,
/// as `cargo run` leaves it), else beside the source.
fn bundled() -> PathBuf {
    let here = PathBuf::from("data/kossou");
    if here.is_dir() {
        return here;
    }
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../data/kossou")
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let err = || format!("expected WIDTHxHEIGHT (e.g. 1280x720), got {s:?}");
    let (w, h) = s.split_once('x').ok_or_else(err)?;
    let (w, h): (u32, u32) = (w.parse().map_err(|_| err())?, h.parse().map_err(|_| err())?);
    if !(1..=8192).contains(&w) || !(1..=8192).contains(&h) {
        return Err(err());
    }
    Ok((w, h))
}

fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let started = std::time::Instant::now();
    if !cli.headless {
        for (flag, given) in [
            ("--screenshot", cli.screenshot.is_some()),
            ("--stats", cli.stats.is_some()),
            ("--inputs", cli.inputs.is_some()),
            ("--loop-inputs", cli.loop_inputs),
            ("--in-step", cli.in_step),
            ("--skip-decode", cli.skip_decode),
            ("--viewers", cli.viewers != 1),
            ("--bench", cli.bench),
        ] {
            if given {
                bail!("{flag} is for the headless viewer: add --headless");
            }
        }
    }
    let script = match &cli.inputs {
        Some(path) => {
            let bytes =
                std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            Some(
                roam_protocol::script::parse_bytes(&bytes)
                    .with_context(|| path.display().to_string())?,
            )
        }
        None => None,
    };
    // Without a display there is nothing to serve or connect for.
    if !cli.headless && !roam_client::window::has_display() {
        bail!("{}", roam_client::window::NO_DISPLAY);
    }
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let (local, addrs, token, fingerprint) = runtime.block_on(serve(&cli))?;
    let (server, truth) = match local {
        Some((server, truth)) => (Some(server), Some(truth)),
        None => (None, None),
    };
    let addr = addrs[0];
    if !cli.headless {
        let shown = window(&runtime, &cli, &addrs, &token, fingerprint);
        if let Some(server) = server {
            runtime.block_on(server.shutdown())?;
        }
        return shown;
    }
    runtime.block_on(async {
        if cli.bench && cli.replay.is_some() {
            let report = roam_client::bench::watch::run(
                addr,
                fingerprint,
                (token.clone(), cli.budget, cli.size),
                started,
            )
            .await;
            if let Some(server) = server {
                server.shutdown().await?;
            }
            return write_report(&cli, &report?);
        }
        if cli.bench {
            let inputs = match script.clone() {
                Some(s) => s,
                None => roam_protocol::script::parse(roam_protocol::script::DRIVE_SCRIPT)
                    .context("the benchmark drive")?,
            };
            let opts = roam_client::bench::Options {
                token: token.clone(),
                budget: cli.budget,
                frames: cli.frames,
                size: cli.size,
                fov_y_deg: cli.fov,
                toggles: cli.toggles(),
                inputs,
                morph_ticks: cli.morph_ticks,
                truth,
            };
            let report = roam_client::bench::run(addr, fingerprint, opts).await;
            if let Some(server) = server {
                server.shutdown().await?;
            }
            return write_report(&cli, &report?);
        }
        // Ctrl-C stops the viewers, which say goodbye and report what they measured.
        let stopped = roam_client::session::ctrl_c();
        let mut tasks = Vec::new();
        // Ticks of driving that cover the run 20 times over at the asked rate.
        let drive_ticks = cli.frames.saturating_mul(100 * 20) / u64::from(cli.frame_rate);
        for i in 0..cli.viewers.max(1) {
            let inputs = match &script {
                Some(s) if cli.loop_inputs => {
                    let start = if cli.in_step { 0 } else { i as usize };
                    Some(looped(s, start, drive_ticks))
                }
                other => other.clone(),
            };
            let opts = ViewerOptions {
                token: token.clone(),
                role: cli.role(),
                budget: cli.budget,
                frames: cli.frames,
                inputs,
                key_phase: (cli.viewers > 1).then(|| {
                    std::time::Duration::from_micros(10_000 * u64::from(i) / u64::from(cli.viewers))
                }),
                in_step: cli.in_step,
                skip_decode: cli.skip_decode,
                frame_rate: cli.frame_rate,
                patience: roam_client::session::Patience {
                    silence: std::time::Duration::from_secs_f64(cli.silence),
                    reconnect_for: std::time::Duration::from_secs_f64(cli.reconnect_for),
                },
                keep_last: cli.screenshot.is_some(),
                stop: Some(stopped.clone()),
                ..ViewerOptions::default()
            };
            let addrs = addrs.clone();
            tasks.push(tokio::spawn(async move {
                headless::measure_any(&addrs, fingerprint, opts).await
            }));
        }
        // A viewer that could not join (refused, or its handshake past the server's
        // deadline in a crowd joining at once) is counted, not measured; the others are.
        let mut all = Vec::new();
        let mut unjoined = Vec::new();
        for t in tasks {
            match t.await.context("a viewer task")? {
                Ok(stats) => all.push(stats),
                Err(e) => unjoined.push(format!("{e:#}")),
            }
        }
        if let Some(server) = server {
            server.shutdown().await?;
        }
        // A session lost for good still reports what it measured, then fails the run.
        let lost: Vec<String> = all.iter().filter_map(|s| s.error.clone()).collect();
        if let Some(path) = &cli.screenshot
            && lost.is_empty()
            && unjoined.is_empty()
        {
            screenshot(path, &mut all[0], &cli)?;
        }
        let mut report = roam_client::stats::report(&all);
        report["join_errors"] = unjoined.len().into();
        write_report(&cli, &report)?;
        match unjoined.as_slice() {
            [] => {}
            [one] => bail!("{one}"),
            [first, ..] => bail!(
                "{} viewers could not join; the first: {first}",
                unjoined.len()
            ),
        }
        match lost.as_slice() {
            [] => Ok(()),
            [one] => bail!("{one}"),
            [first, ..] => bail!("{} viewers ended early; the first: {first}", lost.len()),
        }
    })
}

/// `script` from its segment `start` (modulo their count) on, played again from its first
/// each time it ends, for at least `ticks` ticks (at most the longest script).
fn looped(
    script: &roam_protocol::script::Script,
    start: usize,
    ticks: u64,
) -> roam_protocol::script::Script {
    let segments = &script.segments;
    let mut out = roam_protocol::script::Script::default();
    if segments.is_empty() {
        return out;
    }
    let want = ticks.clamp(1, roam_protocol::script::MAX_TICKS);
    let mut total = 0;
    for &(n, keys) in segments.iter().cycle().skip(start % segments.len()) {
        if total >= want {
            break;
        }
        out.segments.push((n, keys));
        total += n;
    }
    out
}

/// Writes a JSON report to `--stats`, or stdout.
fn write_report(cli: &Cli, report: &serde_json::Value) -> Result<()> {
    match &cli.stats {
        Some(path) => std::fs::write(path, format!("{report:#}\n"))
            .with_context(|| format!("writing {}", path.display())),
        None => {
            println!("{report:#}");
            Ok(())
        }
    }
}

/// An in-process server (`--local`, the default) or the ones given (`--connect`): the
/// addresses (at least one), token and certificate fingerprint.
async fn serve(
    cli: &Cli,
) -> Result<(
    Option<(Server, roam_client::bench::Truth)>,
    Vec<SocketAddr>,
    String,
    [u8; 32],
)> {
    Ok(match &cli.connect {
        None => {
            let dir = cli
                .local
                .clone()
                .or_else(|| cli.data.clone())
                .unwrap_or_else(bundled);
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            // Heights, variance tree, colour and normal tiles from the data set's cache
            // (built and cached the first time), as `roam-server serve` opens them.
            let (terrain, vt, report) =
                roam_server::terrain::dataset::open_cached(&dir, threads, &mut |_, _, _| {})
                    .with_context(|| format!("loading {}", dir.display()))?;
            let cells = terrain.heights.size();
            let (pyramid, _) = roam_server::terrain::color_pyramid::ColorPyramid::open_or_load(
                &dir,
                cells,
                roam_protocol::tiles::DEFAULT_TILE,
                threads,
                || {
                    roam_server::terrain::dataset::load_color(&dir, cells, &mut |_, _| {})
                        .map(std::borrow::Cow::Owned)
                },
                &mut |_, _| {},
            )
            .with_context(|| format!("the colour tiles of {}", dir.display()))?;
            let (normals, _) = roam_server::terrain::normal_pyramid::NormalPyramid::open_or_build(
                &dir,
                &terrain.heights,
                (terrain.map.h_scale, terrain.map.v_scale),
                &report.heights_hash,
                roam_protocol::tiles::DEFAULT_TILE,
                threads,
                &mut |_, _| {},
            )
            .with_context(|| format!("the normal tiles of {}", dir.display()))?;
            // The data set's hash, as `serve` takes it (from its cache), for a recording.
            let hash = match &cli.replay {
                Some(_) => Some(
                    roam_server::terrain::dataset::content_hash_cached(
                        &dir,
                        &terrain,
                        &report,
                        &mut |_, _| {},
                    )
                    .with_context(|| format!("hashing {}", dir.display()))?
                    .0,
                ),
                None => None,
            };
            let identity = tls::generate()?;
            let token = net::random_token();
            let truth = roam_client::bench::Truth {
                terrain: Arc::new(terrain),
                variance: Arc::new(vt),
                guard_deg: f32::from(cli.cut.guard_deg),
            };
            let mut options = Options::new(
                "127.0.0.1:0".parse().expect("a valid address"),
                token.clone(),
            );
            options.limits = cli.cut.limits(options.limits);
            options.normals = Some(Arc::new(normals));
            if let (Some(file), Some(hash)) = (&cli.replay, hash) {
                let replaying = net::replay::Replaying::open(
                    file,
                    cli.follow,
                    None,
                    truth.terrain.clone(),
                    &hash,
                )
                .with_context(|| format!("watching {}", file.display()))?;
                eprintln!(
                    "replaying {}: {}",
                    file.display(),
                    roam_server::sim::watch::describe(&replaying.watch)
                );
                options.replay = Some(replaying);
            }
            let server = Server::start(
                truth.terrain.clone(),
                truth.variance.clone(),
                Arc::new(pyramid),
                &identity,
                options,
            )?;
            let fp = tls::parse_fingerprint(&identity.fingerprint())?;
            let addr = server.addr;
            (Some((server, truth)), vec![addr], token, fp)
        }
        Some(Addresses(addrs)) => {
            let fp = tls::parse_fingerprint(cli.fingerprint.as_deref().unwrap_or_default())?;
            if addrs.is_empty() {
                bail!("--connect names no address");
            }
            (None, addrs.clone(), join_token(cli)?, fp)
        }
    })
}

/// Joins and opens the window.
fn window(
    runtime: &tokio::runtime::Runtime,
    cli: &Cli,
    addrs: &[SocketAddr],
    token: &str,
    fingerprint: [u8; 32],
) -> Result<()> {
    use roam_client::window;
    let hello = roam_client::conversation::hello(
        cli.role(),
        token.to_string(),
        [cli.size.0, cli.size.1],
        cli.fov,
        cli.budget,
        60,
        roam_client::render::native_max_texture(),
    );
    let keys = if cli.spectate || cli.replay.is_some() {
        KeySource::None
    } else {
        KeySource::Latch
    };
    let session = runtime.block_on(Session::join_any(
        addrs,
        fingerprint,
        hello,
        keys,
        roam_client::session::Patience::default(),
        roam_client::color_cache::Keep::Texels,
    ))?;
    session.set_morph(cli.morph_ticks);
    let name = match &cli.connect {
        Some(Addresses(a)) => a
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join(","),
        None => format!(
            "{} (in-process, {})",
            cli.local.clone().unwrap_or_else(bundled).display(),
            session.addr()
        ),
    };
    window::run(
        runtime,
        session,
        window::Options {
            title: format!("roam · {name}"),
            size: cli.size,
            toggles: cli.toggles(),
            server: name,
            edges: addrs.len() > 1,
            driver: !cli.spectate && cli.replay.is_none(),
            fov_y_deg: cli.fov,
        },
    )
}

/// Renders the first viewer's last frame offscreen, from its vehicle, into a PNG.
fn screenshot(path: &std::path::Path, v: &mut headless::ViewerStats, cli: &Cli) -> Result<()> {
    use roam_client::render::{self, Gpu, Renderer, View};
    let (Some(scene), Some(mesh), Some(vehicle)) = (&v.scene, &v.last_mesh, &v.last) else {
        bail!("no frame was decoded: nothing to render");
    };
    let Some(mut colors) = v.colors.take() else {
        bail!("no colour was kept: nothing to render");
    };
    let gpu = Gpu::headless()?;
    let mut renderer = Renderer::new(&gpu, wgpu::TextureFormat::Rgba8UnormSrgb, scene.clone());
    renderer.set_mesh(&gpu, mesh);
    renderer.update_colors(&gpu, &colors.drain(usize::MAX));
    let view = View {
        eye: [
            vehicle.x as f32,
            (vehicle.y + roam_client::camera::EYE_ABOVE_VEHICLE) as f32,
            vehicle.z as f32,
        ],
        yaw_deg: vehicle.heading as f32,
        pitch_deg: roam_client::camera::BASE_PITCH_DEG as f32,
        fov_y_deg: cli.fov,
        time_s: 0.0,
    };
    let toggles = cli.toggles();
    let rgba = render::render_offscreen(&gpu, &mut renderer, cli.size, &view, toggles)?;
    render::write_png(path, cli.size, &rgba)?;
    eprintln!(
        "wrote {} ({}, {})",
        path.display(),
        gpu.adapter.name,
        gpu.adapter.backend
    );
    Ok(())
}

/// The join token for `--connect`: `--token`, else `--token-file`, else `ROAM_TOKEN`.
fn join_token(cli: &Cli) -> Result<String> {
    if let Some(t) = &cli.token {
        return Ok(t.clone());
    }
    if let Some(path) = &cli.token_file {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("reading the token file {}", path.display()))?;
        return Ok(text.trim_end().to_owned());
    }
    std::env::var("ROAM_TOKEN").map_err(|_| {
        anyhow::anyhow!(
            "--connect needs the server's join token: --token-file FILE, the environment \
             variable ROAM_TOKEN, or --token TOKEN"
        )
    })
}

/// A number of seconds: more than 0 and at most an hour.
fn seconds(text: &str) -> Result<f64, String> {
    let s: f64 = text
        .parse()
        .map_err(|_| format!("{text:?}: expected a number of seconds"))?;
    if !(s > 0.0 && s <= 3_600.0) {
        return Err(format!(
            "{text}: expected more than 0 and at most 3600 seconds"
        ));
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::looped;
    use roam_protocol::keys::Keys;
    use roam_protocol::script::{Script, parse};

    /// The capacity drive (`scripts/capacity.sh`).
    const CAPACITY_DRIVE: &str = include_str!("../../scripts/capacity-drive.txt");

    #[test]
    fn the_capacity_drive_drives_as_a_person_does() {
        let drive = parse(CAPACITY_DRIVE).expect("scripts/capacity-drive.txt parses");
        assert!(drive.ticks() >= 3_000, "at least 30 s: {}", drive.ticks());
        let has = |k: Keys| drive.segments.iter().any(|&(_, keys)| keys.contains(k));
        assert!(has(Keys::LEFT) && has(Keys::RIGHT), "turns both ways");
        assert!(has(Keys::UP) && has(Keys::DOWN), "throttle and brake");
        assert!(
            drive.segments.iter().any(|&(_, keys)| keys == Keys::NONE),
            "and coasting"
        );
    }

    #[test]
    fn a_looped_script_starts_at_its_line_and_covers_the_run() {
        let script = parse("100 U\n50 UL\n30 -\n").expect("valid");
        // 1,800 frames at 60 Hz, 20 times over: 60,000 ticks.
        let drive = looped(&script, 1, 60_000);
        assert!(drive.ticks() >= 60_000 && drive.ticks() < 60_000 + 100);
        assert_eq!(
            drive.segments[0], script.segments[1],
            "from its second line"
        );
        assert_eq!(
            drive.segments[2], script.segments[0],
            "then again from the first"
        );
        // Viewer 4 of a 3-line script starts at line 1 again.
        assert_eq!(looped(&script, 4, 1).segments, vec![script.segments[1]]);
        assert_eq!(looped(&Script::default(), 0, 100), Script::default());
    }
}
