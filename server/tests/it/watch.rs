//! Watching a recording (`sim::watch`): every tick watched is the recorded world, a seek
//! lands on it exactly, pause and speed move the clock as said, joins and leaves can be
//! sought, and a damaged, cut or diverging file plays its valid part and says where it
//! stops.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use roam_server::Terrain;
use roam_server::sim::physics::Keys;
use roam_server::sim::recorder::RecordedWorld;
use roam_server::sim::recording;
use roam_server::sim::replay::{self, ReplayError};
use roam_server::sim::watch::{self, Control, OpenError, Stop, Watch};
use roam_server::sim::world::{self, Inputs, Vehicle, World};
use roam_server::terrain::dataset;

fn load(name: &str) -> Arc<Terrain> {
    let root: PathBuf = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the crate lives in the workspace")
        .to_path_buf();
    Arc::new(dataset::load(&root.join("data").join(name), &mut |_, _| {}).expect("bundled"))
}

/// A session of four drivers joining and leaving, recorded (a checkpoint every 50 ticks),
/// and the world at every tick as the live world's snapshot shows it: after that many
/// steps, before that tick's joins and leaves.
struct Session {
    bytes: Vec<u8>,
    worlds: Vec<Vec<Vehicle>>,
    joins_and_leaves: Vec<u64>,
}

const TICKS: u64 = 1700;

fn session(terrain: &Arc<Terrain>) -> Session {
    let mut world = World::new(terrain.clone());
    world
        .add(0, world::start_state(terrain, 0))
        .expect("on the map");
    let mut rec = RecordedWorld::start(world, Vec::new(), terrain.content_hash(), 50)
        .expect("memory does not fail");
    let mut worlds = Vec::new();
    let mut marks = Vec::new();
    let pattern = [Keys::UP, Keys::UP.union(Keys::LEFT), Keys::NONE, Keys::DOWN];
    let mut inputs = Inputs::new();
    for tick in 0..TICKS {
        worlds.push(rec.world().vehicles().to_vec());
        let event = match tick {
            40 => Some(rec.join(1, world::start_state(terrain, 1))),
            333 => Some(rec.join(2, world::start_state(terrain, 2))),
            700 => Some(rec.leave(1)),
            1001 => Some(rec.join(3, world::start_state(terrain, 3))),
            1500 => Some(rec.leave(0)),
            _ => None,
        };
        if let Some(e) = event {
            e.expect("the session's joins and leaves are valid");
            marks.push(tick);
        }
        for v in rec.world().vehicles() {
            let k = (tick / 70 + u64::from(v.id)) as usize % pattern.len();
            inputs.set(v.id, pattern[k]);
        }
        rec.step(&inputs).expect("memory does not fail");
    }
    worlds.push(rec.world().vehicles().to_vec());
    let (_, bytes) = rec.finish().expect("memory does not fail");
    Session {
        bytes,
        worlds,
        joins_and_leaves: marks,
    }
}

fn open(bytes: &[u8], terrain: &Arc<Terrain>) -> Watch<Arc<Terrain>> {
    watch::open_bytes(bytes, terrain.clone(), &terrain.content_hash()).expect("watchable")
}

/// What `roam-server replay` ends on for `bytes` (its valid prefix when damaged).
fn replayed(bytes: &[u8], terrain: &Arc<Terrain>) -> replay::Outcome {
    let (rec, _) = recording::parse_valid(bytes).expect("a header");
    replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays")
}

#[test]
fn every_tick_watched_is_the_recorded_world_and_the_end_is_replays() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    let mut w = open(&s.bytes, &terrain);
    assert_eq!(*w.stop(), Stop::Closed);
    let st = w.status();
    assert_eq!(
        (st.tick, st.start, st.end, st.speed, st.paused),
        (0, 0, TICKS, 4, false)
    );
    for tick in 0..TICKS {
        assert_eq!(w.status().tick, tick);
        assert_eq!(
            w.world().vehicles(),
            &s.worlds[tick as usize][..],
            "tick {tick}"
        );
        assert_eq!(
            w.snapshot().vehicles,
            s.worlds[tick as usize],
            "tick {tick}"
        );
        assert_eq!(w.take_ended(), None);
        w.advance();
    }
    let outcome = replayed(&s.bytes, &terrain);
    assert!(w.at_end());
    assert_eq!(w.world().vehicles(), &outcome.vehicles[..]);
    assert_eq!(w.take_ended(), Some((TICKS, outcome.digest)));
    assert_eq!(w.take_ended(), None, "said once");
    // The last state is held.
    for _ in 0..10 {
        w.advance();
    }
    assert_eq!(w.status().tick, TICKS);
    assert_eq!(w.world().digest(), outcome.digest);
}

