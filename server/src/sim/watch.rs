//! Watching a recording (issue 25): a recording played as a world, at a pace the one
//! watching sets (paused, ¼× to 8×), sought to any tick or to the next or previous join or
//! leave. Clock-free, as [`crate::sim::world_core`] is: the shell calls
//! [`Watch::advance`] once a world tick (10 ms) and hands it the controls that came.
//!
//! **Opening plays the whole valid part once** ([`Watch::open`]), as `roam-server replay`
//! does, checking every checkpoint, and keeps a copy of the [`Player`] every
//! [`KEY_EVERY`] ticks. A seek starts from the copy at or before its tick and plays at most
//! [`KEY_EVERY`] ticks of the recording (a few thousand vehicle steps: well under a
//! millisecond), so it costs the same anywhere in an hour-long file. The pass is the
//! replay's cost (8 million vehicle steps a second on one core: an hour of eight drivers,
//! 2.9 million steps, in about 0.4 s), and tells, before the first frame, how far the
//! recording is valid:
//!
//! - a clean end: to its end record;
//! - a file cut inside a record (a server killed mid-write) or ending without an end
//!   record (still being written, or its server died between records): to its last whole
//!   record, as `replay` plays it;
//! - a damaged record ([`recording::parse_valid`]): to the record before, with its byte
//!   offset and what is wrong;
//! - a replay that fails (a checkpoint that differs, an event the world cannot take): to
//!   the last checkpoint that matched.
//!
//! **A tick's state** is the world after that many steps, before the events recorded at
//! that tick (a join at tick T shows from tick T + 1, as the live world's snapshot does);
//! the last state held is the one after every valid event, whose digest is the one
//! `roam-server replay` prints for the same file.

use std::fmt;

use crate::sim::physics::Ground;
use crate::sim::recording::{self, Event, FormatError, Recording};
use crate::sim::replay::{Player, ReplayError};
use crate::sim::world::{Digest, VehicleId, World};
use crate::sim::world_core::Snapshot;

/// Ticks between the copies a seek starts from (5 s).
pub const KEY_EVERY: u64 = 500;

/// The slowest speed, in quarters (¼×).
pub const MIN_SPEED: u8 = 1;
/// The fastest speed, in quarters (8×).
pub const MAX_SPEED: u8 = 32;
/// 1×, in quarters.
pub const NORMAL_SPEED: u8 = 4;

/// Where a recording's valid part stops, and why.
#[derive(Clone, Debug, PartialEq)]
pub enum Stop {
    /// At its end record: closed cleanly.
    Closed,
    /// The file ends without an end record: cut inside the record at byte `at`, or
    /// (`None`) between records (still being written, or its server died).
    Open { cut_at: Option<u64> },
    /// A record that is wrong (its offset and what is wrong are in the error).
    Damaged(FormatError),
    /// The replay failed (the valid part ends at the last checkpoint that matched).
    Failed(ReplayError),
}

impl fmt::Display for Stop {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Stop::Closed => write!(f, "closed cleanly"),
            Stop::Open { cut_at: Some(at) } => write!(
                f,
                "no end record: the file is cut inside the record at byte {at} (its server \
                 stopped without closing it)"
            ),
            Stop::Open { cut_at: None } => write!(
                f,
                "no end record: the file ends between records (still being written, or its \
                 server stopped without closing it)"
            ),
            Stop::Damaged(e) => write!(f, "stopped at a damaged record: {e}"),
            Stop::Failed(e) => write!(f, "stopped where the replay failed: {e}"),
        }
    }
}

/// A join or a leave, to seek to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Mark {
    pub tick: u64,
    pub vehicle: VehicleId,
    pub join: bool,
}

/// What the one watching asks: the protocol's own `ReplayControl`, taken as it
/// comes (a speed in quarters clamped to [`MIN_SPEED`] ..= [`MAX_SPEED`], a seek to the
/// valid part).
pub use roam_protocol::messages::ReplayControl as Control;

