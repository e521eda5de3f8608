//! End to end: a real server and headless viewers over QUIC on `127.0.0.1:0`.

use roam_tests::fixtures::{self, Running, flat};
use std::sync::Arc;
use std::time::Duration;

use roam_client::headless::{self, ViewerOptions, ViewerStats};
use roam_client::session::{KeySource, Session, Taken};
use roam_link::wire;
use roam_protocol::messages::{ClientMessage, Hello, Role, ViewChange, close};
use roam_protocol::script;
use roam_server::Terrain;
use roam_server::net::Options;
use roam_server::sim::record_files::RecordDir;
use roam_server::sim::session::{self, RecordOptions};

use crate::turn;

/// A server on `terrain`, recording into the directory `record` if given.
fn start(terrain: Arc<Terrain>, record: Option<std::path::PathBuf>) -> Running {
    fixtures::serve(terrain, |o| Options {
        record: record.map(|dir| {
            let files = RecordDir::new(dir, roam_server::net::world_loop::unix_seconds);
            RecordOptions::new(files, session::DEFAULT_MAX_BYTES)
        }),
        ..o
    })
}

fn opts(r: &Running, role: Role, frames: u64) -> ViewerOptions {
    ViewerOptions {
        token: r.token.clone(),
        role,
        budget: 8_000,
        frames,
        ..ViewerOptions::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_viewers_one_driving_and_the_session_replays() {
    let _turn = turn().await;
    let dir = std::env::temp_dir().join(format!("roam-e2e-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    let terrain = flat();
    let r = start(terrain.clone(), Some(dir.clone()));
    let addr = r.server.addr;
    let driver = ViewerOptions {
        inputs: Some(script::parse(fixtures::DRIVE).expect("valid")),
        ..opts(&r, Role::Driver, 330)
    };
    let d = tokio::spawn(headless::run(addr, r.fingerprint, driver));
    // The spectator joins once the driver's vehicle exists.
    let mut world = r.server.watch();
    tokio::time::timeout(
        Duration::from_secs(10),
        world.wait_for(|s| !s.vehicles.is_empty()),
    )
    .await
    .expect("the driver's vehicle appears")
    .expect("the world runs");
    let s = tokio::spawn(headless::run(
        addr,
        r.fingerprint,
        opts(&r, Role::Spectator { follow: None }, 120),
    ));
    let (d, s): (ViewerStats, ViewerStats) = (
        d.await.expect("joins").expect("the driver runs"),
        s.await.expect("joins").expect("the spectator runs"),
    );
    for v in [&d, &s] {
        assert_eq!(v.decode_errors, 0);
        assert!(v.max_triangles > 2 && v.max_triangles <= 8_000);
        assert!(v.first.expect("a first frame") < 2.0);
    }
    assert_eq!(s.vehicle, d.vehicle, "the spectator follows the driver");
    // The drive over the network ends exactly where the script, simulated, ends.
    fixtures::assert_drive_exact(&terrain, d.last, d.last_tick);
    assert!(!d.latencies_ms.is_empty(), "key changes were seen applied");
    // The server's recording replays bit for bit.
    let final_world = r.server.shutdown().await.expect("stops cleanly");
    fixtures::assert_replays(&dir, &terrain, &final_world);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_or_fingerprint_is_refused() {
    let _turn = turn().await;
    let r = start(flat(), None);
    let bad = ViewerOptions {
        token: "nope".into(),
        ..opts(&r, Role::Driver, 5)
    };
    let err = headless::run(r.server.addr, r.fingerprint, bad)
        .await
        .expect_err("refused");
    assert!(format!("{err:#}").contains("wrong token"), "{err:#}");
    let mut wrong = r.fingerprint;
    wrong[0] ^= 1;
    let err = headless::run(r.server.addr, wrong, opts(&r, Role::Driver, 5))
        .await
        .expect_err("the client refuses the server");
    assert!(format!("{err:#}").contains("fingerprint"), "{err:#}");
    assert!(
        r.server.snapshot().vehicles.is_empty(),
        "no vehicle for refused viewers"
    );
    r.server.shutdown().await.expect("stops");
}

/// A driver's hello with `budget`.
fn driver_hello(r: &Running, budget: u32) -> Hello {
    fixtures::hello(Role::Driver, &r.token, [1280, 720], budget, 60)
}

/// A connection that says hello as a driver and then never reads a frame.
async fn stalled_driver(
    r: &Running,
) -> (
    quinn::Endpoint,
    quinn::Connection,
    (quinn::SendStream, quinn::RecvStream),
) {
    let (endpoint, conn) = headless::connect(r.server.addr, r.fingerprint)
        .await
        .expect("connects");
    let (mut send, recv) = conn.open_bi().await.expect("a stream");
    wire::write(&mut send, &ClientMessage::Hello(driver_hello(r, 8_000)))
        .await
        .expect("sends");
    // The control stream stays open (and unread): dropping it would stop the welcome.
    (endpoint, conn, (send, recv))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_viewer_and_garbage_do_not_disturb_the_others() {
    let _turn = turn().await;
    let r = start(flat(), None);
    let (_e1, stalled, _control) = stalled_driver(&r).await;
    // Someone sending garbage: datagrams, and streams of junk.
    // Garbage, each kind on a connection of its own (the server closes a connection at
    // its first junk, so one connection would test one junk): each is refused with the
    // protocol close code, while a good viewer streams beside them.
    let junk = tokio::spawn({
        let (addr, fp) = (r.server.addr, r.fingerprint);
        async move {
            let mut refused = 0;
            for i in 0..12u32 {
                let (_endpoint, conn) = headless::connect(addr, fp).await.expect("connects");
                let _ = conn.send_datagram(vec![i as u8; (i % 50) as usize + 1].into());
                let (mut s, _) = conn.open_bi().await.expect("a stream");
                let bytes: Vec<u8> = match i % 3 {
                    0 => vec![0xff; 64],                                 // a length past any limit
                    1 => [&5u32.to_le_bytes()[..], &[0xee; 5]].concat(), // not a message
                    _ => [&1u32.to_le_bytes()[..], &[1]].concat(),       // a budget, not a hello
                };
                let _ = s.write_all(&bytes).await;
                let closed = tokio::time::timeout(Duration::from_secs(10), conn.closed())
                    .await
                    .expect("the server closes a junk connection");
                match closed {
                    quinn::ConnectionError::ApplicationClosed(c)
                        if c.error_code == close::PROTOCOL.into() =>
                    {
                        refused += 1
                    }
                    other => panic!("junk {i}: closed with {other:?}, expected the protocol code"),
                }
            }
            refused
        }
    });
    let v = headless::run(r.server.addr, r.fingerprint, opts(&r, Role::Driver, 120))
        .await
        .expect("runs");
    assert_eq!(v.decode_errors, 0);
    assert_eq!(v.frames, 120);
    assert_eq!(
        junk.await.expect("the junk task"),
        12,
        "every junk connection refused"
    );
    // A viewer killed mid-stream (no goodbye) has its vehicle held for it to come back
    // to (`tests/tests/it/reconnect.rs` takes it back, and sees it freed after the hold).
    // Which vehicle is the stalled driver's: the one left once the good viewer's goodbye
    // has freed its own (the two hellos may be seated in either order).
    let mut world = r.server.watch();
    let stalled_vehicle = tokio::time::timeout(
        Duration::from_secs(10),
        world.wait_for(|s| s.vehicles.len() == 1),
    )
    .await
    .expect("the good viewer's vehicle is freed by its goodbye")
    .expect("the world runs")
    .vehicles
    .first()
    .map(|v| v.id);
    assert!(
        stalled_vehicle.is_some(),
        "the stalled driver has a vehicle"
    );
    stalled.close(0u32.into(), b"killed");
    drop(stalled);
    let held = tokio::time::timeout(
        Duration::from_secs(10),
        world.wait_for(|s| !s.held.is_empty()),
    )
    .await
    .expect("the vehicle of a killed connection is held")
    .expect("the world runs")
    .held
    .clone();
    assert_eq!(held.first().copied(), stalled_vehicle);
    r.server.shutdown().await.expect("stops");
}

/// Frames from `s` until one's triangle count satisfies `ok` (within a bound), and that
/// count.
async fn until(s: &Session, what: &str, ok: impl Fn(usize) -> bool) -> usize {
    let mut seen = Vec::new();
    let limit = Duration::from_secs(30);
    for _ in 0..600 {
        let taken = tokio::time::timeout(limit, s.next_frame(true))
            .await
            .expect("in time");
        match taken.expect("the stream goes on") {
            Taken::Frame(f) if ok(f.triangles) => return f.triangles,
            Taken::Frame(f) => seen.push(f.triangles),
            Taken::Nothing => {}
            Taken::Dropped(why) => panic!("a frame failed to decode: {why}"),
        }
    }
    panic!("no frame with {what} in 600 tries; triangle counts seen: {seen:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_steers_the_servers_budget_and_camera() {
    let _turn = turn().await;
    // Real terrain (the test terrain's 300 m of noise every 4 m leaves nothing to cull).
    let r = start(fixtures::kossou(), None);
    let hello = driver_hello(&r, 4_000);
    let s = Session::join(r.server.addr, r.fingerprint, hello, KeySource::None)
        .await
        .expect("joins");
    until(&s, "most of the budget", |t| t > 3_000 && t <= 4_000).await;
    // `-` twice in the window: ÷ 2.
    s.set_budget(2_000);
    until(&s, "the new budget", |t| t > 1_500 && t <= 2_000).await;
    // Looking straight down from the vehicle, the frustum holds only the ground below it:
    // the server culls the rest and the mesh shrinks far below the budget.
    let down = |pitch_deg| ViewChange {
        pitch_deg,
        eye_above: 0.0,
        viewport: [1280, 720],
        fog: true,
    };
    s.set_view(down(-89.0));
    until(&s, "the view straight down", |t| t < 500).await;
    s.set_view(down(-5.0));
    until(&s, "the view ahead again", |t| t > 1_500).await;
    assert!(s.quit().await, "the server heard the goodbye");
    r.server.shutdown().await.expect("stops");
}
