//! The reconnection supervisor ([`Supervisor`], shared by the native session and the
//! page) driven with instants made up from one reading of the clock: the verdict on each
//! kind of end, the backoff from 100 ms to 2 s and the deadline, a refusal, another
//! terrain, and a server silent twice with no frame between. No network, no waiting.

use std::time::{Duration, Instant};

use roam_client::conversation::TerrainId;
use roam_client::supervisor::{
    Attempt, BACKOFF_FIRST, End, HANDSHAKE, HANDSHAKE_MANY, Lost, Patience, SILENCE, SessionEnd,
    State, Supervisor,
};
use roam_protocol::messages::Welcome;
use roam_protocol::tiles::ColorLayout;
use roam_tests::fixtures::fake_welcome;

fn welcome(h_scale: f64) -> Welcome {
    let color = ColorLayout {
        cells: 16,
        tile: 16,
        levels: 1,
        window: 1,
    };
    Welcome {
        h_scale,
        ..fake_welcome(color)
    }
}

fn terrain(h_scale: f64) -> TerrainId {
    TerrainId::of(&welcome(h_scale), &[7; 16 * 16 * 3])
}

fn lost(why: &str) -> End {
    End::Lost {
        why: why.into(),
        silent: false,
    }
}

/// The loss of `a:1`, for `why`.
fn lost_at_a(why: &str) -> Lost {
    Lost {
        from: "a:1".into(),
        why: why.into(),
    }
}

fn ms(n: u64) -> Duration {
    Duration::from_millis(n)
}

/// Which ends end the session, in whose words, and which make the supervisor reconnect.
#[test]
fn a_quit_a_final_end_or_a_lone_shutdown_ends_the_session() {
    let t0 = Instant::now();
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    assert_eq!(
        s.ended(End::Quit, &"a", 0, false, 0, t0),
        Err(SessionEnd::Quit)
    );
    let why = "the server is shutting down: bye".to_owned();
    assert_eq!(
        s.ended(End::Shutdown(why.clone()), &"a", 0, false, 0, t0),
        Err(SessionEnd::Final(why.clone()))
    );
    assert_eq!(
        s.ended(End::Final("refused".into()), &"a", 0, true, 0, t0),
        Err(SessionEnd::Final("refused".into()))
    );
    assert_eq!(s.state(), State::Connected);
    // With another address a shutdown is a loss: another edge takes the viewer.
    assert_eq!(
        s.ended(End::Shutdown(why.clone()), &"a", 0, true, 0, t0),
        Ok(())
    );
    assert_eq!(s.state(), State::Reconnecting { why, attempts: 0 });
}

#[test]
fn attempts_back_off_from_100_ms_to_2_s_until_the_time_is_up() {
    let patience = Patience {
        silence: SILENCE,
        reconnect_for: Duration::from_secs(10),
    };
    let t0 = Instant::now();
    let deadline = t0 + patience.reconnect_for;
    let mut s = Supervisor::new(patience, terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, false, 10, t0)
        .expect("a loss reconnects");
    let mut now = t0;
    let mut pauses = Vec::new();
    let (attempts, why) = loop {
        let attempt = s.attempt(false);
        // Fails rather than loops: 10 s of pauses capped at 2 s is fewer than 20 attempts.
        assert!(
            attempt.number < 20,
            "still trying after {} attempts",
            attempt.number
        );
        assert!(
            now < deadline,
            "attempt {} began after the deadline",
            attempt.number
        );
        assert_eq!(attempt.handshake, HANDSHAKE);
        assert_eq!(
            s.state(),
            State::Reconnecting {
                why: "reset".into(),
                attempts: attempt.number
            }
        );
        // Each attempt takes 100 ms to fail.
        now += ms(100);
        match s.failed(&"a:1", true, "timed out", now) {
            Ok(pause) => {
                pauses.push(pause);
                now += pause;
            }
            Err(why) => break (attempt.number, why),
        }
    };
    assert!(now >= deadline);
    assert_eq!(pauses, [100, 200, 400, 800, 1600, 2000, 2000, 2000].map(ms));
    assert_eq!(
        why,
        SessionEnd::TimeUp {
            lost: lost_at_a("reset"),
            secs: 10,
            attempts,
            addr: "a:1".into(),
            message: "timed out".into(),
        }
    );
    assert_eq!(
        why.to_string(),
        format!(
            "lost the server at a:1: reset; tried to reconnect for 10 s ({attempts} attempts; \
             the last: a:1: timed out)"
        )
    );
    // A pause never goes past the deadline.
    let mut s = Supervisor::new(patience, terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, false, 0, t0)
        .expect("a loss");
    s.attempt(false);
    assert_eq!(s.failed(&"a:1", true, "x", deadline - ms(30)), Ok(ms(30)));
    // With other addresses each handshake has a second.
    let mut s = Supervisor::new(patience, terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, true, 0, t0)
        .expect("a loss");
    assert_eq!(
        s.attempt(true),
        Attempt {
            number: 1,
            handshake: HANDSHAKE_MANY
        }
    );
}

