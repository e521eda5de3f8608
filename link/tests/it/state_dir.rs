//! The state directory (`tls::load_or_create`, `tls::rotate`) on a real file system: the
//! modes it makes and tightens, the half or broken identities it refuses without writing
//! anything, the atomic writes (no temporary file left behind), and what it does with the
//! files an interrupted write leaves. Each test works in its own directory under the
//! system's temporary directory. Unix only: modes are the point.
#![cfg(unix)]

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

use roam_link::tls::{self, TlsError};

/// A fresh directory for one test, removed when the test ends.
struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Scratch {
        let path =
            std::env::temp_dir().join(format!("roam-link-state-{}-{name}", std::process::id()));
        let _absent = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).expect("the temporary directory is writable");
        Scratch(path)
    }

    /// A state directory inside the scratch one, made with `mode` (or not made, if `None`).
    fn state(&self, mode: Option<u32>) -> PathBuf {
        let dir = self.0.join("roam-state");
        if let Some(mode) = mode {
            std::fs::create_dir(&dir).expect("a new directory");
            chmod(&dir, mode);
        }
        dir
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _best_effort = std::fs::remove_dir_all(&self.0);
    }
}

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path)
        .expect("the file exists")
        .permissions()
        .mode()
        & 0o777
}

fn chmod(path: &Path, mode: u32) {
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).expect("our own file");
}

