//! Fuzzing in `cargo test`: 100,000 inputs at every decoder (random bytes, and valid
//! encodings with bytes flipped, cut or extended: [`roam_tests::fuzz`], as the
//! million-input bench `cargo bench -p roam-tests --bench fuzz` has them), a decoded
//! frame's mesh on through the mesh decoder and the viewer's vertex builder; and the
//! hostile lengths each limit is for. Nothing may panic, and a counting global allocator
//! proves that no decode allocates beyond its limits.
//!
//! The allocator counts, per thread, the bytes live and their peak (a `realloc` counts its
//! old and new blocks both, as if it moved), so the tests of this file may run side by
//! side: each measures only what its own thread allocates, between [`peak_of`]'s start and
//! end. The bounds ([`bound`]) are formulas of the limits and the length `L` of the bytes
//! a stage reads; see each arm.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::collections::BTreeMap;

use roam_link::wire::{self, READ_CHUNK, WireError};
use roam_protocol::messages::{
    self, ClientMessage, DecodeError, Frame, KEY_HISTORY, KeyDatagram, KeyState, MAX_MESSAGE,
    MAX_REASON, MAX_TILE_BYTES, MAX_TOKEN, MAX_VEHICLES, PREALLOC, ServerMessage,
};
use roam_tests::fuzz::{COLOR_CELLS, Fuzz, HELLO_LIMIT, MAX_TRIANGLES, Stage};

struct Counting;

thread_local! {
    // Const-initialised and without destructors, so touching them from inside the
    // allocator never allocates.
    /// Counting is on for this thread.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    /// Bytes allocated less bytes freed on this thread since counting began.
    static LIVE: Cell<isize> = const { Cell::new(0) };
    /// The most `LIVE` has been since counting began.
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

/// Adds `grow` to the live bytes (the peak counts `transient` more), when counting.
fn count(grow: isize, transient: isize) {
    if !COUNTING.try_with(Cell::get).unwrap_or(false) {
        return;
    }
    let _ = LIVE.try_with(|live| {
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(live.get() + transient)));
        live.set(live.get() + grow);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(live.get())));
    });
}

// SAFETY: every call is forwarded unchanged to `System`; the counters have no effect on
// the memory handed out.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count(layout.size() as isize, 0);
        // SAFETY: the caller upholds `GlobalAlloc::alloc`'s contract, passed on as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count(layout.size() as isize, 0);
        // SAFETY: as for `alloc`.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // Both blocks at once, while the contents move.
        count(
            new_size as isize - layout.size() as isize,
            new_size as isize,
        );
        // SAFETY: as for `alloc`; `ptr` came from this allocator, hence from `System`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        count(-(layout.size() as isize), 0);
        // SAFETY: as for `realloc`.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// What `f` returns, and the most bytes it had allocated at once on this thread (beyond
/// what was allocated before it began).
fn peak_of<R>(f: impl FnOnce() -> R) -> (R, usize) {
    LIVE.with(|c| c.set(0));
    PEAK.with(|c| c.set(0));
    COUNTING.with(|c| c.set(true));
    let r = f();
    COUNTING.with(|c| c.set(false));
    (r, PEAK.with(Cell::get) as usize)
}

/// A serde error message (a variant index or a length out of range, a refusal's text).
const ERROR: usize = 256;
/// Bytes of the fuzzed grid's vertices: the mesh decoders' lists hold at most one `u32`
/// or `u64` (or a `(u32, u16)`) per vertex each, and a `Vec` may be twice its length.
const PER_VERTEX: usize = 64;

