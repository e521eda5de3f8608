//! The bus's proofs: every message between a world and its edges is sealed with a key only
//! they hold, so whoever else can publish or subscribe on their NATS can neither forge,
//! read nor replay one. Pure (no clock, no socket): the shells hand it bytes and counters.
//!
//! **Threat model.** The attacker can publish and subscribe anything on the world's NATS
//! (it reads every subject, `_INBOX.*` included, and publishes on all of them), but holds
//! neither the cluster's secret (`--bus-secret FILE`) nor a process's memory. The world
//! and every edge hold the secret; an edge is trusted with the vehicles the world gave it
//! and no others (a vehicle's keys, leave and hold are taken only from the edge that holds
//! it, [`super::drivers`]). Out of scope: a process holding the secret (a compromised
//! edge can do what an edge can), and a NATS that drops or delays messages (that is an
//! outage, which the world and edges already ride out).
//!
//! **The envelope.** A sealed message is [`MAGIC`], a [`Header`] (what it is, who sent
//! it, to whom, the sender's counter, and the request it answers), then the message
//! encrypted and authenticated with AES-256-GCM, the header as associated data:
//!
//! ```text
//! B5 01 | kind u8 | sender u64 | to u64 | counter u64 | re u64 | ciphertext | tag (16)
//! ```
//!
//! - **Keys.** The secret (any file of at least [`MIN_SECRET`] bytes:
//!   `roam-server bus-secret FILE` makes one) and the world's name make the world's key
//!   (BLAKE3 `derive_key`), so worlds sharing a secret cannot replay into each other. Each
//!   process seals with its own key, derived from the world's key and its random 64-bit
//!   name (`sender`), and counts each kind of its messages from 1: the GCM nonce (counter
//!   and kind) is never used twice under one key, however many processes seal at once.
//! - **Replays.** The world keeps a window per edge (`window.rs`): a counter seen,
//!   or more than 1,024 behind the newest, is refused. Requests name the world process they are
//!   for (`to`): the world takes none for another process (a hello is answered, changing
//!   nothing), so nothing captured before it started can be played to it, and only this
//!   world's edges get windows. A request's seal is bound to its reply subject (hashed
//!   into the associated data, not sent): played again with the attacker's inbox, it does
//!   not open. An answer names the edge and the request (`to`, `re`): an edge takes it only
//!   for a request it is waiting on. Snapshots supersede each other: an edge takes one only
//!   if it is newer than the last it took from the world process it confirmed. No clocks:
//!   the machines' clocks need not agree.
//! - **Cheap refusals first.** A header can be read before its seal is checked
//!   ([`Header::peek`]): key states from an edge holding no vehicle, snapshots of another
//!   process and answers for another edge or request are dropped before any cryptography.
//! - **Confidential too.** Answers carry tickets and claims; requests carry claims and
//!   tickets. Everything is encrypted, snapshots and key states too (one code path; the
//!   cost is measured below).
//!
//! Decisions:
//!
//! - AES-256-GCM from `ring` (already the server's TLS crypto; AES-NI and carry-less
//!   multiply on any server CPU of the last decade) over ChaCha20-Poly1305: faster on the
//!   machines that run worlds; both are in `ring`.
//! - One shared secret rather than per-edge keys or NATS accounts: the world must accept
//!   an edge it has never heard of (edges come and go), and an edge proves itself by the
//!   secret; NATS accounts and permissions still help (docs/cluster.md) but need a NATS
//!   set up for them, and the application's proofs do not.
//! - Cost at 1,000 driving vehicles over 4 edges, measured 2026-12-07 (`measure` profile,
//!   2 cores): the world's CPU per tick sealed against plain 1.08×, 1.04× and 1.02× in three
//!   sessions of A/B rounds (medians 560 / 520, 555 / 535, 610 / 600 µs;
//!   `PROFILE=measure scripts/cluster.sh proofs 1000`; single runs vary 500–720 either way). The seal alone, a 40 KB snapshot sealed and
//!   four edges' key states opened a tick, adds 14.6 µs (`cargo bench -p roam-server
//!   --bench bus_seal`: 89.1 → 103.7 µs).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};

