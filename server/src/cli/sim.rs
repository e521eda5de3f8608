//! `simulate` and `replay`: the vehicle physics without a network, and recordings.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_protocol::script;
use roam_server::Terrain;
use roam_server::sim::physics::{Keys, STEPS_PER_SECOND};
use roam_server::sim::recorder::RecordedWorld;
use roam_server::sim::recording;
use roam_server::sim::replay;
use roam_server::sim::world::{self, Inputs, World};
use roam_server::terrain::dataset;

use super::progress::Progress;

#[derive(Args)]
pub(crate) struct SimulateArgs {
    /// Data set directory.
    pub dir: PathBuf,
    /// Input script: one `<ticks> <keys>` segment per line, keys from U D L R or `-`.
    #[arg(long)]
    pub inputs: PathBuf,
    /// Record the session to this file (replay it with `roam-server replay`).
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Write the CSV (`tick,x,z,y,speed,heading`) here instead of to stdout.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Vehicles driving (a multi-driver session, to record and watch): vehicle i joins
    /// at tick 100 × i from start slot i and drives the script from its segment i on,
    /// round again when it ends. The CSV then has a `vehicle` column after the tick.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub vehicles: u16,
    /// Run this many ticks, the script played round again as often as it takes (default:
    /// the script once).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=360_000_000))]
    pub ticks: Option<u64>,
}

/// A script played round again from one of its segments on: a vehicle's keys, a tick at a
/// time (no buffer the run's length).
struct Looped<'a> {
    segments: &'a [(u64, Keys)],
    at: usize,
    left: u64,
}

impl<'a> Looped<'a> {
    /// `script` from its segment `i` (modulo their count) on.
    fn new(script: &'a script::Script, i: usize) -> Looped<'a> {
        let segments = &script.segments[..];
        let at = if segments.is_empty() {
            0
        } else {
            i % segments.len()
        };
        Looped {
            segments,
            at,
            left: segments.get(at).map_or(0, |s| s.0),
        }
    }

    /// The next tick's keys (none for an empty script).
    fn next_keys(&mut self) -> Keys {
        // Segments of no ticks are skipped; a script of only those holds no keys.
        for _ in 0..=self.segments.len() {
            if self.left > 0 {
                self.left -= 1;
                return self.segments[self.at].1;
            }
            if self.segments.is_empty() {
                break;
            }
            self.at = (self.at + 1) % self.segments.len();
            self.left = self.segments[self.at].0;
        }
        Keys::NONE
    }
}

#[derive(Args)]
pub(crate) struct ReplayArgs {
    /// A recording, from `simulate --record` or the server.
    pub file: PathBuf,
    /// The data set it was recorded on.
    #[arg(long)]
    pub data: PathBuf,
}

/// Recordings larger than this are refused rather than read: the server's size cap keeps
/// its files within it.
const MAX_RECORDING_BYTES: u64 = recording::MAX_FILE_BYTES;

fn load(dir: &Path) -> Result<Arc<Terrain>> {
    let mut p = Progress::new("loading");
    Ok(Arc::new(dataset::load(dir, &mut p.callback())?))
}

/// Writes CSV rows. A reader that went away (`| head`) stops the rows, not the run: the
/// simulation and its recording go on to the end.
struct Csv {
    out: Box<dyn Write>,
    target: String,
    closed: bool,
}

impl Csv {
    /// The rows of tick `tick`: vehicle 0's, or (`many`) every vehicle's with its id.
    fn rows(&mut self, tick: u64, w: &World, many: bool) -> Result<()> {
        for v in w.vehicles() {
            if self.closed || (!many && v.id != 0) {
                continue;
            }
            let s = &v.state;
            let y = w.altitude(s);
            let id = if many {
                format!("{},", v.id)
            } else {
                String::new()
            };
            let r = writeln!(
                self.out,
                "{tick},{id}{},{},{y},{},{}",
                s.x, s.z, s.speed, s.heading
            );
            self.check(r)?;
        }
        Ok(())
    }