/// The most bytes stage `stage` may allocate reading `bytes`.
fn bound(stage: Stage, bytes: &[u8], vertices: usize) -> usize {
    let len = bytes.len();
    // A list reserves at most PREALLOC bytes before its items arrive, then grows with
    // them: at most 3 × what the input holds while it doubles (old and new block).
    let list = PREALLOC + 3 * len;
    // A frame: its vehicles (48 bytes each in memory, at least 41 encoded) and its mesh,
    // copied from the input.
    let frame = PREALLOC + 3 * len * 48 / 41 + len + ERROR;
    // A viewer's message: a reason or a colour tile.
    let server = list.min(PREALLOC.max(3 * MAX_TILE_BYTES)) + ERROR;
    match stage {
        // A hello (variant 0): its token. Others: a reason.
        Stage::ClientMessage if bytes.first() == Some(&0) => MAX_TOKEN + ERROR,
        Stage::ClientMessage => MAX_REASON + ERROR,
        Stage::ServerMessage => server,
        // Eight states of six bytes.
        Stage::KeyDatagram => KEY_HISTORY * size_of::<KeyState>() + ERROR,
        Stage::Frame => frame,
        // The message's bytes (at most the limit), then its decode.
        Stage::WireClient => HELLO_LIMIT + MAX_REASON + ERROR,
        // The message's bytes: at most READ_CHUNK before they arrive.
        Stage::WireServer => READ_CHUNK + 3 * len + server,
        Stage::FrameMesh | Stage::KeyMesh | Stage::DeltaMesh => PER_VERTEX * vertices,
        // The viewer's decoder's maps and lists (as the others'), its log of the frame, the
        // live mesh's slots (64 bytes a diamond) and their vertices (240 bytes a slot).
        Stage::FollowMesh | Stage::ChangeMesh => (PER_VERTEX + 2 * 64 + 2 * 240) * vertices,
        // The mesh (4 + 2 bytes a vertex, 12 a triangle) and its vertices (12 + 12 + 20 a
        // vertex, 60 a triangle), each at most doubled; the triangles at most the limit
        // the decoder was given, and at most two per grid vertex.
        Stage::Vertices => {
            let triangles = (MAX_TRIANGLES as usize).min(2 * vertices);
            2 * (72 * triangles + 50 * vertices) + PER_VERTEX * vertices
        }
        // The texels, two rows of 64-byte cells, and the rANS tables: 2 KiB of slots for
        // each context used (each takes three bytes of input at least) and one shared,
        // at most tripled while growing, and 128 bytes of frequencies a context.
        Stage::ColorMap => {
            let cells = COLOR_CELLS as usize;
            let used = (len / 3).min(192);
            3 * cells * cells + 2 * 64 * (cells + 2) + 3 * 2048 * (used + 1) + 192 * 140
        }
    }
}

/// What one stage did over all the inputs.
#[derive(Default)]
struct Tally {
    inputs: usize,
    values: usize,
    /// The peak closest to its bound, and that bound.
    worst: usize,
    worst_bound: usize,
}

#[test]
fn every_decoder_takes_fuzzed_inputs_within_its_limits() {
    const INPUTS: usize = 100_000;
    let mut fuzz = Fuzz::new(2);
    let vertices = fuzz.grid.vertices();
    let mut tally: BTreeMap<Stage, Tally> = BTreeMap::new();
    let mut failures = Vec::new();
    let mut input = Vec::new();
    for n in 0..INPUTS {
        fuzz.input(n, &mut input);
        fuzz.feed(n, &input, &mut |stage, bytes, step| {
            let (outcome, peak) =
                peak_of(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(step)));
            let limit = bound(stage, bytes, vertices);
            let t = tally.entry(stage).or_default();
            t.inputs += 1;
            if peak * t.worst_bound.max(1) >= t.worst * limit {
                (t.worst, t.worst_bound) = (peak, limit);
            }
            let value = matches!(outcome, Ok(true));
            t.values += usize::from(value);
            if outcome.is_err() || peak > limit {
                failures.push(format!(
                    "{stage:?} on input {n} ({} bytes): {}, {peak} bytes allocated (bound \
                     {limit}); bytes {bytes:02x?}",
                    bytes.len(),
                    if outcome.is_err() { "panicked" } else { "ok" },
                ));
            }
            value
        });
    }
    for (stage, t) in &tally {
        eprintln!(
            "{stage:?}: {} inputs, {} values, at most {} bytes allocated (bound {} there)",
            t.inputs, t.values, t.worst, t.worst_bound
        );
    }
    assert!(
        failures.is_empty(),
        "{} failures, first: {}",
        failures.len(),
        failures[0]
    );
    for (stage, t) in &tally {
        if *stage != Stage::Vertices {
            assert_eq!(t.inputs, INPUTS, "{stage:?}");
        }
    }
    // Only a mesh that decodes is built into vertices: decode → mesh → vertex build, at
    // least 20,000 times (most of the random key frames, flipped bit or not).
    let built = &tally[&Stage::Vertices];
    assert!(built.inputs >= 20_000, "{} meshes built", built.inputs);
    assert_eq!(tally.len(), 13, "every stage ran");
}

