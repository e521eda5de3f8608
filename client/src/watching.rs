//! Watching: what a spectator's keys ask of the server, with no window or clock, shared by
//! the window and the page. Any spectator follows another vehicle (Tab: the next by id;
//! 1–9: the first to ninth by id). Watching a recording (`serve --replay`,
//! `roam-client --replay`), the one holding the controls also steers its clock:
//!
//! | key | what |
//! | --- | --- |
//! | Space | pause, resume |
//! | `[` `]` | half, twice the speed (¼× to 8×) |
//! | ← → | 10 s back, on |
//! | `,` `.` | to the previous, next join or leave |
//! | Home End | to the start, the end |
//!
//! and the HUD's line says the recording's clock, its length, the speed and who holds the
//! controls ([`replay_line`]).

use roam_protocol::messages::{ReplayControl, ReplayStatus};

/// World ticks a second.
const TICKS_PER_SECOND: u64 = 100;

/// How far ← and → seek, ticks (10 s).
pub const SEEK_STEP: u64 = 10 * TICKS_PER_SECOND;

/// What a key asks of the server.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ask {
    /// Follow this vehicle.
    Follow(u16),
    /// Steer the recording's clock.
    Replay(ReplayControl),
}

/// What key `name` (the window's and the page's names: `Space`, `Tab`, `ArrowLeft`, `Home`,
/// a character) asks of a spectator following `me`, with `ids` the vehicles in the newest
/// frame, and (watching a recording) `replay` its state and `tick` the newest frame's.
/// `None`: not a watching key (or one the viewer cannot use: the controls are another's).
pub fn key(name: &str, me: u16, ids: &[u16], replay: Option<(&ReplayStatus, u64)>) -> Option<Ask> {
    let mut sorted = ids.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    match name {
        "Tab" => {
            let next = sorted
                .iter()
                .copied()
                .find(|&id| id > me)
                .or_else(|| sorted.first().copied())?;
            return (next != me).then_some(Ask::Follow(next));
        }
        d if d.len() == 1 && ('1'..='9').contains(&d.chars().next()?) => {
            let k = d.parse::<usize>().ok()? - 1;
            return sorted.get(k).map(|&id| Ask::Follow(id));
        }
        _ => {}
    }
    let (status, tick) = replay?;
    if !status.control {
        return None;
    }
    let c = match name {
        "Space" | " " => {
            if status.paused {
                ReplayControl::Resume
            } else {
                ReplayControl::Pause
            }
        }
        "]" => ReplayControl::Speed(status.speed.saturating_mul(2).min(32)),
        "[" => ReplayControl::Speed((status.speed / 2).max(1)),
        "ArrowRight" => ReplayControl::Seek(tick.saturating_add(SEEK_STEP).min(status.end)),
        "ArrowLeft" => ReplayControl::Seek(tick.saturating_sub(SEEK_STEP).max(status.start)),
        "." => ReplayControl::SeekMark { forward: true },
        "," => ReplayControl::SeekMark { forward: false },
        "Home" => ReplayControl::Seek(status.start),
        "End" => ReplayControl::Seek(status.end),
        _ => return None,
    };
    Some(Ask::Replay(c))
}

/// `ticks` as `m:ss.s`.
fn clock(ticks: u64) -> String {
    let tenths = ticks / (TICKS_PER_SECOND / 10);
    format!("{}:{:02}.{}", tenths / 600, tenths / 10 % 60, tenths % 10)
}

/// The speed, in quarters, as `×2`, `×½`, `×¼`.
fn speed(quarters: u8) -> String {
    match quarters {
        1 => "×¼".into(),
        2 => "×½".into(),
        3 => "×¾".into(),
        q if q % 4 == 0 => format!("×{}", q / 4),
        q => format!("×{:.2}", f64::from(q) / 4.0),
    }
}

