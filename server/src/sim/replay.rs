//! Replaying a recording: the recorded events fed to the same `world::step`, from the world
//! its header gives (at its start tick: a file the server rotated in starts mid-session).

use crate::sim::physics::{Ground, Keys, STEPS_PER_SECOND};
use crate::sim::recording::{Event, Recording};
use crate::sim::world::{self, Digest, Extra, Inputs, Vehicle, World, WorldError};

/// How a replay ended.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    /// The tick the recording starts at (its header's).
    pub start_tick: u64,
    /// The last tick the recording reached.
    pub tick: u64,
    pub vehicles: Vec<Vehicle>,
    pub digest: Digest,
    /// Checkpoints (and the end record) that matched.
    pub checkpoints: u32,
    /// The recording had its end record (a clean close).
    pub ended: bool,
    /// Where the file was cut, if it was.
    pub truncated_at: Option<u64>,
}

/// Why a replay failed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ReplayError {
    #[error(
        "the recording was made on another data set (its hash {recorded}, this one's {actual})"
    )]
    DataSet { recorded: String, actual: String },
    #[error(
        "the recording runs at {found} steps per second; this build steps at {STEPS_PER_SECOND}"
    )]
    Rate { found: u32 },
    #[error(
        "diverged: the first checkpoint that differs is at tick {tick} (recorded digest {recorded}, replayed {replayed}); the last that agreed was at tick {agreed}"
    )]
    Diverged {
        tick: u64,
        recorded: Digest,
        replayed: Digest,
        agreed: u64,
    },
    #[error("at tick {tick}: {error}")]
    World { tick: u64, error: WorldError },
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Replays `recording` on `ground`, whose data set hash is `data_hash`, checking every
/// checkpoint.
pub fn replay<G: Ground>(
    recording: &Recording,
    ground: G,
    data_hash: &[u8; 32],
) -> Result<Outcome, ReplayError> {
    let header = &recording.header;
    if &header.data_hash != data_hash {
        return Err(ReplayError::DataSet {
            recorded: hex(&header.data_hash),
            actual: hex(data_hash),
        });
    }
    if header.steps_per_second != STEPS_PER_SECOND {
        return Err(ReplayError::Rate {
            found: header.steps_per_second,
        });
    }
    let mut world = World::at_tick(ground, header.start_tick);
    for &(id, state) in &header.vehicles {
        world.add(id, state).map_err(|error| ReplayError::World {
            tick: header.start_tick,
            error,
        })?;
    }
    let mut inputs = Inputs::new();
    let (mut checkpoints, mut agreed, mut ended) = (0, header.start_tick, false);
    // A wait or twice is for the next step only.
    let run_to = |world: &mut World<G>, inputs: &mut Inputs, tick: u64| {
        while world.tick() < tick {
            world::step(world, inputs);
            inputs.clear_extra();
        }
    };
    for event in &recording.events {
        run_to(&mut world, &mut inputs, event.tick());
        let tick = world.tick();
        let fail = |error| ReplayError::World { tick, error };
        match *event {
            Event::Input { vehicle, keys, .. } => {
                if world.vehicle(vehicle).is_none() {
                    return Err(fail(WorldError::Missing(vehicle)));
                }
                inputs.set(vehicle, keys)
            }
            Event::Wait { vehicle, .. } | Event::Twice { vehicle, .. }
                if world.vehicle(vehicle).is_none() =>
            {
                return Err(fail(WorldError::Missing(vehicle)));
            }
            Event::Wait { vehicle, .. } => inputs.set_extra(vehicle, Extra::Wait),
            Event::Twice {
                vehicle,
                first,
                second,
                ..
            } => inputs.set_extra(vehicle, Extra::Twice(first, second)),
            Event::Join { vehicle, state, .. } => world.add(vehicle, state).map_err(fail)?,
            Event::Leave { vehicle, .. } => {
                world.remove(vehicle).map_err(fail)?;
                inputs.set(vehicle, Keys::NONE);
            }
            Event::Checkpoint { digest, .. } | Event::End { digest, .. } => {
                let replayed = world.digest();
                if replayed != digest {
                    return Err(ReplayError::Diverged {
                        tick,
                        recorded: digest,
                        replayed,
                        agreed,
                    });
                }
                checkpoints += 1;
                agreed = tick;
                ended = matches!(event, Event::End { .. });
            }
        }
    }
    Ok(Outcome {
        start_tick: header.start_tick,
        tick: world.tick(),
        vehicles: world.vehicles().to_vec(),
        digest: world.digest(),
        checkpoints,
        ended,
        truncated_at: recording.truncated_at,
    })
}
