//! Limits a token holder meets, against a real server on loopback: the 65th viewer is
//! refused as full (and one leaving makes room), a viewer whose state would not fit in
//! `--max-memory` is refused with a reason naming it (a cheaper one still fits, a budget
//! raised later grows its seat only as far as the limit, and one leaving makes room), a
//! viewer asking more triangles and frames
//! than `--max-budget` and `--max-fps` gets those (its frames counted against the world's
//! ticks, both paced by the server's clock), and eight viewers asking the most
//! triangles at the most frames a second do not slow the world (no tick dropped: the
//! world thread always finds a core, `net::Shared::makers`). Counts, not times: the rates
//! are what `roam-flood` and `scripts/capacity.sh` print.

use std::time::Duration;

use roam_client::conversation::ConversationError;
use roam_client::session::{KeySource, Session};
use roam_link::wire;
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, Role, ServerMessage};
use roam_tests::fixtures::{self, Running, flat};

use crate::turn;

fn hello(r: &Running, role: Role, budget: u32, frame_rate: u16) -> Hello {
    fixtures::hello(role, &r.token, [640, 360], budget, frame_rate)
}

/// A raw connection that said hello, its control stream kept open (dropping it would say
/// goodbye), and the server's answer (a welcome or a refusal).
struct Raw {
    _endpoint: quinn::Endpoint,
    conn: quinn::Connection,
    _control: (quinn::SendStream, quinn::RecvStream),
    answer: ServerMessage,
}

