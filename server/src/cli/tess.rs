//! `mesh` and `bench`: one tessellation to a Wavefront OBJ, and the tessellation benchmark.
//!
//! Both weigh each diamond's error by the map's fog (`--fog-priority on`, the default, as
//! `serve` does for a viewer drawing its fog) or not (`off`: the fog-unaware priority).
//! The bench's `serve_fogged_error_px_p99` is what the served cut's fog lets through,
//! measured alike either way (`tessellate::fogged_error_px`); on `kossou` at 32,768
//! triangles (issue 24), `cargo build --profile measure -p roam-server` then
//! `target/measure/roam-server bench data/kossou --budget 32768 --json --fog-priority
//! off` and `on`, three runs of each in turn on a busy two-core machine (the error
//! figures are the same every run):
//!
//! | `--fog-priority` | off | on |
//! |---|---|---|
//! | `serve_fogged_error_px_p99` (what the fog lets through) | 0.283 | 0.102 |
//! | `serve_unfogged_error_px_p99` (the fog's weight left out) | 0.314 | 1.042 |
//! | `serve_screen_error_px_p99` (by the cut's own priority) | 0.312 | 0.102 |
//! | `triangles` | 32,767 | 32,768 |
//! | `serve_frame_us_median` | 27.3–38.8 | 24.5–27.7 |
//! | `serve_evaluated_per_frame_median` | 20 | 18 |
//! | `serve_many_frame_us_mean`, `serve_many_evaluated_mean` | 209–245 µs, 453 | 126–146 µs, 346 |
//! | `tessellate_ms_median` (from scratch) | 0.87–0.89 | 1.01–1.03 |
//!
//! The fog-aware cut lets through a third of the error; what it gives up is far error
//! the fog hides (the fog-unaware measure triples). The served frames cost no more: the
//! validity bound is tighter with fog, but fewer far diamonds are in the cut to fall due
//! (the 32 viewers' frames a third cheaper). From scratch it cost 15 % more when this was
//! written (the fog's transmission, four lanes at once; one scalar `exp` a lane cost 35 %),
//! and 5–7 % more by issue 41; a shorter `exp2` (`F4::exp2_neg`, `tessellate/lanes.rs`)
//! made it 0.97× the plain cut's ns a triangle on `data/kossou` and 0.90× on a steep map at
//! 65,536. At 65,536: fogged 0.161 → 0.047 px, unfogged 0.188 → 0.603.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use roam_protocol::stats::quantile;
use roam_server::Terrain;
use roam_server::sim::flyover;
use roam_server::terrain::dataset;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator};
use roam_server::viewer::{CutArgs, FogPriority, ViewerLimits};

use super::progress::Staged;
use roam_server::terrain::cache::CacheReport;

/// Camera options shared by `mesh` and `bench`.
#[derive(Args, Clone)]
pub(crate) struct CameraArgs {
    /// Eye position in world coordinates, `X,Y,Z`.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub eye: Option<[f64; 3]>,
    /// Heading of the view in degrees: 0 faces south (+Z), 90 east (+X).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub yaw: f64,
    /// Pitch in degrees, positive looking up.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub pitch: f64,
}

#[derive(Args)]
pub(crate) struct MeshArgs {
    /// Data-set directory.
    pub dir: PathBuf,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 60.0)]
    pub fov: f64,
    /// Viewport width in pixels.
    #[arg(long, default_value_t = 1920)]
    pub width: u32,
    /// Viewport height in pixels.
    #[arg(long, default_value_t = 1080)]
    pub height: u32,
    /// Triangle budget.
    #[arg(long, default_value_t = 65536)]
    pub budget: u32,
    /// Stop splitting below this screen-space error, pixels.
    #[arg(long, default_value_t = 0.0)]
    pub threshold: f32,
    /// Weigh each error by the map's fog (`on`), or not (`off`: the fog-unaware priority).
    #[arg(long, value_enum, default_value_t = FogPriority::On)]
    pub fog_priority: FogPriority,
    /// A guard band: the frustum widened by this many degrees either side (0: none).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=i64::from(roam_server::viewer::MAX_GUARD_DEG)))]
    pub guard_deg: u8,
    /// Output Wavefront OBJ (world coordinates, faces counter-clockwise from above).
    #[arg(long)]
    pub obj: PathBuf,
}

