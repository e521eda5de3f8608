//! A viewer against a hostile or broken server: every malformed welcome, colour tile or
//! frame is a clear error or a dropped frame, never a panic or an outsized allocation; a
//! server that welcomes and then says nothing is given up on (after one reconnection),
//! never waited on forever; a frame number no server could send ends the session with
//! the numbers named, and does not wedge the viewer.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use roam_client::session::{KeySource, Patience, Session, State, Taken};
use roam_link::{tls, wire};
use roam_protocol::ColorLayout;
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, ServerMessage, Welcome};
use roam_tests::fixtures::key_frame;

/// What the fake server sends after reading the hello.
#[derive(Clone, Debug)]
enum Say {
    /// A control-stream message.
    Msg(ServerMessage),
    /// Raw bytes on the control stream.
    Raw(Vec<u8>),
    /// A frame stream with these bytes.
    Stream(Vec<u8>),
}

const CELLS: u32 = 64;
/// Tiles of 16 texels: levels of 64², 32² and 16², the last one tile.
const TILE: u32 = 16;

fn layout() -> ColorLayout {
    ColorLayout::new(CELLS, TILE, 4).expect("a valid layout")
}

/// The coarsest level's one tile (16² texels), coded, with texels `fill(i)`.
fn coarsest_tile(fill: impl Fn(u32) -> u8) -> Vec<u8> {
    let rgb: Vec<u8> = (0..TILE * TILE * 3).map(fill).collect();
    let mut out = Vec::new();
    roam_protocol::colormap::encode(TILE, &rgb, &mut out).expect("texels of the right size");
    out
}

fn packed_colors() -> Vec<u8> {
    coarsest_tile(|i| (i % 251) as u8)
}

/// A colour tile message.
fn tile(level: u8, x: u32, z: u32, data: Vec<u8>) -> Say {
    Say::Msg(ServerMessage::ColorTile { level, x, z, data })
}

fn welcome() -> Welcome {
    roam_tests::fixtures::fake_welcome(layout())
}

/// A welcome and the coarsest colour tile.
fn good_join() -> Vec<Say> {
    vec![
        Say::Msg(ServerMessage::Welcome(welcome())),
        tile(2, 0, 0, packed_colors()),
    ]
}

/// A server that answers one viewer with `script`, then closes. Its address and
/// certificate fingerprint.
async fn fake(script: Vec<Say>) -> (SocketAddr, [u8; 32], tokio::task::JoinHandle<()>) {
    let (addr, fp, _, task) = fakes(move |_, _| script.clone(), 1).await;
    (addr, fp, task)
}

/// What a fake server says on its `n`th connection (from 0), given the viewer's hello.
type Scripts = Arc<dyn Fn(usize, &Hello) -> Vec<Say> + Send + Sync>;

/// A server that answers up to `connections` connections, the `n`th with `scripts(n,
/// hello)`: its address, certificate fingerprint, and the count of connections it
/// accepted.
async fn fakes(
    scripts: impl Fn(usize, &Hello) -> Vec<Say> + Send + Sync + 'static,
    connections: usize,
) -> (
    SocketAddr,
    [u8; 32],
    Arc<AtomicUsize>,
    tokio::task::JoinHandle<()>,
) {
    let scripts: Scripts = Arc::new(scripts);
    let id = tls::generate().expect("a certificate");
    let config = tls::server_config(&id).expect("a config");
    let endpoint =
        quinn::Endpoint::server(config, "127.0.0.1:0".parse().expect("valid")).expect("listens");
    let addr = endpoint.local_addr().expect("bound");
    let fingerprint = tls::parse_fingerprint(&id.fingerprint()).expect("valid");
    let accepted = Arc::new(AtomicUsize::new(0));
    let count = accepted.clone();
    let task = tokio::spawn(async move {
        let mut served = tokio::task::JoinSet::new();
        for n in 0..connections {
            let Some(incoming) = endpoint.accept().await else {
                break;
            };
            count.fetch_add(1, Ordering::SeqCst);
            served.spawn(answer(incoming, scripts.clone(), n));
        }
        while served.join_next().await.is_some() {}
        endpoint.wait_idle().await;
    });
    (addr, fingerprint, accepted, task)
}

