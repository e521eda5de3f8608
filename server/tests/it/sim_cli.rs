//! `roam-server simulate` and `roam-server replay`, run as a user would.

use crate::common;

use std::fs;
use std::path::Path;

use common::{TempDir, check, root};
use roam_server::sim::world;

/// Runs `roam-server replay FILE --data DATA`; see [`check`].
fn replay_file(file: &Path, data: &str, exit: i32, expected: &[&str]) -> String {
    let file = file.to_str().expect("temp paths are UTF-8 here");
    check(&["replay", file, "--data", data], exit, expected)
}

/// The `digest …` at the end of `simulate`'s or `replay`'s output.
fn digest_of(out: &str) -> String {
    out.split("digest ")
        .last()
        .expect("a digest")
        .trim()
        .to_owned()
}

#[test]
fn simulate_writes_one_csv_row_per_tick() {
    let dir = TempDir::new("simulate");
    fs::write(
        dir.path("drive.txt"),
        "# test\n120 U\n\n60 UL  # turn\n20 D\n",
    )
    .expect("write");
    let csv = dir.path("out.csv");
    check(
        &[
            "simulate",
            "data/synth-65",
            "--inputs",
            dir.path("drive.txt").to_str().expect("UTF-8"),
            "--csv",
            csv.to_str().expect("UTF-8"),
        ],
        0,
        &["200 ticks (2.00 s)", "digest "],
    );
    let text = fs::read_to_string(&csv).expect("the CSV");
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("tick,x,z,y,speed,heading"));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| {
            l.split(',')
                .map(|v| {
                    v.parse()
                        .unwrap_or_else(|_| panic!("a number: {v:?} in {l:?}"))
                })
                .collect()
        })
        .collect();
    assert_eq!(rows.len(), 201, "tick 0 and one row per tick");
    let terrain =
        roam_server::terrain::dataset::load(&root().join("data/synth-65"), &mut |_, _| {})
            .expect("bundled");
    let start = world::start_state(&terrain, 0);
    assert_eq!(
        rows[0],
        [0.0, start.x, start.z, rows[0][3], 0.0, start.heading]
    );
    for (i, r) in rows.iter().enumerate() {
        assert_eq!(r.len(), 6);
        assert_eq!(r[0], i as f64);
        assert!(r[4] >= 0.0, "speed never negative");
        let ground = roam_server::sim::physics::Ground::height(&terrain, r[1], r[2]);
        assert_eq!(r[3], ground + 2.0, "altitude is the ground plus 2");
    }
    assert!(rows[120][4] > rows[1][4], "accelerated");
    // The same drive coasting instead of braking for its last 20 ticks ends faster.
    fs::write(dir.path("coast.txt"), "120 U\n60 UL\n20 -\n").expect("write");
    let coast = check(
        &[
            "simulate",
            "data/synth-65",
            "--inputs",
            dir.path("coast.txt").to_str().expect("UTF-8"),
        ],
        0,
        &[],
    );
    let last_speed = |csv: &str| -> f64 {
        let last = csv.lines().last().expect("rows");
        last.split(',')
            .nth(4)
            .expect("speed")
            .parse()
            .expect("a number")
    };
    assert!(rows[200][4] < last_speed(&coast), "braked");
    assert_ne!(rows[180][5], rows[120][5], "turned");
    // Full precision: every value reads back to the same f64 (shortest round trip).
    let line = text.lines().nth(150).expect("row 149");
    let again: Vec<String> = line
        .split(',')
        .map(|v| v.parse::<f64>().expect("a number").to_string())
        .collect();
    assert_eq!(again.join(","), line);
    // Without --csv the CSV is stdout, the summary goes to stderr.
    let stdout = check(
        &[
            "simulate",
            "data/synth-65",
            "--inputs",
            dir.path("drive.txt").to_str().expect("UTF-8"),
        ],
        0,
        &["200 ticks"],
    );
    assert_eq!(stdout, text, "same CSV on stdout");
}

#[test]
fn simulate_record_then_replay() {
    let dir = TempDir::new("record");
    fs::write(dir.path("drive.txt"), "250 U\n100 UR\n80 -\n").expect("write");
    let rec = dir.path("drive.rec");
    let rec = rec.to_str().expect("UTF-8");
    let sim = check(
        &[
            "simulate",
            "data/synth-257",
            "--inputs",
            dir.path("drive.txt").to_str().expect("UTF-8"),
            "--record",
            rec,
            "--csv",
            dir.path("out.csv").to_str().expect("UTF-8"),
        ],
        0,
        &["430 ticks"],
    );
    let replayed = check(
        &["replay", rec, "--data", "data/synth-257"],
        0,
        &["replayed 430 ticks", "closed cleanly", "vehicle 0: x "],
    );
    assert_eq!(digest_of(&replayed), digest_of(&sim));
    // Cut short (a killed server): the whole records replay, with a warning.
    let bytes = fs::read(rec).expect("the recording");
    let cut = dir.path("cut.rec");
    fs::write(&cut, &bytes[..bytes.len() - 30]).expect("write");
    check(
        &[
            "replay",
            cut.to_str().expect("UTF-8"),
            "--data",
            "data/synth-257",
        ],
        0,
        &[
            "warning: ",
            "is cut inside the record at byte",
            "replayed 400 ticks",
            "no end record",
        ],
    );
    // Another data set.
    check(
        &["replay", rec, "--data", "data/synth-65"],
        1,
        &["made on another data set"],
    );
    // A corrupt byte.
    let mut bad = bytes.clone();
    bad[100] ^= 0xff;
    fs::write(dir.path("bad.rec"), &bad).expect("write");
    replay_file(
        &dir.path("bad.rec"),
        "data/synth-257",
        1,
        &["bad.rec: record at byte "],
    );
    // Another format version.
    let mut newer = bytes;
    newer[8] = 9;
    fs::write(dir.path("v9.rec"), &newer).expect("write");
    replay_file(
        &dir.path("v9.rec"),
        "data/synth-257",
        1,
        &["recording format version 9; this build reads versions 1 to 3"],
    );
}

