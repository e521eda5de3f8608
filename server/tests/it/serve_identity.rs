//! `roam-server serve --cert F --key F`: the server's identity from files, not the state
//! directory's: the fingerprint it prints is that certificate's, and the state directory
//! gets no identity of its own. The flags go together, and files that are not an identity
//! are refused before the data set is loaded.

use crate::common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use common::{TempDir, check, root};

/// How long a server may take to say its fingerprint (it loads `data/synth-65` first).
const START: Duration = Duration::from_secs(60);

/// Stops the server however the test ends.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _already_gone = self.0.kill();
        let _reaped = self.0.wait();
    }
}

/// The line of `server`'s stdout that starts with `prefix`, less the prefix, waiting at most
/// [`START`].
fn said(server: &mut Running, prefix: &'static str) -> Option<String> {
    let stdout = server.0.stdout.take()?;
    let (found, said) = mpsc::channel();
    std::thread::spawn(move || {
        let line = BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
            .find_map(|line| line.strip_prefix(prefix).map(str::to_owned));
        let _test_gone = found.send(line);
    });
    said.recv_timeout(START).ok().flatten()
}

#[test]
fn serve_with_cert_and_key_prints_that_certificates_fingerprint() {
    let given = TempDir::new("identity-given");
    let made = given.path("made");
    let fingerprint = roam_link::tls::load_or_create(&made)
        .expect("an identity to give")
        .fingerprint();
    let (cert, key) = (made.join("cert.der"), made.join("key.der"));
    let state = TempDir::new("identity-state");
    let child = Command::new(env!("CARGO_BIN_EXE_roam-server"))
        .args(["serve", "data/synth-65", "--listen", "127.0.0.1:0"])
        .arg("--state-dir")
        .arg(state.path("state"))
        .arg("--cert")
        .arg(&cert)
        .arg("--key")
        .arg(&key)
        .current_dir(root())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("run roam-server");
    let mut server = Running(child);
    let printed = said(&mut server, "fingerprint ");
    drop(server);
    assert_eq!(printed.as_deref(), Some(fingerprint.as_str()));
    assert!(
        !state.path("state").join("cert.der").exists(),
        "the state directory got an identity of its own"
    );
}

#[test]
fn cert_without_key_and_files_that_are_not_an_identity_are_refused() {
    let dir = TempDir::new("identity-refused");
    let made = dir.path("made");
    roam_link::tls::load_or_create(&made).expect("an identity");
    let key = made.join("key.der");
    let key = key.to_str().expect("UTF-8 temp path");
    let garbage = dir.path("garbage.pem");
    std::fs::write(&garbage, "not a certificate").expect("writable");
    let garbage = garbage.to_str().expect("UTF-8 temp path");
    let serve = ["serve", "data/synth-65", "--listen", "127.0.0.1:0"];
    check(&[&serve[..], &["--cert", garbage]].concat(), 2, &["--key"]);
    check(&[&serve[..], &["--key", key]].concat(), 2, &["--cert"]);
    check(
        &[
            &serve[..],
            &["--state-dir", dir.str(), "--cert", garbage, "--key", key],
        ]
        .concat(),
        1,
        &[garbage, "not a certificate (X.509, DER or PEM)"],
    );
}
