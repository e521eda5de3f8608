//! Fuzzing every decoder: the inputs, and the decoders with the state a viewer or a server
//! holds when it decodes. Shared by the million-input bench (`cargo bench -p roam-tests
//! --bench fuzz`) and the test that runs a smaller count under a counting allocator
//! (`tests/tests/it/fuzz.rs`).
//!
//! Inputs alternate ([`Fuzz::input`]): random bytes (under 300), and valid encodings
//! ([`seeds`]: messages of every kind, frames carrying real key and change frames, bare
//! meshes, colour maps) with one to four bytes flipped, cut or appended. Each input goes
//! through every [`Stage`] ([`Fuzz::feed`]): the four message decoders, the control
//! stream's framing (the input behind a length prefix that is true, random, or claims up
//! to 32 MiB), the mesh decoders (format 1's for key and delta frames, the viewer's for
//! change frames and every frame's mesh) and the colour-map decoder; a frame that decodes
//! goes on through the mesh decoders and the viewer's vertex builder. The viewer's decoder
//! ([`Follower`]) must agree with the protocol tests' reference decoder (their oracle,
//! `protocol/tests/it/common/reference.rs`, included here by path) on every mesh it is
//! given. The caller runs each stage (to count outcomes, catch panics, measure
//! allocations).

use std::future::Future;
use std::pin::pin;
use std::task::{Context, Poll, Waker};

use roam_client::render::{Scene, TerrainVertices};
use roam_link::wire;
use roam_protocol::messages::{
    self, ClientMessage, Frame, Hello, KeyDatagram, KeyState, Role, ServerMessage, VehicleView,
};
use roam_protocol::{
    BitSet, CHANGES_FORMAT, ChangeEncoder, Follower, Grid, LiveMesh, Mesh, MeshDecoder,
    MeshEncoder, colormap, mesh,
};

use crate::fixtures::SplitMix64;

/// The protocol tests' reference decoder: the oracle the viewer's decoder is held to.
#[path = "../../protocol/tests/it/common/reference.rs"]
#[allow(unreachable_pub)] // `pub` for the protocol tests' modules, which share the file
mod reference;

use reference::{Cut, Reference};

/// The side of the fuzzed colour maps: small, so that the many inputs that get past the
/// header (and decode every texel) stay quick.
pub const COLOR_CELLS: u32 = 32;
/// The fuzzed grid's levels (65 × 65 vertices).
pub const LEVELS: u32 = 6;
/// The triangle limit the mesh decoders are given.
pub const MAX_TRIANGLES: u32 = 100_000;
/// The control-stream limit of a server reading a viewer's messages (as the server does).
pub const HELLO_LIMIT: usize = 4096;

/// One step an input is taken through.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Stage {
    /// `messages::decode::<ClientMessage>`, as a server reads a control message.
    ClientMessage,
    /// `messages::decode::<ServerMessage>`, as a viewer reads one.
    ServerMessage,
    /// `messages::decode::<KeyDatagram>`.
    KeyDatagram,
    /// `messages::decode::<Frame>`.
    Frame,
    /// `wire::read::<ClientMessage>` with the server's limit ([`HELLO_LIMIT`]), over the
    /// framed input.
    WireClient,
    /// `wire::read::<ServerMessage>` with the viewer's limit (`MAX_MESSAGE`).
    WireServer,
    /// A decoded frame's mesh through the reference decoder: against the base a viewer
    /// holds when the frame names one.
    FrameMesh,
    /// A mesh that decoded (a frame's, a key frame's or a change frame's) emitted
    /// (`mesh::emit`) and built into vertices (`TerrainVertices::build`).
    Vertices,
    /// The frame's mesh as [`Stage::FrameMesh`] has it, through the viewer's decoder
    /// (`Follower::decode`, holding the same base), which must agree with the reference;
    /// a mesh that decodes goes on through its `LiveMesh` and `TerrainVertices::update`.
    FollowMesh,
    /// `MeshDecoder::decode` as a key frame.
    KeyMesh,
    /// `MeshDecoder::decode` as a delta on an empty base.
    DeltaMesh,
    /// The viewer's decoder (`Follower::decode`, as [`Stage::FollowMesh`]) against the
    /// change frames' base, which must agree with the reference; random inputs go behind a
    /// change frame's header.
    ChangeMesh,
    /// `colormap::decode` of a [`COLOR_CELLS`]² map.
    ColorMap,
}

