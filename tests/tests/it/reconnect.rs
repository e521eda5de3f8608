//! A driver whose path to the server drops, against a real server on loopback through the lossy relay
//! ([`Relay::cut`] black-holes its datagrams both ways, as a dropped Wi-Fi connection does): the
//! viewer finds the server silent (a short silence here, 10 s by default), reconnects by
//! itself presenting its ticket, and
//!
//! - back within the server's hold (5 s here, 30 s by default, counted from when the path
//!   fell silent), gets **its** vehicle back (`resumed`, the same id, where it had driven
//!   to), and its frames go on;
//! - back after the hold (the server has dropped the connection on its idle timeout, 10 s
//!   of silence, past the hold: the vehicle is freed at once and the snapshot shows it
//!   gone), comes back as a new driver with a new vehicle at the start.
//!
//! Nothing sleeps to wait: the tests wait on the session's status, the server's snapshots
//! and frames, each wait bounded (frames by count: a vehicle the keys no longer move fails
//! the test, never hangs it). The cut is held open only until the viewer (first test) or
//! the server (second) has seen it.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use roam_client::session::{KeySource, Patience, Session, State};
use roam_link::tls;
use roam_protocol::messages::VehicleView;
use roam_server::net::{Options, Server};
use roam_server::sim::world_core::Snapshot;
use roam_server::terrain::variance::VarianceTree;
use roam_tests::fixtures::flat;
use roam_tests::fixtures::{bounded, frame, status_when};
use roam_tests::relay::{Relay, RelayConfig};
use tokio::sync::watch;

use crate::turn;

/// The server's hold on a dropped driver's vehicle, from the path's silence: longer than
/// the viewer's 2 s of patience and its reconnection, shorter than the server's idle timeout.
const HOLD: Duration = Duration::from_secs(5);
/// The viewer's patience: silent for 2 s is lost; reconnect for a minute (longer than the
/// server's 10 s idle timeout and the hold, for the second test).
const PATIENCE: Patience = Patience {
    silence: Duration::from_secs(2),
    reconnect_for: Duration::from_secs(60),
};
/// Accelerate ahead for 1.5 s, then no keys: the vehicle coasts on, away from its start.
const DRIVE: &str = "150 U\n";

struct Running {
    server: Server,
    relay: Relay,
    fingerprint: [u8; 32],
    token: String,
}

async fn start() -> Running {
    let terrain = flat();
    let vt = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
    let identity = tls::generate().expect("a certificate");
    let token = "a-test-token-of-some-length".to_owned();
    let pyramid = roam_tests::fixtures::pyramid(&terrain, roam_protocol::tiles::DEFAULT_TILE);
    let server = Server::start(
        terrain,
        Arc::new(vt),
        pyramid,
        &identity,
        Options {
            hold: HOLD,
            ..Options::new("127.0.0.1:0".parse().expect("valid"), token.clone())
        },
    )
    .expect("listens");
    let relay = Relay::start(server.addr, RelayConfig::default())
        .await
        .expect("relays");
    Running {
        fingerprint: tls::parse_fingerprint(&identity.fingerprint()).expect("valid"),
        server,
        relay,
        token,
    }
}

/// A driver joined through the relay, playing [`DRIVE`].
async fn driver(r: &Running) -> Session {
    let hello = roam_tests::fixtures::driver_hello(&r.token);
    let script = roam_protocol::script::parse(DRIVE).expect("a valid script");
    let addr: SocketAddr = r.relay.addr();
    bounded(
        "joining",
        Session::join_with(
            addr,
            r.fingerprint,
            hello,
            KeySource::Script(script),
            PATIENCE,
        ),
    )
    .await
    .expect("joins")
}

/// Frames a wait on the vehicle may take: 10 s of frames at the driver's 60 a second (the
/// drive takes it 4 m from its start within about one).
const WITHIN: usize = 600;

/// The first frame showing vehicle `id` where `f` holds, within [`WITHIN`] frames (else a
/// panic naming `what`: a vehicle the keys no longer move fails, never waits).
async fn frame_where(
    s: &Session,
    id: u16,
    what: &str,
    f: impl Fn(&VehicleView) -> bool,
) -> VehicleView {
    for _ in 0..WITHIN {
        if let Some(v) = frame(s).await.vehicles.into_iter().find(|v| v.id == id)
            && f(&v)
        {
            return v;
        }
    }
    panic!("{what}: not within {WITHIN} frames");
}