use ring::aead::{AES_256_GCM, Aad, LessSafeKey, Nonce, UnboundKey};

/// The first two bytes of every sealed message (a bincode bus message never starts so:
/// its first byte is a small variant index, a count, or a varint prefix).
pub const MAGIC: [u8; 2] = [0xB5, 0x01];

/// The header's bytes after [`MAGIC`].
const HEADER: usize = 1 + 8 * 4;

/// Bytes a seal adds to a message: magic, header and tag.
pub const OVERHEAD: usize = MAGIC.len() + HEADER + 16;

/// The fewest bytes a secret file may hold (64 hex digits is 256 bits; 32 bytes of
/// anything random is too).
pub const MIN_SECRET: usize = 32;

/// The most bytes read from a secret file.
pub const MAX_SECRET: usize = 4096;

/// Senders' keys an [`Opener`] keeps (past it, it starts again: a key is derived anew).
const MAX_KEYS: usize = 65_536;

/// What a sealed message is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Kind {
    /// An edge's request to the world ([`roam_protocol::bus::Ask`]).
    Ask = 1,
    /// The world's answer to one request ([`roam_protocol::bus::Answer`]).
    Answer = 2,
    /// The world after a tick ([`roam_protocol::bus::Snapshot`]).
    Snapshot = 3,
    /// An edge's drivers' key states ([`roam_protocol::bus::Keys`]).
    Keys = 4,
}

impl Kind {
    fn from_byte(b: u8) -> Option<Kind> {
        Some(match b {
            1 => Kind::Ask,
            2 => Kind::Answer,
            3 => Kind::Snapshot,
            4 => Kind::Keys,
            _ => return None,
        })
    }
}

/// Who sent a sealed message, to whom, and which.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    pub kind: Kind,
    /// The sender's name for itself (an edge's or a world process's random id).
    pub sender: u64,
    /// The world process a request is for (0: whichever answers, for a first hello), the
    /// edge an answer is for; 0 on snapshots.
    pub to: u64,
    /// The sender's count of its messages, from 1.
    pub counter: u64,
    /// The request an answer answers (its counter); 0 otherwise.
    pub re: u64,
}

impl Header {
    fn bytes(&self) -> [u8; MAGIC.len() + HEADER] {
        let mut out = [0u8; MAGIC.len() + HEADER];
        out[..2].copy_from_slice(&MAGIC);
        out[2] = self.kind as u8;
        for (i, v) in [self.sender, self.to, self.counter, self.re]
            .into_iter()
            .enumerate()
        {
            out[3 + 8 * i..11 + 8 * i].copy_from_slice(&v.to_le_bytes());
        }
        out
    }

    /// The header of a sealed message, unchecked (anyone can write one): for a receiver
    /// to drop, before any cryptography, what could not be for it.
    pub fn peek(bytes: &[u8]) -> Option<Header> {
        Header::read(bytes)
    }

    fn read(bytes: &[u8]) -> Option<Header> {
        let word = |i: usize| {
            let b = bytes.get(3 + 8 * i..11 + 8 * i)?;
            Some(u64::from_le_bytes(b.try_into().ok()?))
        };
        if bytes.get(..2)? != MAGIC {
            return None;
        }
        Some(Header {
            kind: Kind::from_byte(*bytes.get(2)?)?,
            sender: word(0)?,
            to: word(1)?,
            counter: word(2)?,
            re: word(3)?,
        })
    }

    /// The nonce: unique per sender key, as each kind's counter is.
    fn nonce(&self) -> Nonce {
        let mut n = [0u8; 12];
        n[..8].copy_from_slice(&self.counter.to_le_bytes());
        n[8] = self.kind as u8;
        Nonce::assume_unique_for_key(n)
    }
}

