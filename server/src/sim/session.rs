//! The server's recording of a session: it fails safe, and it rotates.
//!
//! - **An I/O error never stops the world.** [`SessionRecording`] takes the world's joins,
//!   leaves and steps and records them; a failed write ends the recording, never the
//!   world: the world changes as it would have, the file is cut back to its last whole
//!   record (the [`crate::sim::recorder::Recorder`] knows where that is, and
//!   [`RecordFile::cut`] truncates; a file whose header is not even whole is removed), and
//!   a [`Notice`] says so. The shell drains the notices ([`SessionRecording::notices`]) and
//!   logs them: errors are reported, not returned, so nothing upstream can stop on them.
//!   After a failure the session goes on unrecorded, and every join says so
//!   ([`Notice::JoinedUnrecorded`]). A join is made in the world first and recorded after,
//!   so a failing record never leaves a vehicle without its driver.
//! - **At start it is the other way round.** A first file that cannot be created or
//!   written (a read-only `--record-dir`) is [`SessionRecording::start`]'s error, and the
//!   server does not start: a server that runs unrecorded from its first tick is more
//!   likely a mistake than a choice, and the operator is there to see it. The error says
//!   so and names the file (not the mid-session notice's "…goes on unrecorded").
//! - **A size cap, with rotation.** Before each change (a step's records, a join, a leave)
//!   the recording checks that the file stays within `max_bytes` with the change and an end
//!   record; if not, the file is finished (its end record: the world's tick and digest) and
//!   the next file starts with a header holding the world as it is (its tick and vehicles,
//!   format version 3), so each file replays on its own and the next one's header is the
//!   world at the end of the one before. A file holding nothing but its header is never
//!   rotated (a header larger than the cap gives files of one change each, not a loop).
//! - Where files come from is injected ([`RecordFiles`]): a directory in the server, a
//!   writer that fails after N bytes in the tests.
//! - **Written on the world thread**, at least once a second (about 64 KiB at most at a time):
//!   errors are handled as above, but a write that blocks (a hung network mount) holds the
//!   world up. A writer thread would take that away at the cost of errors arriving late
//!   and the cut point known only there; not done: the README asks for a local disk.

use std::fmt;
use std::io;

use crate::sim::physics::{Ground, VehicleState};
use crate::sim::record_files::{RecordFile, RecordFiles};
use crate::sim::recorder::{Recorder, header_of};
use crate::sim::recording::{MAX_CHECKPOINT_INTERVAL, MAX_FILE_BYTES, STATE, record_len};
use crate::sim::world::{self, Inputs, Vehicle, VehicleId, World, WorldError};

/// The size cap of a recording file unless told otherwise.
pub const DEFAULT_MAX_BYTES: u64 = 64 << 20;
/// The smallest size cap the command line takes (a few seconds of a busy session).
pub const MIN_MAX_BYTES: u64 = 64 << 10;
/// The largest size cap: what `replay` reads.
pub const MAX_MAX_BYTES: u64 = MAX_FILE_BYTES;

/// The most one vehicle's records for a step take (a twice record).
const STEP_PER_VEHICLE: u64 = record_len(12);
/// A checkpoint or an end record.
const CHECKPOINT_LEN: u64 = record_len(40);
const JOIN_LEN: u64 = record_len(10 + STATE);
const LEAVE_LEN: u64 = record_len(10);

/// How to record a session: where its files come from, and the size cap of each.
pub struct RecordOptions {
    pub files: Box<dyn RecordFiles>,
    /// A file is finished, and the next begun, before it would grow past this.
    pub max_bytes: u64,
    /// The terrain's [`crate::Terrain::content_hash`], when the shell computed it (a
    /// terrain opened without its colour map cannot: see
    /// [`crate::Terrain::content_hash_in`]); `None`: the world core computes it.
    pub terrain_hash: Option<[u8; 32]>,
}

impl RecordOptions {
    pub fn new(files: impl RecordFiles + 'static, max_bytes: u64) -> RecordOptions {
        RecordOptions {
            files: Box::new(files),
            max_bytes,
            terrain_hash: None,
        }
    }

    /// These options with the terrain's hash given.
    pub fn with_terrain_hash(self, hash: [u8; 32]) -> RecordOptions {
        RecordOptions {
            terrain_hash: Some(hash),
            ..self
        }
    }
}

/// What happened to the recording, for the shell to log.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Notice {
    /// The first file began, with the world at `tick`.
    Started { file: String, tick: u64 },
    /// `from` reached the size cap and was finished at `tick`; `to` continues from there.
    Rotated { from: String, to: String, tick: u64 },
    /// A write to `file` failed: the recording has ended (`ended` says how the file was
    /// left), and the session goes on unrecorded.
    Failed {
        file: String,
        error: String,
        ended: Ended,
    },
    /// The next file could not be created (the error names it): the recording has ended.
    CreateFailed { error: String },
    /// A driver joined after the recording ended.
    JoinedUnrecorded { vehicle: VehicleId },
    /// The recording was finished, `file` last, at `tick`.
    Closed { file: String, tick: u64 },
}

