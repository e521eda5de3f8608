//! Writing recordings ([`crate::sim::recording`] is the format): [`Recorder`] writes records
//! to any `Write`; [`RecordedWorld`] is a world that records whatever enters it.
//!
//! **Whole records, and knowing where they end.** The recorder keeps the records since
//! the last hand-over in memory and hands them to its writer in one go at each checkpoint
//! (at least every second of world time; and sooner once 64 KiB have piled up), with its
//! own write loop, so that it knows how many bytes the writer took. After a failed write,
//! [`Recorder::whole_len`] is the length of the whole records the writer holds (0 when even
//! the header is not whole): the owner cuts the file back to it
//! ([`crate::sim::session`]), and the file ends at its last whole record whatever byte the
//! failure struck. A recorder that failed refuses every later record, since what its
//! writer holds past `whole_len` is unknown. A recorder dropped without [`Recorder::finish`]
//! loses the records not yet handed over (at most a second's).

use std::io::{self, Write};

use crate::sim::physics::{Ground, Keys, STEPS_PER_SECOND, VehicleState};
use crate::sim::recording::{
    CHECKPOINT, END, HEADER, Header, INPUT, JOIN, LEAVE, MAGIC, MAX_CHECKPOINT_INTERVAL,
    MAX_RECORD, STATE, TWICE, VERSION, WAIT, check, put_state,
};
use crate::sim::world::{self, Digest, Extra, Inputs, Vehicle, VehicleId, World, WorldError};

/// Bytes of records piled up in memory before they are handed over between checkpoints.
const HAND_OVER_AT: usize = 64 << 10;

/// The header of a recording of `world` from where it is now.
pub fn header_of<G: Ground>(
    world: &World<G>,
    data_hash: [u8; 32],
    checkpoint_interval: u32,
) -> Header {
    Header {
        data_hash,
        steps_per_second: STEPS_PER_SECOND,
        checkpoint_interval,
        start_tick: world.tick(),
        vehicles: world.vehicles().iter().map(|v| (v.id, v.state)).collect(),
    }
}

/// Writes a recording to any `Write` (a file in the server; memory in tests): records as
/// they happen, handed to the writer and flushed at every checkpoint.
pub struct Recorder<W: Write> {
    out: W,
    /// The keys last recorded per vehicle, by id.
    keys: Vec<(VehicleId, Keys)>,
    interval: u32,
    start_tick: u64,
    /// Whole records not yet handed to `out`, and where each ends in it.
    pending: Vec<u8>,
    ends: Vec<usize>,
    /// Bytes `out` has taken.
    written: u64,
    /// Bytes of whole records `out` holds: all it took, or less after a failed write.
    whole: u64,
    /// The magic, the version and the header.
    header_len: u64,
    failed: bool,
}