#[test]
fn replay_the_golden_recordings() {
    // Every format version this build reads, and a file that starts mid-session (version
    // 3's start tick, as the server writes after a rotation): the same drive's digest.
    let expected =
        fs::read_to_string(root().join("server/tests/golden/drive.digest")).expect("golden digest");
    for (file, says) in [
        ("drive.rec", "replayed 5280 ticks"),
        ("drive-v1.rec", "replayed 5280 ticks"),
        ("drive-v2.rec", "replayed 5280 ticks"),
        (
            "drive-late.rec",
            "replayed 4046 ticks (40.46 s) of server/tests/golden/drive-late.rec from tick 1234",
        ),
    ] {
        let path = format!("server/tests/golden/{file}");
        let out = check(
            &["replay", &path, "--data", "data/synth-65"],
            0,
            &[says, "checkpoints matched", "closed cleanly"],
        );
        assert_eq!(digest_of(&out), expected.trim(), "{file}");
    }
}

#[test]
fn replay_names_the_tick_where_it_diverged() {
    let dir = TempDir::new("diverged");
    let terrain = std::sync::Arc::new(
        roam_server::terrain::dataset::load(&root().join("data/synth-65"), &mut |_, _| {})
            .expect("bundled"),
    );
    let path = dir.path("x.rec");
    fs::write(&path, common::diverged_recording(&terrain, 200, 50, 150)).expect("write");
    replay_file(
        &path,
        "data/synth-65",
        1,
        &[
            "the first checkpoint that differs is at tick 150",
            "the last that agreed was at tick 100",
        ],
    );
}

#[test]
fn simulate_rejects_bad_input() {
    let dir = TempDir::new("bad-sim");
    fs::write(dir.path("bad.txt"), "10 U\n\n5 UX\n").expect("write");
    check(
        &[
            "simulate",
            "data/synth-65",
            "--inputs",
            dir.path("bad.txt").to_str().expect("UTF-8"),
        ],
        1,
        &["bad.txt: line 3: keys: expected `-` or letters from U, D, L, R, got \"UX\""],
    );
    check(
        &[
            "simulate",
            "data/synth-65",
            "--inputs",
            dir.path("missing.txt").to_str().expect("UTF-8"),
        ],
        1,
        &["missing.txt"],
    );
    check(
        &[
            "replay",
            dir.path("missing.rec").to_str().expect("UTF-8"),
            "--data",
            "data/synth-65",
        ],
        1,
        &["missing.rec"],
    );
    fs::write(dir.path("junk.rec"), b"hello world, not a recording").expect("write");
    check(
        &[
            "replay",
            dir.path("junk.rec").to_str().expect("UTF-8"),
            "--data",
            "data/synth-65",
        ],
        1,
        &["junk.rec: not a roam recording"],
    );
    check(&["simulate", "data/synth-65"], 2, &["--inputs"]);
}

#[test]
fn simulate_drives_many_vehicles_for_any_length_and_records_them() {
    let dir = TempDir::new("many");
    fs::write(dir.path("drive.txt"), "250 U\n100 UR\n80 -\n").expect("write");
    let rec = dir.path("many.rec");
    let rec = rec.to_str().expect("UTF-8");
    let csv = dir.path("many.csv");
    let sim = check(
        &[
            "simulate",
            "data/synth-257",
            "--inputs",
            dir.path("drive.txt").to_str().expect("UTF-8"),
            "--vehicles",
            "3",
            "--ticks",
            "1000",
            "--record",
            rec,
            "--csv",
            csv.to_str().expect("UTF-8"),
        ],
        0,
        &["1000 ticks"],
    );
    // Every vehicle's row at every tick from its join (vehicle i at tick 100 i) on.
    let text = fs::read_to_string(&csv).expect("the CSV");
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("tick,vehicle,x,z,y,speed,heading"));
    let rows: Vec<(u64, u16)> = lines
        .map(|l| {
            let mut f = l.split(',');
            let tick = f.next().and_then(|t| t.parse().ok()).expect("a tick");
            let id = f.next().and_then(|v| v.parse().ok()).expect("a vehicle");
            (tick, id)
        })
        .collect();
    let expected: Vec<(u64, u16)> = (0..=1000u64)
        .flat_map(|t| {
            (0..3u16)
                .filter(move |&i| t > 100 * u64::from(i) || i == 0)
                .map(move |i| (t, i))
        })
        .collect();
    assert_eq!(rows, expected);
    // The recording replays to the same world, its joins in it.
    let replayed = check(
        &["replay", rec, "--data", "data/synth-257"],
        0,
        &["replayed 1000 ticks", "closed cleanly", "vehicle 2: x "],
    );
    assert_eq!(digest_of(&replayed), digest_of(&sim));
    check(
        &[
            "simulate",
            "data/synth-257",
            "--inputs",
            "x",
            "--vehicles",
            "0",
        ],
        2,
        &["--vehicles"],
    );
}