#[derive(Args)]
pub(crate) struct BenchArgs {
    /// Data-set directory.
    pub dir: PathBuf,
    /// Triangle budget per frame.
    #[arg(long, default_value_t = 65536)]
    pub budget: u32,
    /// Frames to time (after warm-up frames that are not counted).
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Stop splitting below this screen-space error, pixels.
    #[arg(long, default_value_t = 0.0)]
    pub threshold: f32,
    /// How the served cuts are made, as `serve`'s: --fog-priority, --guard-deg,
    /// --swap-margin.
    #[command(flatten)]
    pub cut: CutArgs,
    /// One fixed camera instead of the fly-over path (needs `--eye`).
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// The serving figures' drive, an input script (`<ticks> <keys>` lines, as
    /// `simulate --inputs` reads), instead of the built-in one; e.g.
    /// `scripts/capacity-drive.txt`.
    #[arg(long, value_name = "FILE")]
    pub drive: Option<PathBuf>,
    /// The most changes a viewer's cut makes a frame once within its budget, as a loaded
    /// server allows (`net/frames.rs`); the rest waits for the frames after. Unset: none.
    #[arg(long, value_name = "CHANGES")]
    pub allowance: Option<u32>,
}

fn parse_vec3(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!("expected X,Y,Z (three numbers), got {s:?}"));
    };
    let num = |v: &str| {
        v.parse::<f64>()
            .ok()
            .filter(|f| f.is_finite())
            .ok_or_else(|| format!("expected a finite number, got {v:?}"))
    };
    Ok([num(x)?, num(y)?, num(z)?])
}

/// What [`open`] gives: the terrain (without its colour map), the variance tree, what was
/// done with the cache and how long the opening took.
pub(crate) struct Opened {
    pub terrain: Terrain,
    pub variance: VarianceTree,
    pub report: CacheReport,
    pub ms: f64,
}

/// Opens a data set for serving from its cache (`dataset::open_cached`; built on first
/// use), with progress bars on a terminal; why a cache file was rebuilt or not written is
/// logged as a warning.
pub(crate) fn open(dir: &Path) -> Result<Opened> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let started = Instant::now();
    let (terrain, variance, report) = {
        let mut p = Staged::default();
        dataset::open_cached(dir, threads, &mut p.callback())?
    };
    let ms = started.elapsed().as_secs_f64() * 1e3;
    for note in &report.notes {
        tracing::warn!("{note}");
    }
    Ok(Opened {
        terrain,
        variance,
        report,
        ms,
    })
}

fn scales(t: &Terrain) -> Scales {
    Scales {
        h: t.map.h_scale,
        v: t.map.v_scale,
    }
}

pub(crate) fn mesh(args: MeshArgs) -> Result<()> {
    let Opened {
        terrain,
        variance: vt,
        ..
    } = open(&args.dir)?;
    let Some(eye) = args.camera.eye else {
        bail!("--eye X,Y,Z is required");
    };
    if args.width == 0 || args.height == 0 || !(1.0..179.0).contains(&args.fov) {
        bail!("--width and --height must be positive and --fov within 1..179 degrees");
    }
    let camera = Camera {
        eye,
        yaw_deg: args.camera.yaw,
        pitch_deg: args.camera.pitch,
        fov_y_deg: args.fov,
        width: args.width,
        height: args.height,
    };
    let mut tess = Tessellator::new(terrain.heights.side());
    let mut mesh = Mesh::default();
    let limits = Limits {
        budget: args.budget,
        threshold_px: args.threshold,
        fog_density: args.fog_priority.density(&terrain),
        guard_deg: f32::from(args.guard_deg),
    };
    tess.tessellate(
        &terrain.heights,
        &vt,
        scales(&terrain),
        &camera,
        limits,
        &mut mesh,
    );
    write_obj(&args.obj, &terrain, &mesh)
        .with_context(|| format!("writing {}", args.obj.display()))?;
    say!(
        "{} triangles, error bound {:.2} px",
        mesh.triangle_count(),
        mesh.error_bound_px
    );
    Ok(())
}

