//! A viewer given several addresses (`roam-client --connect A,B`: the edges of one world,
//! one certificate, one token), against real servers on loopback (two `serve`s started
//! with one identity, so one fingerprint) and, for an edge's news, a fake edge:
//!
//! - a first address that never answers is passed for the next one, which joins;
//! - none answering is an error naming each;
//! - a session whose server goes silent (its path cut through the relay) moves on to the
//!   next address after a second (not the 10 s a lone address gets) and its frames go on;
//! - a session whose server shuts down moves on to the next address (alone, it would end);
//! - an edge's news: the world gone is in the status, the edges it names join the
//!   rotation, and the session goes to one of them when the edge goes silent;
//! - the world's time gone adds up across its goings and comings (no I/O).
//!
//! Nothing sleeps to wait: the tests wait on the session's status and its frames, each
//! wait bounded.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_client::color_cache::Keep;
use roam_client::headless::{self, ViewerOptions};
use roam_client::session::{KeySource, Patience, Session, State};
use roam_link::{tls, wire};
use roam_protocol::ColorLayout;
use roam_protocol::messages::{self, ClientMessage, Hello, ServerMessage, Welcome, WorldNews};
use roam_server::net::{Options, Server};
use roam_server::terrain::variance::VarianceTree;
use roam_tests::fixtures::{TOKEN, flat, pyramid};
use roam_tests::fixtures::{bounded, frame, key_frame, status_when};
use roam_tests::relay::{Relay, RelayConfig};

use crate::turn;

/// Two servers of one world's terrain with one identity (one fingerprint), as two edges
/// sharing a state directory are.
struct Pair {
    a: Server,
    b: Server,
    fingerprint: [u8; 32],
}

fn pair() -> Pair {
    let terrain = flat();
    let vt = Arc::new(VarianceTree::build(&terrain.heights, 1, &mut |_, _| {}));
    let colors = pyramid(&terrain, roam_protocol::tiles::DEFAULT_TILE);
    let identity = tls::generate().expect("a certificate");
    let start = || {
        Server::start(
            terrain.clone(),
            vt.clone(),
            colors.clone(),
            &identity,
            Options::new("127.0.0.1:0".parse().expect("valid"), TOKEN.to_owned()),
        )
        .expect("listens")
    };
    let (a, b) = (start(), start());
    Pair {
        a,
        b,
        fingerprint: tls::parse_fingerprint(&identity.fingerprint()).expect("valid"),
    }
}

fn hello() -> Hello {
    roam_tests::fixtures::driver_hello(TOKEN)
}

/// A UDP socket that takes datagrams and never answers: an address where nothing serves.
fn dead() -> (std::net::UdpSocket, SocketAddr) {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("binds");
    let addr = socket.local_addr().expect("bound");
    (socket, addr)
}

