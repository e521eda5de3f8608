//! The viewer's frame core ([`ClientCore`]) fed frames by hand, with no network (the
//! clock read once, only to stamp their arrival): a key frame that comes after the frames
//! coded against it is taken first, a base that never comes asks for a key frame, frame
//! numbers no server could send are reported and never wedge the core, the session's
//! [`Gaps`] count reconnections and the time without frames, and geomorphs change only
//! what is drawn.

use std::time::{Duration, Instant};

use roam_client::core::{
    AWAIT_BASE, Broken, ClientCore, Gaps, MAX_FRAME_JUMP, MAX_FRAME_NUMBER, Taken,
};
use roam_protocol::messages::{self, ClientMessage, Frame, Welcome};
use roam_protocol::{BitSet, Grid, MeshEncoder};

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
        color: roam_protocol::ColorLayout::new(8, 256, 8).expect("a valid layout"),
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

/// A driver's core acknowledges in its key datagrams: taking frames queues no control
/// message, and `acked` names the newest taken (an acknowledgement queued before is
/// dropped).
#[test]
fn frames_acknowledged_by_datagram_send_no_control_message() {
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 3);
    let key = frame_bytes(grid, &heights, 0, &cuts[1], None);
    let delta = frame_bytes(grid, &heights, 1, &cuts[2], Some((0, &cuts[1])));
    let mut core = ClientCore::new(&welcome, 1_000).expect("a valid grid");
    let now = Instant::now();
    assert_eq!(core.acked(), None);
    core.offer(&key, now);
    assert!(matches!(core.take(true), Ok(Taken::Frame(_))));
    core.set_acks_in_datagrams();
    assert_eq!(core.acked(), Some(0));
    core.offer(&delta, now);
    assert!(matches!(core.take(true), Ok(Taken::Frame(_))));
    assert_eq!(core.acked(), Some(1));
    assert_eq!(core.poll_control(), None, "no Ack on the control stream");
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
    // Two, and each split diamond's.
    let triangles = |f: usize| {
        let added = |i| grid.added(grid.coords(i).0, grid.coords(i).1) as usize;
        cuts[f].iter().map(added).sum::<usize>() + 2
    };
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

/// `bytes`, a frame message, with its tick and base changed.
fn altered(bytes: &[u8], tick: u64, base: Option<u64>) -> Vec<u8> {
    let mut f: Frame = messages::decode(bytes).expect("a frame");
    f.tick = tick;
    f.base = base;
    let mut out = Vec::new();
    messages::encode(&f, &mut out).expect("within the limits");
    out
}

/// A frame number far ahead of the newest (`u64::MAX`, past [`MAX_FRAME_NUMBER`], or more
/// than [`MAX_FRAME_JUMP`] ahead) is reported once, names the numbers, and is not taken
/// into account: the frames after it are taken as if it had never come (latest wins would
/// otherwise have made every later frame look old).
#[test]
fn a_frame_number_no_server_could_send_is_reported_and_does_not_wedge_the_core() {
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 2);
    let key = |f: u64| frame_bytes(grid, &heights, f, &cuts[1], None);
    let mut core = ClientCore::new(&welcome, 1_000).expect("a valid grid");
    let now = Instant::now();
    let taken = |core: &mut ClientCore| match core.take(true) {
        Ok(Taken::Frame(r)) => Ok(Some(r.frame)),
        Ok(Taken::Nothing) => Ok(None),
        Ok(Taken::Dropped(why)) => panic!("dropped: {why}"),
        Err(e) => Err(e),
    };
    // Before any frame, numbers start at 0: more than the jump ahead of 0 is refused.
    core.offer(&key(MAX_FRAME_JUMP + 1), now);
    assert!(core.has_frame(), "the violation is there to be reported");
    let e = taken(&mut core).expect_err("too far ahead of the start");
    assert_eq!(
        e,
        Broken::FrameAhead {
            frame: MAX_FRAME_JUMP + 1,
            newest: None
        }
    );
    assert!(e.to_string().contains("the start (0)"), "{e}");
    assert!(!core.has_frame(), "reported once");
    core.offer(&key(3), now);
    assert_eq!(taken(&mut core), Ok(Some(3)));
    for poison in [u64::MAX, MAX_FRAME_NUMBER, 3 + MAX_FRAME_JUMP + 1] {
        core.offer(&key(poison), now);
        let e = taken(&mut core).expect_err("a poisoned number");
        assert_eq!(
            e,
            Broken::FrameAhead {
                frame: poison,
                newest: Some(3)
            }
        );
        let text = e.to_string();
        assert!(
            text.contains(&format!("frame {poison}")) && text.contains("the newest frame, 3"),
            "{text}"
        );
    }
    // The next frames are taken: the poison changed nothing. The largest jump allowed
    // is taken too.
    core.offer(&key(4), now);
    assert_eq!(taken(&mut core), Ok(Some(4)));
    core.offer(&key(4 + MAX_FRAME_JUMP), now);
    assert_eq!(taken(&mut core), Ok(Some(4 + MAX_FRAME_JUMP)));
    let acks: Vec<ClientMessage> = std::iter::from_fn(|| core.poll_control()).collect();
    assert_eq!(
        acks,
        [3, 4, 4 + MAX_FRAME_JUMP].map(|frame| ClientMessage::Ack { frame })
    );
}

