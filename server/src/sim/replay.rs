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

/// A recording being replayed: the world its header gives, then its events applied in
/// order ([`Player::play`]), each checkpoint checked. `replay` plays a whole recording
/// with it; [`crate::sim::watch`] plays one at a viewer's pace, and keeps copies of it to
/// seek from.
#[derive(Clone, Debug)]
pub struct Player<G> {
    world: World<G>,
    inputs: Inputs,
    /// Checkpoints (and the end record) that matched.
    checkpoints: u32,
    /// The last tick whose checkpoint matched (the start's, before any).
    agreed: u64,
    /// The end record has been played.
    ended: bool,
}

impl<G: Ground> Player<G> {
    /// The world at the start of `recording`, on `ground` whose data set hash is
    /// `data_hash`: refused for another data set or another physics rate.
    pub fn start(
        recording: &Recording,
        ground: G,
        data_hash: &[u8; 32],
    ) -> Result<Player<G>, ReplayError> {
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
        Ok(Player {
            world,
            inputs: Inputs::new(),
            checkpoints: 0,
            agreed: header.start_tick,
            ended: false,
        })
    }

    pub fn world(&self) -> &World<G> {
        &self.world
    }

    /// Checkpoints (and the end record) matched so far.
    pub fn checkpoints(&self) -> u32 {
        self.checkpoints
    }

    /// Whether the end record has been played.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Steps the world until it has reached `tick` (nothing when it has), with the keys
    /// the events so far gave (a wait or twice is for the next step only).
    pub fn run_to(&mut self, tick: u64) {
        while self.world.tick() < tick {
            world::step(&mut self.world, &self.inputs);
            self.inputs.clear_extra();
        }
    }

    /// Steps to `event`'s tick and applies it; a checkpoint or end record is checked
    /// against the world's digest.
    pub fn play(&mut self, event: &Event) -> Result<(), ReplayError> {
        self.run_to(event.tick());
        let world = &mut self.world;
        let tick = world.tick();
        let fail = |error| ReplayError::World { tick, error };
        match *event {
            Event::Input { vehicle, keys, .. } => {
                if world.vehicle(vehicle).is_none() {
                    return Err(fail(WorldError::Missing(vehicle)));
                }
                self.inputs.set(vehicle, keys)
            }
            Event::Wait { vehicle, .. } | Event::Twice { vehicle, .. }
                if world.vehicle(vehicle).is_none() =>
            {
                return Err(fail(WorldError::Missing(vehicle)));
            }
            Event::Wait { vehicle, .. } => self.inputs.set_extra(vehicle, Extra::Wait),
            Event::Twice {
                vehicle,
                first,
                second,
                ..
            } => self.inputs.set_extra(vehicle, Extra::Twice(first, second)),
            Event::Join { vehicle, state, .. } => world.add(vehicle, state).map_err(fail)?,
            Event::Leave { vehicle, .. } => {
                world.remove(vehicle).map_err(fail)?;
                self.inputs.set(vehicle, Keys::NONE);
            }
            Event::Checkpoint { digest, .. } | Event::End { digest, .. } => {
                let replayed = world.digest();
                if replayed != digest {
                    return Err(ReplayError::Diverged {
                        tick,
                        recorded: digest,
                        replayed,
                        agreed: self.agreed,
                    });
                }
                self.checkpoints += 1;
                self.agreed = tick;
                self.ended = matches!(event, Event::End { .. });
            }
        }
        Ok(())
    }
}

/// Replays `recording` on `ground`, whose data set hash is `data_hash`, checking every
/// checkpoint.
pub fn replay<G: Ground>(
    recording: &Recording,
    ground: G,
    data_hash: &[u8; 32],
) -> Result<Outcome, ReplayError> {
    let mut player = Player::start(recording, ground, data_hash)?;
    for event in &recording.events {
        player.play(event)?;
    }
    let world = player.world();
    Ok(Outcome {
        start_tick: recording.header.start_tick,
        tick: world.tick(),
        vehicles: world.vehicles().to_vec(),
        digest: world.digest(),
        checkpoints: player.checkpoints,
        ended: player.ended,
        truncated_at: recording.truncated_at,
    })
}
