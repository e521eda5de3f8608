//! The reconnection supervisor, without I/O or a clock (instants come in): what a
//! connection's end means, when a lost connection is made again and when the session ends
//! instead, how long each attempt may take, the pause between attempts, how long to keep
//! trying, and the words a session ends with. One [`Supervisor`] and one set of constants,
//! driven by both viewers: the native session's QUIC tasks (`connection.rs`) and the
//! page's WebTransport tasks (`roam-web`'s `net.rs`), which only carry out what it says.
//!
//! **How a connection ends** ([`End`]): *lost* (QUIC or the browser says so: an idle
//! timeout, a reset, a transport error), *silent* (no frame, no control message and no
//! frame bytes for [`Patience::silence`] after the welcome, or [`SILENCE_MANY`] when there
//! are other addresses, unless the patience is shorter: the server sends frames at the
//! viewer's rate whatever the world does, so silence means a stuck path or server), the
//! server *shutting down*, *final* (a refusal, the server's goodbye or close, a frame or
//! message it could not have sent), or the viewer *quitting*. Lost and silent connections
//! are made again; so is one whose server shuts down when there are other addresses
//! (another edge takes the viewer); the rest end the session.
//!
//! **Reconnecting.** The next address in turn (the same one when there is one), at once,
//! then after [`BACKOFF_FIRST`], doubling to [`BACKOFF_MOST`] between attempts, each
//! attempt's handshake within [`HANDSHAKE`] ([`HANDSHAKE_MANY`] with other addresses) and
//! its welcome and coarsest colour tile within [`JOIN_TIMEOUT`], for
//! [`Patience::reconnect_for`] (an attempt begun before then has its whole handshake).
//! Then the session ends with an error naming the server. A refusal ends it at once, and
//! so does a server that comes back with another terrain ([`TerrainId`]).
//!
//! **Silence reconnects once** per address ([`Silences`]): it may be a stuck path, but a
//! server that welcomes again and then stays silent (the same address silent twice with
//! no frame between) is stuck itself, and the session ends.

use std::fmt::Display;
use std::time::Duration;

use web_time::Instant;

use crate::conversation::TerrainId;

/// [`Patience::silence`] unless told otherwise.
pub const SILENCE: Duration = Duration::from_secs(10);

/// How long a viewer with other addresses to try waits on a silent server (no frame, no
/// message) before moving on: the server sends frames at the viewer's rate whatever the
/// world does, so 48 frame intervals of silence at 60 Hz are an edge gone, not a quiet
/// world. Instead of [`Patience::silence`] (10 s), unless that is shorter. 0.8 s, not 1:
/// the move (silence, then a loopback handshake and a resume) took 1.01 s with 1 s
/// (`tests/tests/it/needs_nats/cluster.rs`, an edge killed), the aim being 1 s at most.
pub const SILENCE_MANY: Duration = Duration::from_millis(800);

/// [`Patience::reconnect_for`] unless told otherwise: the server's hold (30 s) and a margin.
pub const RECONNECT_FOR: Duration = Duration::from_secs(35);

/// A reconnection's handshake, at most, with one address (the next attempt starts afresh;
/// the last may end this much after [`Patience::reconnect_for`]).
pub const HANDSHAKE: Duration = Duration::from_secs(5);

/// How long one handshake may take when there are other addresses to try.
pub const HANDSHAKE_MANY: Duration = Duration::from_secs(1);

/// How long the welcome and the coarsest colour tile may take, after the handshake.
pub const JOIN_TIMEOUT: Duration = Duration::from_secs(30);

/// The first pause between reconnection attempts, doubled after each up to
/// [`BACKOFF_MOST`].
pub const BACKOFF_FIRST: Duration = Duration::from_millis(100);
pub const BACKOFF_MOST: Duration = Duration::from_secs(2);

/// How long a session waits on its server.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Patience {
    /// After the welcome, this long without a frame or a control message: the connection
    /// is lost.
    pub silence: Duration,
    /// How long after a loss to keep trying to connect again.
    pub reconnect_for: Duration,
}

impl Default for Patience {
    fn default() -> Self {
        Patience {
            silence: SILENCE,
            reconnect_for: RECONNECT_FOR,
        }
    }
}

impl Patience {
    /// How long the server may be silent on a connection: shorter when there are other
    /// addresses to go to (`many`), [`SILENCE_MANY`] at most.
    pub fn allowed_silence(&self, many: bool) -> Duration {
        if many {
            self.silence.min(SILENCE_MANY)
        } else {
            self.silence
        }
    }
}