/// How a file was left after a failed write.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Ended {
    /// Cut back to its whole records: this many bytes.
    Whole(u64),
    /// It held not even a whole header: removed.
    Removed,
    /// It could not be cut back or removed (the error): it may end inside a record,
    /// which `replay` reports and skips.
    Uncut(String),
}

impl Notice {
    /// Whether the notice is an error (the recording ended).
    pub fn is_error(&self) -> bool {
        matches!(self, Notice::Failed { .. } | Notice::CreateFailed { .. })
    }
}

impl fmt::Display for Notice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Notice::Started { file, tick } => write!(f, "recording to {file} from tick {tick}"),
            Notice::Rotated { from, to, tick } => write!(
                f,
                "recording: {from} reached its size cap and was closed at tick {tick}; {to} continues it"
            ),
            Notice::Failed { file, error, ended } => {
                write!(f, "recording to {file} failed: {error}; ")?;
                match ended {
                    Ended::Whole(n) => {
                        write!(f, "the file ends at its last whole record (byte {n})")?
                    }
                    Ended::Removed => write!(f, "it held no whole header and was removed")?,
                    Ended::Uncut(e) => write!(
                        f,
                        "it could not be cut back to its last whole record ({e}): replay skips the partial record at its end"
                    )?,
                }
                write!(f, "; the session goes on unrecorded")
            }
            Notice::CreateFailed { error } => write!(
                f,
                "recording: the next file could not be started: {error}; the session goes on unrecorded"
            ),
            Notice::JoinedUnrecorded { vehicle } => write!(
                f,
                "vehicle {vehicle} joined unrecorded: the recording ended after an error"
            ),
            Notice::Closed { file, tick } => write!(f, "recording: {file} closed at tick {tick}"),
        }
    }
}

/// The error of a recording that cannot start (its first file cannot be created, or its
/// header written): the server does not start, so the message says so. The notice's own
/// text ("…the session goes on unrecorded") is true only mid-session, and was once shown
/// here, saying the opposite of what happened.
fn start_error(notice: Notice) -> io::Error {
    let why = match notice {
        Notice::CreateFailed { error } => format!("cannot create its first file: {error}"),
        Notice::Failed { file, error, .. } => format!("cannot write {file}: {error}"),
        other => other.to_string(),
    };
    io::Error::other(format!(
        "the recording cannot start ({why}), and the server does not run unrecorded: \
         give a --record-dir it can create files in"
    ))
}

/// The file being written.
struct Live {
    name: String,
    rec: Recorder<Box<dyn RecordFile>>,
}

/// A session's recording (see the module docs): it changes the world it is handed and
/// records the change, and never fails.
pub struct SessionRecording {
    files: Box<dyn RecordFiles>,
    max_bytes: u64,
    data_hash: [u8; 32],
    /// `None` once the recording has ended after an error.
    live: Option<Live>,
    notices: Vec<Notice>,
}

impl SessionRecording {
    /// Starts recording `world` (on the data set whose hash is `data_hash`) into the first
    /// file. An error here (the first file cannot be created or written) is the caller's:
    /// a server refuses to start rather than run unrecorded unnoticed.
    pub fn start<G: Ground>(
        options: RecordOptions,
        data_hash: [u8; 32],
        world: &World<G>,
    ) -> io::Result<SessionRecording> {
        let mut s = SessionRecording {
            files: options.files,
            max_bytes: options.max_bytes,
            data_hash,
            live: None,
            notices: Vec::new(),
        };
        let live = s.open(world).map_err(start_error)?;
        s.notices.push(Notice::Started {
            file: live.name.clone(),
            tick: world.tick(),
        });
        s.live = Some(live);
        Ok(s)
    }

    /// The file being written; `None` once the recording has ended.
    pub fn file(&self) -> Option<&str> {
        self.live.as_ref().map(|l| l.name.as_str())
    }

    /// What happened since the last call, oldest first.
    pub fn notices(&mut self) -> Vec<Notice> {
        std::mem::take(&mut self.notices)
    }

    /// The next file, its header the world as it is; a failure is the notice to give.
    fn open<G: Ground>(&mut self, world: &World<G>) -> Result<Live, Notice> {
        let (name, file) = self.files.create().map_err(|e| Notice::CreateFailed {
            error: e.to_string(),
        })?;
        let header = header_of(world, self.data_hash, MAX_CHECKPOINT_INTERVAL);
        match Recorder::new(file, &header) {
            Ok(rec) => Ok(Live { name, rec }),
            // The file (dropped with the recorder) holds part of a header at most.
            Err(error) => Err(Notice::Failed {
                ended: self.remove(&name),
                file: name,
                error: error.to_string(),
            }),
        }
    }