/// The varint bincode writes for a length: one byte below 251, else a marker and the
/// little-endian `u32`.
fn claim(len: u32) -> Vec<u8> {
    let mut v = vec![252];
    v.extend_from_slice(&len.to_le_bytes());
    v
}

/// `decode::<T>` of `bytes` refuses `what` with `got` against `limit`, allocating less than
/// `most` bytes.
fn refused<T: serde::de::DeserializeOwned + messages::Checked + std::fmt::Debug>(
    bytes: &[u8],
    what: &str,
    got: usize,
    limit: usize,
    most: usize,
) {
    let (r, peak) = peak_of(|| messages::decode::<T>(bytes));
    match r {
        Err(DecodeError::TooLong {
            what: w,
            got: g,
            limit: l,
        }) => assert_eq!((w, g, l), (what, got, limit)),
        other => panic!("{what}: {other:?}"),
    }
    assert!(peak < most, "{what}: {peak} bytes allocated");
}

#[test]
fn hostile_lengths_are_refused_before_allocating() {
    // A hello claiming a 16 MiB token: variant, version, role, then the token's length.
    let mut hello = vec![0, messages::VERSION as u8, 0];
    hello.extend(claim(16 << 20));
    hello.extend_from_slice(b"abc");
    refused::<ClientMessage>(&hello, "join token bytes", 16 << 20, MAX_TOKEN, 1024);
    // A key datagram claiming 2^20 states.
    refused::<KeyDatagram>(&claim(1 << 20), "key states", 1 << 20, KEY_HISTORY, 1024);
    // A colour tile claiming 16 MiB: variant 2, level 0, x 0, z 0, then its length.
    let mut tile = vec![2, 0, 0, 0];
    tile.extend(claim(16 << 20));
    refused::<ServerMessage>(&tile, "colour tile bytes", 16 << 20, MAX_TILE_BYTES, 1024);
    // A reason (variant 4, Bye; reason variant 4, Protocol) claiming a megabyte.
    let mut bye = vec![4, 4];
    bye.extend(claim(1 << 20));
    refused::<ServerMessage>(&bye, "reason bytes", 1 << 20, MAX_REASON, 1024);
    // A frame claiming 2^24 vehicles: frame 3, no base, tick 77, then the count.
    let mut frame = vec![3, 0, 77];
    frame.extend(claim(16 << 20));
    refused::<Frame>(&frame, "vehicles", 16 << 20, MAX_VEHICLES, 1024);
    // Within the limit, but far more than the bytes hold: at most PREALLOC reserved.
    let mut frame = vec![3, 0, 77];
    frame.extend(claim(MAX_VEHICLES as u32));
    frame.extend_from_slice(&[0; 50]);
    let (r, peak) = peak_of(|| messages::decode::<Frame>(&frame));
    assert!(r.is_err());
    assert!(peak <= PREALLOC + ERROR, "{peak} bytes for a short frame");
    // A frame claiming a 16 MiB mesh it does not hold: nothing copied.
    let mut frame = vec![3, 0, 77, 0, 0];
    frame.extend(claim(16 << 20));
    let (r, peak) = peak_of(|| messages::decode::<Frame>(&frame));
    assert!(matches!(r, Err(DecodeError::Bincode(_))), "{r:?}");
    assert!(peak < 1024, "{peak} bytes for a frame claiming its mesh");
}

