//! Recordings: golden files replayed to their expected digests, cuts at every byte,
//! corruption, version and data-set checks, and the input script parser.
//!
//! `UPDATE_EXPECT=1 cargo test --test it recording::` rewrites the golden files in
//! `tests/golden/` (do it only when the physics or the format changes on purpose).

use crate::common;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use roam_protocol::script::{self, Script};
use roam_server::Terrain;
use roam_server::sim::physics::Keys;
use roam_server::sim::recorder::{RecordedWorld, Recorder};
use roam_server::sim::recording::{self, Event, FormatError};
use roam_server::sim::replay::{self, ReplayError};
use roam_server::sim::world::{self, Digest, Extra, Inputs, World};
use roam_server::terrain::dataset;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the crate lives in the workspace")
        .to_path_buf()
}

fn load(name: &str) -> Arc<Terrain> {
    Arc::new(dataset::load(&root().join("data").join(name), &mut |_, _| {}).expect("bundled"))
}

const DRIVE: &str = "\
# a drive that uses every key, and bounces off the map's edge
300 U
200 UL
100 U
150 URD   # brake wins over Up; right turn
400 UR
50 -
4000 U
80 D
";

/// A recorded run and the digest at every tick (after that tick's joins and leaves).
struct Run {
    bytes: Vec<u8>,
    digests: Vec<Digest>,
    /// The closest any vehicle came to the map's edge.
    edge: f64,
}

fn edge_distance<G: roam_server::sim::physics::Ground>(w: &World<G>) -> f64 {
    let size = w.ground().size();
    w.vehicles()
        .iter()
        .map(|v| {
            v.state
                .x
                .min(v.state.z)
                .min(size - v.state.x)
                .min(size - v.state.z)
        })
        .fold(f64::INFINITY, f64::min)
}

/// One vehicle driving `script` from the map's start, recorded.
fn record_drive(terrain: &Arc<Terrain>, script: &Script) -> Run {
    record_drive_from(terrain, script, 0)
}

/// One vehicle driving `script` from the map's start, recorded from tick `from` on (as a
/// file the server starts mid-session).
fn record_drive_from(terrain: &Arc<Terrain>, script: &Script, from: usize) -> Run {
    let mut world = World::new(terrain.clone());
    world
        .add(0, world::start_state(terrain, 0))
        .expect("the start is on the map");
    let mut digests = vec![world.digest()];
    let mut edge = f64::INFINITY;
    let mut inputs = Inputs::new();
    let keys: Vec<Keys> = script.keys().collect();
    for &k in &keys[..from] {
        inputs.set(0, k);
        world::step(&mut world, &inputs);
        digests.push(world.digest());
        edge = edge.min(edge_distance(&world));
    }
    let mut rec = RecordedWorld::start(world, Vec::new(), terrain.content_hash(), 100)
        .expect("memory does not fail");
    for &keys in &keys[from..] {
        inputs.set(0, keys);
        rec.step(&inputs).expect("memory does not fail");
        digests.push(rec.world().digest());
        edge = edge.min(edge_distance(rec.world()));
    }
    let (_, bytes) = rec.finish().expect("memory does not fail");
    Run {
        bytes,
        digests,
        edge,
    }
}

