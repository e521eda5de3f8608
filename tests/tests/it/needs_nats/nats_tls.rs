//! TLS to NATS: a real `nats-server` with TLS whose certificate (for 127.0.0.1) is signed
//! by a CA made here, so no system trusts it. Given that CA (`BusOptions::ca`,
//! `--nats-ca`), a world and an edge reach each other through it; without it, or with
//! another CA, the first connection fails at once saying TLS, the URL and `--nats-ca`.

use std::path::{Path, PathBuf};
use std::time::Duration;

use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
use roam_server::net::bus::edge::Remote;
use roam_server::net::bus::world::{WorldOptions, WorldServer};
use roam_server::net::bus::{BusError, BusOptions};
use roam_tests::fixtures::flat;
use roam_tests::nats::Nats;

/// More than a refusal on loopback takes, far less than a retry loop would run.
const PROMPT: Duration = Duration::from_secs(10);

/// A CA (`ca.pem`) in a temp dir of its own, and NATS's certificate for 127.0.0.1 signed
/// by it (`nats.pem`, `nats-key.pem`); a second, unrelated CA (`other-ca.pem`).
struct Pki {
    dir: PathBuf,
}

impl Pki {
    fn make(name: &str) -> Pki {
        let dir = std::env::temp_dir().join(format!("roam-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("temp dir");
        let ca = ca("roam test CA");
        let key = KeyPair::generate().expect("a key");
        let cert = CertificateParams::new(vec!["127.0.0.1".to_string()])
            .expect("an IP address is a valid name")
            .signed_by(&key, &ca)
            .expect("the CA signs");
        let write = |file: &str, pem: String| std::fs::write(dir.join(file), pem).expect("written");
        write("ca.pem", ca.pem());
        write("nats.pem", cert.pem());
        write("nats-key.pem", key.serialize_pem());
        write("other-ca.pem", self::ca("another CA").pem());
        Pki { dir }
    }

    fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

impl Drop for Pki {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn ca(name: &str) -> CertifiedIssuer<'static, KeyPair> {
    let mut params = CertificateParams::new(Vec::<String>::new()).expect("no names is valid");
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, name);
    CertifiedIssuer::self_signed(params, KeyPair::generate().expect("a key")).expect("self-signs")
}

fn bus(url: String, ca: Option<&Path>) -> BusOptions {
    BusOptions {
        url,
        world: "tls".into(),
        creds: None,
        ca: ca.map(Path::to_owned),
        name: "roam-test".into(),
        secret: Some(roam_tests::nats::test_secret("tls")),
    }
}

/// The first connection's error, within [`PROMPT`].
async fn refused(bus: &BusOptions) -> BusError {
    tokio::time::timeout(PROMPT, bus.connect())
        .await
        .unwrap_or_else(|_| panic!("{}: no answer within {PROMPT:?}", bus.url))
        .err()
        .unwrap_or_else(|| panic!("{}: connected", bus.url))
}

fn assert_tls_refusal(err: &BusError, url: &str) {
    assert!(matches!(err, BusError::Tls { .. }), "{err}");
    let text = err.to_string();
    for part in ["TLS", url, "--nats-ca"] {
        assert!(text.contains(part), "{text} names {part}");
    }
}

/// With the CA, a world starts over `tls://`, an edge reaches it and joins a vehicle, and
/// the world ticks with it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_world_and_an_edge_meet_over_tls_with_the_ca_given() {
    let pki = Pki::make("nats-tls-world");
    let nats = Nats::with_tls(&pki.file("nats.pem"), &pki.file("nats-key.pem"));
    let bus = bus(nats.tls_url(), Some(&pki.file("ca.pem")));
    let terrain = flat();
    let options = WorldOptions {
        record: None,
        hold: Duration::from_secs(30),
        max_vehicles: 8,
        replay: None,
    };
    let world = tokio::time::timeout(
        PROMPT,
        WorldServer::start(terrain.clone(), terrain.content_hash(), options, &bus),
    )
    .await
    .expect("the world starts promptly")
    .expect("the world reaches NATS over TLS");
    let remote = Remote::connect(&bus, terrain.content_hash(), "d", vec![], PROMPT)
        .await
        .expect("the edge reaches the world over TLS");
    let (vehicle, _, _) = remote.join().await.expect("a vehicle joins");
    let mut snaps = world.watch();
    tokio::time::timeout(
        PROMPT,
        snaps.wait_for(|s| s.tick > 0 && s.vehicles.iter().any(|v| v.id == vehicle)),
    )
    .await
    .expect("the world ticks with the vehicle")
    .expect("the world runs");
    world.shutdown().await.expect("the world stops");
}

/// Without the CA (the system's CAs do not know it) or with another CA, `tls://` fails at
/// once, saying TLS, the URL and `--nats-ca`. A `nats://` URL to this server is upgraded
/// to TLS (the server asks for it), so it works with the CA and fails alike without.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_untrusted_certificate_is_said_at_once_and_nats_urls_are_upgraded() {
    let pki = Pki::make("nats-tls-refused");
    let nats = Nats::with_tls(&pki.file("nats.pem"), &pki.file("nats-key.pem"));
    for url in [nats.tls_url(), nats.url()] {
        assert_tls_refusal(&refused(&bus(url.clone(), None)).await, &url);
        let other = bus(url.clone(), Some(&pki.file("other-ca.pem")));
        assert_tls_refusal(&refused(&other).await, &url);
    }
    let plain = bus(nats.url(), Some(&pki.file("ca.pem")));
    let client = tokio::time::timeout(PROMPT, plain.connect())
        .await
        .expect("promptly")
        .expect("nats:// to a TLS server is upgraded with the CA given");
    client.flush().await.expect("the connection works");
}

/// A CA file that is missing, or holds no certificate, is said naming the file before
/// any connection is tried.
#[tokio::test]
async fn a_ca_file_that_is_missing_or_holds_no_certificate_is_named() {
    let pki = Pki::make("nats-tls-files");
    for file in [pki.file("missing.pem"), pki.file("nats-key.pem")] {
        // Nothing listens there: the file is judged first.
        let err = refused(&bus("tls://127.0.0.1:9".into(), Some(&file))).await;
        assert!(matches!(err, BusError::Ca { .. }), "{err}");
        assert!(
            err.to_string().contains(&file.display().to_string()),
            "{err}"
        );
    }
}