/// Answers connection `n` with its script.
async fn answer(incoming: quinn::Incoming, scripts: Scripts, n: usize) {
    let Ok(conn) = incoming.await else { return };
    let Ok((mut send, mut recv)) = conn.accept_bi().await else {
        return;
    };
    let Ok(ClientMessage::Hello(hello)) =
        wire::read::<ClientMessage>(&mut recv, messages::MAX_MESSAGE).await
    else {
        return;
    };
    for say in scripts(n, &hello) {
        let sent = match say {
            Say::Msg(m) => wire::write(&mut send, &m).await.is_ok(),
            Say::Raw(b) => send.write_all(&b).await.is_ok(),
            Say::Stream(b) => match conn.open_uni().await {
                Ok(mut s) => s.write_all(&b).await.is_ok() && s.finish().is_ok(),
                Err(_) => false,
            },
        };
        if !sent {
            return;
        }
    }
    // Everything said: hang up once the viewer has asked for a key frame (it could not
    // decode a frame) or gone away; until then, say nothing more.
    while let Ok(m) = wire::read::<ClientMessage>(&mut recv, messages::MAX_MESSAGE).await {
        if m == ClientMessage::KeyFrame {
            break;
        }
    }
    conn.close(0u32.into(), b"done");
}

/// Takes of a frame a wait may make (each within a minute) before it fails: far more than
/// any fake here sends frames (five at most), so a session that neither ends nor shows a
/// frame fails the test, never hangs it.
const TAKES: usize = 64;

/// `f`, or a failed test after a minute (a regression fails, never hangs).
async fn bounded<T>(f: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(std::time::Duration::from_secs(60), f)
        .await
        .expect("within a minute")
}

fn hello() -> Hello {
    roam_tests::fixtures::driver_hello("t")
}