/// The server's snapshot once `f` holds.
async fn snapshot_when(
    snaps: &mut watch::Receiver<Arc<Snapshot>>,
    what: &str,
    f: impl Fn(&Snapshot) -> bool,
) -> Arc<Snapshot> {
    bounded(what, snaps.wait_for(|s| f(s)))
        .await
        .expect("the world runs")
        .clone()
}

fn from(a: &VehicleView, b: &VehicleView) -> f64 {
    (a.x - b.x).hypot(a.z - b.z)
}

/// Drives away from the start, then cuts the path until the viewer finds the server
/// silent. The driver's vehicle, its start and where it had got to.
async fn drive_then_cut(r: &Running, s: &Session) -> (u16, VehicleView, VehicleView) {
    let id = s.vehicle();
    let start = frame_where(s, id, "the vehicle in the frames", |_| true).await;
    let away = frame_where(s, id, "the vehicle 4 m from its start", |v| {
        from(v, &start) > 4.0
    })
    .await;
    r.relay.cut();
    let lost = status_when(s, "the viewer finds the server silent", |st| {
        matches!(st.state, State::Reconnecting { .. })
    })
    .await;
    let State::Reconnecting { why, .. } = &lost.state else {
        unreachable!("waited for it");
    };
    assert!(why.contains("no frame or message"), "{why}");
    assert_eq!(lost.gaps.reconnects, 0);
    (id, start, away)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_driver_back_within_the_hold_gets_its_vehicle_back() {
    let _turn = turn().await;
    let r = start().await;
    let s = driver(&r).await;
    let welcome = s.welcome();
    assert!(
        welcome.ticket.is_some(),
        "the server gave the driver no ticket: {welcome:?}"
    );
    let (id, start, away) = drive_then_cut(&r, &s).await;
    r.relay.restore();
    let back = status_when(&s, "the viewer reconnects", |st| st.gaps.reconnects == 1).await;
    assert_eq!(back.state, State::Connected);
    assert!(back.welcome.resumed, "not resumed: {:?}", back.welcome);
    assert_eq!(back.welcome.vehicle, id, "the same vehicle");
    assert_eq!(back.gaps.resumed, 1);
    assert!(back.welcome.ticket.is_some(), "a ticket for the next time");
    // Its frames go on, with the vehicle where it had driven to, not back at the start.
    let v = frame_where(
        &s,
        id,
        "the vehicle in the frames after the reconnection",
        |_| true,
    )
    .await;
    assert!(
        from(&v, &start) >= from(&away, &start) - 1e-6,
        "the vehicle is back at {v:?}, it had got to {away:?} from {start:?}"
    );
    let snapshot = r.server.snapshot();
    assert_eq!(snapshot.vehicles.len(), 1, "one vehicle, held then resumed");
    // The gap lasted at least the silence that revealed it.
    let status = s.status();
    assert!(status.gaps.longest(std::time::Instant::now()) >= PATIENCE.silence);
    assert!(s.quit().await, "the server heard the goodbye");
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_driver_back_after_the_hold_gets_a_new_vehicle() {
    let _turn = turn().await;
    let r = start().await;
    let s = driver(&r).await;
    let mut snaps = r.server.watch();
    let (id, start, away) = drive_then_cut(&r, &s).await;
    // The server drops the connection (its idle timeout), holds the vehicle, then frees it.
    snapshot_when(&mut snaps, "the old vehicle leaves the world", |snap| {
        !snap.vehicles.iter().any(|v| v.id == id)
    })
    .await;
    r.relay.restore();
    let back = status_when(&s, "the viewer reconnects", |st| st.gaps.reconnects == 1).await;
    assert_eq!(back.state, State::Connected);
    assert!(!back.welcome.resumed, "resumed after the hold: {back:?}");
    assert_eq!(back.gaps.resumed, 0);
    let new = back.welcome.vehicle;
    assert_eq!(s.vehicle(), new);
    // A new vehicle at the start (the id may be the old one's, free again).
    let v = frame_where(&s, new, "the new vehicle in the frames", |_| true).await;
    assert!(
        from(&v, &start) < from(&away, &start),
        "the new vehicle is at {v:?}; the old one had got to {away:?} from {start:?}"
    );
    let snapshot = snapshot_when(&mut snaps, "the new vehicle in the world", |snap| {
        snap.vehicles.iter().any(|v| v.id == new)
    })
    .await;
    assert_eq!(snapshot.vehicles.len(), 1, "only the new vehicle");
    assert!(s.quit().await, "the server heard the goodbye");
    r.server.shutdown().await.expect("stops");
}
