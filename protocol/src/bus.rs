//! What a world and its edge servers say to each other over NATS (`roam-server world` and
//! `roam-server edge`): subjects, and the messages on them. Pure, as the rest of this
//! crate: the NATS client lives in the server's shell. Every message decodes with
//! [`crate::messages::decode`]: a byte limit per message, a limit per list, an error naming
//! the field, never a panic.
//!
//! ```text
//! edge ──ask (request-reply: hello every ½ s, join, resume, leave, hold, replay)──► world
//! edge ──keys (publish: its drivers' key states, all it had queued, as one message)──► world
//! edge ◄──snapshot (publish, each tick: supersedes the one before)── world
//! ```
//!
//! Decisions:
//!
//! - These are the messages inside the seal: between a world and its edges each goes
//!   encrypted and authenticated with the cluster's secret (the server's `net::bus::seal`),
//!   so the names in them (an edge's, a world's) are checked against who sealed them.
//! - Core NATS is at-most-once. A snapshot supersedes the one before, so a lost one costs
//!   nothing but its tick; key states travel as the viewer's datagram brings them (the
//!   newest few at once), so a lost message is covered by the next one, as on the viewer's
//!   own path; what must not be lost (a join, a resume, a leave, a hold) is a request the
//!   world answers, retried by the edge until it is.
//! - Vehicle states go as `f64` bits, not as the rounded views a frame carries: an edge
//!   computes its viewers' cameras from exactly what the world simulated.
//! - Subjects are namespaced by world (`roam.<world>.…`), so worlds share one NATS.
//! - An edge batches its drivers' key states: what it had queued when the last publish
//!   finished goes as one message, never waiting for more (a key's latency first), so
//!   the messages a second stay bounded by the publishes an edge can make, however many
//!   drivers it has.
//! - Liveness both ways is the edge's hello, asked every half second: the world learns the
//!   edge lives (and the vehicles it drives: an edge silent for 3 s has them held), the
//!   edge learns the world lives (a world silent, or another world process, is news for
//!   its viewers) and where the other edges are.

use serde::{Deserialize, Deserializer, Serialize};

use crate::bounded;
use crate::messages::{Checked, KEY_HISTORY, KeyState, MAX_REASON, MAX_VEHICLES, Ticket};

/// The longest world name: letters, digits, `-` and `_` (a NATS subject token).
pub const MAX_WORLD_NAME: usize = 64;

/// The world name when none is given.
pub const DEFAULT_WORLD: &str = "default";

pub use crate::messages::{MAX_ADDRESS, MAX_EDGES};

/// The subjects of one world.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Subjects {
    /// World → edges, each tick: [`Snapshot`].
    pub snapshots: String,
    /// Edges → world: [`Keys`].
    pub keys: String,
    /// Edges → world, request-reply: [`Ask`], answered with [`Answer`].
    pub ask: String,
}

/// Why a world name cannot be used.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    #[error("a world name is 1 to {MAX_WORLD_NAME} bytes, got {0}")]
    Length(usize),
    #[error("a world name is letters, digits, '-' and '_' (it is a NATS subject token), got {0:?}")]
    Character(char),
}

impl Subjects {
    /// The subjects of world `name`, if it is a valid name.
    pub fn of(name: &str) -> Result<Subjects, NameError> {
        if name.is_empty() || name.len() > MAX_WORLD_NAME {
            return Err(NameError::Length(name.len()));
        }
        if let Some(c) = name
            .chars()
            .find(|c| !(c.is_ascii_alphanumeric() || *c == '-' || *c == '_'))
        {
            return Err(NameError::Character(c));
        }
        Ok(Subjects {
            snapshots: format!("roam.{name}.snap"),
            keys: format!("roam.{name}.keys"),
            ask: format!("roam.{name}.ask"),
        })
    }
}

/// A vehicle as the world simulated it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Vehicle {
    pub id: u16,
    pub x: f64,
    pub z: f64,
    pub speed: f64,
    pub heading: f64,
}