/// Runs one stage: given the stage, the bytes it reads and the step itself (true when it
/// gave a value), returns what the step returned (false if it did not run to the end).
pub type Runner<'a> = dyn FnMut(Stage, &[u8], &mut dyn FnMut() -> bool) -> bool + 'a;

/// A value below `n` (0 when `n` is 0).
pub fn below(rng: &mut SplitMix64, n: usize) -> usize {
    (rng.next_u64() % n.max(1) as u64) as usize
}

/// Random split sets: `n` closed splits at random points.
fn random_splits(grid: Grid, set: &mut BitSet, rng: &mut SplitMix64, n: u32) {
    for _ in 0..n {
        let side = grid.side() as usize;
        let (x, z) = (below(rng, side) as u32, below(rng, side) as u32);
        grid.split_closed(set, x, z);
    }
}

/// The fuzzed terrain's heights.
pub fn heights(grid: Grid) -> Vec<u16> {
    (0..grid.vertices() as u32)
        .map(|i| (i * 7919 % 60_000) as u16)
        .collect()
}

/// The base the change frames are coded against (as a viewer holds it) and the split
/// sets the fuzzed change frames lead to.
pub fn change_base(grid: Grid, heights: &[u16]) -> (Cut, Vec<BitSet>) {
    let mut rng = SplitMix64::new(11);
    let mut base = BitSet::new(grid.vertices());
    random_splits(grid, &mut base, &mut rng, 30);
    let nows = [2, 10, 40]
        .into_iter()
        .map(|n| {
            let mut now = base.clone();
            random_splits(grid, &mut now, &mut rng, n);
            now
        })
        .collect();
    (Cut::of(&grid, base, heights), nows)
}

/// The key frame of `split`.
fn key_frame(grid: Grid, split: &BitSet, heights: &[u16]) -> Vec<u8> {
    let mut b = Vec::new();
    MeshEncoder::new(grid)
        .encode(split, heights, None, &mut b)
        .expect("a closed split set of this grid encodes");
    b
}

fn encoded<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    let mut b = Vec::new();
    messages::encode(msg, &mut b).expect("a message encodes");
    b
}

/// A frame carrying `mesh`.
fn frame(base: Option<u64>, mesh: Vec<u8>) -> Frame {
    Frame {
        frame: 3,
        base,
        tick: 77,
        vehicles: vec![VehicleView {
            id: 1,
            x: 1.0,
            z: 2.0,
            y: 3.0,
            speed: 4.0,
            heading: 5.0,
        }],
        input_seq: None,
        mesh,
    }
}

