//! `roam-server serve` and its recording: a size cap outside what `replay` reads is refused
//! at start, and a server names the file it records to, a new one in the record directory
//! that never overwrites another.

use crate::common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

use common::{TempDir, check, root};

#[test]
fn a_size_cap_replay_could_not_read_is_refused_at_start() {
    for (bytes, says) in [
        ("1000", "65536..=268435456"),
        ("65535", "65536..=268435456"),
        ("268435457", "65536..=268435456"),
        ("lots", "invalid digit"),
    ] {
        check(
            &[
                "serve",
                "data/synth-65",
                "--listen",
                "127.0.0.1:0",
                "--record-max-bytes",
                bytes,
            ],
            2,
            &["--record-max-bytes", says],
        );
    }
}

/// Starts `serve` recording into `dir` and returns the file it says it records to, then
/// stops it.
fn recording_to(state: &TempDir, records: &TempDir) -> String {
    let mut child = Command::new(env!("CARGO_BIN_EXE_roam-server"))
        .args([
            "serve",
            "data/synth-65",
            "--listen",
            "127.0.0.1:0",
            "--state-dir",
            state.str(),
            "--record-dir",
            records.str(),
            "--record-max-bytes",
            "65536",
        ])
        .current_dir(root())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("run roam-server");
    let stdout = child.stdout.take().expect("piped");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(file) = line.strip_prefix("recording to ") {
                let _ = tx.send(file.to_owned());
                return;
            }
        }
    });
    let file = rx.recv_timeout(Duration::from_secs(60));
    child.kill().expect("stop the server");
    child.wait().expect("the server ends");
    file.expect("serve says where it records")
}

#[test]
fn serve_names_a_new_recording_file_each_start() {
    let state = TempDir::new("serve-state");
    let records = TempDir::new("serve-records");
    let first = recording_to(&state, &records);
    let second = recording_to(&state, &records);
    for file in [&first, &second] {
        let name = std::path::Path::new(file)
            .file_name()
            .and_then(|n| n.to_str())
            .expect("a file name");
        assert!(
            name.starts_with("session-")
                && name.ends_with(".rec")
                && file.starts_with(records.str()),
            "{file}"
        );
        // The server was killed: its file ends at a whole record, and replays.
        check(
            &["replay", file, "--data", "data/synth-65"],
            0,
            &["checkpoints matched", "no end record"],
        );
    }
    assert_ne!(first, second, "two starts, two files");
}