async fn join(addrs: &[SocketAddr], fingerprint: [u8; 32]) -> Session {
    bounded(
        "joining",
        Session::join_any(
            addrs,
            fingerprint,
            hello(),
            KeySource::None,
            Patience::default(),
            Keep::Masks,
        ),
    )
    .await
    .expect("joins")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_first_address_is_passed_for_the_live_one() {
    let _turn = turn().await;
    let p = pair();
    let (_socket, nobody) = dead();
    let live = p.b.addr;
    // Through the headless viewer, as `--connect DEAD,LIVE --headless` runs it.
    let stats = bounded(
        "a headless viewer's frames",
        headless::measure_any(
            &[nobody, live],
            p.fingerprint,
            ViewerOptions {
                token: TOKEN.to_owned(),
                budget: 4_000,
                frames: 20,
                ..ViewerOptions::default()
            },
        ),
    )
    .await
    .expect("joins the live one");
    assert_eq!(stats.error, None);
    assert_eq!(stats.frames, 20);
    assert_eq!(stats.reconnects, 0);
    assert_eq!(stats.edges_learned, 0, "serve names no edges");
    // And through the session: it is on the live address.
    let s = join(&[nobody, live], p.fingerprint).await;
    assert_eq!(s.addr(), live);
    assert_eq!(s.addresses(), vec![nobody, live]);
    frame(&s).await;
    s.quit().await;
    p.a.shutdown().await.expect("stops");
    p.b.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_address_answering_is_an_error_naming_each() {
    let (_one, a) = dead();
    let (_two, b) = dead();
    let err = match bounded(
        "giving up",
        Session::join_any(
            &[a, b],
            [7; 32],
            hello(),
            KeySource::None,
            Patience::default(),
            Keep::Masks,
        ),
    )
    .await
    {
        Ok(_) => panic!("joined nobody"),
        Err(e) => format!("{e:#}"),
    };
    for want in [
        "none of the 2 addresses joined".to_owned(),
        format!("{a}: no handshake within 1.0 s"),
        format!("{b}: no handshake within 1.0 s"),
    ] {
        assert!(err.contains(&want), "{want:?} not in {err:?}");
    }
}

/// A live session on A (through a relay) with [A, B]: A's path is cut, the session finds
/// it silent within a second (not 10 s: there is another address) and goes on at B.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_server_is_left_for_the_next_address_after_a_second() {
    let _turn = turn().await;
    let p = pair();
    let relay = Relay::start(p.a.addr, RelayConfig::default())
        .await
        .expect("relays");
    let (via_a, b) = (relay.addr(), p.b.addr);
    let s = join(&[via_a, b], p.fingerprint).await;
    assert_eq!(s.addr(), via_a);
    for _ in 0..5 {
        frame(&s).await;
    }
    relay.cut();
    let lost = status_when(&s, "the viewer finds A silent", |st| {
        matches!(st.state, State::Reconnecting { .. })
    })
    .await;
    let State::Reconnecting { why, .. } = &lost.state else {
        unreachable!("waited for it");
    };
    assert!(
        why.contains("no frame or message from the server for 0.8 s"),
        "{why}"
    );
    let back = status_when(&s, "the viewer goes on at B", |st| {
        st.gaps.reconnects == 1 && st.state == State::Connected
    })
    .await;
    assert_eq!(back.addr, b);
    assert_eq!(s.addr(), b);
    // Frames keep arriving, from B.
    let before = s.reconnects();
    for _ in 0..10 {
        frame(&s).await;
    }
    assert_eq!(s.reconnects(), before, "no further reconnection");
    assert_eq!(s.status().state, State::Connected);
    assert!(s.quit().await, "B heard the goodbye");
    relay.restore();
    p.a.shutdown().await.expect("stops");
    p.b.shutdown().await.expect("stops");
}

/// A server shutting down sends its viewers to the next address (alone, a viewer's
/// session would end: the server closed it on purpose).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_shutting_down_sends_the_session_to_the_next_address() {
    let _turn = turn().await;
    let p = pair();
    let (a, b) = (p.a.addr, p.b.addr);
    let s = join(&[a, b], p.fingerprint).await;
    assert_eq!(s.addr(), a);
    frame(&s).await;
    p.a.shutdown().await.expect("stops");
    let back = status_when(&s, "the viewer goes on at B", |st| {
        st.gaps.reconnects == 1 && st.state == State::Connected
    })
    .await;
    assert_eq!(back.addr, b);
    for _ in 0..5 {
        frame(&s).await;
    }
    assert!(s.quit().await, "B heard the goodbye");
    p.b.shutdown().await.expect("stops");
}

// A fake edge: welcomes, says its world is gone and where the world's other edges are,
// then (news told) says nothing.

const CELLS: u32 = 64;
const TILE: u32 = 16;

fn fake_welcome() -> Welcome {
    roam_tests::fixtures::fake_welcome(ColorLayout::new(CELLS, TILE, 4).expect("a valid layout"))
}

/// The welcome, the coarsest colour tile, `news`, then a key frame every 20 ms while
/// `frames` (else nothing) until the viewer goes.
async fn fake_edge(
    endpoint: quinn::Endpoint,
    news: Vec<WorldNews>,
    frames: bool,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut served = tokio::task::JoinSet::new();
        while let Some(incoming) = endpoint.accept().await {
            let news = news.clone();
            served.spawn(async move {
                let Ok(conn) = incoming.await else { return };
                let Ok((mut send, mut recv)) = conn.accept_bi().await else {
                    return;
                };
                let Ok(ClientMessage::Hello(_)) =
                    wire::read::<ClientMessage>(&mut recv, messages::MAX_MESSAGE).await
                else {
                    return;
                };
                let rgb: Vec<u8> = (0..TILE * TILE * 3).map(|i| (i % 251) as u8).collect();
                let mut data = Vec::new();
                roam_protocol::colormap::encode(TILE, &rgb, &mut data).expect("a tile");
                let mut said = vec![
                    ServerMessage::Welcome(fake_welcome()),
                    ServerMessage::ColorTile {
                        level: 2,
                        x: 0,
                        z: 0,
                        data,
                    },
                ];
                said.extend(news.into_iter().map(ServerMessage::World));
                for m in said {
                    if wire::write(&mut send, &m).await.is_err() {
                        return;
                    }
                }
                let mut tick = tokio::time::interval(Duration::from_millis(20));
                for n in 0u64.. {
                    tick.tick().await;
                    if conn.close_reason().is_some() {
                        return;
                    }
                    if frames {
                        let _ = conn.send_datagram(key_frame(n).into());
                    }
                }
            });
        }
    })
}