/// The world after a tick.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Snapshot {
    /// The world process's name ([`Answer::Hello`]'s `world`): a new one is a world
    /// restarted.
    pub world: u64,
    pub tick: u64,
    #[serde(deserialize_with = "vehicles")]
    pub vehicles: Vec<Vehicle>,
    /// Per driver, the newest key state applied by this tick.
    #[serde(deserialize_with = "applied")]
    pub applied: Vec<(u16, u32)>,
    /// Vehicles held for a driver whose connection dropped, the oldest hold first.
    #[serde(deserialize_with = "held")]
    pub held: Vec<u16>,
    /// The world is a recording being watched (`world --replay`): how its clock stands.
    pub replay: Option<Replay>,
}

/// How a watched recording's clock stands ([`Snapshot::replay`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Replay {
    /// The valid part, first and last tick.
    pub start: u64,
    pub end: u64,
    /// Quarters (4: 1×).
    pub speed: u8,
    pub paused: bool,
}

/// Drivers' key states, as their datagrams brought them to one edge: what the edge had
/// queued when it published (one datagram's when it keeps up; under load, many drivers'
/// in one message).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Keys {
    #[serde(deserialize_with = "drivers")]
    pub drivers: Vec<DriverKeys>,
}

/// One driver's key states, as its datagram brought them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DriverKeys {
    pub vehicle: u16,
    #[serde(deserialize_with = "key_states")]
    pub states: Vec<KeyState>,
}

/// The most drivers in one [`Keys`].
pub const MAX_BATCH: usize = 1024;

/// What an edge asks the world (request-reply).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Ask {
    /// An edge, every half second while it runs (its first hello checks the data set;
    /// the world holds the vehicles of an edge gone silent): the content hash of its data
    /// set, its name for itself (random, per process), the addresses its viewers reach it
    /// at, and the vehicles its drivers drive, each with its claim. Answered with
    /// [`Answer::Hello`].
    Hello {
        data: [u8; 32],
        edge: u64,
        #[serde(deserialize_with = "crate::messages::edge_list")]
        addresses: Vec<String>,
        #[serde(deserialize_with = "driven")]
        vehicles: Vec<(u16, u64)>,
    },
    /// A driver joins: a new vehicle and its ticket, or a refusal.
    Join,
    /// A driver is back with its ticket: its held vehicle, or a refusal.
    Resume { ticket: Ticket },
    /// A driver left (a goodbye, or its join was abandoned): its vehicle goes, if `claim`
    /// is still the vehicle's newest ([`Answer::Joined`], [`Answer::Resumed`]): a leave
    /// asked again after its answer was lost, or told by an edge whose driver has since
    /// come back through another, changes nothing.
    Leave { vehicle: u16, claim: u64 },
    /// A driver's connection dropped: its vehicle is held, counted from `silent` ticks ago
    /// (if `claim` is still its newest, as for a leave).
    Hold {
        vehicle: u16,
        claim: u64,
        silent: u64,
    },
    /// The viewer holding an edge's controls steers a watched recording's clock (a world
    /// serving a recording: [`Snapshot::replay`]).
    Replay(crate::messages::ReplayControl),
}

/// The world's answer to an [`Ask`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Answer {
    /// The world's data set, its name for itself (random, per process: a new one is a
    /// world restarted, which knows none of the old vehicles), and the addresses of the
    /// edges it hears from.
    Hello {
        data: [u8; 32],
        world: u64,
        #[serde(deserialize_with = "crate::messages::edge_list")]
        edges: Vec<String>,
    },
    /// A new vehicle, its driver's ticket, and the claim its edge names it by: a random
    /// number the world gives each join and resume.
    Joined {
        vehicle: u16,
        ticket: Ticket,
        claim: u64,
    },
    /// The held vehicle given back, and its new claim.
    Resumed { vehicle: u16, claim: u64 },
    /// Taken (a leave, a hold).
    Done,
    Refused {
        #[serde(deserialize_with = "reason")]
        reason: String,
    },
}