/// Joining a server that says `script` fails with an error containing `want`.
async fn check(script: Vec<Say>, want: &str) {
    let (addr, fp, task) = fake(script).await;
    let err = match bounded(Session::join(addr, fp, hello(), KeySource::None)).await {
        Ok(_) => panic!("joined, expected an error with {want:?}"),
        Err(e) => format!("{e:#}"),
    };
    assert!(err.contains(want), "{want:?} not in {err:?}");
    task.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_malformed_welcome_or_colour_tile_is_a_clear_error() {
    let packed = packed_colors();
    let n = packed.len();
    let with = |w: Welcome, rest: Vec<Say>| {
        let mut v = vec![Say::Msg(ServerMessage::Welcome(w))];
        v.extend(rest);
        v
    };
    check(
        vec![Say::Msg(ServerMessage::Refused(Reason::WrongToken))],
        "refused: wrong token",
    )
    .await;
    check(
        vec![Say::Msg(ServerMessage::Bye(Reason::Shutdown))],
        "expected a welcome",
    )
    .await;
    // A length prefix of 2^32 - 1: refused before anything is allocated.
    check(
        vec![Say::Raw(vec![0xff; 64])],
        "the welcome: a message of 4294967295 bytes, more than the",
    )
    .await;
    check(
        with(
            Welcome {
                levels: 16,
                ..welcome()
            },
            vec![],
        ),
        "Welcome.levels",
    )
    .await;
    // A colour map of another size than the grid's cells.
    let other = ColorLayout::new(32, TILE, 4).expect("a valid layout");
    check(
        with(
            Welcome {
                color: other,
                ..welcome()
            },
            vec![],
        ),
        "Welcome.color.cells",
    )
    .await;
    // A layout whose level count does not follow from its cells and tile.
    let mut bad = layout();
    bad.levels = 9;
    check(
        with(
            Welcome {
                color: bad,
                ..welcome()
            },
            vec![],
        ),
        "Welcome.color",
    )
    .await;
    // A window wider than the viewer asked for.
    let mut wide = layout();
    wide.window = 9;
    check(
        with(
            Welcome {
                color: wide,
                ..welcome()
            },
            vec![],
        ),
        "Welcome.color.window",
    )
    .await;
    check(
        with(welcome(), vec![tile(3, 0, 0, packed.clone())]),
        "ColorTile.level",
    )
    .await;
    check(
        with(welcome(), vec![tile(2, 1, 0, packed.clone())]),
        "ColorTile.x/z",
    )
    .await;
    // Longer than the protocol's largest tile: refused before it is allocated.
    check(
        with(welcome(), vec![tile(2, 0, 0, vec![0; 1 << 20])]),
        "colour tile bytes: 1048576, at most",
    )
    .await;
    // Within that, but longer than any tile of its side codes to: refused before decoding.
    check(
        with(welcome(), vec![tile(2, 0, 0, vec![0; 100_000])]),
        "ColorTile.data: 100000 bytes for a tile of 16² texels",
    )
    .await;
    let mut damaged = packed.clone();
    damaged[n / 2] ^= 0x10;
    check(
        with(welcome(), vec![tile(2, 0, 0, damaged)]),
        "ColorTile.data",
    )
    .await;
    check(
        with(welcome(), vec![Say::Msg(ServerMessage::Bye(Reason::Quit))]),
        "expected the coarsest colour tile",
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn junk_frames_are_dropped_and_the_end_is_noticed() {
    let frame = |frame: u64, mesh: Vec<u8>| {
        let mut b = Vec::new();
        messages::encode(
            &messages::Frame {
                frame,
                base: None,
                tick: 1,
                vehicles: Vec::new(),
                input_seq: None,
                mesh,
            },
            &mut b,
        )
        .expect("encodes");
        b
    };
    let mut script = good_join();
    script.push(Say::Stream(vec![0xab; 100]));
    script.push(Say::Stream(frame(1, vec![1, 2, 3])));
    let (addr, fp, task) = fake(script).await;
    let s = bounded(Session::join(addr, fp, hello(), KeySource::None))
        .await
        .expect("joins");
    assert!(s.colors().has_coarsest(), "the coarsest tile is resident");
    let mut dropped = 0;
    // Two streams, then the server hangs up and `next_frame` must say so.
    let ended = 'end: {
        for _ in 0..TAKES {
            match bounded(s.next_frame(true)).await {
                Ok(Taken::Dropped(_)) => dropped += 1,
                Ok(Taken::Frame(f)) => panic!("junk decoded as frame {}", f.frame),
                Ok(Taken::Nothing) => {}
                Err(e) => break 'end format!("{e:#}"),
            }
            assert!(dropped <= 2, "only two streams were sent");
        }
        panic!("the session did not end within {TAKES} takes");
    };
    assert!(dropped >= 1, "the junk was seen and dropped");
    assert!(
        ended.contains("closed") || ended.contains("ended") || ended.contains("lost"),
        "{ended}"
    );
    task.abort();
}

/// A server that welcomes and then says nothing (no frame, no control message; its QUIC
/// stack still answers): the session finds it silent after the configured silence,
/// reconnects once (it might have been the path), finds it silent again with no frame
/// between, and ends with an error saying so. Never waited on forever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_goes_silent_is_given_up_on() {
    let (addr, fp, accepted, task) = fakes(|_, _| good_join(), 4).await;
    let patience = Patience {
        silence: Duration::from_secs(1),
        reconnect_for: Duration::from_secs(10),
    };
    let s = bounded(Session::join_with(
        addr,
        fp,
        hello(),
        KeySource::None,
        patience,
    ))
    .await
    .expect("joins");
    let mut changes = s.status_changes();
    let err = 'end: {
        for _ in 0..TAKES {
            match bounded(s.next_frame(true)).await {
                Ok(Taken::Frame(f)) => panic!("the silent server sent frame {}", f.frame),
                Ok(_) => {}
                Err(e) => break 'end format!("{e:#}"),
            }
        }
        panic!("the session did not end within {TAKES} takes");
    };
    for want in [
        &format!("lost the server at {addr}"),
        "no frame or message from the server for 1.0 s",
        "again right after reconnecting",
    ] {
        assert!(err.contains(want), "{want:?} not in {err:?}");
    }
    assert_eq!(accepted.load(Ordering::SeqCst), 2, "one reconnection");
    let status = changes.borrow_and_update().clone();
    assert_eq!(status.gaps.reconnects, 1);
    assert!(
        matches!(status.state, State::Ended(_)),
        "{:?}",
        status.state
    );
    task.abort();
}