fn write_obj(path: &Path, terrain: &Terrain, mesh: &Mesh) -> std::io::Result<()> {
    let mut w = BufWriter::new(File::create(path)?);
    writeln!(w, "# roam-server mesh: {} triangles", mesh.triangle_count())?;
    let h = terrain.map.h_scale;
    for &[x, z] in &mesh.vertices {
        let y = terrain.world_height(u32::from(x), u32::from(z));
        writeln!(w, "v {} {} {}", f64::from(x) * h, y, f64::from(z) * h)?;
    }
    for t in mesh.indices.chunks_exact(3) {
        writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
    }
    w.flush()
}

pub(crate) fn bench(args: BenchArgs) -> Result<()> {
    let Opened {
        terrain,
        variance: vt,
        report: cache,
        ms: variance_build_ms,
    } = open(&args.dir)?;
    let frames = args.frames.max(1);
    let cameras: Vec<Camera> = match args.camera.eye {
        Some(eye) => vec![Camera {
            eye,
            yaw_deg: args.camera.yaw,
            pitch_deg: args.camera.pitch,
            fov_y_deg: flyover::FOV_Y_DEG,
            width: flyover::WIDTH,
            height: flyover::HEIGHT,
        }],
        None => flyover::flyover(&terrain, frames),
    };
    let limits = Limits {
        budget: args.budget,
        threshold_px: args.threshold,
        fog_density: args.cut.fog_priority.density(&terrain),
        guard_deg: 0.0,
    };
    let mut tess = Tessellator::new(terrain.heights.side());
    let mut mesh = Mesh::default();
    let sc = scales(&terrain);
    // Warm-up: fill the pools and caches.
    for cam in cameras.iter().cycle().take(10) {
        tess.tessellate(&terrain.heights, &vt, sc, cam, limits, &mut mesh);
    }
    let (mut ms, mut ns_per_tri, mut tris, mut err) = (vec![], vec![], vec![], vec![]);
    for cam in cameras.iter().cycle().take(frames) {
        let started = Instant::now();
        tess.tessellate(&terrain.heights, &vt, sc, cam, limits, &mut mesh);
        let ns = started.elapsed().as_nanos() as f64;
        let n = mesh.triangle_count().max(1) as f64;
        ms.push(ns / 1e6);
        ns_per_tri.push(ns / n);
        tris.push(n);
        err.push(f64::from(mesh.error_bound_px));
    }
    let terrain = std::sync::Arc::new(terrain);
    let vehicle_steps_per_second = super::sim::bench_physics(&terrain);
    let codec = codec_bench(&terrain, &vt, limits)?;
    let script = match &args.drive {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading the drive {}", path.display()))?;
            roam_protocol::script::parse(&text)
                .with_context(|| format!("the drive {}", path.display()))?
        }
        None => roam_protocol::script::parse(roam_protocol::script::DRIVE_SCRIPT)
            .expect("the built-in drive is a valid script"),
    };
    let caps = args.cut.limits(ViewerLimits::default());
    let allowance = args.allowance.unwrap_or(u32::MAX);
    let serve = serve_bench(&terrain, &vt, limits, caps, allowance, &script)?;
    let many = serve_many_bench(&terrain, &vt, limits, caps, allowance, &script);
    let samples = f64::from(terrain.heights.side()).powi(2);
    let resident = (terrain.heights.bytes() + vt.bytes()) as f64 / samples;
    let mut report = serde_json::json!({
        "data_set": args.dir.display().to_string(),
        "side": terrain.heights.side(),
        "budget": args.budget,
        "frames": frames,
        "triangles": quantile(&tris, 0.5),
        "tessellate_ns_per_triangle_median": quantile(&ns_per_tri, 0.5),
        "tessellate_ms_median": quantile(&ms, 0.5),
        "tessellate_ms_p99": quantile(&ms, 0.99),
        "variance_bytes_per_sample": vt.bytes_per_sample(),
        "variance_build_ms": variance_build_ms,
        "variance_source": format!("{:?}", cache.variance).to_lowercase(),
        "screen_error_px_median": quantile(&err, 0.5),
        "screen_error_px_p99": quantile(&err, 0.99),
        "resident_bytes_per_sample": resident,
        "tessellator_bytes": tess.heap_bytes(),
        "vehicle_steps_per_second": vehicle_steps_per_second,
        "wire_bytes_per_triangle_first": codec.first,
        "wire_bytes_per_triangle_steady": codec.steady,
        "encode_ns_per_triangle": codec.encode_ns,
        "decode_ns_per_triangle": codec.decode_ns,
        "codec_frames": codec.frames,
        "serve_frame_us_median": serve.frame_us_median,
        "serve_frame_us_p99": serve.frame_us_p99,
        "serve_changes_per_frame_median": serve.changes_median,
        "serve_screen_error_px_p99": serve.error_p99,
        "scratch_screen_error_px_p99": serve.scratch_error_p99,
        "serve_fogged_error_px_p99": serve.fogged_error_p99,
        "serve_unfogged_error_px_p99": serve.unfogged_error_p99,
        "serve_wire_bytes_per_triangle_first": serve.bytes_per_triangle_first,
        "serve_wire_bytes_per_triangle_steady": serve.bytes_per_triangle_steady,
        "serve_rebuilds": serve.rebuilds,
        "serve_viewer_heap_bytes": serve.viewer_bytes,
        "serve_viewer_heap_bytes_peak": serve.viewer_bytes_peak,
        "serve_viewer_heap_parts": serve.viewer_parts,
        "serve_evaluated_per_frame_median": serve.evaluated_median,
        "last_frame": {
            "evaluated": tess.stats().evaluated,
            "culled": tess.stats().culled,
            "popped": tess.stats().popped,
            "split": tess.stats().split,
            "forcing": tess.stats().forcing,
        },
    });
    // Added apart: one `json!` of every key passes the macro's recursion limit.
    let more = report.as_object_mut().expect("built as an object above");
    for (k, v) in [
        (
            "serve_popped_per_frame_median",
            serde_json::json!(serve.popped_median),
        ),
        ("serve_many_viewers", serde_json::json!(MANY_VIEWERS)),
        (
            "fog_priority",
            serde_json::json!(if caps.fog_priority { "on" } else { "off" }),
        ),
        ("fog_density", serde_json::json!(terrain.map.fog_density)),
        ("swap_margin_pct", serde_json::json!(caps.swap_margin_pct)),
        ("allowance", serde_json::json!(args.allowance)),
        ("serve_short_share", serde_json::json!(serve.short_share)),
        ("serve_first_frame_us", serde_json::json!(serve.first_us)),
        ("serve_many_frame_us_median", serde_json::json!(many.median)),
        (
            "serve_join_frame_us_median",
            serde_json::json!(many.first[0]),
        ),
        ("serve_join_frame_us_max", serde_json::json!(many.first[1])),
        ("serve_many_frame_us_p99", serde_json::json!(many.p99)),
        ("serve_many_frame_us_p90", serde_json::json!(many.p90)),
        ("serve_many_frame_us_mean", serde_json::json!(many.mean)),
        (
            "serve_many_changes_mean",
            serde_json::json!(many.per_frame[0]),
        ),
        (
            "serve_many_evaluated_mean",
            serde_json::json!(many.per_frame[1]),
        ),
        (
            "serve_many_popped_mean",
            serde_json::json!(many.per_frame[2]),
        ),
    ] {
        more.insert(k.into(), v);
    }
    if args.json {
        say!("{report}");
    } else {
        let obj = report.as_object().expect("built as an object above");
        for (k, v) in obj {
            say!("{k:>36}  {v}");
        }
    }
    Ok(())
}