/// Several vehicles joining and leaving, each with its own keys, with a checkpoint every
/// 37 ticks.
fn record_convoy(terrain: &Arc<Terrain>) -> Run {
    let mut world = World::new(terrain.clone());
    world
        .add(10, world::start_state(terrain, 0))
        .expect("on the map");
    let mut rec = RecordedWorld::start(world, Vec::new(), terrain.content_hash(), 37)
        .expect("memory does not fail");
    let mut digests = vec![rec.world().digest()];
    let pattern = [Keys::UP, Keys::UP.union(Keys::LEFT), Keys::NONE, Keys::DOWN];
    let mut inputs = Inputs::new();
    for tick in 0u32..900 {
        match tick {
            50 => rec.join(11, world::start_state(terrain, 1)).expect("joins"),
            120 => rec.join(12, world::start_state(terrain, 2)).expect("joins"),
            400 => rec.leave(11).expect("leaves"),
            650 => rec
                .join(11, world::start_state(terrain, 3))
                .expect("joins again"),
            _ => {}
        }
        // The world at this tick, as a replay ending on these events sees it.
        *digests.last_mut().expect("tick 0 at least") = rec.world().digest();
        for v in rec.world().vehicles() {
            let k = (tick / 60 + u32::from(v.id)) as usize % pattern.len();
            inputs.set(v.id, pattern[k]);
        }
        // Vehicle 12 waits now and then, and catches up with two steps (a driver whose
        // key states came late).
        inputs.clear_extra();
        match tick % 53 {
            7 if rec.world().vehicle(12).is_some() => inputs.set_extra(12, Extra::Wait),
            9 if rec.world().vehicle(12).is_some() => {
                inputs.set_extra(12, Extra::Twice(Keys::UP, Keys::UP.union(Keys::RIGHT)))
            }
            _ => {}
        }
        rec.step(&inputs).expect("memory does not fail");
        digests.push(rec.world().digest());
    }
    let edge = edge_distance(rec.world());
    let (_, bytes) = rec.finish().expect("memory does not fail");
    Run {
        bytes,
        digests,
        edge,
    }
}

fn drive_script() -> Script {
    script::parse(DRIVE).expect("a valid script")
}

/// Compares a fresh recording with the committed one, and replays the committed one to the
/// committed final digest.
fn golden(name: &str, data: &str, run: impl Fn(&Arc<Terrain>) -> Run) {
    let terrain = load(data);
    let fresh = run(&terrain);
    let dir = root().join("server/tests/golden");
    let (rec_path, digest_path) = (
        dir.join(format!("{name}.rec")),
        dir.join(format!("{name}.digest")),
    );
    if std::env::var_os("UPDATE_EXPECT").is_some() {
        std::fs::create_dir_all(&dir).expect("create tests/golden");
        std::fs::write(&rec_path, &fresh.bytes).expect("write golden recording");
        let last = fresh.digests.last().expect("tick 0 at least");
        std::fs::write(&digest_path, format!("{last}\n")).expect("write golden digest");
    }
    let committed = std::fs::read(&rec_path).unwrap_or_else(|e| {
        panic!(
            "{}: {e} (run with UPDATE_EXPECT=1 to create it)",
            rec_path.display()
        )
    });
    let expected = std::fs::read_to_string(&digest_path).expect("golden digest");
    let rec = recording::parse(&committed).expect("the golden recording parses");
    let out = replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays");
    assert!(out.ended && out.truncated_at.is_none());
    assert_eq!(
        format!("{}\n", out.digest),
        expected,
        "{name}: final digest"
    );
    assert!(
        fresh.bytes == committed,
        "{name}: a fresh recording differs from the committed one: the physics or the format \
         changed (UPDATE_EXPECT=1 rewrites it)"
    );
}

#[test]
fn older_versions_still_replay() {
    // `drive-v1.rec` and `drive-v2.rec` are `drive.rec` as format versions 1 (no wait or
    // twice records) and 2 (no start tick) wrote it: the same drive, the same digest.
    let terrain = load("synth-65");
    let dir = root().join("server/tests/golden");
    let expected = std::fs::read_to_string(dir.join("drive.digest")).expect("golden digest");
    for version in [1u32, 2] {
        let bytes = std::fs::read(dir.join(format!("drive-v{version}.rec"))).expect("golden");
        assert_eq!(
            bytes[8..12],
            version.to_le_bytes(),
            "written as version {version}"
        );
        let rec = recording::parse(&bytes).expect("parses");
        assert_eq!(rec.header.start_tick, 0);
        let out = replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays");
        assert!(out.ended && out.start_tick == 0);
        assert_eq!(format!("{}\n", out.digest), expected, "version {version}");
    }
}