#[test]
fn a_seek_lands_on_the_recorded_world_from_anywhere() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    let mut w = open(&s.bytes, &terrain);
    // Back and forth, across and within the copies' spacing, the ends included.
    let ticks = [
        900, 899, 901, 0, 1699, 499, 500, 501, 1000, 40, 41, 333, 1, 1250, 1249, 1700, 3, 777,
    ];
    for tick in ticks {
        w.seek(tick);
        assert_eq!(w.status().tick, tick);
        if tick < TICKS {
            assert_eq!(
                w.world().vehicles(),
                &s.worlds[tick as usize][..],
                "seek to {tick}"
            );
        } else {
            assert_eq!(w.world().digest(), replayed(&s.bytes, &terrain).digest);
        }
        // And plays on from there as recorded.
        if tick + 3 < TICKS {
            for _ in 0..3 {
                w.advance();
            }
            assert_eq!(w.world().vehicles(), &s.worlds[tick as usize + 3][..]);
        }
    }
    // Past the end: the end.
    w.control(Control::Seek(u64::MAX));
    assert_eq!(w.status().tick, TICKS);
}

#[test]
fn pause_stops_the_clock_and_a_speed_moves_it_by_its_ticks() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    let mut w = open(&s.bytes, &terrain);
    w.seek(100);
    w.control(Control::Pause);
    for _ in 0..20 {
        w.advance();
    }
    assert_eq!(w.status().tick, 100, "paused");
    assert!(w.status().paused);
    w.control(Control::Resume);
    let check = |w: &mut Watch<Arc<Terrain>>, quarters: u8, calls: u64, ticks: u64| {
        w.control(Control::Speed(quarters));
        let from = w.status().tick;
        for k in 1..=calls {
            w.advance();
            let want = from + ticks * k / calls;
            assert_eq!(w.status().tick, want, "{quarters}/4 × after {k} calls");
            assert_eq!(w.world().vehicles(), &s.worlds[want as usize][..]);
        }
    };
    check(&mut w, 8, 10, 20); // 2×: two ticks a tick
    check(&mut w, 32, 10, 80); // 8×
    check(&mut w, 4, 10, 10); // 1×
    // ¼×: a tick every fourth call.
    w.control(Control::Speed(1));
    let from = w.status().tick;
    let ticks: Vec<u64> = (0..8)
        .map(|_| {
            w.advance();
            w.status().tick - from
        })
        .collect();
    assert_eq!(ticks, [0, 0, 0, 1, 1, 1, 1, 2]);
    // Out of range: clamped.
    w.control(Control::Speed(200));
    assert_eq!(w.status().speed, watch::MAX_SPEED);
    w.control(Control::Speed(0));
    assert_eq!(w.status().speed, watch::MIN_SPEED);
    // At 8× near the end: it stops there.
    w.control(Control::Speed(32));
    w.seek(TICKS - 3);
    w.advance();
    assert_eq!(w.status().tick, TICKS);
    assert!(w.take_ended().is_some());
}

#[test]
fn joins_and_leaves_are_sought_forward_and_back() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    let mut w = open(&s.bytes, &terrain);
    let marks: Vec<u64> = w.marks().iter().map(|m| m.tick).collect();
    assert_eq!(marks, s.joins_and_leaves);
    for &m in &s.joins_and_leaves {
        w.control(Control::SeekMark { forward: true });
        assert_eq!(w.status().tick, m);
        assert_eq!(w.world().vehicles(), &s.worlds[m as usize][..]);
    }
    w.control(Control::SeekMark { forward: true });
    assert_eq!(w.status().tick, 1500, "none after the last: it stays");
    w.seek(1200);
    w.control(Control::SeekMark { forward: false });
    assert_eq!(w.status().tick, 1001);
    w.control(Control::SeekMark { forward: false });
    assert_eq!(w.status().tick, 700);
}

#[test]
fn a_cut_file_plays_its_whole_records_to_replays_end() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    // Cuts inside the header are the parse's error; every other cut plays.
    let header_end = 12 + 5 + 52 + 34 + 8;
    for cut in (header_end..s.bytes.len()).step_by(97) {
        let bytes = &s.bytes[..cut];
        let mut w = open(bytes, &terrain);
        let outcome = replayed(bytes, &terrain);
        assert!(matches!(w.stop(), Stop::Open { .. }), "cut at {cut}");
        let end = w.status().end;
        assert_eq!(end, outcome.tick, "cut at {cut}");
        w.seek(end);
        assert_eq!(w.world().digest(), outcome.digest, "cut at {cut}");
        assert_eq!(w.take_ended(), Some((outcome.tick, outcome.digest)));
        if end > 0 {
            w.seek(end - 1);
            assert_eq!(w.world().vehicles(), &s.worlds[end as usize - 1][..]);
        }
    }
    assert!(matches!(
        watch::open_bytes(&s.bytes[..40], terrain.clone(), &terrain.content_hash()),
        Err(OpenError::Format(recording::FormatError::TruncatedHeader {
            len: 40
        }))
    ));
}

/// The byte offsets of the records after the header.
fn record_starts(bytes: &[u8]) -> Vec<usize> {
    let mut at = 12;
    let mut starts = Vec::new();
    while at + 5 <= bytes.len() {
        starts.push(at);
        let len = u32::from_le_bytes([bytes[at + 1], bytes[at + 2], bytes[at + 3], bytes[at + 4]]);
        at += 5 + len as usize + 8;
    }
    starts.remove(0);
    starts
}

