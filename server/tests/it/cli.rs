//! End-to-end tests of the `roam-server` binary: exit codes, messages, and the files and
//! JSON it writes.

use std::collections::HashMap;
use std::fs;
use std::path::Path;

use crate::common;

use common::{TempDir, check, root};

/// A copy of `data/synth-65` in a temp dir, to break.
fn copy_synth65(name: &str) -> TempDir {
    let dir = TempDir::new(name);
    for f in ["map", "hf.pgm", "color.ppm"] {
        fs::copy(root().join("data/synth-65").join(f), dir.path(f)).expect("copy data set");
    }
    dir
}

#[test]
fn help_on_everything() {
    check(
        &["--help"],
        0,
        &[
            "check", "generate", "import", "mesh", "bench", "simulate", "replay", "serve",
        ],
    );
    check(&["serve", "--help"], 0, &["--max-memory", "MemAvailable"]);
    for (cmd, flag) in [
        ("check", "DIR"),
        ("generate", "--side"),
        ("import", "--h-scale"),
        ("mesh", "--eye"),
        ("bench", "--frames"),
        ("simulate", "--inputs"),
        ("replay", "--data"),
        ("serve", "--state-dir"),
    ] {
        check(&[cmd, "--help"], 0, &[flag]);
    }
}

#[test]
fn check_bundled() {
    check(
        &["check", "data/synth-65"],
        0,
        &[
            "side 65 (N = 6)",
            "hScale 10",
            "vScale 0.002",
            "heights: samples 0 .. 40000",
            "variance tree: ",
            " bytes/sample (",
            "resident: ",
            "colour map 3.00 bytes/cell aside",
        ],
    );
    let out = check(&["check", "data/synth-257"], 0, &["side 257 (N = 8)"]);
    // The variance tree fits the budget of 1 byte per sample, heights + tree 3.
    let per_sample = |prefix: &str| -> f64 {
        let line = out
            .lines()
            .find(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no {prefix:?} line in\n{out}"));
        line[prefix.len()..]
            .split_whitespace()
            .next()
            .and_then(|w| w.parse().ok())
            .unwrap_or_else(|| panic!("no number after {prefix:?} in {line:?}"))
    };
    let vt = per_sample("variance tree: ");
    assert!(vt > 0.0 && vt <= 1.0, "variance tree {vt} bytes/sample");
    let resident = per_sample("resident: ");
    assert!(
        resident <= 3.0 && resident > vt,
        "resident {resident} bytes/sample"
    );
}

#[test]
fn check_rejects_broken_data_sets() {
    check(
        &["check", "data/no-such-set"],
        1,
        &["data/no-such-set/hf.pgm", "cannot open"],
    );

    // Each case: a file to overwrite in a copy of synth-65, its new content, and what the
    // error must name (file and field).
    let truncated =
        fs::read(root().join("data/synth-65/hf.pgm")).expect("bundled hf.pgm")[..1000].to_vec();
    let cases: Vec<(&str, Vec<u8>, &[&str])> = vec![
        (
            "map",
            b"hScale = -1.0\nvScale = 0.5\n".to_vec(),
            &["map:1: hScale: expected 1e-3 ..= 1e4", "got -1.0"],
        ),
        // Issue 39: absurd values once passed `check` (and `serve`).
        (
            "map",
            b"vScale = 1e308\n".to_vec(),
            &["map:1: vScale: expected 1e-6 ..= 1e3", "got 1e308"],
        ),
        (
            "map",
            b"fogDensity = 1e30\n".to_vec(),
            &[
                "map:1: fogDensity: expected 0 ..= 10 (10 / hScale",
                "got 1e30",
            ],
        ),
        (
            "map",
            b"waterLevel = 1e300\n".to_vec(),
            &["map:1: waterLevel: expected 0 ..= ", "got 1e300"],
        ),
        (
            "map",
            b"hScale = 1.0\nvScale = 0.5\nbogus = 3\n".to_vec(),
            &["map:3", "bogus"],
        ),
        ("hf.pgm", truncated, &["hf.pgm: data: expected 8450 bytes"]),
        (
            "hf.pgm",
            b"P5\n100000 100000\n65535\n".to_vec(),
            &["hf.pgm: width: expected 2^N + 1"],
        ),
        ("hf.pgm", b"P2\n65 65\n65535\n".to_vec(), &["hf.pgm: magic"]),
        (
            "color.ppm",
            b"P6\n32 32\n255\n".to_vec(),
            &["color.ppm: width", "64"],
        ),
    ];
    for (file, content, expected) in cases {
        let dir = copy_synth65(file);
        fs::write(dir.path(file), content).expect("write broken file");
        check(&["check", dir.str()], 1, expected);
    }
}

#[test]
fn generate_then_check() {
    let dir = TempDir::new("generated");
    let out = dir.path("set");
    let out = out.to_str().expect("UTF-8 temp path");
    check(
        &["generate", out, "--side", "33", "--seed", "5"],
        0,
        &["wrote", "side 33 (N = 5)"],
    );
    check(
        &["check", out],
        0,
        &["side 33 (N = 5)", "variance tree: ", "resident: "],
    );
    check(
        &["generate", out, "--side", "100"],
        1,
        &["--side: expected 2^N + 1", "got 100"],
    );
}

#[test]
fn bad_cli_values() {
    let obj = TempDir::new("bad-cli");
    let obj = obj.path("m.obj");
    let obj = obj.to_str().expect("UTF-8 temp path");
    // clap's usage errors exit 2; checks done by the commands exit 1.
    for (args, exit, expected) in [
        (
            vec!["mesh", "data/synth-65", "--eye", "1,2", "--obj", obj],
            2,
            &["--eye", "expected X,Y,Z"][..],
        ),
        (
            vec!["mesh", "data/synth-65", "--eye", "1,2,x", "--obj", obj],
            2,
            &["--eye", "\"x\""],
        ),
        (
            vec![
                "mesh",
                "data/synth-65",
                "--eye",
                "1,2,3",
                "--budget=-5",
                "--obj",
                obj,
            ],
            2,
            &["--budget"],
        ),
        (
            vec![
                "mesh",
                "data/synth-65",
                "--eye",
                "1,2,3",
                "--fov",
                "0",
                "--obj",
                obj,
            ],
            1,
            &["--fov"],
        ),
        (vec!["mesh", "data/synth-65", "--obj", obj], 1, &["--eye"]),
        (
            vec!["mesh", "data/synth-65", "--eye", "1,2,3"],
            2,
            &["--obj"],
        ),
        (
            vec!["bench", "data/synth-65", "--frames", "many"],
            2,
            &["--frames"],
        ),
        (vec!["generate"], 2, &["OUT"]),
        (vec!["frobnicate"], 2, &["frobnicate"]),
        (
            vec!["serve", "data/synth-65", "--max-memory", "4X"],
            2,
            &["--max-memory", "expected a number of bytes"],
        ),
        (
            vec!["serve", "data/synth-65", "--max-memory", "1K"],
            2,
            &["--max-memory", "expected at least"],
        ),
    ] {
        check(&args, exit, expected);
    }
    assert!(!Path::new(obj).exists(), "a failed mesh wrote {obj}");
}

/// `world` and `edge` want the cluster's secret (or `--insecure-bus`, said so), before they
/// reach for NATS; `bus-secret` writes a new one for its owner's eyes only, never over a
/// file; a secret too short is refused naming the file.
#[test]
fn the_bus_secret_is_asked_for_made_and_checked() {
    use std::os::unix::fs::PermissionsExt;
    let dir = TempDir::new("bus-secret");
    let key = dir.path("lake.key");
    let key = key.to_str().expect("UTF-8 temp path");
    let short = dir.path("short.key");
    fs::write(&short, "s3cret\n").expect("written");
    let short = short.to_str().expect("UTF-8 temp path");
    // Nothing listens on port 1: a command that got past its secret would fail there.
    let nats = ["--nats", "nats://127.0.0.1:1"];
    for cmd in ["world", "edge"] {
        let args = [&[cmd, "data/synth-65"][..], &nats[..]].concat();
        check(
            &args,
            1,
            &[
                "--bus-secret FILE",
                "roam-server bus-secret",
                "--insecure-bus",
            ],
        );
        let with = [&args[..], &["--bus-secret", short][..]].concat();
        check(&with, 1, &[short, "expected at least 32 bytes", "got 6"]);
        let both = [&args[..], &["--bus-secret", short, "--insecure-bus"][..]].concat();
        check(&both, 2, &["--insecure-bus", "cannot be used with"]);
    }
    check(&["bus-secret", key], 0, &["wrote a new bus secret", key]);
    let text = fs::read_to_string(key).expect("the secret was written");
    assert_eq!(text.len(), 65, "{text:?}");
    assert!(
        text.trim_end().chars().all(|c| c.is_ascii_hexdigit()),
        "{text:?}"
    );
    let mode = fs::metadata(key).expect("written").permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "readable by its owner only");
    check(&["bus-secret", key], 1, &[key, "never replaced"]);
    assert_eq!(
        fs::read_to_string(key).expect("still there"),
        text,
        "not replaced"
    );
}