/// Valid encodings to mutate: messages of every kind, frames carrying a key frame, a
/// change frame and bytes that are no mesh, bare meshes (key frames and change frames)
/// and colour maps.
pub fn seeds(grid: Grid) -> Vec<Vec<u8>> {
    // Every field set: a ticket presented too.
    let hello = ClientMessage::Hello(Hello {
        resume: Some([7; 16]),
        ..crate::fixtures::hello(Role::Driver, "token", [1280, 720], 65_536, 60)
    });
    let mut out = vec![
        encoded(&hello),
        encoded(&ClientMessage::Ack { frame: 99 }),
        encoded(&ServerMessage::ColorTile {
            level: 1,
            x: 3,
            z: 300,
            data: vec![1; 64],
        }),
        encoded(&ServerMessage::ColorWindow {
            level: 0,
            x0: 2,
            z0: 1000,
        }),
        encoded(&ServerMessage::NormalTile {
            level: 2,
            x: 1,
            z: 0,
            data: vec![2; 48],
        }),
        encoded(&frame(Some(2), vec![9; 40])),
        encoded(&KeyDatagram {
            states: vec![
                KeyState {
                    seq: 5,
                    held: 3,
                    pressed: 1
                };
                4
            ],
            acked: Some(2),
        }),
    ];
    let heights = heights(grid);
    let (base, nows) = change_base(grid, &heights);
    out.push(encoded(&frame(
        None,
        key_frame(grid, &base.split, &heights),
    )));
    let mut enc = ChangeEncoder::new(grid, 1);
    for now in &nows {
        for (from, to) in [(&base.split, now), (now, &base.split)] {
            let changes: Vec<u32> = (0..grid.vertices() as u32)
                .filter(|&i| from.contains(i) != to.contains(i))
                .collect();
            let cut = Cut::of(&grid, to.clone(), &heights);
            let mut b = Vec::new();
            enc.encode(
                &changes,
                |i| to.contains(i),
                &heights,
                cut.triangles,
                to.len() as u32,
                cut.hash,
                &mut b,
            )
            .expect("a change list of this grid encodes");
            if std::ptr::eq(from, &base.split) && std::ptr::eq(now, &nows[1]) {
                out.push(encoded(&frame(Some(1), b.clone())));
            }
            // Those back to the base are coded against `now`: wrong-base frames here.
            out.push(b);
        }
    }
    let empty = BitSet::new(grid.vertices());
    for n in [3u32, 40, 400] {
        let mut set = BitSet::new(grid.vertices());
        random_splits(grid, &mut set, &mut SplitMix64::new(u64::from(n)), n);
        out.push(key_frame(grid, &set, &heights));
        if n == 40 {
            // A delta frame (format 1) against the empty split set.
            let mut b = Vec::new();
            MeshEncoder::new(grid)
                .encode(&set, &heights, Some(&empty), &mut b)
                .expect("a closed split set of this grid encodes");
            out.push(b);
        }
    }
    let mut rng = SplitMix64::new(7);
    let n = COLOR_CELLS * COLOR_CELLS;
    for amp in [0u64, 8, 256] {
        // Smooth colour under noise of growing strength (256: pure noise).
        let rgb: Vec<u8> = (0..n * 3)
            .map(|i| (i / 3 % COLOR_CELLS * 5 + i / 3 / COLOR_CELLS * 3) as u64)
            .map(|smooth| (smooth + rng.next_u64() % amp.max(1)) as u8)
            .collect();
        let mut b = Vec::new();
        colormap::encode(COLOR_CELLS, &rgb, &mut b).expect("texels of the right size");
        out.push(b);
    }
    out
}

/// The output of a future that is ready at once (reading bytes in memory), or `None`.
fn now<F: Future>(f: F) -> Option<F::Output> {
    match pin!(f).poll(&mut Context::from_waker(Waker::noop())) {
        Poll::Ready(v) => Some(v),
        Poll::Pending => None,
    }
}

/// The inputs, and every decoder with the state it decodes against.
pub struct Fuzz {
    pub grid: Grid,
    seeds: Vec<Vec<u8>>,
    rng: SplitMix64,
    /// Key and delta frames (format 1).
    dec: MeshDecoder,
    empty: BitSet,
    got: BitSet,
    /// The reference decoding change frames against `cut_base`, whose heights it holds.
    change_ref: Reference,
    /// The reference decoding a frame's mesh, as a viewer holding `cut_base` does.
    frame_ref: Reference,
    cut_base: Cut,
    cut: Cut,
    /// The viewer's decoder holding `cut_base` as frame 0, for frames' meshes.
    following: Following,
    /// Another, for change frames.
    changing: Following,
    view: View,
    texels: Vec<u8>,
    /// Scratch: a change frame's header on random bytes, a framed input.
    forced: Vec<u8>,
    framed: Vec<u8>,
    /// The terrain's heights, for the random key frames.
    heights: Vec<u16>,
    /// Scratch: a random split set; the random key frame made of it.
    split: BitSet,
    key: Vec<u8>,
}