#[test]
fn a_damaged_record_stops_the_valid_part_before_it() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    let starts = record_starts(&s.bytes);
    for &at in starts.iter().step_by(starts.len() / 9) {
        let mut bad = s.bytes.clone();
        bad[at + 6] ^= 0x40; // inside the payload: the check no longer matches
        let mut w = open(&bad, &terrain);
        match w.stop() {
            Stop::Damaged(recording::FormatError::Corrupt { offset, what }) => {
                assert_eq!(*offset, at as u64);
                assert!(what.contains("check bytes"), "{what}");
            }
            other => panic!("damaged at {at}: {other:?}"),
        }
        let end = w.status().end;
        let outcome = replayed(&s.bytes[..at], &terrain);
        assert_eq!(end, outcome.tick);
        w.seek(end);
        assert_eq!(w.world().digest(), outcome.digest);
        assert!(watch::describe(&w).contains(&format!("record at byte {at}")));
    }
}

#[test]
fn a_diverging_file_plays_to_its_last_matching_checkpoint() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    // Another data set of the same size: the recording's hash names it, so the watch is
    // refused naming both; told it is this one, the replay diverges at its first
    // checkpoint with a vehicle moving.
    let other = load("synth-257");
    let refused = watch::open_bytes(&s.bytes, other.clone(), &other.content_hash());
    match refused {
        Err(OpenError::Replay(ReplayError::DataSet { recorded, actual })) => {
            assert_eq!(recorded, hex(&terrain.content_hash()));
            assert_eq!(actual, hex(&other.content_hash()));
        }
        r => panic!("{r:?}"),
    }
    let w = watch::open_bytes(&s.bytes, other.clone(), &terrain.content_hash())
        .expect("its header is taken");
    match w.stop() {
        Stop::Failed(ReplayError::Diverged { tick, agreed, .. }) => {
            assert_eq!(w.status().end, *agreed);
            assert!(agreed < tick);
        }
        other => panic!("{other:?}"),
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[test]
fn a_growing_file_is_followed_to_its_newest_tick_and_its_end() {
    let terrain = load("synth-65");
    let s = session(&terrain);
    // The file as its writer leaves it: the header, then pieces of any size.
    let header_end = 12 + 5 + 52 + 34 + 8;
    let mut reader = recording::Reader::open(&s.bytes[..header_end + 300]).expect("a header");
    let mut events = Vec::new();
    reader.read(&mut events).expect("whole records");
    let recording = recording::Recording {
        header: reader.header().clone(),
        events,
        truncated_at: reader.cut_at(),
    };
    let mut w =
        Watch::open(&recording, None, terrain.clone(), &terrain.content_hash()).expect("opens");
    w.follow();
    w.control(Control::Speed(32));
    let mut at = header_end + 300;
    let mut last_end = w.status().end;
    while at < s.bytes.len() {
        let piece = (at * 7 % 997 + 1).min(s.bytes.len() - at);
        let mut more = Vec::new();
        reader
            .feed(&s.bytes[at..at + piece], &mut more)
            .expect("whole records");
        at += piece;
        w.append(&more, None, reader.cut_at());
        let st = w.status();
        assert!(st.end >= last_end, "the valid part only grows");
        last_end = st.end;
        for _ in 0..3 {
            w.advance();
            let tick = w.status().tick;
            assert!(tick <= w.status().end);
            if tick < w.status().end {
                assert_eq!(
                    w.world().vehicles(),
                    &s.worlds[tick as usize][..],
                    "tick {tick}"
                );
            }
            if at < s.bytes.len() {
                assert_eq!(w.take_ended(), None, "not ended while the file grows");
            }
        }
    }
    assert_eq!(*w.stop(), Stop::Closed);
    while !w.at_end() {
        w.advance();
    }
    let outcome = replayed(&s.bytes, &terrain);
    assert_eq!(w.take_ended(), Some((TICKS, outcome.digest)));
    // A damaged record met while following stops it there.
    let mut reader = recording::Reader::open(&s.bytes[..header_end]).expect("a header");
    let mut bad = s.bytes[header_end..].to_vec();
    bad[2000] ^= 0x55;
    let mut events = Vec::new();
    let err = reader.feed(&bad, &mut events).expect_err("damaged");
    let recording = recording::Recording {
        header: reader.header().clone(),
        events: Vec::new(),
        truncated_at: None,
    };
    let mut w =
        Watch::open(&recording, None, terrain.clone(), &terrain.content_hash()).expect("opens");
    w.follow();
    w.append(&events, Some(err), None);
    assert!(matches!(w.stop(), Stop::Damaged(_)), "{:?}", w.stop());
    assert!(!w.growing());
    w.seek(u64::MAX);
    assert_eq!(w.take_ended().map(|e| e.0), Some(w.status().end));
}