    fn check(&mut self, r: io::Result<()>) -> Result<()> {
        match r {
            _ if self.closed => Ok(()),
            Err(e) if e.kind() == io::ErrorKind::BrokenPipe => {
                self.closed = true;
                Ok(())
            }
            r => r.with_context(|| format!("writing {}", self.target)),
        }
    }
}

pub(crate) fn simulate(args: SimulateArgs) -> Result<()> {
    let text = std::fs::read(&args.inputs)
        .with_context(|| format!("reading {}", args.inputs.display()))?;
    let script =
        script::parse_bytes(&text).with_context(|| format!("{}", args.inputs.display()))?;
    let terrain = load(&args.dir)?;
    let total = args.ticks.unwrap_or_else(|| script.keys().count() as u64);
    let many = args.vehicles > 1;
    let mut world = World::new(terrain.clone());
    world.add(0, world::start_state(&terrain, 0))?;
    let mut csv = match &args.csv {
        Some(path) => Csv {
            out: Box::new(BufWriter::new(
                File::create(path).with_context(|| format!("creating {}", path.display()))?,
            )),
            target: path.display().to_string(),
            closed: false,
        },
        None => Csv {
            out: Box::new(BufWriter::new(io::stdout().lock())),
            target: "stdout".into(),
            closed: false,
        },
    };
    let header = if many {
        "tick,vehicle,x,z,y,speed,heading"
    } else {
        "tick,x,z,y,speed,heading"
    };
    let r = writeln!(csv.out, "{header}");
    csv.check(r)?;
    csv.rows(0, &world, many)?;
    let mut driver = match &args.record {
        Some(path) => {
            let file =
                File::create(path).with_context(|| format!("creating {}", path.display()))?;
            let (hash, interval) = (terrain.content_hash(), recording::MAX_CHECKPOINT_INTERVAL);
            Driver::Recorded(
                RecordedWorld::start(world, BufWriter::new(file), hash, interval)
                    .with_context(|| format!("writing {}", path.display()))?,
            )
        }
        None => Driver::Plain(world),
    };
    // Each vehicle's keys from its join on (vehicle i joins at tick 100 i).
    let join_at = |i: u16| u64::from(i) * 100;
    let mut keys: Vec<Looped> = (0..args.vehicles)
        .map(|i| Looped::new(&script, usize::from(i)))
        .collect();
    let mut inputs = Inputs::new();
    for tick in 0..total {
        for i in 1..args.vehicles {
            if join_at(i) == tick {
                driver
                    .join(i, world::start_state(&terrain, u32::from(i)))
                    .context("writing the recording")?;
            }
        }
        for (i, k) in keys.iter_mut().enumerate() {
            let i = i as u16;
            if tick >= join_at(i) {
                inputs.set(i, k.next_keys());
            }
        }
        driver.step(&inputs).context("writing the recording")?;
        let w = driver.world();
        csv.rows(w.tick(), w, many)?;
    }
    let r = csv.out.flush();
    csv.check(r)?;
    let world = driver.finish().context("writing the recording")?;
    let v = &world.vehicles()[0].state;
    let summary = format!(
        "{} ticks ({:.2} s): x {} z {} speed {} heading {}; digest {}",
        world.tick(),
        world.tick() as f64 / f64::from(STEPS_PER_SECOND),
        v.x,
        v.z,
        v.speed,
        v.heading,
        world.digest()
    );
    if args.csv.is_some() {
        say!("{summary}");
    } else {
        eprintln!("{summary}");
    }
    Ok(())
}

/// A world stepped as it is, or recorded.
enum Driver {
    Plain(World),
    Recorded(RecordedWorld<Arc<Terrain>, BufWriter<File>>),
}

impl Driver {
    fn step(&mut self, inputs: &Inputs) -> io::Result<()> {
        match self {
            Driver::Plain(w) => {
                world::step(w, inputs);
                Ok(())
            }
            Driver::Recorded(r) => r.step(inputs),
        }
    }