/// `wire::read` of `bytes` with `limit`.
fn read<T: serde::de::DeserializeOwned + messages::Checked>(
    bytes: &[u8],
    limit: usize,
) -> (Result<T, WireError>, usize) {
    let mut source = bytes;
    peak_of(|| {
        let read = std::pin::pin!(wire::read::<T>(&mut source, limit));
        match std::future::Future::poll(
            read,
            &mut std::task::Context::from_waker(std::task::Waker::noop()),
        ) {
            std::task::Poll::Ready(r) => r,
            std::task::Poll::Pending => panic!("bytes in memory are read at once"),
        }
    })
}

#[test]
fn the_control_stream_refuses_long_claims_before_allocating() {
    // A length prefix claiming 4 GiB.
    let (r, peak) = read::<ServerMessage>(&[0xff; 12], MAX_MESSAGE);
    assert!(
        matches!(
            r,
            Err(WireError::TooLong {
                len: 0xffff_ffff,
                limit: MAX_MESSAGE
            })
        ),
        "{r:?}"
    );
    assert_eq!(peak, 0);
    // Past the server's limit for a viewer's messages.
    let (r, _) = read::<ClientMessage>(&[0x01, 0x10, 0, 0, 0], HELLO_LIMIT);
    assert!(
        matches!(r, Err(WireError::TooLong { len: 4097, .. })),
        "{r:?}"
    );
    // 16 MiB claimed, within the viewer's limit, ten bytes sent: one chunk reserved.
    let mut short = (16u32 << 20).to_le_bytes().to_vec();
    short.extend_from_slice(&[0; 10]);
    let (r, peak) = read::<ServerMessage>(&short, MAX_MESSAGE);
    assert!(matches!(r, Err(WireError::Read(_))), "{r:?}");
    assert!(peak <= READ_CHUNK, "{peak} bytes");
    // A colour tile of the largest payload reads back whole.
    let tile = ServerMessage::ColorTile {
        level: 0,
        x: 7,
        z: 9,
        data: vec![5; MAX_TILE_BYTES],
    };
    let mut framed = vec![0; 4];
    messages::encode(&tile, &mut framed).expect("a tile encodes");
    let len = (framed.len() - 4) as u32;
    framed[..4].copy_from_slice(&len.to_le_bytes());
    let (r, peak) = read::<ServerMessage>(&framed, MAX_MESSAGE);
    assert_eq!(r.expect("a whole tile reads"), tile);
    assert!(peak <= 4 * framed.len(), "{peak} bytes for a tile");
}

#[test]
fn every_stage_takes_its_valid_inputs() {
    // The inputs the fuzzing mutates, whole: each stage decodes some (the wire stages those
    // behind their true length), and every mesh that decodes builds its vertices.
    let mut fuzz = Fuzz::new(3);
    let mut values: BTreeMap<Stage, usize> = BTreeMap::new();
    for seed in roam_tests::fuzz::seeds(fuzz.grid) {
        fuzz.feed(1, &seed, &mut |stage, _, step| {
            let value = step();
            *values.entry(stage).or_default() += usize::from(value);
            value
        });
    }
    let meshes = values[&Stage::FrameMesh] + values[&Stage::KeyMesh] + values[&Stage::ChangeMesh];
    assert_eq!(values[&Stage::Vertices], meshes);
    // Three seeds are frames (two carry a mesh: a key frame, a change frame); the other
    // seeds bring random key frames to the frame's mesh stage (odd `n`), most of which decode.
    assert_eq!(values[&Stage::Frame], 3);
    assert!(values[&Stage::FrameMesh] >= 2);
    let none: Vec<_> = values.iter().filter(|&(_, &v)| v == 0).collect();
    assert!(
        none.is_empty(),
        "stages no valid input decoded in: {none:?}"
    );
}