#[test]
fn a_refusal_or_another_terrain_ends_the_reconnection_and_the_same_terrain_ends_it_well() {
    let t0 = Instant::now();
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, false, 0, t0)
        .expect("a loss");
    s.attempt(false);
    let refused = s
        .failed(&"a:1", false, "refused: wrong token", t0)
        .expect_err("a refusal");
    assert_eq!(
        refused,
        SessionEnd::Refused {
            lost: lost_at_a("reset"),
            addr: "a:1".into(),
            message: "refused: wrong token".into(),
        }
    );
    assert_eq!(
        refused.to_string(),
        "lost the server at a:1: reset; reconnecting to a:1: refused: wrong token"
    );
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, false, 0, t0)
        .expect("a loss");
    s.attempt(false);
    let err = s.joined(&terrain(2.0)).expect_err("another terrain");
    assert!(
        matches!(&err, SessionEnd::TerrainChanged { lost: Some(l), .. } if *l == lost_at_a("reset")),
        "{err:?}"
    );
    assert!(
        err.to_string()
            .starts_with("lost the server at a:1: reset; the server changed its terrain: scales 2"),
        "{err}"
    );
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    s.ended(lost("reset"), &"a:1", 0, false, 0, t0)
        .expect("a loss");
    s.attempt(false);
    assert_eq!(s.joined(&terrain(1.0)), Ok(()));
    assert_eq!(s.state(), State::Connected);
    // The next loss starts afresh: its first attempt is number 1, after no pause.
    s.ended(lost("reset again"), &"a:1", 0, false, 0, t0)
        .expect("a loss");
    assert_eq!(s.attempt(false).number, 1);
    assert_eq!(s.failed(&"a:1", true, "x", t0), Ok(BACKOFF_FIRST));
}

#[test]
fn a_server_silent_twice_with_no_frame_between_ends_the_session() {
    let t0 = Instant::now();
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    let silence = || End::silence(ms(1_000));
    s.ended(silence(), &"a:1", 0, false, 5, t0).expect("once");
    s.attempt(false);
    s.joined(&terrain(1.0)).expect("the same terrain");
    let err = s
        .ended(silence(), &"a:1", 0, false, 5, t0)
        .expect_err("twice");
    assert!(matches!(&err, SessionEnd::SilentAgain { addr, .. } if addr == "a:1"));
    assert_eq!(
        err.to_string(),
        "lost the server at a:1: silent: no frame or message from the server for 1.0 s, again \
         right after reconnecting, with no frame between: the server welcomes but sends nothing"
    );
    // A frame between: another chance.
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    s.ended(silence(), &"a:1", 0, false, 5, t0).expect("once");
    s.ended(silence(), &"a:1", 0, false, 6, t0)
        .expect("a frame came between");
    // A loss that is not a silence is not counted.
    s.ended(lost("reset"), &"a:1", 0, false, 6, t0)
        .expect("not a silence");
}

/// How each end of a session reads: the words the window and the page show.
#[test]
fn every_end_of_a_session_names_the_server_and_why() {
    let cases = [
        (SessionEnd::Quit, "quit"),
        (
            SessionEnd::Final("refused: wrong token".into()),
            "refused: wrong token",
        ),
        (
            SessionEnd::Connecting {
                addr: "a:1".into(),
                message: "timed out".into(),
            },
            "connecting to a:1: timed out",
        ),
        (
            SessionEnd::TerrainChanged {
                lost: None,
                differences: "another colour map".into(),
            },
            "the server changed its terrain: another colour map",
        ),
        (
            SessionEnd::TerrainChanged {
                lost: Some(lost_at_a("reset")),
                differences: "another colour map".into(),
            },
            "lost the server at a:1: reset; the server changed its terrain: another colour map",
        ),
    ];
    for (end, words) in cases {
        assert_eq!(end.to_string(), words);
    }
    // The first join's failure, before any loss, names the address tried.
    let mut s = Supervisor::new(Patience::default(), terrain(1.0));
    assert_eq!(
        s.failed(&"a:1", true, "timed out", Instant::now()),
        Err(SessionEnd::Connecting {
            addr: "a:1".into(),
            message: "timed out".into(),
        })
    );
}