#[test]
fn golden_drive_from_a_later_tick_replays_to_the_same_digest() {
    // Version 3: the header's start tick. A file that starts at tick 1234 (as one the
    // server rotates in) replays on its own to the whole drive's final digest.
    golden("drive-late", "synth-65", |t| {
        let run = record_drive_from(t, &drive_script(), 1234);
        let rec = recording::parse(&run.bytes).expect("whole");
        assert_eq!(rec.header.start_tick, 1234);
        assert_eq!(run.bytes[8..12], recording::VERSION.to_le_bytes());
        run
    });
    let dir = root().join("server/tests/golden");
    let read = |f: &str| std::fs::read_to_string(dir.join(f)).expect("golden digest");
    assert_eq!(read("drive-late.digest"), read("drive.digest"));
}

#[test]
fn golden_drive_replays_to_its_digest() {
    golden("drive", "synth-65", |t| {
        let run = record_drive(t, &drive_script());
        assert!(run.edge < 0.2, "the drive reaches the edge: {}", run.edge);
        run
    });
}

#[test]
fn golden_convoy_replays_to_its_digest() {
    golden("convoy", "synth-65", record_convoy);
}

#[test]
fn golden_kossou_drive_replays_to_its_digest() {
    let script = script::parse("500 U\n300 UL\n200 UR\n100 D\n").expect("valid");
    golden("kossou", "kossou", |t| record_drive(t, &script));
}

/// Byte offsets where each record starts, and the end of the header.
fn record_starts(bytes: &[u8]) -> Vec<usize> {
    let mut at = 12;
    let mut starts = Vec::new();
    while at < bytes.len() {
        starts.push(at);
        let len = u32::from_le_bytes(bytes[at + 1..at + 5].try_into().expect("4 bytes")) as usize;
        at += 5 + len + 8;
    }
    starts
}

fn check_every_cut(run: &Run, terrain: &Arc<Terrain>) {
    let full = recording::parse(&run.bytes).expect("whole");
    let starts = record_starts(&run.bytes);
    let header_end = starts[1];
    let hash = terrain.content_hash();
    for cut in 0..=run.bytes.len() {
        let parsed = recording::parse(&run.bytes[..cut]);
        if cut < header_end {
            assert_eq!(
                parsed,
                Err(FormatError::TruncatedHeader { len: cut as u64 }),
                "cut at {cut}"
            );
            continue;
        }
        let rec = parsed.unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        // Whole records before the cut: those ending at or before it.
        let whole = starts[1..]
            .iter()
            .zip(starts[2..].iter().chain([&run.bytes.len()]))
            .take_while(|&(_, &end)| end <= cut)
            .count();
        assert_eq!(rec.events, full.events[..whole], "cut at {cut}");
        let boundary = starts.contains(&cut) || cut == run.bytes.len();
        assert_eq!(
            rec.truncated_at,
            (!boundary).then(|| starts[1 + whole] as u64),
            "cut at {cut}"
        );
        let out = replay::replay(&rec, terrain.clone(), &hash)
            .unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        let last_tick = rec.events.last().map_or(rec.header.start_tick, Event::tick);
        assert_eq!(out.tick, last_tick, "cut at {cut}");
        assert_eq!(out.digest, run.digests[last_tick as usize], "cut at {cut}");
    }
}

#[test]
fn a_recording_cut_at_any_byte_replays_its_whole_records() {
    let terrain = load("synth-65");
    let script = script::parse("150 U\n120 UL\n40 D\n60 R\n").expect("valid");
    check_every_cut(&record_drive(&terrain, &script), &terrain);
    check_every_cut(&record_convoy(&terrain), &terrain);
    check_every_cut(&record_drive_from(&terrain, &script, 77), &terrain);
}

#[test]
fn a_corrupt_record_is_reported_at_its_offset() {
    let terrain = load("synth-65");
    let script = script::parse("150 U\n120 UL\n").expect("valid");
    let run = record_drive(&terrain, &script);
    let starts = record_starts(&run.bytes);
    for (i, &at) in starts.iter().enumerate() {
        let end = starts.get(i + 1).copied().unwrap_or(run.bytes.len());
        // A payload byte, then a check byte.
        for flip in [at + 5, end - 1] {
            let mut bad = run.bytes.clone();
            bad[flip] ^= 0x20;
            match recording::parse(&bad) {
                Err(FormatError::Corrupt { offset, .. }) => {
                    assert_eq!(offset, at as u64, "flip at {flip}")
                }
                other => panic!("flip at {flip}: {other:?}"),
            }
        }
    }
    let mut bad = run.bytes.clone();
    bad[0] = b'R';
    assert_eq!(recording::parse(&bad), Err(FormatError::Magic));
    let mut bad = run.bytes.clone();
    bad[8] = 4;
    assert_eq!(
        recording::parse(&bad),
        Err(FormatError::Version { found: 4 })
    );
    // A record after the end.
    let mut bad = run.bytes.clone();
    let last = *starts.last().expect("an end record");
    bad.extend_from_slice(&run.bytes[last..]);
    assert!(matches!(
        recording::parse(&bad),
        Err(FormatError::Corrupt { offset, .. }) if offset == run.bytes.len() as u64
    ));
}