/// Where the watching stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Status {
    /// The clock: the tick shown.
    pub tick: u64,
    /// The valid part's first and last ticks.
    pub start: u64,
    pub end: u64,
    /// Quarters (4: 1×).
    pub speed: u8,
    pub paused: bool,
}

/// A copy of the player at a tick, and the first event it has not played.
#[derive(Clone, Debug)]
struct Key<G> {
    player: Player<G>,
    next: usize,
}

/// A recording being watched.
#[derive(Debug)]
pub struct Watch<G> {
    /// The valid part's events.
    events: Vec<Event>,
    /// A copy every [`KEY_EVERY`] ticks from the start, the first at the start.
    keys: Vec<Key<G>>,
    /// The pass that checks the events as they come, after the last one, and the tick of
    /// the next copy it keeps.
    tail: Player<G>,
    next_key: u64,
    /// Events through the last checkpoint that matched.
    verified: usize,
    player: Player<G>,
    /// The first event not played.
    next: usize,
    start: u64,
    end: u64,
    stop: Stop,
    marks: Vec<Mark>,
    speed: u8,
    paused: bool,
    /// Quarter ticks owed (below 4).
    owed: u8,
    /// The end has been reached since the last [`Watch::take_ended`] said so.
    ended_told: bool,
    /// Following a recording still being written ([`Watch::follow`]).
    following: bool,
}

impl<G: Ground + Clone> Watch<G> {
    /// Opens `recording` (its valid part, and `damaged`: why the bytes after it are not,
    /// from [`recording::parse_valid`]) on `ground` whose data set hash is `data_hash`,
    /// playing it through once (see the module docs). Refused, as `replay` refuses, for
    /// another data set or physics rate, or a header the world cannot take. Starts
    /// playing at 1× from the start.
    pub fn open(
        recording: &Recording,
        damaged: Option<FormatError>,
        ground: G,
        data_hash: &[u8; 32],
    ) -> Result<Watch<G>, ReplayError> {
        let start = recording.header.start_tick;
        let first = Player::start(recording, ground, data_hash)?;
        let mut watch = Watch {
            events: Vec::new(),
            keys: vec![Key {
                player: first.clone(),
                next: 0,
            }],
            tail: first.clone(),
            next_key: start + KEY_EVERY,
            verified: 0,
            player: first,
            next: 0,
            start,
            end: start,
            stop: Stop::Open { cut_at: None },
            marks: Vec::new(),
            speed: NORMAL_SPEED,
            paused: false,
            owed: 0,
            ended_told: false,
            following: false,
        };
        watch.append(&recording.events, damaged, recording.truncated_at);
        Ok(watch)
    }

    /// Follows a recording still being written: [`Watch::append`] gives its new events as
    /// they come, and its end is not said ended until its end record comes.
    pub fn follow(&mut self) {
        self.following = true;
    }

    /// Stops following (the file can no longer be read): its end is the end.
    pub fn unfollow(&mut self) {
        self.following = false;
    }

    /// Whether the valid part may still grow (no end record, nothing wrong yet).
    pub fn growing(&self) -> bool {
        matches!(self.stop, Stop::Open { .. })
    }