/// A parsed Wavefront OBJ: vertices and 1-based faces.
struct Obj {
    vertices: Vec<[f64; 3]>,
    faces: Vec<[usize; 3]>,
}

fn parse_obj(text: &str) -> Obj {
    let mut obj = Obj {
        vertices: vec![],
        faces: vec![],
    };
    for (n, line) in text.lines().enumerate() {
        let mut words = line.split_whitespace();
        let kind = words.next();
        let rest: Vec<&str> = words.collect();
        match kind {
            None | Some("#") => {}
            Some("v") => {
                let v: Vec<f64> = rest
                    .iter()
                    .map(|w| w.parse().expect("a vertex coordinate is a number"))
                    .collect();
                let v: [f64; 3] = v
                    .try_into()
                    .unwrap_or_else(|_| panic!("line {}: three coordinates", n + 1));
                obj.vertices.push(v);
            }
            Some("f") => {
                let f: Vec<usize> = rest
                    .iter()
                    .map(|w| w.parse().expect("a face index is a positive integer"))
                    .collect();
                let f: [usize; 3] = f
                    .try_into()
                    .unwrap_or_else(|_| panic!("line {}: three indices", n + 1));
                obj.faces.push(f);
            }
            Some(other) => panic!("line {}: unexpected {other:?}", n + 1),
        }
    }
    obj
}