/// The HUD's line for a watched recording whose newest frame shows `tick`.
pub fn replay_line(status: &ReplayStatus, tick: u64) -> String {
    // (A server saying its end comes before its start is shown as a recording of none.)
    let end = status.end.max(status.start);
    let at = tick.clamp(status.start, end) - status.start;
    let length = end - status.start;
    let state = if status.paused {
        "paused".to_string()
    } else if tick >= status.end {
        "at its end".to_string()
    } else {
        speed(status.speed)
    };
    let controls = if status.control {
        "[space] pause · [ ] speed · ←/→ 10 s · [,]/[.] joins and leaves · Home/End".to_string()
    } else {
        format!("the controls are {}'s", status.controller)
    };
    format!(
        "replay {} / {} · {state} · {controls}",
        clock(at),
        clock(length)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(control: bool, paused: bool, speed: u8) -> ReplayStatus {
        ReplayStatus {
            tick: 0,
            start: 100,
            end: 100 + 60 * 60 * 100,
            speed,
            paused,
            control,
            controller: "127.0.0.1:5000".into(),
        }
    }

    fn check(name: &str, me: u16, replay: Option<(&ReplayStatus, u64)>, expected: Option<Ask>) {
        assert_eq!(key(name, me, &[7, 3, 12], replay), expected, "{name}");
    }

    #[test]
    fn keys_follow_and_steer_the_clock() {
        use Ask::{Follow, Replay};
        use ReplayControl::*;
        // Following, live or watching: by id order, wrapping.
        check("Tab", 3, None, Some(Follow(7)));
        check("Tab", 12, None, Some(Follow(3)));
        check("Tab", 5, None, Some(Follow(7)));
        check("1", 12, None, Some(Follow(3)));
        check("3", 3, None, Some(Follow(12)));
        check("4", 3, None, None);
        check("Space", 3, None, None);
        assert_eq!(
            key("Tab", 3, &[3], None),
            None,
            "alone: nothing to switch to"
        );
        // The clock, by the one holding the controls.
        let playing = status(true, false, 4);
        let s = Some((&playing, 5000));
        check("Space", 3, s, Some(Replay(Pause)));
        check(
            "Space",
            3,
            Some((&status(true, true, 4), 5000)),
            Some(Replay(Resume)),
        );
        check("]", 3, s, Some(Replay(Speed(8))));
        check("[", 3, s, Some(Replay(Speed(2))));
        check(
            "]",
            3,
            Some((&status(true, false, 32), 0)),
            Some(Replay(Speed(32))),
        );
        check(
            "[",
            3,
            Some((&status(true, false, 1), 0)),
            Some(Replay(Speed(1))),
        );
        check("ArrowRight", 3, s, Some(Replay(Seek(6000))));
        check("ArrowLeft", 3, s, Some(Replay(Seek(4000))));
        check(
            "ArrowLeft",
            3,
            Some((&playing, 150)),
            Some(Replay(Seek(100))),
        );
        check(
            "ArrowRight",
            3,
            Some((&playing, playing.end - 5)),
            Some(Replay(Seek(playing.end))),
        );
        check(".", 3, s, Some(Replay(SeekMark { forward: true })));
        check(",", 3, s, Some(Replay(SeekMark { forward: false })));
        check("Home", 3, s, Some(Replay(Seek(100))));
        check("End", 3, s, Some(Replay(Seek(playing.end))));
        check("x", 3, s, None);
        // Another's controls: following only.
        let theirs = status(false, false, 4);
        check("Space", 3, Some((&theirs, 5000)), None);
        check("Tab", 3, Some((&theirs, 5000)), Some(Follow(7)));
    }

    #[test]
    fn the_hud_says_the_clock_length_speed_and_who_controls() {
        let s = status(true, false, 8);
        let line = replay_line(&s, 100 + 83 * 100 + 40);
        assert!(
            line.starts_with("replay 1:23.4 / 60:00.0 · ×2 · [space]"),
            "{line}"
        );
        assert!(replay_line(&status(true, true, 8), 100).contains("0:00.0 / 60:00.0 · paused"));
        assert!(
            replay_line(&status(false, false, 1), 100)
                .contains("×¼ · the controls are 127.0.0.1:5000's")
        );
        assert!(replay_line(&s, s.end).contains("at its end"));
        // Nonsense from a server is shown, not a panic.
        let upside_down = ReplayStatus {
            start: 500,
            end: 100,
            ..s
        };
        assert!(replay_line(&upside_down, 0).starts_with("replay 0:00.0 / 0:00.0"));
    }
}