/// Why a secret cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SecretError {
    #[error("the bus secret {file}: {error}")]
    Read {
        file: std::path::PathBuf,
        error: std::io::Error,
    },
    #[error(
        "the bus secret {file}: expected at least {MIN_SECRET} bytes (besides spaces and line \
         ends), got {got}; make one with: roam-server bus-secret FILE"
    )]
    Short {
        file: std::path::PathBuf,
        got: usize,
    },
    #[error("the bus secret {file}: expected at most {MAX_SECRET} bytes, got {got}")]
    Long {
        file: std::path::PathBuf,
        got: usize,
    },
}

/// The cluster's secret, as read from its file (shared by the world and its edges).
#[derive(Clone)]
pub struct BusSecret(Vec<u8>);

impl std::fmt::Debug for BusSecret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BusSecret({} bytes)", self.0.len())
    }
}

impl BusSecret {
    /// The secret in `file`: its bytes, less leading and trailing ASCII whitespace (so
    /// `echo`, an editor's line end, or 64 hex digits all do), at least [`MIN_SECRET`].
    pub fn read(file: &std::path::Path) -> Result<BusSecret, SecretError> {
        let bytes = std::fs::read(file).map_err(|error| SecretError::Read {
            file: file.to_owned(),
            error,
        })?;
        BusSecret::from_bytes(&bytes).map_err(|got| {
            if got > MAX_SECRET {
                SecretError::Long {
                    file: file.to_owned(),
                    got,
                }
            } else {
                SecretError::Short {
                    file: file.to_owned(),
                    got,
                }
            }
        })
    }

    /// A secret from its bytes (trimmed as [`BusSecret::read`] trims); `Err` is their
    /// length, trimmed, when it is not [`MIN_SECRET`] to [`MAX_SECRET`].
    pub fn from_bytes(bytes: &[u8]) -> Result<BusSecret, usize> {
        let trimmed = bytes.trim_ascii();
        if (MIN_SECRET..=MAX_SECRET).contains(&trimmed.len()) {
            Ok(BusSecret(trimmed.to_vec()))
        } else {
            Err(trimmed.len())
        }
    }

    /// A new random secret, as 64 hex digits (the text `roam-server bus-secret` writes).
    pub fn random() -> BusSecret {
        let a = crate::net::tickets::random_ticket();
        let b = crate::net::tickets::random_ticket();
        let hex = roam_link::tls::hex(&[a, b].concat());
        BusSecret(hex.into_bytes())
    }

    /// The text of the secret (for writing it to a file).
    pub fn as_bytes(&self) -> &[u8] {
        &self.0
    }

    /// World `world`'s key: the secret and the world's name.
    pub fn key(&self, world: &str) -> BusKey {
        let mut material = Vec::with_capacity(self.0.len() + 8 + world.len());
        material.extend_from_slice(&(self.0.len() as u64).to_le_bytes());
        material.extend_from_slice(&self.0);
        material.extend_from_slice(world.as_bytes());
        BusKey(blake3::derive_key(
            "roam bus 2026-12-07 world key",
            &material,
        ))
    }
}

/// One world's key, from which each sender's is derived.
#[derive(Clone)]
pub struct BusKey([u8; 32]);

impl BusKey {
    fn sender(&self, sender: u64) -> LessSafeKey {
        let mut material = [0u8; 40];
        material[..32].copy_from_slice(&self.0);
        material[32..].copy_from_slice(&sender.to_le_bytes());
        let key = blake3::derive_key("roam bus 2026-12-07 sender key", &material);
        LessSafeKey::new(
            UnboundKey::new(&AES_256_GCM, &key).expect("32 bytes is AES-256's key length"),
        )
    }
}

/// One process's sealing: its name, its key, its counter.
pub struct Sealer {
    sender: u64,
    key: LessSafeKey,
    /// A count per kind (the nonce holds the kind): each receiver's window sees one
    /// kind's counters only, so a burst of one kind cannot push another's out of it.
    counters: [AtomicU64; 4],
}