/// Where a session stands.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum State {
    Connected,
    /// The connection was lost (`why`); `attempts` to connect again so far, the one under
    /// way included.
    Reconnecting {
        why: String,
        attempts: u32,
    },
    /// No more frames will come: why.
    Ended(String),
}

/// How a connection ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum End {
    /// The viewer quit (or the session was dropped).
    Quit,
    /// Lost: worth connecting again. `silent`: the server went silent.
    Lost { why: String, silent: bool },
    /// The server is shutting down (it said goodbye so, or closed with that code): for
    /// good when there is no other address to go to.
    Shutdown(String),
    /// For good.
    Final(String),
}

impl End {
    /// The server said nothing for `silence`.
    pub fn silence(silence: Duration) -> End {
        End::Lost {
            why: format!(
                "silent: no frame or message from the server for {}",
                secs(silence)
            ),
            silent: true,
        }
    }

    /// Whether the connection is worth making again (`many`: there are other addresses).
    pub fn worth_reconnecting(&self, many: bool) -> bool {
        match self {
            End::Lost { .. } => true,
            End::Shutdown(_) => many,
            End::Quit | End::Final(_) => false,
        }
    }
}

/// Seconds, as people read them.
pub fn secs(d: Duration) -> String {
    format!("{:.1} s", d.as_secs_f64())
}

/// The rule "silence reconnects once", counted per address: a server that welcomes and
/// then stays silent twice with no frame between is stuck, and the session ends; but a
/// silence on *another* address is news of that one only. So the session ends on a
/// silence when this address was already silent since the last frame (one address: the
/// second silence in a row, as before); with several, each gets its second chance, and
/// a rotation through welcoming but silent addresses still ends.
#[derive(Clone, Debug, Default)]
pub struct Silences {
    /// The frame count at the silences below.
    frames: Option<u64>,
    /// The addresses silent since then.
    silent: Vec<usize>,
}

impl Silences {
    /// Address `i` was silent, `frames` having been received so far in the session: true
    /// when the session should end.
    pub fn silent(&mut self, i: usize, frames: u64) -> bool {
        if self.frames != Some(frames) {
            self.frames = Some(frames);
            self.silent.clear();
        }
        if self.silent.contains(&i) {
            return true;
        }
        self.silent.push(i);
        false
    }
}

/// Why a session ends, as the supervisor decides it: in the words the viewers show (the
/// window's last line, the page's message).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SessionEnd {
    /// The viewer quit.
    #[error("quit")]
    Quit,
    /// A connection ended for good (or its server shut down, with nowhere else to go), in
    /// the words of its [`End`].
    #[error("{0}")]
    Final(String),
    /// The same address went silent twice with no frame between.
    #[error(
        "lost the server at {addr}: {why}, again right after reconnecting, with no frame \
         between: the server welcomes but sends nothing"
    )]
    SilentAgain { addr: String, why: String },
    /// An attempt failed before any connection was lost (the first join's).
    #[error("connecting to {addr}: {message}")]
    Connecting { addr: String, message: String },
    /// A reconnection's attempt failed in a way another attempt cannot mend (a refusal).
    #[error("{lost}; reconnecting to {addr}: {message}")]
    Refused {
        lost: Lost,
        addr: String,
        message: String,
    },
    /// The time to reconnect ran out (`secs`), after `attempts`, the last at `addr`.
    #[error(
        "{lost}; tried to reconnect for {secs} s ({attempts} attempts; the last: {addr}: \
         {message})"
    )]
    TimeUp {
        lost: Lost,
        secs: u64,
        attempts: u32,
        addr: String,
        message: String,
    },
    /// A server came back with another terrain (`differences`, as
    /// [`TerrainId::differences`] says), after `lost` (none: no connection was lost).
    #[error(
        "{}the server changed its terrain: {differences}",
        lost.as_ref().map(|l| format!("{l}; ")).unwrap_or_default()
    )]
    TerrainChanged {
        lost: Option<Lost>,
        differences: String,
    },
}

/// The connection whose loss a reconnection is for: its address and why it was lost.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lost {
    pub from: String,
    pub why: String,
}

impl Display for Lost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "lost the server at {}: {}", self.from, self.why)
    }
}

/// One attempt to connect again: its number (from 1) and how long its handshake may take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attempt {
    pub number: u32,
    pub handshake: Duration,
}

/// A reconnection under way.
#[derive(Clone, Debug)]
struct Round {
    /// The connection lost.
    lost: Lost,
    /// No attempt begins after this.
    deadline: Instant,
    attempts: u32,
    /// The pause after the next failure.
    backoff: Duration,
}

