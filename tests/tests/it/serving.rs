//! The serving path's rules, against a real server on loopback with raw QUIC viewers: a
//! viewer that sends a malformed or oversized control message after its welcome is closed
//! with the protocol code (and its vehicle freed), while a control stream that merely
//! ends leaves the end to the connection (frames go on; a lost connection is held); and
//! drivers joining at once at the viewer limit free distinct held vehicles, so held ones
//! never take the world past the limit.
//!
//! Bounds are counts (frames received, the world's ticks), with a generous timeout only
//! so a regression fails rather than hangs.

use std::time::Duration;

use roam_link::wire;
use roam_protocol::messages::{self, ClientMessage, Hello, Role, ServerMessage, Welcome, close};
use roam_tests::fixtures::{self, Running, flat};

/// A hang guard only: every wait below ends on a count long before it.
const HANG: Duration = Duration::from_secs(60);

fn driver(r: &Running) -> Hello {
    fixtures::hello(Role::Driver, &r.token, [640, 360], messages::MIN_BUDGET, 60)
}

/// A raw viewer past its welcome, its control stream kept.
struct Raw {
    _endpoint: quinn::Endpoint,
    conn: quinn::Connection,
    send: quinn::SendStream,
    _recv: quinn::RecvStream,
    welcome: Welcome,
}

async fn join(r: &Running) -> Raw {
    let (endpoint, conn) = roam_client::quic::connect(r.server.addr, r.fingerprint)
        .await
        .expect("connects");
    let (mut send, mut recv) = conn.open_bi().await.expect("a control stream");
    wire::write(&mut send, &ClientMessage::Hello(driver(r)))
        .await
        .expect("the hello goes");
    let answer = wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE)
        .await
        .expect("an answer");
    let ServerMessage::Welcome(welcome) = answer else {
        panic!("expected a welcome, got {answer:?}");
    };
    Raw {
        _endpoint: endpoint,
        conn,
        send,
        _recv: recv,
        welcome,
    }
}

/// Frame datagrams at most while waiting for a close: 5 s of frames at 60 a second.
const FRAMES_BEFORE_CLOSE: usize = 300;

/// How the connection ended, or `None` if `FRAMES_BEFORE_CLOSE` frames came first.
async fn closed_within_frames(conn: &quinn::Connection) -> Option<quinn::ConnectionError> {
    let count = async {
        for _ in 0..FRAMES_BEFORE_CLOSE {
            if conn.read_datagram().await.is_err() {
                break;
            }
        }
    };
    let ended = tokio::time::timeout(HANG, async {
        tokio::select! {
            biased;
            e = conn.closed() => Some(e),
            () = count => conn.close_reason(),
        }
    });
    ended.await.expect("closed or served within the hang guard")
}

/// Sends `bytes` raw on the control stream after the welcome, and checks the server closes
/// the connection with the protocol code and frees the vehicle (no hold).
async fn broken_control_closes(bytes: &[u8]) {
    let r = fixtures::serve(flat(), |o| o);
    let mut v = join(&r).await;
    let vehicle = v.welcome.vehicle;
    v.send.write_all(bytes).await.expect("written");
    match closed_within_frames(&v.conn).await {
        Some(quinn::ConnectionError::ApplicationClosed(c)) => {
            assert_eq!(
                c.error_code,
                close::PROTOCOL.into(),
                "closed with {c:?}, expected the protocol code"
            );
        }
        other => panic!(
            "{FRAMES_BEFORE_CLOSE} frames after a broken control message, and the \
             connection {other:?}: expected a close with the protocol code"
        ),
    }
    // Not a lost connection: its vehicle goes, not held.
    let mut world = r.server.watch();
    let gone = tokio::time::timeout(
        HANG,
        world.wait_for(|s| s.vehicles.iter().all(|x| x.id != vehicle)),
    )
    .await
    .expect("the vehicle goes")
    .expect("the world runs")
    .clone();
    assert!(!gone.held.contains(&vehicle), "{:?}", gone.held);
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_control_message_closes_with_the_protocol_code() {
    // Four bytes that are no client message (a variant past the last).
    broken_control_closes(&[4, 0, 0, 0, 0xff, 0xff, 0xff, 0xff]).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_control_message_closes_with_the_protocol_code() {
    let len = u32::try_from(roam_server::net::MAX_CONTROL + 1).expect("small");
    let mut bytes = len.to_le_bytes().to_vec();
    bytes.extend([0u8; 64]);
    broken_control_closes(&bytes).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_control_stream_leaves_the_end_to_the_connection() {
    let r = fixtures::serve(flat(), |o| o);
    let mut v = join(&r).await;
    let vehicle = v.welcome.vehicle;
    v.send.finish().expect("finishes");
    // Frames go on: the stream's end is not a goodbye.
    for k in 0..60 {
        let got = tokio::time::timeout(HANG, v.conn.read_datagram()).await;
        assert!(
            matches!(got, Ok(Ok(_))),
            "frame {k} after the control stream finished: {got:?}"
        );
    }
    assert!(v.conn.close_reason().is_none());
    // Then the connection is lost (any code but the goodbye's): the vehicle is held.
    v.conn.close(0u32.into(), b"lost");
    let mut world = r.server.watch();
    tokio::time::timeout(HANG, world.wait_for(|s| s.held.contains(&vehicle)))
        .await
        .expect("held")
        .expect("the world runs");
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn joins_at_once_at_the_limit_free_distinct_held_vehicles() {
    const LIMIT: usize = 4;
    let r = fixtures::serve(flat(), |o| roam_server::net::Options {
        max_viewers: LIMIT,
        ..o
    });
    // LIMIT drivers whose connections are lost: LIMIT held vehicles, no seat taken.
    let mut first = Vec::new();
    for _ in 0..LIMIT {
        first.push(join(&r).await);
    }
    let held: Vec<u16> = first.iter().map(|v| v.welcome.vehicle).collect();
    for v in &first {
        v.conn.close(0u32.into(), b"lost");
    }
    let mut world = r.server.watch();
    tokio::time::timeout(HANG, world.wait_for(|s| s.held.len() == LIMIT))
        .await
        .expect("all held")
        .expect("the world runs");
    // Seats are given back just after the hold is sent: waited for on the world's ticks.
    for _ in 0..3_000 {
        if r.server.load().1 == 0 {
            break;
        }
        let _ = world.changed().await;
    }
    assert_eq!(r.server.load().1, 0, "the seats given back");
    // LIMIT join at once: each frees a held vehicle of its own.
    let (a, b, c, d) = tokio::join!(join(&r), join(&r), join(&r), join(&r));
    let second = [a, b, c, d];
    let new: Vec<u16> = second.iter().map(|v| v.welcome.vehicle).collect();
    let snap = tokio::time::timeout(
        HANG,
        world.wait_for(|s| new.iter().all(|id| s.vehicles.iter().any(|x| x.id == *id))),
    )
    .await
    .expect("the new vehicles appear")
    .expect("the world runs")
    .clone();
    let ids: Vec<u16> = snap.vehicles.iter().map(|x| x.id).collect();
    assert_eq!(
        ids.len(),
        LIMIT,
        "vehicles {ids:?} (held before: {held:?}, joined: {new:?}, held now: {:?})",
        snap.held
    );
    assert!(snap.held.is_empty(), "{:?}", snap.held);
    drop(first);
    drop(second);
    r.server.shutdown().await.expect("stops");
}