    /// More of the recording: `events` after those taken so far (from a
    /// [`recording::Reader`]), played through once as at open (copies kept, checkpoints
    /// checked); `damaged` the reader's error if it met a wrong record, and `cut_at` where
    /// a partial record starts. Nothing once the valid part has stopped (an end record,
    /// a damaged record, a failed replay). A clock held at the end plays on into them.
    pub fn append(&mut self, events: &[Event], damaged: Option<FormatError>, cut_at: Option<u64>) {
        if !self.growing() {
            return;
        }
        let mut failed = None;
        for event in events {
            while event.tick() >= self.next_key {
                self.tail.run_to(self.next_key);
                self.keys.push(Key {
                    player: self.tail.clone(),
                    next: self.events.len(),
                });
                self.next_key += KEY_EVERY;
            }
            if let Err(e) = self.tail.play(event) {
                failed = Some(e);
                break;
            }
            self.events.push(*event);
            match *event {
                Event::Join { tick, vehicle, .. } => self.marks.push(Mark {
                    tick,
                    vehicle,
                    join: true,
                }),
                Event::Leave { tick, vehicle } => self.marks.push(Mark {
                    tick,
                    vehicle,
                    join: false,
                }),
                Event::Checkpoint { .. } | Event::End { .. } => self.verified = self.events.len(),
                _ => {}
            }
        }
        self.stop = match (failed, damaged) {
            (Some(e), _) => {
                // To the last checkpoint that matched (a join or leave recorded after it,
                // at its tick, goes too).
                self.events.truncate(self.verified);
                let joins_and_leaves = self
                    .events
                    .iter()
                    .filter(|e| matches!(e, Event::Join { .. } | Event::Leave { .. }));
                self.marks.truncate(joins_and_leaves.count());
                Stop::Failed(e)
            }
            (None, Some(e)) => Stop::Damaged(e),
            (None, None) if self.tail.ended() => Stop::Closed,
            (None, None) => Stop::Open { cut_at },
        };
        self.end = self.events.last().map_or(self.start, Event::tick);
        let (end, len) = (self.end, self.events.len());
        self.keys
            .retain(|k| k.player.world().tick() <= end && k.next <= len);
        if self.next > len || self.player.world().tick() > end {
            self.seek(end);
        }
    }

    /// Where the valid part stops, and why.
    pub fn stop(&self) -> &Stop {
        &self.stop
    }

    /// The joins and leaves, in order.
    pub fn marks(&self) -> &[Mark] {
        &self.marks
    }

    pub fn world(&self) -> &World<G> {
        self.player.world()
    }

    pub fn status(&self) -> Status {
        Status {
            tick: self.player.world().tick(),
            start: self.start,
            end: self.end,
            speed: self.speed,
            paused: self.paused,
        }
    }

    /// Whether the clock is at the valid part's end (its last state held).
    pub fn at_end(&self) -> bool {
        self.player.world().tick() >= self.end && self.next >= self.events.len()
    }

    /// The world as the live world's snapshot shows it.
    pub fn snapshot(&self) -> Snapshot {
        let world = self.player.world();
        Snapshot {
            tick: world.tick(),
            vehicles: world.vehicles().to_vec(),
            applied: Vec::new(),
            held: Vec::new(),
        }
    }

    /// Takes a control.
    pub fn control(&mut self, control: Control) {
        match control {
            Control::Pause => self.paused = true,
            Control::Resume => self.paused = false,
            Control::Speed(q) => self.speed = q.clamp(MIN_SPEED, MAX_SPEED),
            Control::Seek(tick) => self.seek(tick),
            Control::SeekMark { forward } => {
                let now = self.player.world().tick();
                let mark = if forward {
                    self.marks.iter().find(|m| m.tick > now)
                } else {
                    self.marks.iter().rev().find(|m| m.tick < now)
                };
                if let Some(m) = mark.copied() {
                    self.seek(m.tick);
                }
            }
        }
    }

    /// One world tick of the one watching: the clock moves by the speed (¼× one tick in
    /// four, 8× eight ticks), not while paused, and stops at the end.
    pub fn advance(&mut self) {
        if self.paused || self.at_end() {
            return;
        }
        let owed = self.owed + self.speed;
        self.owed = owed % NORMAL_SPEED;
        let steps = u64::from(owed / NORMAL_SPEED);
        let to = (self.player.world().tick() + steps).min(self.end);
        self.play_to(to);
    }

    /// The end, the first time it is reached since the last seek before it: its tick and
    /// the world's digest (the one `roam-server replay` prints for the file).
    pub fn take_ended(&mut self) -> Option<(u64, Digest)> {
        if self.following && self.growing() {
            return None;
        }
        if self.at_end() && !self.ended_told {
            self.ended_told = true;
            let world = self.player.world();
            return Some((world.tick(), world.digest()));
        }
        None
    }