/// A frame coded against a frame not before it, and a frame showing an older tick than
/// the frame taken before it, are reported and not taken.
#[test]
fn a_base_ahead_of_its_frame_or_a_tick_going_back_is_reported() {
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 3);
    let mut core = ClientCore::new(&welcome, 1_000).expect("a valid grid");
    let now = Instant::now();
    let key = frame_bytes(grid, &heights, 5, &cuts[1], None);
    core.offer(&altered(&key, 50, None), now);
    assert!(matches!(core.take(true), Ok(Taken::Frame(r)) if r.frame == 5 && r.tick == 50));
    for base in [6, 7] {
        let delta = frame_bytes(grid, &heights, 6, &cuts[2], Some((5, &cuts[1])));
        core.offer(&altered(&delta, 60, Some(base)), now);
        let e = core.take(true).expect_err("a base not before its frame");
        assert_eq!(e, Broken::BaseAhead { frame: 6, base });
        assert!(e.to_string().contains("not before it"), "{e}");
    }
    let delta = frame_bytes(grid, &heights, 6, &cuts[2], Some((5, &cuts[1])));
    core.offer(&altered(&delta, 49, Some(5)), now);
    let e = core.take(true).expect_err("a tick going back");
    assert_eq!(
        e,
        Broken::TickBackwards {
            frame: 6,
            tick: 49,
            newest: 5,
            newest_tick: 50
        }
    );
    // The same tick again is fine (the world did not tick between two frames).
    let next = frame_bytes(grid, &heights, 7, &cuts[2], Some((5, &cuts[1])));
    core.offer(&altered(&next, 50, Some(5)), now);
    assert!(matches!(core.take(true), Ok(Taken::Frame(r)) if r.frame == 7 && r.tick == 50));
}

/// The gaps of a session: the longest time between two frames taken (a reconnection's
/// included), the gap going on while reconnecting, and the reconnections counted with
/// those that got the vehicle back.
#[test]
fn gaps_count_reconnections_and_the_time_without_frames() {
    let t0 = Instant::now();
    let ms = |n: u64| t0 + Duration::from_millis(n);
    let mut g = Gaps::default();
    assert_eq!(g.current(ms(5)), None);
    g.frame(ms(0));
    g.frame(ms(16));
    g.frame(ms(40));
    assert_eq!(g.longest(ms(41)), Duration::from_millis(24));
    // Lost at 1.04 s (the silence noticed): the gap runs from the last frame.
    g.lost(ms(1_040));
    assert_eq!(g.current(ms(2_040)), Some(Duration::from_millis(2_000)));
    assert_eq!(g.longest(ms(2_040)), Duration::from_millis(2_000));
    g.reconnected(true);
    assert_eq!(g.current(ms(2_100)), None, "connected again");
    g.frame(ms(2_140));
    assert_eq!(g.longest(ms(9_000)), Duration::from_millis(2_100));
    g.lost(ms(3_000));
    g.reconnected(false);
    assert_eq!((g.reconnects, g.resumed), (2, 1));
}