impl<W: Write> Recorder<W> {
    /// Starts a recording: writes the magic, the version and the header, and flushes.
    pub fn new(out: W, header: &Header) -> io::Result<Recorder<W>> {
        if !(1..=MAX_CHECKPOINT_INTERVAL).contains(&header.checkpoint_interval) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!(
                    "checkpoint interval {} is not in 1 ..= {MAX_CHECKPOINT_INTERVAL}",
                    header.checkpoint_interval
                ),
            ));
        }
        let mut p = Vec::new();
        p.extend_from_slice(&header.data_hash);
        p.extend_from_slice(&header.steps_per_second.to_le_bytes());
        p.extend_from_slice(&header.checkpoint_interval.to_le_bytes());
        p.extend_from_slice(&header.start_tick.to_le_bytes());
        p.extend_from_slice(&(header.vehicles.len() as u32).to_le_bytes());
        for (id, state) in &header.vehicles {
            p.extend_from_slice(&id.to_le_bytes());
            put_state(&mut p, state);
        }
        if p.len() > MAX_RECORD {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "too many vehicles for one header record",
            ));
        }
        let mut rec = Recorder {
            out,
            keys: Vec::new(),
            interval: header.checkpoint_interval,
            start_tick: header.start_tick,
            pending: Vec::new(),
            ends: Vec::new(),
            written: 0,
            whole: 0,
            header_len: 0,
            failed: false,
        };
        // The magic and version count as part of the header: no whole record before it.
        rec.pending.extend_from_slice(&MAGIC);
        rec.pending.extend_from_slice(&VERSION.to_le_bytes());
        rec.frame(HEADER, &p);
        rec.header_len = rec.pending.len() as u64;
        rec.flush()?;
        Ok(rec)
    }

    /// Ticks between checkpoints.
    pub fn checkpoint_interval(&self) -> u32 {
        self.interval
    }

    /// Whether a checkpoint is due when the world has taken `tick` steps: every interval
    /// from the start tick.
    pub fn checkpoint_due(&self, tick: u64) -> bool {
        tick.checked_sub(self.start_tick)
            .is_some_and(|t| t > 0 && t.is_multiple_of(u64::from(self.interval)))
    }

    /// Bytes the file holds once every record so far is handed over.
    pub fn len(&self) -> u64 {
        self.written + self.pending.len() as u64
    }

    /// Whether nothing was recorded after the header.
    pub fn is_empty(&self) -> bool {
        self.len() == self.header_len
    }

    /// Bytes of whole records the writer holds: after a failed write, where to cut the
    /// file back to (0: not even the header is whole).
    pub fn whole_len(&self) -> u64 {
        self.whole
    }

    /// The writer (to cut it back after a failure).
    pub fn get_mut(&mut self) -> &mut W {
        &mut self.out
    }

    fn frame(&mut self, kind: u8, payload: &[u8]) {
        self.pending.push(kind);
        self.pending
            .extend_from_slice(&(payload.len() as u32).to_le_bytes());
        self.pending.extend_from_slice(payload);
        self.pending.extend_from_slice(&check(kind, payload));
        self.ends.push(self.pending.len());
    }

    fn write(&mut self, kind: u8, payload: &[u8]) -> io::Result<()> {
        if self.failed {
            return Err(failed_before());
        }
        self.frame(kind, payload);
        if self.pending.len() >= HAND_OVER_AT {
            self.hand_over()?;
        }
        Ok(())
    }

    /// Hands every pending record to the writer and flushes it.
    pub fn flush(&mut self) -> io::Result<()> {
        if self.failed {
            return Err(failed_before());
        }
        self.hand_over()?;
        // A writer that buffers may fail here: what reached the file is then unknown, and
        // the cut back to `whole` (which never lengthens a file) is the best there is.
        self.out.flush().inspect_err(|_| self.failed = true)
    }

    /// Writes the pending records; on an error, `whole` is where the last whole record the
    /// writer took ends.
    fn hand_over(&mut self) -> io::Result<()> {
        let mut done = 0;
        let result = loop {
            let rest = &self.pending[done..];
            if rest.is_empty() {
                break Ok(());
            }
            match self.out.write(rest) {
                Ok(0) => {
                    break Err(io::Error::new(
                        io::ErrorKind::WriteZero,
                        "the recording's writer took no more bytes",
                    ));
                }
                Ok(n) => done += n.min(rest.len()),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => break Err(e),
            }
        };
        let kept = match result {
            Ok(()) => done,
            Err(_) => match self.ends.partition_point(|&end| end <= done) {
                0 => 0,
                n => self.ends[n - 1],
            },
        };
        // Before the header is whole, nothing is.
        let whole = self.written + kept as u64;
        self.whole = if whole < self.header_len { 0 } else { whole };
        self.written += done as u64;
        self.pending.clear();
        self.ends.clear();
        self.failed = result.is_err();
        result
    }

    /// Records the keys, waits and double steps of every vehicle in `vehicles` for the step
    /// after `tick`.
    pub fn step_inputs(
        &mut self,
        tick: u64,
        vehicles: &[Vehicle],
        inputs: &Inputs,
    ) -> io::Result<()> {
        for v in vehicles {
            match inputs.extra(v.id) {
                None => self.input(tick, v.id, inputs.get(v.id))?,
                Some(Extra::Wait) => self.wait(tick, v.id)?,
                Some(Extra::Twice(a, b)) => self.twice(tick, v.id, a, b)?,
            }
        }
        Ok(())
    }

    /// Records `keys` for `vehicle` from the step after `tick`, if they differ from the
    /// last keys recorded for it.
    pub fn input(&mut self, tick: u64, vehicle: VehicleId, keys: Keys) -> io::Result<()> {
        let last = match self.keys.binary_search_by_key(&vehicle, |&(v, _)| v) {
            Ok(at) => &mut self.keys[at].1,
            Err(at) => {
                self.keys.insert(at, (vehicle, Keys::NONE));
                &mut self.keys[at].1
            }
        };
        if *last == keys {
            return Ok(());
        }
        *last = keys;
        let mut p = [0u8; 11];
        p[..8].copy_from_slice(&tick.to_le_bytes());
        p[8..10].copy_from_slice(&vehicle.to_le_bytes());
        p[10] = keys.bits();
        self.write(INPUT, &p)
    }

    /// Records that `vehicle` takes no step in the step after `tick` (its keys as recorded
    /// stay).
    pub fn wait(&mut self, tick: u64, vehicle: VehicleId) -> io::Result<()> {
        let mut p = [0u8; 10];
        p[..8].copy_from_slice(&tick.to_le_bytes());
        p[8..].copy_from_slice(&vehicle.to_le_bytes());
        self.write(WAIT, &p)
    }

    /// Records that `vehicle` takes two steps in the step after `tick`, with `first` and
    /// `second` (its keys as recorded stay).
    pub fn twice(
        &mut self,
        tick: u64,
        vehicle: VehicleId,
        first: Keys,
        second: Keys,
    ) -> io::Result<()> {
        let mut p = [0u8; 12];
        p[..8].copy_from_slice(&tick.to_le_bytes());
        p[8..10].copy_from_slice(&vehicle.to_le_bytes());
        p[10] = first.bits();
        p[11] = second.bits();
        self.write(TWICE, &p)
    }

    pub fn join(&mut self, tick: u64, vehicle: VehicleId, state: &VehicleState) -> io::Result<()> {
        let mut p = Vec::with_capacity(10 + STATE);
        p.extend_from_slice(&tick.to_le_bytes());
        p.extend_from_slice(&vehicle.to_le_bytes());
        put_state(&mut p, state);
        self.write(JOIN, &p)
    }

    pub fn leave(&mut self, tick: u64, vehicle: VehicleId) -> io::Result<()> {
        if let Ok(at) = self.keys.binary_search_by_key(&vehicle, |&(v, _)| v) {
            self.keys.remove(at);
        }
        let mut p = [0u8; 10];
        p[..8].copy_from_slice(&tick.to_le_bytes());
        p[8..].copy_from_slice(&vehicle.to_le_bytes());
        self.write(LEAVE, &p)
    }

    /// Records the world's digest after `tick` steps, hands the records over and flushes.
    pub fn checkpoint(&mut self, tick: u64, digest: &Digest) -> io::Result<()> {
        self.write(CHECKPOINT, &tick_digest(tick, digest))?;
        self.flush()
    }

    /// Ends the recording with the final tick and digest, and flushes.
    pub fn end(&mut self, tick: u64, digest: &Digest) -> io::Result<()> {
        self.write(END, &tick_digest(tick, digest))?;
        self.flush()
    }

    /// Ends the recording (as [`Recorder::end`]) and returns the writer.
    pub fn finish(mut self, tick: u64, digest: &Digest) -> io::Result<W> {
        self.end(tick, digest)?;
        Ok(self.out)
    }
}