/// `N triangles, error bound X px` → `(N, X)`.
fn parse_summary(stdout: &str) -> (usize, f64) {
    let line = stdout
        .lines()
        .find(|l| l.contains(" triangles, error bound "))
        .unwrap_or_else(|| panic!("no summary line in {stdout:?}"));
    let words: Vec<&str> = line.split_whitespace().collect();
    match words[..] {
        [n, "triangles,", "error", "bound", x, "px"] => (
            n.parse().expect("triangle count"),
            x.parse().expect("error bound"),
        ),
        _ => panic!("summary {line:?}"),
    }
}

#[test]
fn mesh_writes_a_valid_obj() {
    // synth-257: hScale 10, so the map spans 0..=2560 world units on X and Z.
    let world = 2560.0;
    let dir = TempDir::new("mesh");
    for (i, (eye, yaw, pitch, budget)) in [
        ("1000,300,500", "30", "-20", 5000u32),
        ("1280,150,1280", "0", "-90", 20_000),
        ("100,600,2400", "135", "-10", 100),
        ("-500,800,-500", "45", "-25", 2),
    ]
    .into_iter()
    .enumerate()
    {
        let obj_path = dir.path(&format!("{i}.obj"));
        let budget_arg = budget.to_string();
        let args = [
            "mesh",
            "data/synth-257",
            "--eye",
            eye,
            "--yaw",
            yaw,
            "--pitch",
            pitch,
            "--fov",
            "60",
            "--width",
            "800",
            "--height",
            "600",
            "--budget",
            &budget_arg,
            "--obj",
            obj_path.to_str().expect("UTF-8 temp path"),
        ];
        let stdout = check(&args, 0, &[" triangles, error bound "]);
        let (n, bound) = parse_summary(&stdout);
        let obj = parse_obj(&fs::read_to_string(&obj_path).expect("the OBJ was written"));
        let ctx = format!("mesh {eye} yaw {yaw} pitch {pitch} budget {budget}");

        assert_eq!(obj.faces.len(), n, "{ctx}: faces vs summary");
        assert!(n >= 2 && n <= budget.max(2) as usize, "{ctx}: {n} faces");
        assert!(bound.is_finite() && bound >= 0.0, "{ctx}: bound {bound}");

        let nv = obj.vertices.len();
        let mut used = vec![false; nv];
        let mut edges: HashMap<(usize, usize), u32> = HashMap::new();
        let mut area = 0.0;
        for (k, f) in obj.faces.iter().enumerate() {
            for &i in f {
                assert!((1..=nv).contains(&i), "{ctx}: face {k} index {i} of {nv}");
                used[i - 1] = true;
            }
            let [a, b, c] = f.map(|i| obj.vertices[i - 1]);
            let (u, v) = (sub(b, a), sub(c, a));
            let normal = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            assert!(
                normal[1] > 0.0,
                "{ctx}: face {k} {f:?} normal {normal:?} does not point up"
            );
            area += normal[1] / 2.0; // the footprint's area on the XZ plane
            for (p, q) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
                *edges.entry((p.min(q), p.max(q))).or_default() += 1;
            }
        }
        assert!(used.iter().all(|&u| u), "{ctx}: unreferenced vertices");
        for v in &obj.vertices {
            assert!(
                (0.0..=world).contains(&v[0]) && (0.0..=world).contains(&v[2]),
                "{ctx}: vertex {v:?} off the map"
            );
        }
        // Faces cover the map once: areas add up, interior edges are shared by two faces,
        // border edges lie on the border, and Euler's formula for a disc ties the vertex
        // count to the face count: V = (F + B + 2) / 2.
        assert!(
            (area - world * world).abs() < 1e-6 * world * world,
            "{ctx}: footprint area {area}, map {}",
            world * world
        );
        let mut border = 0;
        for (&(p, q), &uses) in &edges {
            assert!(uses <= 2, "{ctx}: edge {p}-{q} used {uses} times");
            if uses == 1 {
                border += 1;
                let on_border = |a: usize, b: usize, axis: usize| {
                    let (s, t) = (obj.vertices[a - 1][axis], obj.vertices[b - 1][axis]);
                    s == t && (s == 0.0 || s == world)
                };
                assert!(
                    on_border(p, q, 0) || on_border(p, q, 2),
                    "{ctx}: open edge {p}-{q} inside the map"
                );
            }
        }
        assert_eq!(nv * 2, n + border + 2, "{ctx}: vertices vs faces");
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[test]
fn bench_json() {
    let keys = [
        "triangles",
        "frames",
        "tessellate_ns_per_triangle_median",
        "tessellate_ms_median",
        "variance_bytes_per_sample",
        "variance_build_ms",
        "screen_error_px_median",
        "screen_error_px_p99",
        "resident_bytes_per_sample",
        "vehicle_steps_per_second",
        "wire_bytes_per_triangle_first",
        "wire_bytes_per_triangle_steady",
        "encode_ns_per_triangle",
        "decode_ns_per_triangle",
    ];
    for (args, frames, budget) in [
        (
            vec!["bench", "data/synth-65", "--frames", "5", "--json"],
            5,
            65536,
        ),
        (
            vec![
                "bench",
                "data/synth-65",
                "--frames",
                "3",
                "--budget",
                "300",
                "--eye",
                "320,150,-100",
                "--yaw",
                "0",
                "--pitch",
                "-20",
                "--json",
            ],
            3,
            300,
        ),
    ] {
        let stdout = check(&args, 0, &keys);
        let lines: Vec<&str> = stdout.lines().filter(|l| !l.trim().is_empty()).collect();
        assert_eq!(lines.len(), 1, "{args:?}: one JSON line, got {stdout:?}");
        let report: serde_json::Value =
            serde_json::from_str(lines[0]).expect("bench --json prints valid JSON");
        let obj = report.as_object().expect("a JSON object");
        let num = |k: &str| {
            obj.get(k)
                .and_then(serde_json::Value::as_f64)
                .unwrap_or_else(|| panic!("{args:?}: {k} missing or not a number: {report}"))
        };
        for k in keys {
            let v = num(k);
            assert!(v.is_finite() && v >= 0.0, "{args:?}: {k} = {v}");
        }
        assert_eq!(num("frames"), f64::from(frames));
        let tris = num("triangles");
        assert!(tris >= 2.0 && tris <= f64::from(budget), "triangles {tris}");
        assert!(num("tessellate_ns_per_triangle_median") > 0.0);
        assert!(num("tessellate_ms_median") > 0.0);
        assert!(num("screen_error_px_p99") >= num("screen_error_px_median"));
        let vt = num("variance_bytes_per_sample");
        assert!(vt > 0.0 && vt <= 1.0, "variance {vt} bytes/sample");
        let resident = num("resident_bytes_per_sample");
        assert!(resident > vt && resident <= 3.0, "resident {resident}");
    }
    // Without --json: one `key  value` line per field.
    check(
        &["bench", "data/synth-65", "--frames", "2"],
        0,
        &["tessellate_ms_median", "resident_bytes_per_sample"],
    );
}

#[test]
fn serve_replay_refuses_what_it_cannot_watch() {
    let dir = TempDir::new("replay-state");
    let state = dir.str();
    let golden = "server/tests/golden/drive.rec";
    // The controls and following are for a replay.
    check(
        &["serve", "data/synth-65", "--control", "0123456789abcdef"],
        2,
        &["--replay"],
    );
    check(&["serve", "data/synth-65", "--follow"], 2, &["--replay"]);
    // Recorded on synth-65: another data set is refused, naming both hashes.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_roam-server"))
        .args([
            "serve",
            "data/synth-257",
            "--replay",
            golden,
            "--state-dir",
            state,
        ])
        .current_dir(root())
        .output()
        .expect("run roam-server");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains(&format!("watching {golden}")), "{stderr}");
    assert!(
        stderr.contains("the recording was made on another data set (its hash "),
        "{stderr}"
    );
    // A control token must be a good token.
    check(
        &[
            "serve",
            "data/synth-65",
            "--replay",
            golden,
            "--control",
            "short",
            "--state-dir",
            state,
        ],
        1,
        &["--control", "16"],
    );
}
