//! What the tests share: a small terrain ([`flat`]), the bundled real one ([`kossou`]), a
//! server on loopback ([`serve`], [`serve_tiled`]), its colour and normal pyramids
//! ([`pyramid`], [`normals`]), and the seeded generator the relay and the simulated
//! network draw every random choice from ([`SplitMix64`]).

use std::sync::Arc;

use roam_link::tls;
use roam_server::net::{Options, Server};
use roam_server::terrain::color_pyramid::ColorPyramid;
use roam_server::terrain::normal_pyramid::NormalPyramid;
use roam_server::terrain::variance::VarianceTree;
use roam_server::{ColorMap, Heightfield, MapParams, Terrain};

/// A server running on loopback, and what a viewer needs to join it.
pub struct Running {
    pub server: Server,
    pub token: String,
    pub fingerprint: [u8; 32],
}

/// The token [`serve`] gives its servers.
pub const TOKEN: &str = "test-token-0123456789";

/// A server on `127.0.0.1:0` for `terrain`, with the default options as `tune` changes
/// them (on the current tokio runtime).
pub fn serve(terrain: Arc<Terrain>, tune: impl FnOnce(Options) -> Options) -> Running {
    serve_tiled(terrain, roam_protocol::tiles::DEFAULT_TILE, tune)
}

/// [`serve`] with the colour map in tiles of `tile` texels a side.
pub fn serve_tiled(
    terrain: Arc<Terrain>,
    tile: u32,
    tune: impl FnOnce(Options) -> Options,
) -> Running {
    let identity = tls::generate().expect("a certificate");
    serve_as(terrain, tile, &identity, tune)
}

/// [`serve_tiled`] with `identity`'s certificate (servers sharing one: the edges of a
/// world, pinned by one fingerprint).
pub fn serve_as(
    terrain: Arc<Terrain>,
    tile: u32,
    identity: &tls::Identity,
    tune: impl FnOnce(Options) -> Options,
) -> Running {
    let pyramid = pyramid(&terrain, tile);
    let vt = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
    let options = tune(Options::new(
        "127.0.0.1:0".parse().expect("valid"),
        TOKEN.to_owned(),
    ));
    let token = options.token.clone();
    let server = Server::start(terrain, Arc::new(vt), pyramid, identity, options).expect("listens");
    let fingerprint = tls::parse_fingerprint(&identity.fingerprint()).expect("valid");
    Running {
        server,
        token,
        fingerprint,
    }
}

/// `terrain`'s colour pyramid in tiles of `tile` texels, built in memory on two threads.
pub fn pyramid(terrain: &Terrain, tile: u32) -> Arc<ColorPyramid> {
    let color = (terrain.color.as_ref()).expect("the test terrains are loaded whole");
    let p = ColorPyramid::build(color, tile, 2, &mut |_, _| {})
        .expect("the test terrains' colour maps are powers of two");
    Arc::new(p)
}

/// `terrain`'s normal pyramid in tiles of `tile` texels (what a server it is given to
/// builds when not given one).
pub fn normals(terrain: &Terrain, tile: u32) -> Arc<NormalPyramid> {
    let scales = (terrain.map.h_scale, terrain.map.v_scale);
    let p = NormalPyramid::build(&terrain.heights, scales, tile, 2, &mut |_, _| {})
        .expect("the test terrains' grids are 2^N + 1");
    Arc::new(p)
}

/// The bundled data set (`data/kossou`, 1025² samples).
pub fn kossou() -> Arc<Terrain> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/kossou");
    Arc::new(roam_server::terrain::dataset::load(&dir, &mut |_, _| {}).expect("bundled"))
}

/// A 129² terrain, flat around the start and rough beyond: a vehicle at rest stays put
/// until keys arrive (so a drive over the network can be compared with the same script
/// simulated), and there is detail to stream.
pub fn flat() -> Arc<Terrain> {
    let side = 129u32;
    let heights = (0..side * side)
        .map(|i| {
            let (x, z) = (i % side, i / side);
            let (dx, dz) = (x.abs_diff(64), z.abs_diff(64));
            let rough = (x * 7_919 + z * 104_729) % 3_000;
            20_000 + if dx.max(dz) > 16 { rough as u16 } else { 0 }
        })
        .collect();
    let mut map = MapParams::default_for_side(side);
    map.h_scale = 4.0;
    map.start.x = 256.0;
    map.start.z = 256.0;
    Arc::new(Terrain {
        map,
        heights: Heightfield::new(side, heights).expect("valid"),
        color: Some(ColorMap::new(128, vec![[90, 120, 60]; 128 * 128]).expect("cells²")),
    })
}

/// A small deterministic generator (Vigna's SplitMix64; not for secrets).
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> SplitMix64 {
        SplitMix64(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.unit() < p
    }
}

/// Accelerate, turn, then brake to a stop: the end state is still, whatever the timing.
pub const DRIVE: &str = "10 U\n5 UL\n8 U\n400 D\n";

/// Where vehicle 0 ends, driven by [`DRIVE`] from the first start slot of `terrain`,
/// simulated without a network (the other vehicles of a world never touch it).
pub fn simulated_drive(terrain: &Arc<Terrain>) -> roam_server::sim::world::Vehicle {
    use roam_server::sim::world::{self, Inputs, World};
    let s = roam_protocol::script::parse(DRIVE).expect("valid");
    let mut w = World::new(terrain.clone());
    w.add(0, world::start_state(terrain, 0))
        .expect("on the map");
    let mut inputs = Inputs::new();
    for k in s.keys() {
        inputs.set(0, k);
        world::step(&mut w, &inputs);
    }
    w.vehicles()[0]
}