/// A snapshot of the most vehicles: `MAX_VEHICLES` of them at 42 bytes or less each.
const MAX_SNAPSHOT: usize = 120 + MAX_VEHICLES * (1 + 4 * 9 + 3 + 5 + 3 + 3);

impl Checked for Snapshot {
    const MAX_BYTES: usize = MAX_SNAPSHOT;
}
impl Checked for Keys {
    /// A driver's entry: its vehicle (3), the count (1), and [`KEY_HISTORY`] states of 7.
    const MAX_BYTES: usize = 64 + MAX_BATCH * (4 + KEY_HISTORY * 7);
}
impl Checked for Ask {
    const MAX_BYTES: usize = 64 + MAX_EDGES * (MAX_ADDRESS + 3) + MAX_VEHICLES * (3 + 9);
}
impl Checked for Answer {
    const MAX_BYTES: usize = 64 + MAX_REASON + MAX_EDGES * (MAX_ADDRESS + 3);
}

fn vehicles<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Vehicle>, D::Error> {
    bounded::list(d, "vehicles", MAX_VEHICLES)
}

fn applied<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<(u16, u32)>, D::Error> {
    bounded::list(d, "applied key states", MAX_VEHICLES)
}

fn held<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u16>, D::Error> {
    bounded::list(d, "held vehicles", MAX_VEHICLES)
}

fn driven<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<(u16, u64)>, D::Error> {
    bounded::list(d, "driven vehicles", MAX_VEHICLES)
}

fn drivers<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<DriverKeys>, D::Error> {
    bounded::list(d, "drivers", MAX_BATCH)
}

fn key_states<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<KeyState>, D::Error> {
    bounded::list(d, "key states", KEY_HISTORY)
}