async fn say_hello(r: &Running, hello: &Hello) -> Raw {
    let (endpoint, conn) = roam_client::quic::connect(r.server.addr, r.fingerprint)
        .await
        .expect("connects");
    let (mut send, mut recv) = conn.open_bi().await.expect("a control stream");
    wire::write(&mut send, &ClientMessage::Hello(hello.clone()))
        .await
        .expect("the hello goes");
    let answer = wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE)
        .await
        .expect("an answer");
    Raw {
        _endpoint: endpoint,
        conn,
        _control: (send, recv),
        answer,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_65th_viewer_is_refused_as_full_and_a_leave_makes_room() {
    let _turn = turn().await;
    let r = fixtures::serve(flat(), |o| o);
    // Drivers at the least budget and one frame a second: the server's limit is on
    // viewers, whatever each costs.
    let cheap = hello(&r, Role::Driver, messages::MIN_BUDGET, 1);
    let mut viewers = Vec::new();
    for k in 0..roam_server::net::MAX_VIEWERS {
        let v = say_hello(&r, &cheap).await;
        assert!(
            matches!(v.answer, ServerMessage::Welcome(_)),
            "viewer {k}: {:?}",
            v.answer
        );
        viewers.push(v);
    }
    let extra = say_hello(&r, &cheap).await;
    assert_eq!(
        extra.answer,
        ServerMessage::Refused(Reason::Full {
            viewers: roam_server::net::MAX_VIEWERS as u32
        })
    );
    let spectator = hello(&r, Role::Spectator { follow: None }, 2, 1);
    let extra = say_hello(&r, &spectator).await;
    assert!(matches!(
        extra.answer,
        ServerMessage::Refused(Reason::Full { .. })
    ));
    assert_eq!(r.server.counts().refused, 2);
    // One leaves (with its goodbye code): the next is welcome.
    let gone = viewers.pop().expect("64 of them");
    gone.conn.close(messages::close::BYE.into(), b"bye");
    // Once the server has seen it go (waited for on the world's ticks, bounded), the
    // next is welcome.
    let mut ticks = r.server.watch();
    for _ in 0..3_000 {
        if r.server.load().1 < roam_server::net::MAX_VIEWERS {
            break;
        }
        let _ = ticks.changed().await;
    }
    let next = say_hello(&r, &cheap).await;
    let answer = matches!(next.answer, ServerMessage::Welcome(_)).then_some(next);
    assert!(answer.is_some(), "a place after a leave");
    r.server.shutdown().await.expect("stops");
}

/// Waits (on the world's ticks, bounded) until `done` says so of the server.
async fn until(r: &Running, what: &str, done: impl Fn(&roam_server::net::Server) -> bool) {
    let mut ticks = r.server.watch();
    for _ in 0..3_000 {
        if done(&r.server) {
            return;
        }
        let _ = ticks.changed().await;
    }
    panic!("{what}: not within 3,000 ticks");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_past_the_memory_limit_is_refused_naming_it() {
    use roam_server::viewer::admission::viewer_bytes;
    let _turn = turn().await;
    const BUDGET: u32 = 65_536;
    // Room for two viewers at 65,536 triangles, and half of one more.
    let limit = viewer_bytes(BUDGET) * 5 / 2;
    let r = fixtures::serve(flat(), |o| roam_server::net::Options {
        max_memory: Some(limit),
        ..o
    });
    assert_eq!(r.server.memory(), (0, limit));
    let big = hello(&r, Role::Driver, BUDGET, 30);
    let first = say_hello(&r, &big).await;
    let second = say_hello(&r, &big).await;
    for v in [&first, &second] {
        assert!(
            matches!(v.answer, ServerMessage::Welcome(_)),
            "{:?}",
            v.answer
        );
    }
    assert_eq!(r.server.memory().0, 2 * viewer_bytes(BUDGET));
    // The third would not fit: refused, with the limit named (the viewer shows the reason).
    let third = say_hello(&r, &big).await;
    let ServerMessage::Refused(Reason::Unavailable(why)) = &third.answer else {
        panic!("expected a refusal, got {:?}", third.answer);
    };
    assert!(why.contains("--max-memory"), "{why}");
    assert!(why.contains("65536 triangles"), "{why}");
    let shown = roam_client::conversation::welcome_of(third.answer.clone()).expect_err("refused");
    assert!(
        matches!(&shown, ConversationError::Refused(Reason::Unavailable(w)) if w == why),
        "{shown:?}"
    );
    assert!(shown.to_string().contains("--max-memory"), "{shown}");
    assert_eq!(r.server.counts().refused, 1);
    assert_eq!(r.server.load().1, 2);
    // A viewer asking few triangles still fits in what is left ...
    let small = hello(&r, Role::Driver, messages::MIN_BUDGET, 30);
    let mut cheap = say_hello(&r, &small).await;
    assert!(
        matches!(cheap.answer, ServerMessage::Welcome(_)),
        "{:?}",
        cheap.answer
    );
    // ... and asking for more later, its seat grows only as far as the limit.
    wire::write(
        &mut cheap._control.0,
        &ClientMessage::Budget(messages::MAX_BUDGET),
    )
    .await
    .expect("the budget goes");
    until(&r, "the seat grows to the limit", |s| s.memory().0 == limit).await;
    let fourth = say_hello(&r, &small).await;
    assert!(
        matches!(
            fourth.answer,
            ServerMessage::Refused(Reason::Unavailable(_))
        ),
        "{:?}",
        fourth.answer
    );
    // One leaves (with its goodbye code): its seat is given back, and the next is welcome.
    first.conn.close(messages::close::BYE.into(), b"bye");
    until(&r, "the seat is given back", |s| {
        s.memory().0 == limit - viewer_bytes(BUDGET)
    })
    .await;
    let next = say_hello(&r, &big).await;
    assert!(
        matches!(next.answer, ServerMessage::Welcome(_)),
        "{:?}",
        next.answer
    );
    drop((second, cheap, next));
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn greedy_viewers_do_not_slow_the_world() {
    let _turn = turn().await;
    // Eight seats of 67 MiB each (admission's estimate at the most triangles): no memory
    // limit, whatever the machine's default; the world's ticks are what this tests.
    let r = fixtures::serve(fixtures::kossou(), |o| roam_server::net::Options {
        max_memory: Some(u64::MAX),
        ..o
    });
    let greedy = hello(&r, Role::Driver, messages::MAX_BUDGET, 240);
    let mut sessions = Vec::new();
    for _ in 0..8 {
        let s = Session::join(
            r.server.addr,
            r.fingerprint,
            greedy.clone(),
            KeySource::None,
        )
        .await
        .expect("joins");
        sessions.push(s);
    }
    let start = r.server.snapshot().tick;
    let stats = r.server.world_stats();
    let dropped_before = stats.dropped();
    // Each viewer takes frames (without decoding: the load under test is the server's)
    // while the world makes 500 ticks.
    let mut watch = r.server.watch();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let takers: Vec<_> = sessions
        .into_iter()
        .map(|s| {
            let mut stopped = stopped.clone();
            tokio::spawn(async move {
                let mut frames = 0u32;
                loop {
                    tokio::select! {
                        f = s.next_frame(false) => match f {
                            Ok(_) => frames += 1,
                            Err(_) => break,
                        },
                        _ = stopped.wait_for(|&s| s) => break,
                    }
                }
                s.quit().await;
                frames
            })
        })
        .collect();
    tokio::time::timeout(
        Duration::from_secs(120),
        watch.wait_for(|s| s.tick >= start + 500),
    )
    .await
    .expect("the world makes 500 ticks")
    .expect("the world runs");
    assert_eq!(
        stats.dropped(),
        dropped_before,
        "no tick dropped under eight greedy viewers"
    );
    stop.send_replace(true);
    for t in takers {
        let frames = t.await.expect("a viewer's task");
        assert!(frames > 0, "every greedy viewer is served");
    }
    r.server.shutdown().await.expect("stops");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_asking_more_than_the_caps_is_served_the_caps() {
    let _turn = turn().await;
    const MAX_BUDGET: u32 = 4_096;
    const MAX_FPS: u16 = 20;
    let r = fixtures::serve(fixtures::kossou(), |o| roam_server::net::Options {
        limits: roam_server::viewer::ViewerLimits {
            max_budget: MAX_BUDGET,
            max_fps: MAX_FPS,
            ..Default::default()
        },
        ..o
    });
    let stats = r.server.world_stats();
    let (start, dropped_before) = (r.server.snapshot().tick, stats.dropped());
    let got = roam_client::headless::run(
        r.server.addr,
        r.fingerprint,
        roam_client::headless::ViewerOptions {
            token: r.token.clone(),
            budget: messages::MAX_BUDGET,
            frame_rate: 240,
            frames: 30,
            ..Default::default()
        },
    )
    .await
    .expect("the viewer is served");
    let ticks = r.server.snapshot().tick - start + (stats.dropped() - dropped_before);
    assert_eq!(got.budget_served, MAX_BUDGET);
    assert!(
        got.max_triangles <= MAX_BUDGET as usize && got.max_triangles > MAX_BUDGET as usize / 2,
        "{} triangles",
        got.max_triangles
    );
    // Frames are paced by the server's clock, as the world's ticks are: at 20 a second
    // against 100 ticks, at most one frame per 5 ticks (and a few at the edges). Asked
    // 240, an uncapped server would make 12 times as many.
    let made = got.last_frame - got.first_frame.expect("frames came") + 1;
    assert!(
        made * 5 <= ticks + 15,
        "{made} frames in {ticks} ticks: more than {MAX_FPS} a second"
    );
    r.server.shutdown().await.expect("stops");
}