/// A frame numbered `u64::MAX` (which would make every later frame look old), with good
/// frames around it: the session ends with an error naming the server and the numbers
/// rather than ignoring frames forever, and does not reconnect (the server is broken, not
/// lost).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_poisoned_frame_number_ends_the_session_and_never_wedges_it() {
    let mut script = good_join();
    script.push(Say::Stream(key_frame(0)));
    script.push(Say::Stream(key_frame(u64::MAX)));
    for f in 1..4 {
        script.push(Say::Stream(key_frame(f)));
    }
    let (addr, fp, accepted, task) = fakes(move |_, _| script.clone(), 2).await;
    let s = bounded(Session::join(addr, fp, hello(), KeySource::None))
        .await
        .expect("joins");
    let mut taken = Vec::new();
    let err = 'end: {
        for _ in 0..TAKES {
            match bounded(s.next_frame(true)).await {
                Ok(Taken::Frame(f)) => taken.push(f.frame),
                Ok(Taken::Dropped(why)) => panic!("a good frame dropped: {why}"),
                Ok(Taken::Nothing) => {}
                Err(e) => break 'end format!("{e:#}"),
            }
            assert!(taken.len() <= 4, "only four good frames were sent");
        }
        panic!("the session did not end within {TAKES} takes: frames {taken:?}");
    };
    for want in [
        format!("the server at {addr}"),
        format!("frame {}", u64::MAX),
        "frame numbers rise by one".to_string(),
    ] {
        assert!(err.contains(&want), "{want:?} not in {err:?}");
    }
    assert!(
        taken.windows(2).all(|w| w[0] < w[1]),
        "frames in order: {taken:?}"
    );
    assert_eq!(accepted.load(Ordering::SeqCst), 1, "no reconnection");
    assert!(
        bounded(s.next_frame(true)).await.is_err(),
        "the session stays ended"
    );
    task.abort();
}

/// A join with `w` as the welcome and the coarsest colour tile, then `frames` key frames.
fn join_as(w: Welcome, frames: std::ops::Range<u64>) -> Vec<Say> {
    let mut out = vec![
        Say::Msg(ServerMessage::Welcome(w)),
        tile(2, 0, 0, packed_colors()),
    ];
    out.extend(frames.map(|f| Say::Stream(key_frame(f))));
    out
}

const TICKET: [u8; 16] = [7; 16];

/// Short patience, for a fake that falls silent to make the viewer reconnect.
const QUICK: Patience = Patience {
    silence: Duration::from_secs(1),
    reconnect_for: Duration::from_secs(10),
};

/// A driver's connection that goes silent after two frames (a lost path, for the
/// viewer): what the fakes below say first.
fn first_connection() -> Vec<Say> {
    join_as(
        Welcome {
            vehicle: 3,
            ticket: Some(TICKET),
            ..welcome()
        },
        0..2,
    )
}