fn reason<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    bounded::string(d, "reason bytes", MAX_REASON)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::{DecodeError, decode, encode};

    fn bytes<T: Serialize>(msg: &T) -> Vec<u8> {
        let mut out = Vec::new();
        encode(msg, &mut out).expect("a bus message encodes");
        out
    }

    /// Each message comes back as it went.
    #[test]
    fn messages_round_trip() {
        let snap = Snapshot {
            world: 9,
            tick: 1 << 40,
            vehicles: vec![Vehicle {
                id: 3,
                x: 0.1,
                z: f64::MAX,
                speed: 12.5,
                heading: 359.999,
            }],
            applied: vec![(3, 77)],
            held: vec![5, 9],
            replay: None,
        };
        assert_eq!(decode::<Snapshot>(&bytes(&snap)).expect("decodes"), snap);
        let watched = Snapshot {
            replay: Some(Replay {
                start: 7,
                end: u64::MAX,
                speed: 32,
                paused: true,
            }),
            ..snap.clone()
        };
        assert_eq!(
            decode::<Snapshot>(&bytes(&watched)).expect("decodes"),
            watched
        );
        let ask = Ask::Replay(crate::messages::ReplayControl::Seek(u64::MAX));
        assert_eq!(decode::<Ask>(&bytes(&ask)).expect("decodes"), ask);
        let keys = Keys {
            drivers: vec![
                DriverKeys {
                    vehicle: 7,
                    states: vec![
                        KeyState {
                            seq: u32::MAX,
                            held: 0xff,
                            pressed: 0xff,
                        };
                        KEY_HISTORY
                    ],
                };
                MAX_BATCH
            ],
        };
        assert!(
            bytes(&keys).len() <= Keys::MAX_BYTES,
            "the largest batch fits"
        );
        assert_eq!(decode::<Keys>(&bytes(&keys)).expect("decodes"), keys);
        for ask in [
            Ask::Hello {
                data: [7; 32],
                edge: u64::MAX,
                addresses: vec!["127.0.0.1:4433".into()],
                vehicles: vec![(0, 1), (9, u64::MAX)],
            },
            Ask::Join,
            Ask::Resume { ticket: [1; 16] },
            Ask::Leave {
                vehicle: 2,
                claim: 3,
            },
            Ask::Hold {
                vehicle: 2,
                claim: 4,
                silent: 40,
            },
        ] {
            assert_eq!(decode::<Ask>(&bytes(&ask)).expect("decodes"), ask);
        }
        for answer in [
            Answer::Hello {
                data: [1; 32],
                world: 5,
                edges: vec!["a:1".into(), "b:2".into()],
            },
            Answer::Joined {
                vehicle: 1,
                ticket: [2; 16],
                claim: 7,
            },
            Answer::Resumed {
                vehicle: 1,
                claim: 8,
            },
            Answer::Done,
            Answer::Refused {
                reason: "no vehicle free".into(),
            },
        ] {
            assert_eq!(decode::<Answer>(&bytes(&answer)).expect("decodes"), answer);
        }
    }

    /// A list claiming more than its limit is refused by name, before it is read.
    #[test]
    fn long_lists_are_refused_by_name() {
        let check = |msg: Vec<u8>, what: &str| match decode::<Ask>(&msg) {
            Err(DecodeError::TooLong { what: w, .. }) => assert_eq!(w, what),
            other => panic!("{what}: {other:?}"),
        };
        let many = Ask::Hello {
            data: [0; 32],
            edge: 1,
            addresses: vec!["x".into(); MAX_EDGES + 1],
            vehicles: vec![],
        };
        check(bytes(&many), "addresses");
        let long = Ask::Hello {
            data: [0; 32],
            edge: 1,
            addresses: vec!["x".repeat(MAX_ADDRESS + 1)],
            vehicles: vec![],
        };
        check(bytes(&long), "address bytes");
        let keys = DriverKeys {
            vehicle: 1,
            states: vec![
                KeyState {
                    seq: 0,
                    held: 0,
                    pressed: 0
                };
                KEY_HISTORY + 1
            ],
        };
        assert!(matches!(
            decode::<Keys>(&bytes(&Keys {
                drivers: vec![keys]
            })),
            Err(DecodeError::TooLong {
                what: "key states",
                ..
            })
        ));
    }

    /// Every prefix of a message, and every byte flipped, decodes to a value or an error.
    #[test]
    fn damaged_messages_never_panic() {
        let msg = bytes(&Snapshot {
            world: 1,
            tick: 5,
            vehicles: vec![
                Vehicle {
                    id: 1,
                    x: 1.0,
                    z: 2.0,
                    speed: 3.0,
                    heading: 4.0
                };
                3
            ],
            applied: vec![(1, 2)],
            held: vec![1],
            replay: Some(Replay::default()),
        });
        for n in 0..msg.len() {
            let _ = decode::<Snapshot>(&msg[..n]);
            let _ = decode::<Ask>(&msg[..n]);
            let _ = decode::<Answer>(&msg[..n]);
        }
        for i in 0..msg.len() {
            for bit in 0..8 {
                let mut m = msg.clone();
                m[i] ^= 1 << bit;
                let _ = decode::<Snapshot>(&m);
                let _ = decode::<Keys>(&m);
            }
        }
    }

    #[test]
    fn world_names_are_subject_tokens() {
        let check = |name: &str, expected: Result<&str, NameError>| {
            assert_eq!(
                Subjects::of(name).map(|s| s.ask),
                expected.map(String::from),
                "{name:?}"
            );
        };
        check("default", Ok("roam.default.ask"));
        check("east-1_b", Ok("roam.east-1_b.ask"));
        check("", Err(NameError::Length(0)));
        check(&"w".repeat(65), Err(NameError::Length(65)));
        check("a.b", Err(NameError::Character('.')));
        check("a*", Err(NameError::Character('*')));
        check("a b", Err(NameError::Character(' ')));
    }
}
