//! An identity given in files (`tls::load_files`, what `serve --cert F --key F` loads): the
//! state directory's own `cert.der` and `key.der`, and the same pair as PEM, load with the
//! fingerprint of their certificate; a key that is not the certificate's, a missing file,
//! and files that are not a certificate or a PKCS#8 key are errors naming the file.

use std::path::{Path, PathBuf};

use roam_link::tls::{self, Identity};

/// A directory of its own for one test under the system's temporary directory, removed
/// when the test ends.
struct Workspace {
    root: PathBuf,
}

impl Drop for Workspace {
    fn drop(&mut self) {
        let _best_effort = std::fs::remove_dir_all(&self.root);
    }
}

fn workspace(test: &str) -> Workspace {
    let root = std::env::temp_dir().join(format!("roam-link-files-{}-{test}", std::process::id()));
    let _stale = std::fs::remove_dir_all(&root);
    std::fs::create_dir_all(&root).expect("the temporary directory is writable");
    Workspace { root }
}

/// A fresh identity made in the state directory `name` inside `ws`: its `cert.der` and
/// `key.der` paths and its fingerprint.
fn made(ws: &Workspace, name: &str) -> (PathBuf, PathBuf, String) {
    let dir = ws.root.join(name);
    let fingerprint = tls::load_or_create(&dir)
        .expect("a fresh identity")
        .fingerprint();
    (dir.join("cert.der"), dir.join("key.der"), fingerprint)
}

/// `der` as a PEM section labelled `label` (base64 in lines of 64).
fn pem(label: &str, der: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut base64 = String::new();
    for chunk in der.chunks(3) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &b)| n | u32::from(b) << (16 - 8 * i));
        for i in 0..4 {
            base64.push(if i <= chunk.len() {
                char::from(ALPHABET[(n >> (18 - 6 * i) & 63) as usize])
            } else {
                '='
            });
        }
    }
    let mut out = format!("-----BEGIN {label}-----\n");
    for line in base64.as_bytes().chunks(64) {
        out.push_str(std::str::from_utf8(line).expect("base64 is ASCII"));
        out.push('\n');
    }
    out + &format!("-----END {label}-----\n")
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).expect("written by the test")
}

fn loaded(cert: &Path, key: &Path) -> Identity {
    tls::load_files(cert, key)
        .unwrap_or_else(|e| panic!("{} with {}: {e}", cert.display(), key.display()))
}

fn refused(cert: &Path, key: &Path) -> String {
    match tls::load_files(cert, key) {
        Ok(id) => panic!("expected an error, got an identity {}", id.fingerprint()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn der_and_pem_files_load_with_their_certificates_fingerprint() {
    let ws = workspace("formats");
    let (cert_der, key_der, fingerprint) = made(&ws, "state");
    let (other_cert, _, _) = made(&ws, "other");
    // PEM as openssl writes it, with text before the section; the certificate file holds a
    // second certificate after the first (a chain), which is not the one used.
    let cert_pem = ws.root.join("cert.pem");
    let key_pem = ws.root.join("key.pem");
    let chain = format!(
        "subject=CN = roam\n{}{}",
        pem("CERTIFICATE", &read(&cert_der)),
        pem("CERTIFICATE", &read(&other_cert))
    );
    std::fs::write(&cert_pem, chain).expect("writable");
    std::fs::write(&key_pem, pem("PRIVATE KEY", &read(&key_der))).expect("writable");
    for (cert, key) in [
        (&cert_der, &key_der),
        (&cert_pem, &key_pem),
        (&cert_pem, &key_der),
        (&cert_der, &key_pem),
    ] {
        let id = loaded(cert, key);
        assert_eq!(id.fingerprint(), fingerprint, "{}", cert.display());
        tls::server_config(&id).expect("the pair makes a server configuration");
    }
    // Loading wrote nothing beside the files.
    assert!(!ws.root.join("state").join(".cert.der.new").exists());
}

#[test]
fn a_key_of_another_identity_is_refused() {
    let ws = workspace("mismatch");
    let (cert, _, _) = made(&ws, "one");
    let (_, key, _) = made(&ws, "two");
    let text = refused(&cert, &key);
    assert!(
        text.contains(&key.display().to_string())
            && text.contains("the key does not match the certificate")
            && text.contains(&cert.display().to_string()),
        "{text}"
    );
}

#[test]
fn missing_and_garbage_files_are_errors_naming_them() {
    let ws = workspace("garbage");
    let (cert, key, _) = made(&ws, "state");
    let file = |name: &str, bytes: &[u8]| {
        let path = ws.root.join(name);
        std::fs::write(&path, bytes).expect("writable");
        path
    };
    let missing = ws.root.join("missing.pem");
    let garbage = file("garbage", b"\x30\x03garbage, not DER");
    let oversized = file("oversized", &vec![b'A'; 65 << 10]);
    let cert_pem = file("cert.pem", pem("CERTIFICATE", &read(&cert)).as_bytes());
    let rsa_key = file("rsa.pem", pem("RSA PRIVATE KEY", &read(&key)).as_bytes());
    let unended = file("unended.pem", b"-----BEGIN CERTIFICATE-----\nMIIB\n");
    // (the certificate file, the key file, the file the error names, words it says)
    let cases: [(&Path, &Path, &Path, &str); 8] = [
        (&missing, &key, &missing, "No such file"),
        (&cert, &missing, &missing, "No such file"),
        (
            &garbage,
            &key,
            &garbage,
            "not a certificate (X.509, DER or PEM)",
        ),
        (
            &cert,
            &garbage,
            &garbage,
            "not a private key (PKCS#8, DER or PEM)",
        ),
        (&oversized, &key, &oversized, "over 65536 bytes"),
        // A key file given as the certificate, a certificate as the key.
        (&rsa_key, &key, &rsa_key, "no `-----BEGIN CERTIFICATE-----`"),
        (&cert, &cert_pem, &cert_pem, "no PKCS#8 private key"),
        (&unended, &key, &unended, "PEM that does not decode"),
    ];
    for (i, (cert, key, named, says)) in cases.into_iter().enumerate() {
        let text = refused(cert, key);
        assert!(
            text.contains(&named.display().to_string()) && text.contains(says),
            "case {i}: {text}"
        );
    }
    // An RSA (PKCS#1) PEM key is pointed at the conversion.
    let text = refused(&cert, &rsa_key);
    assert!(text.contains("openssl pkcs8 -topk8 -nocrypt"), "{text}");
}