    /// The clock to `tick` (clamped to the valid part), from the copy at or before it.
    pub fn seek(&mut self, tick: u64) {
        let tick = tick.clamp(self.start, self.end);
        let now = self.player.world().tick();
        // Forward within a key's reach: on from here.
        let k = self
            .keys
            .partition_point(|k| k.player.world().tick() <= tick)
            .saturating_sub(1);
        let key_tick = self.keys[k].player.world().tick();
        if !(tick >= now && now >= key_tick) {
            self.player = self.keys[k].player.clone();
            self.next = self.keys[k].next;
        }
        self.owed = 0;
        if tick < self.end {
            self.ended_told = false;
        }
        self.play_to(tick);
    }

    /// Plays the events before `tick` and steps to it; at the end, the end's events too.
    fn play_to(&mut self, tick: u64) {
        while let Some(event) = self.events.get(self.next) {
            if event.tick() >= tick && tick < self.end {
                break;
            }
            // Checked when the recording was opened: the valid part plays.
            let played = self.player.play(event);
            debug_assert!(played.is_ok(), "the valid part replays: {played:?}");
            self.next += 1;
        }
        self.player.run_to(tick);
    }
}

impl Status {
    /// The clock as seconds since the valid part's start.
    pub fn seconds(&self) -> f64 {
        (self.tick - self.start) as f64 / f64::from(crate::sim::physics::STEPS_PER_SECOND)
    }
}

/// The header's vehicles and events' joins give the vehicles a recording shows; this is
/// what a log line says of a recording opened to watch.
pub fn describe<G>(watch: &Watch<G>) -> String {
    let ticks = watch.end - watch.start;
    format!(
        "valid from tick {} to tick {} ({ticks} ticks, {:.2} s), {} joins and leaves; {}",
        watch.start,
        watch.end,
        ticks as f64 / f64::from(crate::sim::physics::STEPS_PER_SECOND),
        watch.marks.len(),
        watch.stop
    )
}

/// Parses `bytes` and opens them to watch (see [`Watch::open`]); a file whose header is
/// wrong is the parse error, one refused by the replay the replay's.
pub fn open_bytes<G: Ground + Clone>(
    bytes: &[u8],
    ground: G,
    data_hash: &[u8; 32],
) -> Result<Watch<G>, OpenError> {
    let (recording, damaged) = recording::parse_valid(bytes)?;
    Ok(Watch::open(&recording, damaged, ground, data_hash)?)
}

/// Reads `path` (at most [`recording::MAX_FILE_BYTES`]) and opens it to watch.
pub fn open_file<G: Ground + Clone>(
    path: &std::path::Path,
    ground: G,
    data_hash: &[u8; 32],
) -> Result<Watch<G>, OpenError> {
    open_file_reading(path, ground, data_hash).map(|(watch, _, _)| watch)
}

/// As [`open_file`], and the file and the reader that read it, positioned at its end so
/// far: for following a file still being written.
pub fn open_file_reading<G: Ground + Clone>(
    path: &std::path::Path,
    ground: G,
    data_hash: &[u8; 32],
) -> Result<(Watch<G>, std::fs::File, recording::Reader), OpenError> {
    use std::io::Read;
    let mut file = std::fs::File::open(path)?;
    let mut bytes = Vec::new();
    (&mut file)
        .take(recording::MAX_FILE_BYTES + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > recording::MAX_FILE_BYTES {
        return Err(OpenError::TooLarge);
    }
    // The bytes read become the reader's (no second copy of a file of up to 256 MiB).
    let mut reader = recording::Reader::open_owned(bytes)?;
    let mut events = Vec::new();
    let damaged = reader.read(&mut events).err();
    let recording = Recording {
        header: reader.header().clone(),
        events,
        truncated_at: reader.cut_at(),
    };
    let watch = Watch::open(&recording, damaged, ground, data_hash)?;
    Ok((watch, file, reader))
}

/// Why a recording cannot be watched.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("reading it: {0}")]
    Io(#[from] std::io::Error),
    #[error(
        "more than the {} bytes a recording may have",
        recording::MAX_FILE_BYTES
    )]
    TooLarge,
    #[error(transparent)]
    Format(#[from] FormatError),
    #[error(transparent)]
    Replay(#[from] ReplayError),
}