/// The mesh codec over a drive: the first frame's size, then each frame coded against the
/// one before (as a viewer acknowledging every frame sees it).
struct CodecFigures {
    frames: usize,
    /// Bytes per triangle of the key frame, and the median of the delta frames.
    first: f64,
    steady: f64,
    /// Median time per triangle to encode, and to decode and build the mesh.
    encode_ns: f64,
    decode_ns: f64,
}

fn codec_bench(
    terrain: &std::sync::Arc<Terrain>,
    vt: &VarianceTree,
    limits: Limits,
) -> Result<CodecFigures> {
    use roam_protocol::{BitSet, Grid, MeshDecoder, MeshEncoder, mesh};
    let script =
        roam_protocol::script::parse(roam_protocol::script::DRIVE_SCRIPT).expect("a valid script");
    let cameras = flyover::drive(terrain, &script, 60);
    let grid = Grid::new(terrain.heights.levels()).expect("data sets have 1 ..= 15 levels");
    let step = roam_protocol::height_step(terrain.heights.samples());
    let (mut enc, mut dec) = (MeshEncoder::with_step(grid, step), MeshDecoder::new(grid));
    let mut tess = Tessellator::new(terrain.heights.side());
    let (mut server_mesh, mut viewer_mesh) = (Mesh::default(), mesh::Mesh::default());
    let (mut split, mut decoded) = (BitSet::default(), BitSet::default());
    let mut base: Option<BitSet> = None;
    let (mut bytes, mut encode_ns, mut decode_ns) = (vec![], vec![], vec![]);
    let mut payload = Vec::new();
    for cam in &cameras {
        tess.tessellate(
            &terrain.heights,
            vt,
            scales(terrain),
            cam,
            limits,
            &mut server_mesh,
        );
        let tris = server_mesh.triangle_count().max(1) as f64;
        tess.split_set(&grid, &mut split);
        payload.clear();
        let started = Instant::now();
        enc.encode(
            &split,
            terrain.heights.samples(),
            base.as_ref(),
            &mut payload,
        )?;
        encode_ns.push(started.elapsed().as_nanos() as f64 / tris);
        let started = Instant::now();
        dec.decode(&payload, base.as_ref(), u32::MAX, &mut decoded)?;
        mesh::emit(&grid, &decoded, dec.heights(), &mut viewer_mesh);
        decode_ns.push(started.elapsed().as_nanos() as f64 / tris);
        if decoded != split || viewer_mesh.indices != server_mesh.indices {
            bail!("the decoded mesh differs from the server's: a codec bug");
        }
        bytes.push(payload.len() as f64 / tris);
        base = Some(split.clone());
    }
    Ok(CodecFigures {
        frames: cameras.len(),
        first: bytes.first().copied().unwrap_or(0.0),
        steady: quantile(bytes.get(1..).unwrap_or(&[]), 0.5),
        encode_ns: quantile(&encode_ns, 0.5),
        decode_ns: quantile(&decode_ns, 0.5),
    })
}

