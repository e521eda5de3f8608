//! The `roam-client` command line, run as a user would.

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the crate lives in the workspace")
        .to_path_buf()
}

fn run(args: &[&str]) -> (Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_roam-client"))
        .args(args)
        .current_dir(root())
        // No display: the windowed mode must say how to run headless.
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        // No token but the one given.
        .env_remove("ROAM_TOKEN")
        .output()
        .expect("run roam-client");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn help_and_usage_errors() {
    let (code, out, _) = run(&["--help"]);
    assert_eq!(code, Some(0));
    for flag in [
        "--connect",
        "--token",
        "--fingerprint",
        "--local",
        "--headless",
        "--inputs",
        "--frames",
        "--budget",
        "--viewers",
        "--stats",
        "--screenshot",
        "--size",
        "--no-fog",
        "--no-lighting",
        "--wireframe",
        "--no-water",
        "--no-vehicles",
    ] {
        assert!(out.contains(flag), "{flag} in --help");
    }
    let (code, _, err) = run(&["--headless", "--token", "t"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--connect"), "{err}");
    let (code, _, err) = run(&["--connect", "127.0.0.1:9", "--headless"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--fingerprint"), "{err}");
    // No token from any source: says where one may come from (not a usage error: the
    // environment is one of them).
    let fp = "00".repeat(32);
    let (code, _, err) = run(&[
        "--connect",
        "127.0.0.1:9",
        "--fingerprint",
        &fp,
        "--headless",
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("--token-file") && err.contains("ROAM_TOKEN"),
        "{err}"
    );
    let (code, _, err) = run(&[
        "--connect",
        "127.0.0.1:9",
        "--fingerprint",
        &fp,
        "--token-file",
        "/nonexistent/roam-token",
        "--headless",
    ]);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("/nonexistent/roam-token"), "{err}");
    // The window without a display: how to run headless instead.
    let (code, _, err) = run(&["--local", "data/synth-65"]);
    assert_eq!(code, Some(1));
    assert!(
        err.contains("no display") && err.contains("--headless --frames"),
        "{err}"
    );
    let (code, _, err) = run(&["--local", "data/synth-65", "--screenshot", "x.png"]);
    assert_eq!(code, Some(1));
    assert!(
        err.contains("--screenshot is for the headless viewer"),
        "{err}"
    );
    let (code, _, err) = run(&[
        "--connect",
        "127.0.0.1:9",
        "--token",
        "t",
        "--fingerprint",
        "12ab",
        "--headless",
    ]);
    assert_eq!(code, Some(1));
    assert!(err.contains("expected 64 hex digits"), "{err}");
}

#[test]
fn local_headless_run_writes_stats() {
    let stats = std::env::temp_dir().join(format!("roam-client-stats-{}.json", std::process::id()));
    let inputs =
        std::env::temp_dir().join(format!("roam-client-inputs-{}.txt", std::process::id()));
    std::fs::write(&inputs, "30 U\n20 UL\n").expect("write");
    // A copy: the server caches its colour tiles in the data set's `.cache`.
    let data = std::env::temp_dir().join(format!("roam-client-synth-65-{}", std::process::id()));
    std::fs::create_dir_all(&data).expect("a temporary directory");
    let source = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/synth-65");
    for name in ["map", "hf.pgm", "color.ppm"] {
        std::fs::copy(source.join(name), data.join(name)).expect("the bundled data set");
    }
    let (code, out, err) = run(&[
        "--local",
        data.to_str().expect("UTF-8"),
        "--headless",
        "--frames",
        "30",
        "--budget",
        "3000",
        "--inputs",
        inputs.to_str().expect("UTF-8"),
        "--stats",
        stats.to_str().expect("UTF-8"),
    ]);
    assert_eq!(code, Some(0), "{out}\n{err}");
    assert!(
        !out.contains("token") && !err.contains("token"),
        "nothing secret is printed"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).expect("stats")).expect("JSON");
    for key in [
        "frames",
        "frames_per_second",
        "wire_bytes_per_triangle_first",
        "wire_bytes_per_triangle_steady",
        "input_to_frame_ms_median",
        "input_to_frame_ms_p99",
        "decode_errors",
    ] {
        assert!(
            report
                .get(key)
                .and_then(serde_json::Value::as_f64)
                .is_some(),
            "{key}: {report}"
        );
    }
    assert_eq!(report["frames"], 30);
    assert_eq!(report["decode_errors"], 0);
    // synth-65: 64 cells, one colour tile, received before the first frame.
    assert_eq!(report["color_tiles"], 1, "{report}");
    assert_eq!(report["color_capacity"], 1, "{report}");
    let color_bytes = report["color_bytes"].as_u64().unwrap_or(0);
    assert!(
        color_bytes > 16 && color_bytes <= 64 * 64 * 3 + (64 << 10),
        "{report}"
    );
    let _ = std::fs::remove_file(stats);
    let _ = std::fs::remove_file(inputs);
    let _ = std::fs::remove_dir_all(data);
}