impl Fuzz {
    /// Inputs drawn from `seed`.
    pub fn new(seed: u64) -> Fuzz {
        let grid = Grid::new(LEVELS).expect("a valid number of levels");
        let heights = heights(grid);
        let (cut_base, _) = change_base(grid, &heights);
        let key = key_frame(grid, &cut_base.split, &heights);
        let holding_base = || {
            let mut dec = Reference::new(grid);
            let mut cut = Cut::default();
            dec.decode_cut(&key, None, u32::MAX, &mut cut)
                .expect("the key frame just encoded decodes");
            assert_eq!(cut, cut_base, "the key frame decodes to its cut");
            dec
        };
        let scene = Scene {
            levels: LEVELS,
            h_scale: 30.0,
            v_scale: 0.05,
            sun_dir: [0.0, 1.0, 0.0],
            sun_color: [255; 3],
            fog_density: 0.0,
            fog_color: [200; 3],
            water_level: None,
            color: roam_protocol::ColorLayout::new(1 << LEVELS, 256, 8)
                .expect("a grid's cells, a valid tile and window"),
        };
        Fuzz {
            grid,
            seeds: seeds(grid),
            rng: SplitMix64::new(seed),
            dec: MeshDecoder::new(grid),
            empty: BitSet::new(grid.vertices()),
            got: BitSet::default(),
            change_ref: holding_base(),
            frame_ref: holding_base(),
            cut_base,
            cut: Cut::default(),
            following: Following::new(grid, &key),
            changing: Following::new(grid, &key),
            view: View {
                mesh: Mesh::default(),
                scene,
                vertices: TerrainVertices::default(),
            },
            texels: Vec::new(),
            forced: Vec::new(),
            framed: Vec::new(),
            split: BitSet::new(grid.vertices()),
            heights,
            key: Vec::new(),
        }
    }

    /// Input `n` into `input`: random bytes when `n` is even, else a seed mutated.
    pub fn input(&mut self, n: usize, input: &mut Vec<u8>) {
        let rng = &mut self.rng;
        input.clear();
        if n.is_multiple_of(2) {
            let len = below(rng, 300);
            input.extend((0..len).map(|_| rng.next_u64() as u8));
            return;
        }
        input.extend_from_slice(&self.seeds[below(rng, self.seeds.len())]);
        for _ in 0..1 + below(rng, 4) {
            match below(rng, 3) {
                0 if !input.is_empty() => {
                    let i = below(rng, input.len());
                    input[i] ^= 1 << below(rng, 8);
                }
                1 => input.truncate(below(rng, input.len() + 1)),
                _ => input.push(rng.next_u64() as u8),
            }
        }
    }

