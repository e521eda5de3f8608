//! The viewer's frame core ([`ClientCore`]) fed frames by hand, with no network (the
//! clock read once, only to stamp their arrival): a key frame that comes after the frames
//! coded against it is taken first, and a base that never comes asks for a key frame.

use std::time::Instant;

use roam_client::core::{AWAIT_BASE, ClientCore, Taken};
use roam_protocol::messages::{self, ClientMessage, Frame, Welcome};
use roam_protocol::{BitSet, Cut, Grid, MeshEncoder};

/// A 9² grid's heights, and a welcome for it.
fn small_grid() -> (Grid, Vec<u16>, Welcome) {
    let grid = Grid::new(3).expect("a valid size");
    let heights = (0..grid.vertices() as u32)
        .map(|i| (i * 37 % 101) as u16)
        .collect();
    let welcome = Welcome {
        version: messages::VERSION,
        levels: 3,
        h_scale: 1.0,
        v_scale: 1.0,
        sun_dir: [0.0, 1.0, 0.0],
        sun_color: [255; 3],
        fog_density: 0.0,
        fog_color: [0; 3],
        water_level: None,
        vehicle: 0,
        color_cells: 8,
        color_bytes: 0,
        tick: 0,
        ticket: None,
        resumed: false,
        max_budget: messages::MAX_BUDGET,
        max_fps: 240,
    };
    (grid, heights, welcome)
}

/// A frame message's bytes: frame `frame` with the cut `split`, coded against `base` (its
/// number and split set) or as a key frame.
fn frame_bytes(
    grid: Grid,
    heights: &[u16],
    frame: u64,
    split: &BitSet,
    base: Option<(u64, &BitSet)>,
) -> Vec<u8> {
    let mut mesh = Vec::new();
    MeshEncoder::new(grid)
        .encode(split, heights, base.map(|(_, b)| b), &mut mesh)
        .expect("a closed cut");
    let mut out = Vec::new();
    let frame = Frame {
        frame,
        base: base.map(|(f, _)| f),
        tick: frame,
        vehicles: Vec::new(),
        input_seq: None,
        mesh,
    };
    messages::encode(&frame, &mut out).expect("within the limits");
    out
}

/// Cuts growing frame by frame from the root: `cuts[k]` has the first `k` diamonds split.
fn growing_cuts(grid: Grid, n: usize) -> Vec<BitSet> {
    let order = [
        (4, 4),
        (2, 2),
        (6, 6),
        (2, 6),
        (6, 2),
        (1, 1),
        (3, 3),
        (5, 5),
    ];
    (0..n)
        .map(|k| {
            let mut set = BitSet::new(grid.vertices());
            for &(x, z) in &order[..k.min(order.len())] {
                grid.split_closed(&mut set, x, z);
            }
            set
        })
        .collect()
}

/// The server codes the frames after a key frame against it before the viewer has it, and
/// the key frame (larger, on a stream) may come after them: the viewer passes over a frame
/// whose base has not come (no error, no key-frame request), keeps the key frame apart when
/// a newer frame is offered before it is taken, takes it first, then the newer frame.
#[test]
fn a_key_frame_that_comes_after_the_frames_coded_against_it_is_taken_first() {
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 4);
    let key = frame_bytes(grid, &heights, 0, &cuts[1], None);
    let delta = |f: usize| frame_bytes(grid, &heights, f as u64, &cuts[f], Some((0, &cuts[1])));
    let mut core = ClientCore::new(&welcome, 1_000).expect("a valid grid");
    let now = Instant::now();
    let taken = |core: &mut ClientCore| match core.take(true).expect("consistent") {
        Taken::Frame(r) => Some((r.frame, r.triangles)),
        Taken::Nothing => None,
        Taken::Dropped(why) => panic!("dropped: {why}"),
    };
    core.offer(&delta(2), now);
    assert_eq!(taken(&mut core), None, "frame 2 waits for its base");
    assert_eq!(core.poll_control(), None, "no key frame asked for");
    core.offer(&delta(3), now);
    core.offer(&key, now);
    let triangles = |f: usize| Cut::of(&grid, cuts[f].clone(), &heights).triangles as usize;
    assert_eq!(
        taken(&mut core),
        Some((0, triangles(1))),
        "the key frame first"
    );
    assert_eq!(
        taken(&mut core),
        Some((3, triangles(3))),
        "then the newer frame"
    );
    assert!(!core.has_frame());
    assert_eq!(core.poll_control(), Some(ClientMessage::Ack { frame: 0 }));
    assert_eq!(core.poll_control(), Some(ClientMessage::Ack { frame: 3 }));
    assert_eq!(core.poll_control(), None);
    // The frame passed over, come again late: older than the newest taken.
    core.offer(&delta(2), now);
    assert_eq!(taken(&mut core), None);
}

/// A frame coded against a base newer than the newest taken waits for it up to
/// [`AWAIT_BASE`] frames in a row; then the viewer asks for a key frame. A frame coded
/// against an older base it does not have asks at once.
#[test]
fn a_base_that_never_comes_asks_for_a_key_frame() {
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 3);
    let mut core = ClientCore::new(&welcome, 1_000).expect("a valid grid");
    let now = Instant::now();
    let limit = u64::from(AWAIT_BASE);
    for f in 1..=limit + 1 {
        core.offer(
            &frame_bytes(grid, &heights, f, &cuts[2], Some((0, &cuts[1]))),
            now,
        );
        let t = core.take(true).expect("consistent");
        if f <= limit {
            assert!(matches!(t, Taken::Nothing), "frame {f}: {t:?}");
            assert_eq!(core.poll_control(), None, "frame {f}");
        } else {
            assert!(matches!(t, Taken::Dropped(_)), "frame {f}: {t:?}");
            assert_eq!(core.poll_control(), Some(ClientMessage::KeyFrame));
        }
    }
    // A key frame, then a frame against a base before it that this viewer never had.
    let k = limit + 2;
    core.offer(&frame_bytes(grid, &heights, k, &cuts[1], None), now);
    assert!(matches!(core.take(true), Ok(Taken::Frame(_))));
    assert_eq!(core.poll_control(), Some(ClientMessage::Ack { frame: k }));
    core.offer(
        &frame_bytes(grid, &heights, k + 1, &cuts[2], Some((1, &cuts[1]))),
        now,
    );
    let t = core.take(true).expect("consistent");
    assert!(matches!(t, Taken::Dropped(_)), "{t:?}");
    assert_eq!(core.poll_control(), Some(ClientMessage::KeyFrame));
}