/// The serving path along the codec's drive: one viewer's frames, 1/60 s apart, made by
/// the per-viewer core (the cut carried by split/merge, coded as changes against the frame
/// before, which the viewer acknowledges at once), each decoded as the viewer would and
/// checked against the server's cut (not timed).
struct ServeFigures {
    frame_us_median: f64,
    frame_us_p99: f64,
    changes_median: f64,
    /// The served cut's own error bound (by the priority it was made with).
    error_p99: f64,
    scratch_error_p99: f64,
    /// The served cut's error through the map's fog, and without it, measured alike
    /// whichever priority made the cut (`fogged_error_px`, `measured_error`).
    fogged_error_p99: f64,
    unfogged_error_p99: f64,
    bytes_per_triangle_first: f64,
    bytes_per_triangle_steady: f64,
    rebuilds: usize,
    evaluated_median: f64,
    /// Schedule entries taken per frame (stale ones included).
    popped_median: f64,
    viewer_bytes: usize,
    /// The most the core had reserved after any frame of the drive.
    viewer_bytes_peak: usize,
    /// The share of frames whose update stopped at the allowance.
    short_share: f64,
    /// The first frame (a cut from scratch, its frontiers, a key frame), µs.
    first_us: f64,
    /// Where the cut's bytes go (`Coherent::heap_parts`).
    viewer_parts: Vec<serde_json::Value>,
}