/// Given only edge A, whose world is gone and which names B among the world's edges (and
/// a page's address, which a native viewer skips): the status says the world is gone, B
/// joins the rotation, and when A falls silent the session goes to B (whose world is not
/// said gone).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_tells_of_its_world_and_its_other_edges() {
    let id = tls::generate().expect("a certificate");
    let fingerprint = tls::parse_fingerprint(&id.fingerprint()).expect("valid");
    let listen = || {
        let config = tls::server_config(&id).expect("a config");
        quinn::Endpoint::server(config, "127.0.0.1:0".parse().expect("valid")).expect("listens")
    };
    let (ea, eb) = (listen(), listen());
    let (a, b) = (
        ea.local_addr().expect("bound"),
        eb.local_addr().expect("bound"),
    );
    let page = format!(
        "https://127.0.0.1:{}/roam#hashes={}",
        b.port(),
        "ab".repeat(32)
    );
    let task_a = fake_edge(
        ea,
        vec![
            WorldNews::Gone("the world has not answered for 1.5 s".into()),
            WorldNews::Edges(vec![a.to_string(), b.to_string(), page]),
        ],
        false,
    )
    .await;
    let task_b = fake_edge(eb, Vec::new(), true).await;
    let s = join(&[a], fingerprint).await;
    let told = status_when(&s, "the edge's news", |st| {
        st.edges_learned == 1 && st.world.gone.is_some()
    })
    .await;
    assert_eq!(
        told.world.gone.as_deref(),
        Some("the world has not answered for 1.5 s")
    );
    assert_eq!(s.addresses(), vec![a, b]);
    // A sends nothing more: silent for a second (there is another address now), the
    // session goes to B.
    let back = status_when(&s, "the viewer goes on at B", |st| {
        st.gaps.reconnects == 1 && st.state == State::Connected
    })
    .await;
    assert_eq!(back.addr, b);
    assert_eq!(back.world.gone, None, "B does not say its world is gone");
    assert!(back.world.gone_total(Instant::now()) > Duration::ZERO);
    frame(&s).await;
    drop(s);
    task_a.abort();
    task_b.abort();
}

/// What an edge says of its world, as the session keeps it (no I/O: instants passed in):
/// gone and back, news repeated, and the time gone adding up.
#[test]
fn the_world_goes_and_comes_back_and_its_time_gone_adds_up() {
    use roam_client::edges::{Change, World};
    let t0 = Instant::now();
    let s = Duration::from_secs;
    let mut w = World::default();
    assert_eq!(w.apply(&WorldNews::Edges(vec![]), t0), None);
    assert_eq!(w.apply(&WorldNews::Back, t0), None, "back without going");
    assert_eq!(
        w.apply(&WorldNews::Gone("no answer".into()), t0),
        Some(Change::Gone("no answer".into()))
    );
    assert_eq!(
        w.apply(&WorldNews::Gone("no answer".into()), t0 + s(1)),
        None
    );
    assert_eq!(w.gone.as_deref(), Some("no answer"));
    assert_eq!(w.gone_total(t0 + s(2)), s(2));
    assert_eq!(
        w.apply(&WorldNews::Back, t0 + s(3)),
        Some(Change::Back(s(3)))
    );
    assert_eq!(w.gone, None);
    w.apply(&WorldNews::Gone("restarting".into()), t0 + s(10));
    assert_eq!(w.gone_total(t0 + s(11)), s(4));
    assert_eq!(w.back(t0 + s(12)), Some(s(2)));
    assert_eq!(w.gone_total(t0 + s(20)), s(5));
}