impl Sealer {
    /// Seals as `sender` (this process's random name) under world key `key`.
    pub fn new(key: &BusKey, sender: u64) -> Sealer {
        Sealer {
            sender,
            key: key.sender(sender),
            counters: Default::default(),
        }
    }

    pub fn sender(&self) -> u64 {
        self.sender
    }

    /// `message` sealed as `kind` for `to` (answering request `re`, or 0), bound to `bind`
    /// (not sent: the receiver must open it with the same, e.g. a request's reply
    /// subject), and its counter.
    pub fn seal(
        &self,
        kind: Kind,
        to: u64,
        re: u64,
        bind: &[u8],
        message: &[u8],
    ) -> (u64, Vec<u8>) {
        let counter = self.take(kind);
        (
            counter,
            self.seal_numbered(kind, counter, to, re, bind, message),
        )
    }

    /// The next counter of `kind`, taken (for [`Sealer::seal_numbered`]: a request's
    /// reply subject names it, and the seal is bound to that subject).
    pub fn take(&self, kind: Kind) -> u64 {
        self.counters[kind as usize - 1].fetch_add(1, Ordering::Relaxed) + 1
    }

    /// [`Sealer::seal`] under `counter`, which [`Sealer::take`] gave (never twice).
    pub fn seal_numbered(
        &self,
        kind: Kind,
        counter: u64,
        to: u64,
        re: u64,
        bind: &[u8],
        message: &[u8],
    ) -> Vec<u8> {
        let header = Header {
            kind,
            sender: self.sender,
            to,
            counter,
            re,
        };
        let head = header.bytes();
        let mut out = Vec::with_capacity(message.len() + OVERHEAD);
        out.extend_from_slice(&head);
        out.extend_from_slice(message);
        let tag = self
            .key
            .seal_in_place_separate_tag(
                header.nonce(),
                Aad::from(aad(&head, bind)),
                &mut out[head.len()..],
            )
            .expect("a bus message is far below GCM's length limit");
        out.extend_from_slice(tag.as_ref());
        out
    }
}

/// The associated data: the header, and what the message is bound to (hashed: a fixed
/// size, whatever it is).
fn aad(head: &[u8], bind: &[u8]) -> [u8; MAGIC.len() + HEADER + 32] {
    let mut out = [0u8; MAGIC.len() + HEADER + 32];
    out[..head.len()].copy_from_slice(head);
    out[MAGIC.len() + HEADER..].copy_from_slice(blake3::hash(bind).as_bytes());
    out
}

/// Why a message was not taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refusal {
    #[error("not sealed (a sender without the bus secret, or one started with --insecure-bus)")]
    Unsealed,
    #[error("its seal does not hold (forged, damaged, or sealed with another secret)")]
    Forged,
    #[error("a {got:?} where a {want:?} was expected")]
    Kind { got: Kind, want: Kind },
    #[error("a replay (its counter was seen, or is too old)")]
    Replayed,
    #[error("longer than a {0:?} can be")]
    Long(Kind),
}

/// Opens sealed messages: each sender's key, derived once it has sealed one message that
/// opened (so a flood of made-up senders costs a derivation each, and no memory).
pub struct Opener {
    key: BusKey,
    keys: HashMap<u64, LessSafeKey>,
}

impl Opener {
    pub fn new(key: &BusKey) -> Opener {
        Opener {
            key: key.clone(),
            keys: HashMap::new(),
        }
    }