/// The session, joined to a fake with short patience, once it has reconnected or ended;
/// and the first frame of the new connection, or the error it ended with.
async fn reconnected(addr: SocketAddr, fp: [u8; 32]) -> (Session, anyhow::Result<u64>) {
    let s = bounded(Session::join_with(
        addr,
        fp,
        hello(),
        KeySource::None,
        QUICK,
    ))
    .await
    .expect("joins");
    let mut changes = s.status_changes();
    bounded(changes.wait_for(|st| st.gaps.reconnects > 0 || matches!(st.state, State::Ended(_))))
        .await
        .expect("the session is there");
    // The core is the new connection's once the reconnection counts.
    let end = 'end: {
        for _ in 0..TAKES {
            match bounded(s.next_frame(true)).await {
                Ok(Taken::Frame(f)) => break 'end Ok(f.frame),
                Ok(Taken::Dropped(why)) => panic!("a good frame dropped: {why}"),
                Ok(Taken::Nothing) => {}
                Err(e) => break 'end Err(e),
            }
        }
        panic!("no frame and no end within {TAKES} takes");
    };
    (s, end)
}

/// After a silence the driver connects again presenting the ticket of its welcome; a
/// server that still holds the vehicle says `resumed`, and the frames of the new
/// connection (numbered from 0 again) are taken.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnection_presents_the_ticket_and_takes_the_vehicle_back() {
    let (addr, fp, accepted, task) = fakes(
        |n, hello| match (n, hello.resume) {
            (0, None) => first_connection(),
            (_, Some(TICKET)) => join_as(
                Welcome {
                    vehicle: 3,
                    ticket: Some([8; 16]),
                    resumed: true,
                    ..welcome()
                },
                0..3,
            ),
            (n, resume) => vec![Say::Msg(ServerMessage::Refused(Reason::Protocol(format!(
                "connection {n}: a hello presenting {resume:?}"
            ))))],
        },
        2,
    )
    .await;
    let (s, end) = reconnected(addr, fp).await;
    let frame = end.unwrap_or_else(|e| panic!("the session ended: {e:#}"));
    assert!(
        frame < 3,
        "frame {frame}: the new connection's, numbered from 0"
    );
    let status = s.status();
    assert_eq!((status.gaps.reconnects, status.gaps.resumed), (1, 1));
    assert!(status.welcome.resumed);
    assert_eq!(s.vehicle(), 3);
    assert_eq!(
        status.welcome.ticket,
        Some([8; 16]),
        "the newest ticket kept"
    );
    assert_eq!(accepted.load(Ordering::SeqCst), 2);
    task.abort();
}

/// A reconnection finding another terrain (here another colour map) ends the session:
/// the scene drawn would no longer be the server's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reconnection_to_another_terrain_ends_the_session() {
    let (addr, fp, _, task) = fakes(
        |n, _| match n {
            0 => first_connection(),
            _ => vec![
                Say::Msg(ServerMessage::Welcome(welcome())),
                tile(2, 0, 0, coarsest_tile(|_| 9)),
            ],
        },
        2,
    )
    .await;
    let (_s, end) = reconnected(addr, fp).await;
    let err = format!("{:#}", end.expect_err("another terrain"));
    for want in [
        &format!("lost the server at {addr}"),
        "the server changed its terrain: another colour map",
    ] {
        assert!(err.contains(want), "{want:?} not in {err:?}");
    }
    task.abort();
}

/// A refusal on reconnecting (a full server) is final: no attempt after it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_server_on_reconnecting_is_not_tried_again() {
    let (addr, fp, accepted, task) = fakes(
        |n, _| match n {
            0 => first_connection(),
            _ => vec![Say::Msg(ServerMessage::Refused(Reason::Full {
                viewers: 64,
            }))],
        },
        3,
    )
    .await;
    let (s, end) = reconnected(addr, fp).await;
    let err = format!("{:#}", end.expect_err("refused"));
    assert!(
        err.contains("refused: the server is full (64 viewers)"),
        "{err}"
    );
    assert_eq!(accepted.load(Ordering::SeqCst), 2, "no third attempt");
    assert_eq!(s.status().gaps.reconnects, 0);
    task.abort();
}