    /// Removes a file without a whole header.
    fn remove(&mut self, name: &str) -> Ended {
        match self.files.remove(name) {
            Ok(()) => Ended::Removed,
            Err(e) => Ended::Uncut(e.to_string()),
        }
    }

    /// The recording ends after `error`: the file is cut back to its whole records.
    fn fail(&mut self, error: io::Error) {
        let Some(Live { name, mut rec }) = self.live.take() else {
            return;
        };
        let whole = rec.whole_len();
        let ended = if whole == 0 {
            drop(rec);
            self.remove(&name)
        } else {
            match rec.get_mut().cut(whole) {
                Ok(()) => Ended::Whole(whole),
                Err(e) => Ended::Uncut(e.to_string()),
            }
        };
        self.notices.push(Notice::Failed {
            file: name,
            error: error.to_string(),
            ended,
        });
    }

    /// Makes sure `need` more bytes and an end record fit in the file, rotating if not.
    fn room<G: Ground>(&mut self, world: &World<G>, need: u64) {
        let Some(live) = &mut self.live else {
            return;
        };
        if live.rec.is_empty() || live.rec.len() + need + CHECKPOINT_LEN <= self.max_bytes {
            return;
        }
        let tick = world.tick();
        if let Err(e) = live.rec.end(tick, &world.digest()) {
            return self.fail(e);
        }
        let Some(Live { name: from, .. }) = self.live.take() else {
            return;
        };
        match self.open(world) {
            Ok(next) => {
                self.notices.push(Notice::Rotated {
                    from,
                    to: next.name.clone(),
                    tick,
                });
                self.live = Some(next);
            }
            Err(notice) => {
                self.notices.push(Notice::Closed { file: from, tick });
                self.notices.push(notice);
            }
        }
    }

    /// One step of `world` with `inputs`, recorded (with a checkpoint when one is due).
    pub fn step<G: Ground>(&mut self, world: &mut World<G>, inputs: &Inputs) {
        let need = world.vehicles().len() as u64 * STEP_PER_VEHICLE + CHECKPOINT_LEN;
        self.room(world, need);
        if let Some(live) = &mut self.live
            && let Err(e) = live.rec.step_inputs(world.tick(), world.vehicles(), inputs)
        {
            self.fail(e);
        }
        world::step(world, inputs);
        let tick = world.tick();
        if let Some(live) = &mut self.live
            && live.rec.checkpoint_due(tick)
            && let Err(e) = live.rec.checkpoint(tick, &world.digest())
        {
            self.fail(e);
        }
    }

    /// Adds a vehicle to `world`, recorded. Only the world can refuse it.
    pub fn join<G: Ground>(
        &mut self,
        world: &mut World<G>,
        id: VehicleId,
        state: VehicleState,
    ) -> Result<(), WorldError> {
        if world.vehicle(id).is_some() {
            return Err(WorldError::Duplicate(id));
        }
        // Room first: a rotated-in file's header must not hold the vehicle yet.
        self.room(world, JOIN_LEN);
        world.add(id, state)?;
        match &mut self.live {
            Some(live) => {
                if let Err(e) = live.rec.join(world.tick(), id, &state) {
                    self.fail(e);
                }
            }
            None => self.notices.push(Notice::JoinedUnrecorded { vehicle: id }),
        }
        Ok(())
    }

    /// Removes a vehicle from `world`, recorded. Only the world can refuse it.
    pub fn leave<G: Ground>(
        &mut self,
        world: &mut World<G>,
        id: VehicleId,
    ) -> Result<Vehicle, WorldError> {
        if world.vehicle(id).is_none() {
            return Err(WorldError::Missing(id));
        }
        self.room(world, LEAVE_LEN);
        let gone = world.remove(id)?;
        if let Some(live) = &mut self.live
            && let Err(e) = live.rec.leave(world.tick(), id)
        {
            self.fail(e);
        }
        Ok(gone)
    }

    /// Finishes the recording with the world's last tick: the file gets its end record.
    /// Returns the notices not yet taken, this one's last.
    pub fn finish<G: Ground>(mut self, world: &World<G>) -> Vec<Notice> {
        if let Some(live) = &mut self.live {
            let tick = world.tick();
            match live.rec.end(tick, &world.digest()) {
                Ok(()) => {
                    let file = live.name.clone();
                    self.notices.push(Notice::Closed { file, tick });
                }
                Err(e) => self.fail(e),
            }
        }
        self.notices
    }
}
