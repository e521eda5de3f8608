//! How a world or an edge says and hears bus messages: sealed ([`super::seal`], with the
//! cluster's secret) or, only when told `--insecure-bus`, plain bincode as before. A
//! [`Voice`] encodes and seals; an [`Ear`] opens, refuses replays, decodes, and counts
//! (and logs, at the first, second, fourth… of each kind) what it refuses.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use roam_protocol::messages::{Checked, decode};
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::Malformed;
use super::seal::{BusKey, Header, Kind, MAGIC, Opener, Refusal, RefusedCounts, Sealer};
use super::window::Replays;

/// This process's voice on the bus.
pub struct Voice {
    sealer: Option<Sealer>,
    /// Plain messages' count (a request's number, for its answer's inbox).
    plain: AtomicU64,
}

impl Voice {
    /// Sealing as `sender` under `key`, or plain (`None`: `--insecure-bus`).
    pub fn new(key: Option<&BusKey>, sender: u64) -> Voice {
        Voice {
            sealer: key.map(|k| Sealer::new(k, sender)),
            plain: AtomicU64::new(0),
        }
    }

    /// `msg` as it goes on the bus (a `kind` for `to`, answering `re`), and its number.
    pub fn say<T: Serialize>(&self, kind: Kind, to: u64, re: u64, msg: &T) -> (u64, bytes::Bytes) {
        self.say_bound(kind, to, re, b"", msg)
    }

    /// The number the next `kind` this voice says will carry (taken: [`Voice::say_numbered`]
    /// says it).
    pub fn next(&self, kind: Kind) -> u64 {
        match &self.sealer {
            Some(s) => s.take(kind),
            None => self.plain.fetch_add(1, Ordering::Relaxed) + 1,
        }
    }

    /// `msg` as [`Voice::say_bound`] says it, under number `counter` from [`Voice::next`].
    pub fn say_numbered<T: Serialize>(
        &self,
        kind: Kind,
        counter: u64,
        (to, re): (u64, u64),
        bind: &[u8],
        msg: &T,
    ) -> bytes::Bytes {
        let plain = super::encode(msg);
        match &self.sealer {
            Some(s) => s.seal_numbered(kind, counter, to, re, bind, &plain).into(),
            None => plain,
        }
    }

    /// [`Voice::say`], the seal bound to `bind` (a request's reply subject: played again
    /// with another, it does not open).
    pub fn say_bound<T: Serialize>(
        &self,
        kind: Kind,
        to: u64,
        re: u64,
        bind: &[u8],
        msg: &T,
    ) -> (u64, bytes::Bytes) {
        let counter = self.next(kind);
        (
            counter,
            self.say_numbered(kind, counter, (to, re), bind, msg),
        )
    }
}

/// One task's hearing of one kind of message.
pub struct Ear {
    kind: Kind,
    opener: Option<Opener>,
    replays: Replays,
    counts: Arc<RefusedCounts>,
    malformed: Malformed,
}

impl Ear {
    /// Hearing `kind`s sealed under `key` (or plain, `None`), counting refusals in
    /// `counts`; `what` names the message in the log.
    pub fn new(
        kind: Kind,
        key: Option<&BusKey>,
        counts: Arc<RefusedCounts>,
        what: &'static str,
    ) -> Ear {
        Ear {
            kind,
            opener: key.map(Opener::new),
            replays: Replays::default(),
            counts,
            malformed: Malformed::new(what),
        }
    }

    /// The message in `bytes` and, sealed, its header; `None` (counted, logged) if it is
    /// refused (a replay too) or does not decode.
    pub fn hear<T: DeserializeOwned + Checked>(
        &mut self,
        bytes: &[u8],
    ) -> Option<(Option<Header>, T)> {
        let (header, msg) = self.open(bytes, b"")?;
        match header {
            Some(h) if !self.fresh(&h) => None,
            _ => Some((header, msg)),
        }
    }

    /// Whether `header`'s counter is new from its sender (counted, logged if not): for a
    /// caller of [`Ear::open`] once it knows the message is for it.
    pub fn fresh(&mut self, header: &Header) -> bool {
        let fresh = self.replays.accept(header);
        if !fresh {
            self.refuse(Refusal::Replayed, Some(header.sender));
        }
        fresh
    }

    /// [`Ear::hear`] of a message sealed bound to `bind`, without the replay check (the
    /// caller's, [`Ear::fresh`]: a message that changes nothing need not be remembered).
    pub fn open<T: DeserializeOwned + Checked>(
        &mut self,
        bytes: &[u8],
        bind: &[u8],
    ) -> Option<(Option<Header>, T)> {
        let Some(opener) = &mut self.opener else {
            return match decode::<T>(bytes) {
                Ok(msg) => Some((None, msg)),
                Err(e) => {
                    if bytes.starts_with(&MAGIC) {
                        self.malformed.note_sealed();
                    } else {
                        self.malformed.note(&e);
                    }
                    None
                }
            };
        };
        let (header, inside) = match opener.open(self.kind, T::MAX_BYTES, bytes, bind) {
            Ok(opened) => opened,
            Err(refusal) => {
                self.refuse(refusal, None);
                return None;
            }
        };
        match decode::<T>(&inside) {
            Ok(msg) => Some((Some(header), msg)),
            Err(e) => {
                // Sealed by one holding the secret, yet not a message: a version mismatch.
                self.malformed.note(&e);
                None
            }
        }
    }

    /// Whether this ear takes only sealed messages.
    pub fn sealed(&self) -> bool {
        self.opener.is_some()
    }

    /// Counts (and logs) a message refused for `refusal`, from `sender` if known.
    pub fn refuse(&self, refusal: Refusal, sender: Option<u64>) {
        count(
            self.counts.of(refusal),
            format_args!(
                "a {:?} on the bus refused{}: {refusal}",
                self.kind,
                From(sender)
            ),
        );
    }
}

/// " from SENDER", when the sender is known (written only when logged).
struct From(Option<u64>);

impl std::fmt::Display for From {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            Some(s) => write!(f, " from {s:x}"),
            None => Ok(()),
        }
    }
}

/// Counts one more of `counter`, logging `what` at the first, second, fourth….
pub(crate) fn count(counter: &AtomicU64, what: std::fmt::Arguments<'_>) {
    let n = counter.fetch_add(1, Ordering::Relaxed) + 1;
    if n.is_power_of_two() {
        tracing::warn!(refused = n, "{what}");
    }
}