    /// The header and the message inside `bytes`, if it is a `want` sealed under this
    /// world's key, bound to `bind` ([`Sealer::seal`]), at most `max` bytes inside.
    /// Replays are the caller's (`window.rs`).
    pub fn open(
        &mut self,
        want: Kind,
        max: usize,
        bytes: &[u8],
        bind: &[u8],
    ) -> Result<(Header, Vec<u8>), Refusal> {
        let header = Header::read(bytes).ok_or(Refusal::Unsealed)?;
        if header.kind != want {
            return Err(Refusal::Kind {
                got: header.kind,
                want,
            });
        }
        if bytes.len() > max + OVERHEAD {
            return Err(Refusal::Long(want));
        }
        let head = MAGIC.len() + HEADER;
        if bytes.len() < head + 16 {
            return Err(Refusal::Forged);
        }
        let mut inside = bytes[head..].to_vec();
        let fresh =
            (!self.keys.contains_key(&header.sender)).then(|| self.key.sender(header.sender));
        let key = match &fresh {
            Some(k) => k,
            None => self
                .keys
                .get(&header.sender)
                .expect("derived when not kept"),
        };
        let len = key
            .open_in_place(
                header.nonce(),
                Aad::from(aad(&bytes[..head], bind)),
                &mut inside,
            )
            .map_err(|_| Refusal::Forged)?
            .len();
        inside.truncate(len);
        if let Some(key) = fresh {
            if self.keys.len() >= MAX_KEYS {
                self.keys.clear();
            }
            self.keys.insert(header.sender, key);
        }
        Ok((header, inside))
    }
}

/// Messages refused, by why (the world's and an edge's counts; `Copy` for a look).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Refused {
    /// Not sealed.
    pub unsealed: u64,
    /// Sealed, but the seal does not hold (or the wrong kind, or too long).
    pub forged: u64,
    /// A counter seen before.
    pub replayed: u64,
    /// A request for another world process (one from before this one started).
    pub other_world: u64,
    /// Keys, a leave or a hold for a vehicle the sending edge does not hold.
    pub not_holder: u64,
    /// Vehicles held because no edge named them (a join nobody drives).
    pub unnamed: u64,
    /// Snapshots of a world process the edge has not confirmed by a hello.
    pub unconfirmed: u64,
}

/// [`Refused`] as counters the tasks share.
#[derive(Default, Debug)]
pub struct RefusedCounts {
    pub unsealed: AtomicU64,
    pub forged: AtomicU64,
    pub replayed: AtomicU64,
    pub other_world: AtomicU64,
    pub not_holder: AtomicU64,
    pub unnamed: AtomicU64,
    pub unconfirmed: AtomicU64,
}

impl RefusedCounts {
    pub fn get(&self) -> Refused {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        Refused {
            unsealed: l(&self.unsealed),
            forged: l(&self.forged),
            replayed: l(&self.replayed),
            other_world: l(&self.other_world),
            not_holder: l(&self.not_holder),
            unnamed: l(&self.unnamed),
            unconfirmed: l(&self.unconfirmed),
        }
    }

