//! The reconnection supervisor's rules that need no instant: the ends worth connecting
//! again, the silence allowed and its words, and the silence rule per address. Its
//! decisions over time (the backoff, the deadline, refusals, another terrain, a server
//! silent twice) are driven with made-up instants in `tests/tests/it/supervisor.rs` (a core
//! reads no clock, not even in its tests).

use std::time::Duration;

use super::*;

#[test]
fn which_ends_are_worth_connecting_again() {
    let lost = End::Lost {
        why: "reset".into(),
        silent: false,
    };
    assert!(lost.worth_reconnecting(false));
    assert!(End::silence(Duration::from_millis(800)).worth_reconnecting(false));
    assert!(!End::Shutdown("x".into()).worth_reconnecting(false));
    // With another address a shutdown is a loss: another edge takes the viewer.
    assert!(End::Shutdown("x".into()).worth_reconnecting(true));
    assert!(!End::Final("x".into()).worth_reconnecting(true));
    assert!(!End::Quit.worth_reconnecting(true));
}

#[test]
fn the_silence_allowed_is_shorter_with_other_addresses() {
    let p = Patience::default();
    assert_eq!(p.allowed_silence(false), SILENCE);
    assert_eq!(p.allowed_silence(true), SILENCE_MANY);
    let short = Patience {
        silence: Duration::from_millis(300),
        ..p
    };
    assert_eq!(short.allowed_silence(true), Duration::from_millis(300));
    let End::Lost { why, silent } = End::silence(Duration::from_millis(800)) else {
        unreachable!("a silence is a loss");
    };
    assert!(silent);
    assert_eq!(why, "silent: no frame or message from the server for 0.8 s");
}

#[test]
fn silence_ends_a_session_only_when_the_same_address_is_silent_again() {
    // One address: the second silence with no frame between ends it.
    let mut s = Silences::default();
    assert!(!s.silent(0, 10));
    assert!(s.silent(0, 10));
    // A frame between: a fresh chance.
    let mut s = Silences::default();
    assert!(!s.silent(0, 10));
    assert!(!s.silent(0, 11));
    // Two addresses: a silence on the other is not the same one's second.
    let mut s = Silences::default();
    assert!(!s.silent(0, 5));
    assert!(!s.silent(1, 5));
    assert!(s.silent(0, 5));
    let mut s = Silences::default();
    assert!(!s.silent(0, 5));
    assert!(!s.silent(1, 5));
    assert!(
        !s.silent(0, 6),
        "frames came from 1 before 0 was silent again"
    );
}
