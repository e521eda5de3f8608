//! `cargo bench -p roam-server --bench bus_seal`: what sealing the bus (issue 39) adds to
//! a world's tick at 1,000 driving vehicles over 4 edges, the work that differs alone: a
//! snapshot said (encoded, and sealed) and 4 edges' key states heard (opened, checked for
//! replay, and decoded), plain (`--insecure-bus`) against sealed. The best of several
//! rounds of 1,000 ticks each; one JSON object. The whole world's CPU a tick, sealed and
//! plain, is `scripts/cluster.sh proofs`.
// A benchmark prints its figures (JSON), and shares helpers with the tests by path.
#![allow(unreachable_pub, clippy::print_stdout)]

use std::sync::Arc;
use std::time::Instant;

use roam_protocol::bus::{DriverKeys, Keys, Snapshot, Vehicle};
use roam_protocol::messages::{KEY_HISTORY, KeyState};
use roam_server::net::bus::BusSecret;
use roam_server::net::bus::seal::{Kind, RefusedCounts};
use roam_server::net::bus::voice::{Ear, Voice};

const VEHICLES: u16 = 1000;
const EDGES: u16 = 4;
const TICKS: u64 = 1000;
const ROUNDS: usize = 5;

fn snapshot(tick: u64) -> Snapshot {
    Snapshot {
        world: 0x5eed,
        tick,
        vehicles: (0..VEHICLES)
            .map(|id| Vehicle {
                id,
                x: 1000.0 + f64::from(id) * 0.37,
                z: 2000.0 - f64::from(id) * 0.11,
                speed: 12.0 + f64::from(id % 7),
                heading: f64::from(id % 360) + 0.25,
            })
            .collect(),
        applied: (0..VEHICLES)
            .map(|id| (id, 40_000 + u32::from(id)))
            .collect(),
        held: vec![],
        replay: None,
    }
}

/// Edge `e`'s drivers' newest [`KEY_HISTORY`] states at `seq`, as bus-load sends them.
fn keys(e: u16, seq: u32) -> Keys {
    Keys {
        drivers: (0..VEHICLES)
            .filter(|v| v % EDGES == e)
            .map(|vehicle| DriverKeys {
                vehicle,
                states: (0..KEY_HISTORY as u32)
                    .map(|k| KeyState {
                        seq: seq - k,
                        held: 1,
                        pressed: 0,
                    })
                    .collect(),
            })
            .collect(),
    }
}

/// µs a tick to say the snapshot and hear the edges' keys, sealed under `secret` or plain.
fn round(secret: Option<&BusSecret>) -> f64 {
    let key = secret.map(|s| s.key("bench"));
    let world = Voice::new(key.as_ref(), 1);
    let edges: Vec<Voice> = (0..EDGES)
        .map(|e| Voice::new(key.as_ref(), 100 + u64::from(e)))
        .collect();
    let counts = Arc::new(RefusedCounts::default());
    let mut ear = Ear::new(Kind::Keys, key.as_ref(), counts.clone(), "key states");
    let snap = snapshot(7);
    // What the edges publish, made beforehand: the world only hears them.
    let sent: Vec<Vec<bytes::Bytes>> = (0..TICKS)
        .map(|t| {
            edges
                .iter()
                .enumerate()
                .map(|(e, v)| v.say(Kind::Keys, 1, 0, &keys(e as u16, 100 + t as u32)).1)
                .collect()
        })
        .collect();
    let started = Instant::now();
    let mut heard = 0usize;
    for batches in &sent {
        let (_, said) = world.say(Kind::Snapshot, 0, 0, &snap);
        std::hint::black_box(said);
        for b in batches {
            let (_, k) = ear.hear::<Keys>(b).expect("the bench's own key states");
            heard += k.drivers.len();
        }
    }
    let us = started.elapsed().as_secs_f64() * 1e6 / TICKS as f64;
    assert_eq!(heard, usize::from(VEHICLES) * TICKS as usize);
    assert_eq!(counts.get(), Default::default(), "nothing refused");
    us
}

fn main() {
    let secret = BusSecret::random();
    let (mut plain, mut sealed) = (f64::MAX, f64::MAX);
    for _ in 0..ROUNDS {
        plain = plain.min(round(None));
        sealed = sealed.min(round(Some(&secret)));
    }
    let snapshot_bytes = roam_server::net::bus::voice::Voice::new(None, 1)
        .say(Kind::Snapshot, 0, 0, &snapshot(7))
        .1
        .len();
    println!(
        "{{\"vehicles\":{VEHICLES},\"edges\":{EDGES},\"snapshot_bytes\":{snapshot_bytes},\"plain_us_per_tick\":{plain:.1},\"sealed_us_per_tick\":{sealed:.1},\"added_us_per_tick\":{:.1}}}",
        sealed - plain
    );
}