/// A well-formed recording (every record's framing valid) whose content is whatever
/// `header` and `write` make it, without an end record.
fn with_records(
    terrain: &Arc<Terrain>,
    header: impl FnOnce(&mut recording::Header),
    write: impl FnOnce(&mut Recorder<Vec<u8>>),
) -> Vec<u8> {
    let mut h = recording::Header {
        data_hash: terrain.content_hash(),
        steps_per_second: 100,
        checkpoint_interval: 100,
        start_tick: 0,
        vehicles: vec![(0, world::start_state(terrain, 0))],
    };
    header(&mut h);
    let mut rec = Recorder::new(Vec::new(), &h).expect("memory");
    write(&mut rec);
    rec.finish(0, &Digest([0; 32]))
        .map(|mut b| {
            // Drop the end record: the cases below are about what comes before it.
            b.truncate(b.len() - 53);
            b
        })
        .expect("memory")
}

#[test]
fn framing_damage_and_broken_discipline_are_corrupt() {
    let terrain = load("synth-65");
    let script = script::parse("150 U\n120 UL\n").expect("valid");
    let run = record_drive(&terrain, &script);
    let starts = record_starts(&run.bytes);
    let corrupt_at = |bytes: &[u8]| match recording::parse(bytes) {
        Err(FormatError::Corrupt { offset, what }) => (offset, what),
        other => panic!("{other:?}"),
    };
    for &at in &starts {
        // The kind, then the length's low byte: both checked before the end of the file.
        for (flip, value) in [(at, 0x7e), (at + 1, 0xff), (at + 3, 0x01)] {
            let mut bad = run.bytes.clone();
            bad[flip] = value;
            assert_eq!(corrupt_at(&bad).0, at as u64, "byte {flip} set to {value}");
        }
    }
    // Bytes after the end record.
    let mut bad = run.bytes.clone();
    bad.extend_from_slice(&[2, 11, 0]);
    let (offset, what) = corrupt_at(&bad);
    assert_eq!(
        (offset, what.as_str()),
        (run.bytes.len() as u64, "bytes after the end record")
    );
    // Inputs past the next checkpoint, and a checkpoint off the interval.
    let late = with_records(
        &terrain,
        |_| {},
        |r| {
            r.input(150, 0, Keys::UP).expect("memory");
        },
    );
    assert!(
        corrupt_at(&late)
            .1
            .contains("more than 100 ticks past the last checkpoint")
    );
    let off = with_records(
        &terrain,
        |_| {},
        |r| {
            r.checkpoint(60, &Digest([0; 32])).expect("memory");
        },
    );
    assert!(
        corrupt_at(&off)
            .1
            .contains("a checkpoint at tick 60, expected tick 100")
    );
}

