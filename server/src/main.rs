//! `roam-server`: the command-line front end. Owns the clock and the terminal; everything it
//! runs is library code from `roam_server`.

/// `println!` for command output: a reader that went away (`| head`) ends the program
/// quietly instead of panicking.
macro_rules! say {
    ($($arg:tt)*) => {
        $crate::say_line(format_args!($($arg)*))
    };
}

mod cli;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "roam-server",
    version,
    about = "Stream split-only ROAM terrain to viewers"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Validate a data set and print its shape, scales, height range and variance-tree size.
    Check(cli::data::CheckArgs),
    /// Write a synthetic data set (seeded fBm) of any 2^N + 1 side.
    Generate(cli::data::GenerateArgs),
    /// Build a data set from a heightfield (PGM, PNG, SRTM .hgt): fill voids, resample to
    /// 2^N + 1, derive a colour map, write a map file.
    Import(cli::import::ImportArgs),
    /// Tessellate once for a camera and write the mesh as a Wavefront OBJ.
    Mesh(cli::tess::MeshArgs),
    /// Time the tessellator along a fly-over path (or one fixed camera), and the physics.
    ///
    /// The serving figures are made as `serve` makes a viewer's cut (--fog-priority,
    /// --guard-deg, --swap-margin); the guard band also widens the from-scratch cut they
    /// are compared with, not the from-scratch timing figures' (which have none), and
    /// `serve_fogged_error_px_p99` measures either fog priority alike.
    Bench(cli::tess::BenchArgs),
    /// Drive one vehicle from the map's start by an input script, without a network; print
    /// its state at every tick as CSV.
    Simulate(cli::sim::SimulateArgs),
    /// Re-simulate a recording, checking every checkpoint; print the final states.
    Replay(cli::sim::ReplayArgs),
    /// Serve the terrain to viewers over QUIC, the world at 100 Hz; stop with Ctrl-C.
    Serve(cli::net::ServeArgs),
    /// Run the world alone (physics at 100 Hz, tickets, the recording) for edges to serve,
    /// over NATS; stop with Ctrl-C.
    World(cli::cluster::WorldArgs),
    /// Serve viewers as `serve` does, the world being the one on NATS (`world`); stop with
    /// Ctrl-C.
    Edge(cli::cluster::EdgeArgs),
    /// Write a new random secret for a world and its edges (`--bus-secret FILE`).
    BusSecret(cli::cluster::BusSecretArgs),
    /// Stand in for E edges of a world on NATS (joins, hellos, key states, snapshot
    /// subscribers) and measure the snapshot fan-out; one JSON line (`scripts/cluster.sh`).
    #[command(hide = true)]
    BusLoad(cli::bus_load::BusLoadArgs),
    /// Serve a data set in process and measure a driving viewer's colour stream: connect
    /// to first frame, bytes before it, colour bytes a second; one JSON line.
    ColorBench(cli::color_bench::ColorBenchArgs),
    /// Print the server's certificate fingerprint (made if absent); `--rotate` replaces it.
    Identity(cli::identity::IdentityArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    init_logs();
    let result = match cli.command {
        Command::Check(args) => cli::data::check(args),
        Command::Generate(args) => cli::data::generate(args),
        Command::Import(args) => cli::import::import(args),
        Command::Mesh(args) => cli::tess::mesh(args),
        Command::Bench(args) => cli::tess::bench(args),
        Command::Simulate(args) => cli::sim::simulate(args),
        Command::Replay(args) => cli::sim::replay(args),
        Command::Serve(args) => cli::net::serve(args),
        Command::World(args) => cli::cluster::world(args),
        Command::Edge(args) => cli::cluster::edge(args),
        Command::BusSecret(args) => cli::cluster::bus_secret(args),
        Command::BusLoad(args) => cli::bus_load::bus_load(args),
        Command::ColorBench(args) => cli::color_bench::color_bench(args),
        Command::Identity(args) => cli::identity::identity(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

/// Logs (`tracing`) go to stderr, filtered by `RUST_LOG` (default: `info` for roam's own
/// crates, `warn` for the rest); command output stays on stdout.
fn init_logs() {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new("warn,roam_server=info,roam_link=info"));
    let _already_set = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .try_init();
}

/// Writes one line to stdout for `say!`.
fn say_line(args: std::fmt::Arguments) {
    use std::io::Write;
    if let Err(err) = writeln!(std::io::stdout().lock(), "{args}") {
        if err.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("error: writing to stdout: {err}");
        std::process::exit(1);
    }
}