    /// The count `refusal` goes into.
    pub fn of(&self, refusal: Refusal) -> &AtomicU64 {
        match refusal {
            Refusal::Unsealed => &self.unsealed,
            Refusal::Forged | Refusal::Kind { .. } | Refusal::Long(_) => &self.forged,
            Refusal::Replayed => &self.replayed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn secret(s: &str) -> BusSecret {
        BusSecret::from_bytes(s.as_bytes()).expect("long enough")
    }

    const S: &str = "0123456789abcdef0123456789abcdef";

    #[test]
    fn a_sealed_message_opens_once_and_only_with_its_world_key() {
        let key = secret(S).key("lake");
        let edge = Sealer::new(&key, 77);
        let (counter, sealed) = edge.seal(Kind::Ask, 5, 0, b"", b"join me");
        assert_eq!(counter, 1);
        assert!(!sealed.windows(7).any(|w| w == b"join me"), "encrypted");
        let mut opener = Opener::new(&key);
        let (header, inside) = opener.open(Kind::Ask, 100, &sealed, b"").expect("opens");
        assert_eq!(inside, b"join me");
        assert_eq!(
            header,
            Header {
                kind: Kind::Ask,
                sender: 77,
                to: 5,
                counter: 1,
                re: 0
            }
        );
        // Another world's key, or another secret: the seal does not hold.
        let check = |key: &BusKey, bytes: &[u8], want: Result<(), Refusal>| {
            let got = Opener::new(key)
                .open(Kind::Ask, 100, bytes, b"")
                .map(|_| ());
            assert_eq!(got, want);
        };
        check(&secret(S).key("sea"), &sealed, Err(Refusal::Forged));
        check(
            &secret("another secret, 32 bytes or more.").key("lake"),
            &sealed,
            Err(Refusal::Forged),
        );
        check(&key, b"\x01plain bincode", Err(Refusal::Unsealed));
        check(&key, &sealed[..20], Err(Refusal::Unsealed));
        check(&key, &sealed[..40], Err(Refusal::Forged));
        // Every byte flipped: the header is authenticated with the message.
        for i in 2..sealed.len() {
            let mut bad = sealed.clone();
            bad[i] ^= 0x10;
            let got = Opener::new(&key).open(Kind::Ask, 100, &bad, b"");
            assert!(got.is_err(), "byte {i} flipped opened: {got:?}");
        }
        // Bound to something else (a request played again with another reply subject).
        let (_, bound) = edge.seal(Kind::Ask, 5, 0, b"_INBOX.edge.7", b"join me");
        let open = |bind: &[u8]| {
            Opener::new(&key)
                .open(Kind::Ask, 100, &bound, bind)
                .map(|_| ())
        };
        assert_eq!(open(b"_INBOX.edge.7"), Ok(()));
        assert_eq!(open(b"_INBOX.thief.7"), Err(Refusal::Forged));
        assert_eq!(open(b""), Err(Refusal::Forged));
        assert_eq!(Header::peek(&bound).map(|h| h.counter), Some(2));
        // Too long for its kind, or another kind.
        check(&key, &sealed, Ok(()));
        assert_eq!(
            Opener::new(&key)
                .open(Kind::Ask, 3, &sealed, b"")
                .map(|_| ()),
            Err(Refusal::Long(Kind::Ask))
        );
        assert_eq!(
            Opener::new(&key)
                .open(Kind::Keys, 100, &sealed, b"")
                .map(|_| ()),
            Err(Refusal::Kind {
                got: Kind::Ask,
                want: Kind::Keys
            })
        );
    }

    #[test]
    fn counters_rise_and_senders_keys_differ() {
        let key = secret(S).key("lake");
        let a = Sealer::new(&key, 1);
        let b = Sealer::new(&key, 2);
        let (c1, m1) = a.seal(Kind::Keys, 0, 0, b"", b"same");
        let (c2, m2) = a.seal(Kind::Keys, 0, 0, b"", b"same");
        let (c3, m3) = b.seal(Kind::Keys, 0, 0, b"", b"same");
        let (c4, m4) = a.seal(Kind::Ask, 0, 0, b"", b"same");
        assert_eq!(
            (c1, c2, c3, c4),
            (1, 2, 1, 1),
            "a count per sender and kind"
        );
        assert_ne!(m1[MAGIC.len() + HEADER..], m4[MAGIC.len() + HEADER..]);
        let body = |m: &[u8]| m[MAGIC.len() + HEADER..].to_vec();
        assert_ne!(body(&m1), body(&m2));
        assert_ne!(body(&m1), body(&m3), "one counter, two senders: two keys");
    }

    #[test]
    fn secrets_are_long_enough_and_trimmed() {
        let check = |text: &str, expected: Result<usize, usize>| {
            assert_eq!(
                BusSecret::from_bytes(text.as_bytes()).map(|s| s.as_bytes().len()),
                expected,
                "{text:?}"
            );
        };
        check(S, Ok(32));
        check(&format!("  {S}\n"), Ok(32));
        check("short\n", Err(5));
        check(&"x".repeat(31), Err(31));
        check("", Err(0));
        check(&"x".repeat(MAX_SECRET + 1), Err(MAX_SECRET + 1));
        assert_eq!(BusSecret::random().as_bytes().len(), 64);
        assert_ne!(
            BusSecret::random().as_bytes(),
            BusSecret::random().as_bytes()
        );
    }
}