#[test]
fn replay_refuses_what_the_world_cannot_take() {
    let terrain = load("synth-65");
    let hash = terrain.content_hash();
    let replay_of = |bytes: Vec<u8>| {
        let rec = recording::parse(&bytes).expect("well-formed");
        replay::replay(&rec, terrain.clone(), &hash)
    };
    let slow = with_records(&terrain, |h| h.steps_per_second = 50, |_| {});
    assert_eq!(replay_of(slow), Err(ReplayError::Rate { found: 50 }));
    let twice = with_records(
        &terrain,
        |_| {},
        |r| {
            r.join(5, 0, &world::start_state(&terrain, 1))
                .expect("memory");
        },
    );
    assert!(matches!(
        replay_of(twice),
        Err(ReplayError::World {
            tick: 5,
            error: world::WorldError::Duplicate(0)
        })
    ));
    let ghost = with_records(
        &terrain,
        |_| {},
        |r| {
            r.input(3, 9, Keys::UP).expect("memory");
        },
    );
    assert!(matches!(
        replay_of(ghost),
        Err(ReplayError::World {
            tick: 3,
            error: world::WorldError::Missing(9)
        })
    ));
    let gone = with_records(
        &terrain,
        |_| {},
        |r| {
            r.leave(7, 4).expect("memory");
        },
    );
    assert!(matches!(
        replay_of(gone),
        Err(ReplayError::World {
            tick: 7,
            error: world::WorldError::Missing(4)
        })
    ));
}

#[test]
fn another_data_set_is_refused() {
    let terrain = load("synth-65");
    let run = record_drive(&terrain, &script::parse("10 U").expect("valid"));
    let rec = recording::parse(&run.bytes).expect("whole");
    let other = load("synth-257");
    let err = replay::replay(&rec, other.clone(), &other.content_hash()).expect_err("refused");
    assert!(matches!(err, ReplayError::DataSet { .. }), "{err}");
    assert!(err.to_string().contains("another data set"));
}

#[test]
fn divergence_names_the_first_checkpoint_that_differs() {
    let terrain = load("synth-65");
    let bytes = common::diverged_recording(&terrain, 300, 100, 200);
    let rec = recording::parse(&bytes).expect("whole");
    match replay::replay(&rec, terrain.clone(), &terrain.content_hash()) {
        Err(ReplayError::Diverged { tick, agreed, .. }) => assert_eq!((tick, agreed), (200, 100)),
        other => panic!("{other:?}"),
    }
}

#[test]
fn inputs_are_recorded_only_when_they_change() {
    let terrain = load("synth-65");
    let run = record_drive(
        &terrain,
        &script::parse("100 U\n100 U\n50 -\n1 L\n").expect("valid"),
    );
    let rec = recording::parse(&run.bytes).expect("whole");
    let inputs: Vec<(u64, Keys)> = rec
        .events
        .iter()
        .filter_map(|e| match *e {
            Event::Input { tick, keys, .. } => Some((tick, keys)),
            _ => None,
        })
        .collect();
    assert_eq!(
        inputs,
        [(0, Keys::UP), (200, Keys::NONE), (250, Keys::LEFT)]
    );
}

/// `check(script, expected)`: the parsed segments as `ticks keys` words, or the error.
fn check(text: &str, expected: Result<&str, &str>) {
    let got = script::parse(text)
        .map(|s| {
            s.segments
                .iter()
                .map(|(n, k)| format!("{n} {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .map_err(|e| e.to_string());
    assert_eq!(
        got.as_deref(),
        expected.map_err(str::to_owned).as_deref(),
        "{text:?}"
    );
}

#[test]
fn input_scripts() {
    check("", Ok(""));
    check("# only a comment\n\n   \n", Ok(""));
    check(
        "10 U\n5 -\n3 ul # turn\n2 DLRU",
        Ok("10 U, 5 -, 3 UL, 2 UDLR"),
    );
    check(
        "10\n",
        Err("line 1: expected `<ticks> <keys>` (e.g. `100 UL`), got \"10\""),
    );
    check(
        "\n\n10 U X\n",
        Err("line 3: expected `<ticks> <keys>` (e.g. `100 UL`), got \"10 U X\""),
    );
    check(
        "0 U",
        Err("line 1: ticks: expected a whole number ≥ 1, got \"0\""),
    );
    check(
        "-5 U",
        Err("line 1: ticks: expected a whole number ≥ 1, got \"-5\""),
    );
    check(
        "1.5 U",
        Err("line 1: ticks: expected a whole number ≥ 1, got \"1.5\""),
    );
    check(
        "10 U\n10 Q",
        Err("line 2: keys: expected `-` or letters from U, D, L, R, got \"Q\""),
    );
    check(
        "99999999 U\n2 U",
        Err("line 2: the script runs past 100000000 ticks (the longest allowed)"),
    );
}