fn serve_bench(
    terrain: &std::sync::Arc<Terrain>,
    vt: &VarianceTree,
    limits: Limits,
    caps: ViewerLimits,
    allowance: u32,
    script: &roam_protocol::script::Script,
) -> Result<ServeFigures> {
    use roam_protocol::{BitSet, Follower, Grid, mesh};
    use roam_server::tessellate::{Mode, fogged_error_px, measured_error};
    use roam_server::viewer::{Event, Scene, ViewerCore};
    let cameras = flyover::drive(terrain, script, 60);
    // The served cut's guard band, for the from-scratch cut beside it and the measures.
    let limits = Limits {
        guard_deg: f32::from(caps.guard_deg),
        ..limits
    };
    let sc = scales(terrain);
    let levels = terrain.heights.levels();
    let step = roam_protocol::height_step(terrain.heights.samples());
    let mut core = ViewerCore::new(
        levels,
        step,
        flyover::FOV_Y_DEG as f32,
        [flyover::WIDTH, flyover::HEIGHT],
        limits.budget,
    )
    .with_caps(caps);
    core.set_allowance(allowance);
    let pool = roam_server::tessellate::Scratch::new(terrain.heights.side(), 1);
    let scene = Scene {
        terrain,
        variance: vt,
        scratch: &pool,
    };
    let grid = Grid::new(levels).expect("data sets have 1 ..= 15 levels");
    // The viewer's decoder, and its cut mirrored over the grid for `mesh::emit`.
    let mut decoder = Follower::new(grid, 2);
    let (mut split, mut heights) = (BitSet::new(grid.vertices()), vec![0; grid.vertices()]);
    let mut scratch = Tessellator::new(terrain.heights.side());
    let (mut served, mut viewer) = (Mesh::default(), mesh::Mesh::default());
    let (mut us, mut changes, mut err, mut scratch_err) = (vec![], vec![], vec![], vec![]);
    let (mut fogged, mut unfogged) = (vec![], vec![]);
    let (side, density) = (terrain.heights.side(), terrain.map.fog_density as f32);
    let (mut bytes, mut evaluated, mut popped, mut rebuilds) = (vec![], vec![], vec![], 0);
    let (mut peak, mut short, mut first_us) = (0, 0, 0.0);
    for (k, cam) in cameras.iter().enumerate() {
        let started = Instant::now();
        let made = core.make_frame_at(&scene, cam);
        let elapsed = started.elapsed().as_nanos() as f64 / 1e3;
        let tris = f64::from(made.triangles.max(1));
        bytes.push(made.payload.len() as f64 / tris);
        if k == 0 {
            first_us = elapsed;
        } else {
            us.push(elapsed);
            changes.push(f64::from(made.changes));
            evaluated.push(f64::from(core.cut().stats().evaluated));
            popped.push(f64::from(core.cut().stats().popped));
            rebuilds += usize::from(made.mode == Mode::Rebuild);
            short += usize::from(core.cut().stats().short);
        }
        decoder.decode(made.frame, &made.payload, made.base, u32::MAX)?;
        decoder.mirror(&mut split, &mut heights);
        mesh::emit(&grid, &split, &heights, &mut viewer);
        core.mesh(&pool, &mut served);
        if viewer.indices != served.indices {
            bail!(
                "frame {k}: the viewer's mesh differs from the server's: a codec bug \
                 ({} vs {} triangles, base {:?}, {:?})",
                viewer.triangle_count(),
                served.triangle_count(),
                made.base,
                made.mode,
            );
        }
        core.handle(Event::Acked(made.frame));
        peak = peak.max(core.heap_bytes());
        if made.triangles > limits.budget.max(2) {
            bail!("the served cut is over budget at frame {k}: a tessellator bug");
        }
        scratch.tessellate(&terrain.heights, vt, sc, cam, limits, &mut served);
        // Both cuts measured the same way (from scratch reports only what its queue reached).
        err.push(f64::from(core.cut().error_bound_px()));
        let h = &terrain.heights;
        scratch_err.push(f64::from(measured_error(
            h,
            vt,
            sc,
            cam,
            limits,
            scratch.split_diamonds(),
        )));
        // The served cut through the fog and without it, whichever priority made it.
        let cut = core.cut();
        let is_split = |i: u32| cut.is_split(i % side, i / side);
        fogged.push(f64::from(fogged_error_px(
            h,
            vt,
            sc,
            cam,
            density,
            limits.guard_deg,
            is_split,
        )));
        let plain = Limits {
            fog_density: 0.0,
            ..limits
        };
        unfogged.push(f64::from(measured_error(
            h,
            vt,
            sc,
            cam,
            plain,
            cut.split_diamonds(),
        )));
    }
    Ok(ServeFigures {
        frame_us_median: quantile(&us, 0.5),
        frame_us_p99: quantile(&us, 0.99),
        changes_median: quantile(&changes, 0.5),
        error_p99: quantile(&err, 0.99),
        scratch_error_p99: quantile(&scratch_err, 0.99),
        fogged_error_p99: quantile(&fogged, 0.99),
        unfogged_error_p99: quantile(&unfogged, 0.99),
        bytes_per_triangle_first: bytes.first().copied().unwrap_or(0.0),
        bytes_per_triangle_steady: quantile(bytes.get(1..).unwrap_or(&[]), 0.5),
        rebuilds,
        short_share: short as f64 / us.len().max(1) as f64,
        first_us,
        evaluated_median: quantile(&evaluated, 0.5),
        popped_median: quantile(&popped, 0.5),
        viewer_bytes: core.heap_bytes(),
        viewer_bytes_peak: peak,
        viewer_parts: core
            .cut()
            .heap_parts()
            .into_iter()
            .map(|(part, bytes, entries)| serde_json::json!({"part": part, "bytes": bytes, "entries": entries}))
            .collect(),
    })
}