/// Geomorphs are drawing only: a core drawing through a [`roam_client::render::Morph`]
/// decodes, acknowledges and holds exactly the mesh a core without does, frame by frame,
/// while the cut grows and shrinks; the drawn cut holds the decoded one meanwhile, and
/// once the frames' ticks have run past the morphs' length it is the decoded one, with
/// every vertex at its height (the vertices the same triangles, corner for corner).
#[test]
fn geomorphs_change_the_drawing_and_nothing_decoded() {
    use roam_client::render::{MORPH_TICKS, Scene, TerrainVertices};
    let (grid, heights, welcome) = small_grid();
    let cuts = growing_cuts(grid, 9);
    // Up and back down, a frame each: splits, then merges.
    let order: Vec<usize> = (0..9).chain((0..8).rev()).collect();
    let scene = Scene::of(&welcome);
    let (mut plain, mut drawn) = (
        ClientCore::new(&welcome, 1_000).expect("a valid grid"),
        ClientCore::new(&welcome, 1_000).expect("a valid grid"),
    );
    drawn.set_morph(MORPH_TICKS);
    let (mut vp, mut vd) = (TerrainVertices::default(), TerrainVertices::default());
    let now = Instant::now();
    let sorted = |v: &TerrainVertices| {
        let mut t: Vec<Vec<u32>> = v
            .corners
            .chunks_exact(3)
            .filter(|t| t.iter().any(|c| *c != Default::default()))
            .map(|t| {
                let mut k: Vec<u32> = t
                    .iter()
                    .flat_map(|c| c.pos.iter().map(|p| p.to_bits()))
                    .collect();
                k.sort_unstable();
                k
            })
            .collect();
        t.sort_unstable();
        t
    };
    let mut last = 0;
    for (f, &k) in order.iter().enumerate() {
        let f = f as u64;
        let base = f.checked_sub(1).map(|b| (b, &cuts[order[b as usize]]));
        let bytes = frame_bytes(grid, &heights, f, &cuts[k], base);
        for core in [&mut plain, &mut drawn] {
            core.offer(&bytes, now);
            assert!(matches!(core.take(true), Ok(Taken::Frame(_))), "frame {f}");
        }
        assert_eq!(plain.mesh(), drawn.mesh(), "frame {f}: the decoded mesh");
        assert_eq!(plain.poll_control(), drawn.poll_control(), "frame {f}");
        plain.update_vertices(&scene, &mut vp);
        drawn.update_vertices(&scene, &mut vd);
        let m = drawn.morph().expect("drawn through a morph");
        for i in cuts[k].iter() {
            assert!(m.contains(i), "frame {f}: decoded diamond {i} drawn");
        }
        last = f;
    }
    let morphing = drawn.morph().map_or(0, |m| m.morphing());
    assert!(morphing > 0, "the last frames' merges are still morphing");
    // The same cut again, a morph's length of ticks later.
    let k = *order.last().expect("frames");
    let later = frame_bytes(grid, &heights, last + 1, &cuts[k], Some((last, &cuts[k])));
    let mut f: Frame = messages::decode(&later).expect("a frame");
    f.tick = last + 1 + u64::from(MORPH_TICKS);
    let mut later = Vec::new();
    messages::encode(&f, &mut later).expect("within the limits");
    for (core, v) in [(&mut plain, &mut vp), (&mut drawn, &mut vd)] {
        core.offer(&later, now);
        assert!(matches!(core.take(true), Ok(Taken::Frame(_))));
        core.update_vertices(&scene, v);
    }
    let m = drawn.morph().expect("drawn through a morph");
    assert_eq!(m.morphing(), 0);
    assert_eq!(m.len(), cuts[k].len(), "the drawn cut is the decoded one");
    assert_eq!(sorted(&vp), sorted(&vd), "every vertex at its height");
}