/// A session's reconnections, decided: fed each connection's end, each attempt's outcome
/// and the time, it says whether to connect again, how, after what pause, and why the
/// session ends when it does.
#[derive(Clone, Debug)]
pub struct Supervisor {
    patience: Patience,
    /// The first connection's terrain: every later one must show it.
    terrain: TerrainId,
    silences: Silences,
    round: Option<Round>,
}

impl Supervisor {
    /// A session joined showing `terrain`, waiting on its servers as `patience` says.
    pub fn new(patience: Patience, terrain: TerrainId) -> Supervisor {
        Supervisor {
            patience,
            terrain,
            silences: Silences::default(),
            round: None,
        }
    }

    pub fn patience(&self) -> Patience {
        self.patience
    }

    /// The connection to `addr` (place `here` in the rotation; `many`: there are other
    /// addresses) ended as `end`, `frames` frames having been received in the session so
    /// far: `Ok` to connect again ([`Supervisor::attempt`]), or why the session ends.
    pub fn ended(
        &mut self,
        end: End,
        addr: &dyn Display,
        here: usize,
        many: bool,
        frames: u64,
        now: Instant,
    ) -> Result<(), SessionEnd> {
        let (why, silent) = match end {
            End::Quit => return Err(SessionEnd::Quit),
            // Another edge takes the viewer.
            End::Shutdown(why) if many => (why, false),
            End::Final(why) | End::Shutdown(why) => return Err(SessionEnd::Final(why)),
            End::Lost { why, silent } => (why, silent),
        };
        if silent && self.silences.silent(here, frames) {
            let addr = addr.to_string();
            return Err(SessionEnd::SilentAgain { addr, why });
        }
        self.round = Some(Round {
            lost: Lost {
                from: addr.to_string(),
                why,
            },
            deadline: now + self.patience.reconnect_for,
            attempts: 0,
            backoff: BACKOFF_FIRST,
        });
        Ok(())
    }

    /// The next attempt to connect again (`many`: there are other addresses; the first
    /// attempt comes at once, each other after the pause [`Supervisor::failed`] gave).
    pub fn attempt(&mut self, many: bool) -> Attempt {
        let number = match &mut self.round {
            Some(round) => {
                round.attempts += 1;
                round.attempts
            }
            None => 1,
        };
        Attempt {
            number,
            handshake: if many { HANDSHAKE_MANY } else { HANDSHAKE },
        }
    }

    /// Where the session stands as far as the supervisor knows: reconnecting while a
    /// reconnection is under way, else connected.
    pub fn state(&self) -> State {
        match &self.round {
            Some(round) => State::Reconnecting {
                why: round.lost.why.clone(),
                attempts: round.attempts,
            },
            None => State::Connected,
        }
    }

    /// The attempt at `addr` failed with `message` (`lost`: another attempt may succeed):
    /// the pause before the next one, or why the session ends (a refusal; the time is up).
    pub fn failed(
        &mut self,
        addr: &dyn Display,
        lost: bool,
        message: &str,
        now: Instant,
    ) -> Result<Duration, SessionEnd> {
        let reconnect_for = self.patience.reconnect_for;
        let (addr, message) = (addr.to_string(), message.to_owned());
        let Some(round) = &mut self.round else {
            return Err(SessionEnd::Connecting { addr, message });
        };
        if !lost {
            let lost = round.lost.clone();
            return Err(SessionEnd::Refused {
                lost,
                addr,
                message,
            });
        }
        let left = round.deadline.saturating_duration_since(now);
        if left.is_zero() {
            return Err(SessionEnd::TimeUp {
                lost: round.lost.clone(),
                secs: reconnect_for.as_secs(),
                attempts: round.attempts,
                addr,
                message,
            });
        }
        let pause = round.backoff.min(left);
        round.backoff = (round.backoff * 2).min(BACKOFF_MOST);
        Ok(pause)
    }

    /// An attempt joined, showing the terrain `found`: `Ok` when it is the session's (the
    /// reconnection is over), else why the session ends.
    pub fn joined(&mut self, found: &TerrainId) -> Result<(), SessionEnd> {
        let round = self.round.take();
        match self.terrain.differences(found) {
            None => Ok(()),
            Some(differences) => Err(SessionEnd::TerrainChanged {
                lost: round.map(|r| r.lost),
                differences,
            }),
        }
    }
}

#[cfg(test)]
#[path = "supervisor_tests.rs"]
mod tests;