    fn join(&mut self, id: u16, state: roam_server::sim::physics::VehicleState) -> Result<()> {
        match self {
            Driver::Plain(w) => w.add(id, state)?,
            Driver::Recorded(r) => r.join(id, state)?,
        }
        Ok(())
    }

    fn world(&self) -> &World {
        match self {
            Driver::Plain(w) => w,
            Driver::Recorded(r) => r.world(),
        }
    }

    fn finish(self) -> io::Result<World> {
        match self {
            Driver::Plain(w) => Ok(w),
            Driver::Recorded(r) => Ok(r.finish()?.0),
        }
    }
}

pub(crate) fn replay(args: ReplayArgs) -> Result<()> {
    let name = args.file.display();
    let len = std::fs::metadata(&args.file)
        .with_context(|| format!("reading {name}"))?
        .len();
    if len > MAX_RECORDING_BYTES {
        bail!("{name}: {len} bytes, more than the {MAX_RECORDING_BYTES} a recording may have");
    }
    let bytes = std::fs::read(&args.file).with_context(|| format!("reading {name}"))?;
    let rec = recording::parse(&bytes).with_context(|| format!("{name}"))?;
    if let Some(at) = rec.truncated_at {
        eprintln!(
            "warning: {name} is cut inside the record at byte {at} (the server stopped \
             without closing it); replaying the {} whole records before it",
            rec.events.len()
        );
    }
    let terrain = load(&args.data)?;
    let outcome = replay::replay(&rec, terrain.clone(), &terrain.content_hash())
        .with_context(|| format!("replaying {name} on {}", args.data.display()))?;
    let ticks = outcome.tick - outcome.start_tick;
    let from = match outcome.start_tick {
        0 => String::new(),
        t => format!(" from tick {t} (the file continues a session)"),
    };
    say!(
        "replayed {ticks} ticks ({:.2} s) of {name}{from}: {} checkpoints matched, {}",
        ticks as f64 / f64::from(STEPS_PER_SECOND),
        outcome.checkpoints,
        if outcome.ended {
            "closed cleanly"
        } else {
            "no end record"
        }
    );
    for v in &outcome.vehicles {
        let s = &v.state;
        say!(
            "vehicle {}: x {} z {} y {} speed {} heading {}",
            v.id,
            s.x,
            s.z,
            roam_server::sim::physics::altitude(&*terrain, s.x, s.z),
            s.speed,
            s.heading
        );
    }
    say!("digest {}", outcome.digest);
    Ok(())
}

/// Vehicle steps per second on one core: 64 vehicles driving varied key patterns.
pub(crate) fn bench_physics(terrain: &Arc<Terrain>) -> f64 {
    const VEHICLES: u16 = 64;
    const TICKS: u32 = 20_000;
    let mut world = World::new(terrain.clone());
    for id in 0..VEHICLES {
        world
            .add(id, world::start_state(terrain, u32::from(id)))
            .expect("start states are on the map");
    }
    let patterns = [
        Keys::UP,
        Keys::UP.union(Keys::LEFT),
        Keys::NONE,
        Keys::UP.union(Keys::RIGHT),
        Keys::DOWN,
        Keys::LEFT,
    ];
    let mut inputs = Inputs::new();
    let started = Instant::now();
    for tick in 0..TICKS {
        for id in 0..VEHICLES {
            let k = (tick / 150 + u32::from(id)) as usize % patterns.len();
            inputs.set(id, patterns[k]);
        }
        world::step(&mut world, &inputs);
    }
    let secs = started.elapsed().as_secs_f64();
    std::hint::black_box(world.digest());
    f64::from(TICKS) * f64::from(VEHICLES) / secs
}