fn failed_before() -> io::Error {
    io::Error::other("the recording failed earlier: nothing more is written to it")
}

fn tick_digest(tick: u64, digest: &Digest) -> [u8; 40] {
    let mut p = [0u8; 40];
    p[..8].copy_from_slice(&tick.to_le_bytes());
    p[8..].copy_from_slice(&digest.0);
    p
}

/// Why a recorded world refused a change.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    World(#[from] WorldError),
    #[error("writing the recording: {0}")]
    Io(#[from] io::Error),
}

/// A world that records everything that enters it: the same `world::step`, with the inputs,
/// joins and leaves written down on the tick they apply, and a checkpoint every interval.
pub struct RecordedWorld<G, W: Write> {
    world: World<G>,
    recorder: Recorder<W>,
}

impl<G: Ground, W: Write> RecordedWorld<G, W> {
    /// Starts recording `world`, from the tick it has reached, into `out`.
    pub fn start(
        world: World<G>,
        out: W,
        data_hash: [u8; 32],
        checkpoint_interval: u32,
    ) -> io::Result<Self> {
        let recorder = Recorder::new(out, &header_of(&world, data_hash, checkpoint_interval))?;
        Ok(RecordedWorld { world, recorder })
    }

    pub fn world(&self) -> &World<G> {
        &self.world
    }

    /// Records the vehicles' keys, steps, and checkpoints when the interval comes round.
    pub fn step(&mut self, inputs: &Inputs) -> io::Result<()> {
        self.recorder
            .step_inputs(self.world.tick(), self.world.vehicles(), inputs)?;
        world::step(&mut self.world, inputs);
        let tick = self.world.tick();
        if self.recorder.checkpoint_due(tick) {
            self.recorder.checkpoint(tick, &self.world.digest())?;
        }
        Ok(())
    }

    pub fn join(&mut self, id: VehicleId, state: VehicleState) -> Result<(), RecordError> {
        self.world.add(id, state)?;
        self.recorder.join(self.world.tick(), id, &state)?;
        Ok(())
    }

    pub fn leave(&mut self, id: VehicleId) -> Result<(), RecordError> {
        self.world.remove(id)?;
        self.recorder.leave(self.world.tick(), id)?;
        Ok(())
    }

    /// Writes the end record and returns the world and the writer.
    pub fn finish(self) -> io::Result<(World<G>, W)> {
        let out = self
            .recorder
            .finish(self.world.tick(), &self.world.digest())?;
        Ok((self.world, out))
    }
}