/// The names in `dir`, sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut out: Vec<String> = std::fs::read_dir(dir)
        .expect("a readable directory")
        .map(|e| {
            e.expect("a readable entry")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    out.sort();
    out
}

/// The identity files of a fresh identity: (certificate, key) bytes and its fingerprint.
fn other_identity(scratch: &Scratch) -> (Vec<u8>, Vec<u8>, String) {
    let dir = scratch.0.join("other");
    let fingerprint = tls::load_or_create(&dir)
        .expect("a fresh identity")
        .fingerprint();
    let read = |name: &str| std::fs::read(dir.join(name)).expect("just written");
    (read("cert.der"), read("key.der"), fingerprint)
}

fn error_text(dir: &Path) -> String {
    match tls::load_or_create(dir) {
        Ok(id) => panic!("expected an error, got an identity {}", id.fingerprint()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn a_fresh_state_dir_is_private_and_the_identity_round_trips() {
    let scratch = Scratch::new("fresh");
    // Nested: every directory made on the way is private too.
    let dir = scratch.0.join("a").join("roam-state");
    let made = tls::load_or_create(&dir).expect("a fresh identity");
    assert_eq!(mode(&dir), 0o700);
    assert_eq!(mode(&scratch.0.join("a")), 0o700);
    assert_eq!(mode(&dir.join("key.der")), 0o600);
    assert_eq!(mode(&dir.join("cert.der")), 0o644);
    assert_eq!(
        names(&dir),
        ["cert.der", "key.der"],
        "no temporary file left"
    );
    let loaded = tls::load_or_create(&dir).expect("the saved identity");
    assert_eq!(loaded.fingerprint(), made.fingerprint());
    assert_eq!(names(&dir), ["cert.der", "key.der"]);
    // The pair serves.
    tls::server_config(&loaded).expect("the saved pair makes a server configuration");
}

#[test]
fn a_state_dir_and_key_others_can_read_are_tightened() {
    let scratch = Scratch::new("loose");
    let dir = scratch.state(None);
    let made = tls::load_or_create(&dir).expect("a fresh identity");
    // What earlier versions left: a 0755 directory and a 0644 key.
    chmod(&dir, 0o755);
    chmod(&dir.join("key.der"), 0o644);
    let loaded = tls::load_or_create(&dir).expect("a loose identity is tightened, not refused");
    assert_eq!(loaded.fingerprint(), made.fingerprint());
    assert_eq!(mode(&dir), 0o700);
    assert_eq!(mode(&dir.join("key.der")), 0o600);
    assert_eq!(
        mode(&dir.join("cert.der")),
        0o644,
        "the certificate is public"
    );
}

#[test]
fn a_state_dir_others_can_write_is_refused_untouched() {
    for loose in [0o777, 0o770, 0o1777, 0o702] {
        let scratch = Scratch::new(&format!("shared-{loose:o}"));
        let dir = scratch.state(Some(loose));
        let err = tls::load_or_create(&dir).err().expect("refused");
        assert!(
            matches!(err, TlsError::SharedDir { .. }),
            "{loose:o}: {err}"
        );
        let text = err.to_string();
        assert!(
            text.contains(&dir.display().to_string()) && text.contains("chmod 700"),
            "{loose:o}: {text}"
        );
        assert!(names(&dir).is_empty(), "{loose:o}: nothing written");
        assert_eq!(
            std::fs::metadata(&dir)
                .expect("still there")
                .permissions()
                .mode()
                & 0o1777,
            loose,
            "mode left alone"
        );
        assert!(tls::rotate(&dir).is_err(), "{loose:o}: rotate refuses too");
    }
}

#[test]
fn one_file_without_the_other_is_an_error_naming_both() {
    let scratch = Scratch::new("half");
    let (cert, key, fingerprint) = other_identity(&scratch);
    // (the file there, its bytes, the file missing, what the message restores)
    let cases = [
        ("cert.der", &cert, "key.der", "restore the key"),
        ("key.der", &key, "cert.der", "restore the certificate"),
    ];
    for (present, bytes, missing, restore) in cases {
        let dir = scratch.0.join(present);
        std::fs::create_dir(&dir).expect("a new directory");
        chmod(&dir, 0o700);
        std::fs::write(dir.join(present), bytes).expect("a writable directory");
        chmod(&dir.join(present), 0o600);
        let text = error_text(&dir);
        let (present_path, missing_path) = (dir.join(present), dir.join(missing));
        let says = format!(
            "{} exists but {} does not: {restore}, or remove {} to make a new identity",
            present_path.display(),
            missing_path.display(),
            present_path.display()
        );
        assert!(text.contains(&says), "{present}: {text}");
        // Only a certificate tells which fingerprint the viewers pinned.
        assert_eq!(text.contains(&fingerprint), present == "cert.der", "{text}");
        assert_eq!(names(&dir), [present], "nothing made");
        assert_eq!(&std::fs::read(&present_path).expect("still there"), bytes);
    }
}

#[test]
fn files_that_do_not_parse_or_do_not_pair_are_errors_naming_them() {
    let scratch = Scratch::new("broken");
    let (cert, key, _) = other_identity(&scratch);
    let (other_cert, _, other_fingerprint) = {
        let again = Scratch::new("broken-other");
        other_identity(&again)
    };
    let oversized = vec![0u8; 65 << 10];
    // (what cert.der holds, what key.der holds, the file the error names, words it says)
    let cases: [(&[u8], &[u8], &str, &str); 5] = [
        (&cert, b"not a key", "key.der", "not a private key"),
        (b"not a certificate", &key, "cert.der", "not a certificate"),
        (&cert, &oversized, "key.der", "over 65536 bytes"),
        (&other_cert, &key, "key.der", "is not the key of"),
        (&cert, &[], "key.der", "not a private key"),
    ];
    for (i, (cert_bytes, key_bytes, named, says)) in cases.into_iter().enumerate() {
        let dir = scratch.0.join(format!("case-{i}"));
        std::fs::create_dir(&dir).expect("a new directory");
        chmod(&dir, 0o700);
        std::fs::write(dir.join("cert.der"), cert_bytes).expect("writable");
        std::fs::write(dir.join("key.der"), key_bytes).expect("writable");
        chmod(&dir.join("key.der"), 0o600);
        let text = error_text(&dir);
        assert!(
            text.contains(&dir.join(named).display().to_string()) && text.contains(says),
            "case {i}: {text}"
        );
        assert_eq!(
            names(&dir),
            ["cert.der", "key.der"],
            "case {i}: nothing made"
        );
        assert_eq!(std::fs::read(dir.join("key.der")).expect("kept"), key_bytes);
        assert_eq!(
            std::fs::read(dir.join("cert.der")).expect("kept"),
            cert_bytes
        );
    }
    // The mismatch names the fingerprint the viewers pinned (the certificate's).
    let text = error_text(&scratch.0.join("case-3"));
    assert!(text.contains(&other_fingerprint), "{text}");
}

#[test]
fn rotate_replaces_the_identity_and_reports_both_fingerprints() {
    let scratch = Scratch::new("rotate");
    let dir = scratch.state(None);
    let first = tls::rotate(&dir).expect("rotating nothing makes an identity");
    assert!(first.old.is_none());
    assert_eq!(names(&dir), ["cert.der", "key.der"]);
    let second = tls::rotate(&dir).expect("a rotation");
    assert_eq!(
        second.old.as_deref(),
        Some(first.new.fingerprint().as_str())
    );
    assert_ne!(second.new.fingerprint(), first.new.fingerprint());
    assert_eq!(
        names(&dir),
        ["cert.der", "key.der"],
        "no temporary file left"
    );
    assert_eq!(mode(&dir.join("key.der")), 0o600);
    let loaded = tls::load_or_create(&dir).expect("the new identity");
    assert_eq!(loaded.fingerprint(), second.new.fingerprint());
    // A half identity is what rotating is for.
    std::fs::remove_file(dir.join("key.der")).expect("there");
    let third = tls::rotate(&dir).expect("rotating a half identity");
    assert_eq!(
        third.old.as_deref(),
        Some(second.new.fingerprint().as_str())
    );
    assert_eq!(
        tls::load_or_create(&dir)
            .expect("whole again")
            .fingerprint(),
        third.new.fingerprint()
    );
}

#[test]
fn an_interrupted_write_is_finished_or_undone_at_the_next_start() {
    let scratch = Scratch::new("interrupted");
    let dir = scratch.state(None);
    let old = tls::load_or_create(&dir)
        .expect("a fresh identity")
        .fingerprint();
    let (new_cert, new_key, new) = other_identity(&scratch);
    let put = |name: &str, bytes: &[u8]| {
        std::fs::write(dir.join(name), bytes).expect("writable");
        chmod(&dir.join(name), 0o600);
    };

    // Before the first rename, the certificate half written: the old identity stands.
    put(".key.der.new", &new_key);
    put(".cert.der.new", &new_cert[..new_cert.len() / 2]);
    let loaded = tls::load_or_create(&dir).expect("the old identity");
    assert_eq!(loaded.fingerprint(), old);
    assert_eq!(names(&dir), ["cert.der", "key.der"]);

    // The key half written, no certificate yet: likewise.
    put(".key.der.new", &new_key[..new_key.len() / 2]);
    assert_eq!(tls::load_or_create(&dir).expect("old").fingerprint(), old);
    assert_eq!(names(&dir), ["cert.der", "key.der"]);

    // Between the renames: the new key in place beside the old certificate.
    put("key.der", &new_key);
    put(".cert.der.new", &new_cert);
    let loaded = tls::load_or_create(&dir).expect("the change finished");
    assert_eq!(loaded.fingerprint(), new);
    assert_eq!(names(&dir), ["cert.der", "key.der"]);
    assert_eq!(
        std::fs::read(dir.join("cert.der")).expect("there"),
        new_cert
    );
}
