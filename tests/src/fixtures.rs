//! What the tests share: a small terrain ([`flat`]), the bundled real one ([`kossou`]), a
//! server on loopback ([`serve`], [`serve_tiled`]), its colour pyramid ([`pyramid`]), and the seeded generator the relay and the simulated
//! network draw every random choice from ([`SplitMix64`]).

use std::sync::Arc;

use roam_link::tls;
use roam_server::net::{Options, Server};
use roam_server::terrain::color_pyramid::ColorPyramid;
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