    /// Takes input `n` through every stage, each run by `run`.
    pub fn feed(&mut self, n: usize, input: &[u8], run: &mut Runner) {
        run(Stage::ClientMessage, input, &mut || {
            messages::decode::<ClientMessage>(input).is_ok()
        });
        run(Stage::ServerMessage, input, &mut || {
            messages::decode::<ServerMessage>(input).is_ok()
        });
        run(Stage::KeyDatagram, input, &mut || {
            messages::decode::<KeyDatagram>(input).is_ok()
        });
        self.frame(n, input, run);
        // The control stream: the input behind its length, a random length, or one of up
        // to 32 MiB (mostly within the viewer's limit, and far more than the input).
        let claimed = match n % 4 {
            0 | 1 => input.len() as u32,
            2 => self.rng.next_u64() as u32,
            _ => below(&mut self.rng, 32 << 20) as u32,
        };
        self.framed.clear();
        self.framed.extend_from_slice(&claimed.to_le_bytes());
        self.framed.extend_from_slice(input);
        let framed = &self.framed[..];
        let ready = "bytes in memory are read at once";
        run(Stage::WireClient, framed, &mut || {
            now(wire::read::<ClientMessage>(&mut &*framed, HELLO_LIMIT))
                .expect(ready)
                .is_ok()
        });
        run(Stage::WireServer, framed, &mut || {
            now(wire::read::<ServerMessage>(
                &mut &*framed,
                messages::MAX_MESSAGE,
            ))
            .expect(ready)
            .is_ok()
        });
        let (dec, got, empty) = (&mut self.dec, &mut self.got, &self.empty);
        if run(Stage::KeyMesh, input, &mut || {
            dec.decode(input, None, MAX_TRIANGLES, got).is_ok()
        }) {
            self.view.build(&self.grid, got, dec.heights(), input, run);
        }
        run(Stage::DeltaMesh, input, &mut || {
            dec.decode(input, Some(empty), MAX_TRIANGLES, got).is_ok()
        });
        // Random bytes reach the change frame decoder behind a change frame's header.
        let change_input: &[u8] = if n.is_multiple_of(2) && input.len() >= 4 {
            self.forced.clear();
            self.forced.extend_from_slice(input);
            self.forced[..4].copy_from_slice(&[CHANGES_FORMAT, LEVELS as u8, 0, 0]);
            &self.forced
        } else {
            input
        };
        let (change_ref, base, cut) = (&mut self.change_ref, &self.cut_base, &mut self.cut);
        let want = change_ref
            .decode_cut(change_input, Some(base), MAX_TRIANGLES, cut)
            .ok()
            .map(|_| (cut.triangles, cut.hash));
        let scene = &self.view.scene;
        let decoded = self.changing.feed(
            Stage::ChangeMesh,
            &self.grid,
            scene,
            change_input,
            true,
            want,
            run,
        );
        if decoded {
            let heights = self.change_ref.heights();
            self.view
                .build(&self.grid, &self.cut.split, heights, change_input, run);
        }
        let texels = &mut self.texels;
        run(Stage::ColorMap, input, &mut || {
            colormap::decode(COLOR_CELLS, input, texels).is_ok()
        });
    }

    /// A frame: decoded, then its mesh decoded and built into vertices. Random bytes seldom
    /// decode as a frame, so every input brings a frame's mesh all the same: the frame's
    /// own, else (odd `n`) a random key frame with, every other time, one bit flipped (most
    /// decode, so the vertex build sees tens of thousands of meshes), else the input as a
    /// mesh against the base or as a key frame.
    fn frame(&mut self, n: usize, input: &[u8], run: &mut Runner) {
        let mut frame = None;
        run(Stage::Frame, input, &mut || {
            frame = messages::decode::<Frame>(input).ok();
            frame.is_some()
        });
        let (mesh, against_base): (&[u8], bool) = match &frame {
            Some(f) => (&f.mesh, f.base.is_some()),
            None if n % 2 == 1 => {
                self.random_key_frame();
                (&self.key, false)
            }
            None => (input, n.is_multiple_of(4)),
        };
        let base = against_base.then_some(&self.cut_base);
        let (dec, cut) = (&mut self.frame_ref, &mut self.cut);
        let decoded = run(Stage::FrameMesh, mesh, &mut || {
            dec.decode_cut(mesh, base, MAX_TRIANGLES, cut).is_ok()
        });
        let want = decoded.then_some((cut.triangles, cut.hash));
        self.following.feed(
            Stage::FollowMesh,
            &self.grid,
            &self.view.scene,
            mesh,
            against_base,
            want,
            run,
        );
        if !decoded {
            return;
        }
        self.view
            .build(&self.grid, &cut.split, dec.heights(), mesh, run);
    }

    /// A key frame of a random split set into `self.key`, one bit flipped half the time.
    fn random_key_frame(&mut self) {
        let rng = &mut self.rng;
        self.split.reset(self.grid.vertices());
        let splits = below(rng, 64) as u32;
        random_splits(self.grid, &mut self.split, rng, splits);
        self.key = key_frame(self.grid, &self.split, &self.heights);
        if below(rng, 2) == 0 && !self.key.is_empty() {
            let i = below(rng, self.key.len());
            self.key[i] ^= 1 << below(rng, 8);
        }
    }
}

/// The viewer's decoder holding a base as frame 0, its mesh and vertices, and the key
/// frame that gives it the base again once it has let it go.
struct Following {
    follower: Follower,
    live: LiveMesh,
    vertices: TerrainVertices,
    base_key: Vec<u8>,
    /// Frames the follower decoded (numbered from 1).
    followed: u64,
}