/// Viewers served in turn by [`serve_many_bench`].
const MANY_VIEWERS: usize = 32;

/// Frame times with caches as a busy server has them.
struct ManyFigures {
    median: f64,
    p90: f64,
    p99: f64,
    /// What a server spends a frame on average (the tail included).
    mean: f64,
    /// Changes, evaluations and schedule entries taken, a frame on average.
    per_frame: [f64; 3],
    /// The cores' first frames (a join's: a cut from scratch, its frontiers, a key frame),
    /// each at another point of the drive, µs: median and slowest.
    first: [f64; 2],
}

/// The serving path as a server with many viewers runs it: [`MANY_VIEWERS`] per-viewer
/// cores along the codec's drive, each from another point of it, making their frames in
/// turn (so each finds its own state gone from the caches, as it does when a server
/// serves many viewers), every frame acknowledged at once. Each core's first frame (a
/// rebuild, as a join's) is timed apart: `first`.
fn serve_many_bench(
    terrain: &std::sync::Arc<Terrain>,
    vt: &VarianceTree,
    limits: Limits,
    caps: ViewerLimits,
    allowance: u32,
    script: &roam_protocol::script::Script,
) -> ManyFigures {
    use roam_server::viewer::{Event, Scene, ViewerCore};
    let cameras = flyover::drive(terrain, script, 60);
    let levels = terrain.heights.levels();
    let step = roam_protocol::height_step(terrain.heights.samples());
    let pool = roam_server::tessellate::Scratch::new(terrain.heights.side(), 1);
    let scene = Scene {
        terrain,
        variance: vt,
        scratch: &pool,
    };
    let mut cores: Vec<ViewerCore> = (0..MANY_VIEWERS)
        .map(|_| {
            ViewerCore::new(
                levels,
                step,
                flyover::FOV_Y_DEG as f32,
                [flyover::WIDTH, flyover::HEIGHT],
                limits.budget,
            )
            .with_caps(caps)
        })
        .collect();
    for core in &mut cores {
        core.set_allowance(allowance);
    }
    let n = cameras.len();
    let mut us = Vec::with_capacity(n * MANY_VIEWERS);
    // Changes, evaluations and schedule entries taken, summed over the timed frames.
    let mut counts = [0f64; 3];
    let mut first = Vec::with_capacity(MANY_VIEWERS);
    for k in 0..n {
        for (i, core) in cores.iter_mut().enumerate() {
            let cam = &cameras[(k + i * n / MANY_VIEWERS) % n];
            let started = Instant::now();
            let made = core.make_frame_at(&scene, cam);
            let elapsed = started.elapsed().as_nanos() as f64 / 1e3;
            if k > 0 {
                us.push(elapsed);
                let st = core.cut().stats();
                counts[0] += f64::from(made.changes);
                counts[1] += f64::from(st.evaluated);
                counts[2] += f64::from(st.popped);
            } else {
                first.push(elapsed);
            }
            core.handle(Event::Acked(made.frame));
        }
    }
    ManyFigures {
        median: quantile(&us, 0.5),
        p90: quantile(&us, 0.9),
        p99: quantile(&us, 0.99),
        mean: us.iter().sum::<f64>() / us.len().max(1) as f64,
        per_frame: counts.map(|c| c / us.len().max(1) as f64),
        first: [quantile(&first, 0.5), quantile(&first, 1.0)],
    }
}