/// Checks that a drive of [`DRIVE`] ends, in the frames, exactly where
/// [`simulated_drive`] puts it (`last`: the driven vehicle in the last frame, at `tick`).
pub fn assert_drive_exact(
    terrain: &Arc<Terrain>,
    last: Option<roam_protocol::messages::VehicleView>,
    tick: u64,
) {
    let want = simulated_drive(terrain);
    let got = last.expect("a vehicle in the frames");
    assert_eq!(
        (got.x, got.z, got.speed, got.heading),
        (
            want.state.x,
            want.state.z,
            want.state.speed,
            want.state.heading
        ),
        "at tick {tick}"
    );
}

/// Checks that the one recording in `dir` replays to `final_world` bit for bit, closed
/// cleanly, and removes `dir`.
pub fn assert_replays(
    dir: &std::path::Path,
    terrain: &Arc<Terrain>,
    final_world: &roam_server::sim::world::World,
) {
    use roam_server::sim::{recording, replay};
    let files: Vec<_> = std::fs::read_dir(dir)
        .expect("the recording directory")
        .map(|e| e.expect("a directory entry").path())
        .collect();
    assert_eq!(files.len(), 1, "one recording file: {files:?}");
    let bytes = std::fs::read(&files[0]).expect("the recording");
    let rec = recording::parse(&bytes).expect("parses");
    let out = replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays");
    assert!(out.ended, "closed cleanly");
    assert_eq!(out.tick, final_world.tick());
    assert_eq!(out.digest, final_world.digest());
    let _ = std::fs::remove_dir_all(dir);
}

/// A key frame of the whole 65² grid unsplit, numbered `frame` (what a fake server sends).
pub fn key_frame(frame: u64) -> Vec<u8> {
    use roam_protocol::{BitSet, Grid, MeshEncoder, messages};
    let grid = Grid::new(6).expect("a valid size");
    let heights = vec![100u16; grid.vertices()];
    let mut mesh = Vec::new();
    MeshEncoder::new(grid)
        .encode(&BitSet::new(grid.vertices()), &heights, None, &mut mesh)
        .expect("a closed cut");
    let mut out = Vec::new();
    messages::encode(
        &messages::Frame {
            frame,
            base: None,
            tick: frame,
            vehicles: Vec::new(),
            input_seq: None,
            mesh,
        },
        &mut out,
    )
    .expect("within the limits");
    out
}

/// How long a session test waits for any one thing.
pub const BOUND: std::time::Duration = std::time::Duration::from_secs(60);

/// `f`, or a panic naming `what` after [`BOUND`].
pub async fn bounded<T>(what: &str, f: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(BOUND, f)
        .await
        .unwrap_or_else(|_| panic!("{what}: not within {} s", BOUND.as_secs()))
}

/// `s`'s status once `f` holds, within [`BOUND`].
pub async fn status_when(
    s: &roam_client::session::Session,
    what: &str,
    f: impl Fn(&roam_client::session::Status) -> bool,
) -> roam_client::session::Status {
    let mut changes = s.status_changes();
    bounded(what, changes.wait_for(|st| f(st)))
        .await
        .expect("the session is there")
        .clone()
}

/// Frames [`frame`] may see passed over ([`Taken::Nothing`](roam_client::session::Taken):
/// older than one taken, or coded against a base not taken yet) before it fails: ten
/// times the viewer's patience for a base (`AWAIT_BASE`, 60 frames).
pub const PASSED_OVER: usize = 600;

/// The next frame `s` takes (frames that fail to decode are not expected), each take
/// within [`BOUND`], at most [`PASSED_OVER`] passed over first.
pub async fn frame(s: &roam_client::session::Session) -> roam_client::session::Received {
    use roam_client::session::Taken;
    for _ in 0..=PASSED_OVER {
        match bounded("a frame", s.next_frame(true)).await {
            Ok(Taken::Frame(r)) => return r,
            Ok(Taken::Nothing) => {}
            Ok(Taken::Dropped(why)) => panic!("a frame failed to decode: {why}"),
            Err(e) => panic!("the session ended: {e:#}"),
        }
    }
    panic!("no frame taken: {PASSED_OVER} in a row passed over");
}

/// What a fake server welcomes with: the 65² grid of [`key_frame`], colour in `color`.
pub fn fake_welcome(color: roam_protocol::ColorLayout) -> roam_protocol::messages::Welcome {
    use roam_protocol::messages::{MAX_BUDGET, VERSION, Welcome};
    Welcome {
        version: VERSION,
        levels: 6,
        h_scale: 10.0,
        v_scale: 0.1,
        sun_dir: [0.0, 1.0, 0.0],
        sun_color: [255; 3],
        fog_density: 1e-3,
        fog_color: [200; 3],
        water_level: None,
        vehicle: 0,
        color,
        tick: 0,
        ticket: None,
        resumed: false,
        max_budget: MAX_BUDGET,
        max_fps: 240,
    }
}

/// A driver's hello with `token`: 640×480, 4,000 triangles, 60 frames a second.
pub fn driver_hello(token: &str) -> roam_protocol::messages::Hello {
    hello(
        roam_protocol::messages::Role::Driver,
        token,
        [640, 480],
        4_000,
        60,
    )
}

/// A first hello as a native viewer makes it ([`roam_client::conversation::hello`]): a 60°
/// field of view, the colour window of a native viewer's device.
pub fn hello(
    role: roam_protocol::messages::Role,
    token: &str,
    viewport: [u32; 2],
    budget: u32,
    frame_rate: u16,
) -> roam_protocol::messages::Hello {
    roam_client::conversation::hello(
        role,
        token.to_owned(),
        viewport,
        60.0,
        budget,
        frame_rate,
        roam_client::render::native_max_texture(),
    )
}