impl Following {
    /// A viewer's decoder that has decoded `key` as frame 0.
    fn new(grid: Grid, key: &[u8]) -> Following {
        let (follower, live) = following(grid, key);
        Following {
            follower,
            live,
            vertices: TerrainVertices::default(),
            base_key: key.to_vec(),
            followed: 0,
        }
    }

    /// `mesh` through the viewer's decoder against frame 0 (or as a key frame), as
    /// `stage`: it must decode where the reference did (`want`: its triangles and hash),
    /// and fail where it failed. Whether it decoded.
    #[allow(clippy::too_many_arguments)]
    fn feed(
        &mut self,
        stage: Stage,
        grid: &Grid,
        scene: &Scene,
        mesh: &[u8],
        against_base: bool,
        want: Option<(u32, u64)>,
        run: &mut Runner,
    ) -> bool {
        if !self.follower.has_base(0) {
            (self.follower, self.live) = following(*grid, &self.base_key);
        }
        self.followed += 1;
        let frame = self.followed;
        let (f, live, vertices) = (&mut self.follower, &mut self.live, &mut self.vertices);
        let got = run(stage, mesh, &mut || {
            let got = f
                .decode(frame, mesh, against_base.then_some(0), MAX_TRIANGLES)
                .is_ok();
            if got {
                live.update(grid, f.toggled(), |i| f.contains(i));
                vertices.update(scene, live, |i| f.height(i), |_| 0.0);
                vertices.forget_changes();
            }
            got && live.triangle_count() == f.triangles() as usize
        });
        let got = got.then(|| (self.follower.triangles(), self.follower.hash()));
        // The reference's heights are one array over the grid, which a format-1 frame that
        // fails leaves written: a later frame against the base may then fail there only.
        // A reference holding nothing but the base must agree.
        let want = match (got, want) {
            (Some(_), None) => reference(*grid, &self.base_key, mesh, against_base),
            _ => want,
        };
        assert_eq!(got, want, "the viewer's decoder and the reference disagree");
        got.is_some()
    }
}

/// A viewer's decoder that has decoded `key` as frame 0, keeping every base the server
/// may code against, and its mesh.
fn following(grid: Grid, key: &[u8]) -> (Follower, LiveMesh) {
    let mut f = Follower::new(grid, roam_client::core::BASES);
    f.decode(0, key, None, u32::MAX)
        .expect("the key frame just encoded decodes");
    let mut live = LiveMesh::new(&grid);
    live.update(&grid, f.toggled(), |i| f.contains(i));
    (f, live)
}

/// `mesh` decoded by a fresh reference decoder holding the cut of `key` (against it, or
/// as a key frame): its triangles and hash, if it decodes.
fn reference(grid: Grid, key: &[u8], mesh: &[u8], against_base: bool) -> Option<(u32, u64)> {
    let mut dec = Reference::new(grid);
    let (mut base, mut cut) = (Cut::default(), Cut::default());
    dec.decode_cut(key, None, u32::MAX, &mut base)
        .expect("the key frame just encoded decodes");
    dec.decode_cut(mesh, against_base.then_some(&base), MAX_TRIANGLES, &mut cut)
        .ok()
        .map(|_| (cut.triangles, cut.hash))
}

/// What a viewer makes of a decoded mesh.
struct View {
    mesh: Mesh,
    scene: Scene,
    vertices: TerrainVertices,
}

impl View {
    /// The mesh of `split` emitted and built into vertices, run as [`Stage::Vertices`] on
    /// `bytes` (the mesh's payload).
    fn build(
        &mut self,
        grid: &Grid,
        split: &BitSet,
        heights: &[u16],
        bytes: &[u8],
        run: &mut Runner,
    ) {
        let (mesh, scene, vertices) = (&mut self.mesh, &self.scene, &mut self.vertices);
        run(Stage::Vertices, bytes, &mut || {
            mesh::emit(grid, split, heights, mesh);
            vertices.build(scene, mesh);
            vertices.triangles() == mesh.triangle_count()
        });
    }
}
