//! Session recordings: what entered the world, tick by tick, so a replay rebuilds it. This
//! module is the format and its reader; [`crate::sim::recorder`] writes it, and
//! [`crate::sim::session`] is the server's fail-safe, rotating use of the writer.
//!
//! # Format (version 3; versions 1 and 2 read as well)
//!
//! All integers little-endian; `f64`s as their IEEE bits.
//!
//! ```text
//! magic    8 bytes  "roamrec\n"
//! version  u32      3
//! records  …        the first is the header; then events, ticks never decreasing
//! ```
//!
//! A record is `kind: u8`, `len: u32` (≤ 1 MiB), `len` bytes of payload, then 8 bytes of
//! check: the start of BLAKE3 over kind, len and payload. Kinds and payloads:
//!
//! | kind | record | payload |
//! | --- | --- | --- |
//! | 1 | header | data-set hash `[u8; 32]`, steps per second `u32`, checkpoint interval `u32`, start tick `u64` (version 3 only), vehicle count `u32`, then per vehicle: id `u16`, state (x, z, speed, heading: 4 × `f64`) |
//! | 2 | input | tick `u64`, vehicle `u16`, keys `u8` (bits: Up, Down, Left, Right) |
//! | 3 | join | tick `u64`, vehicle `u16`, state (4 × `f64`) |
//! | 4 | leave | tick `u64`, vehicle `u16` |
//! | 5 | checkpoint | tick `u64`, world digest `[u8; 32]` |
//! | 6 | end | tick `u64`, world digest `[u8; 32]` |
//! | 7 | wait | tick `u64`, vehicle `u16`: the vehicle takes no physics step in step T + 1 |
//! | 8 | twice | tick `u64`, vehicle `u16`, keys `u8`, keys `u8`: two physics steps in step T + 1, with these keys |
//!
//! The header holds the world where the recording starts: its vehicles, and (version 3) the
//! tick it has reached, so that a file the server starts mid-session, when the one before it
//! reached its size cap, replays on its own (versions 1 and 2 always start at tick 0). Every
//! vehicle holds no keys at the start: an input record gives a vehicle's first keys.
//!
//! An event "at tick T" happens when the world has taken T steps, before the next step: an
//! input record gives the keys a vehicle holds from step T + 1 on (inputs are recorded only
//! when they change); a wait or twice record is for step T + 1 only, and leaves the keys
//! an input record set; a checkpoint or end gives the digest after T steps. Checkpoints come
//! every interval (at most 100) ticks counted from the start tick, and the writer hands its
//! records to the file at each, so a killed server loses at most the last second. The file
//! is append-only: a cut anywhere leaves a prefix of whole records followed by a partial
//! one, which [`parse`] reports and skips; a whole record that is wrong (its check, kind,
//! length or content) is an error naming its byte offset. The server never leaves a
//! partial record behind itself: a failed write is cut back to the last whole record
//! ([`crate::sim::session`]).

use crate::sim::physics::{Keys, VehicleState};
use crate::sim::world::{Digest, VehicleId};

/// The file's first bytes.
pub const MAGIC: [u8; 8] = *b"roamrec\n";
/// The format version this code writes; it reads this one and [`MIN_VERSION`] on.
pub const VERSION: u32 = 3;
/// The oldest format version this code reads (version 1 has no wait or twice records).
pub const MIN_VERSION: u32 = 1;
/// Largest payload of a record.
pub const MAX_RECORD: usize = 1 << 20;
/// Longest interval between checkpoints, ticks.
pub const MAX_CHECKPOINT_INTERVAL: u32 = 100;
/// The largest recording `replay` reads, and so the largest file the server writes (its
/// size cap may be at most this).
pub const MAX_FILE_BYTES: u64 = 256 << 20;
pub(crate) const CHECK: usize = 8;
/// Bytes of a header vehicle and of a state.
pub(crate) const STATE: usize = 32;
/// The latest start tick a header may give (millennia at 100 Hz): a replay's ticks count
/// on from it without overflowing.
pub const MAX_START_TICK: u64 = 1 << 48;
/// Bytes of a header's payload before its vehicles, by version.
const fn header_fixed(version: u32) -> usize {
    if version >= 3 { 52 } else { 44 }
}

/// Bytes a record with a payload of `payload` bytes takes in the file.
pub const fn record_len(payload: usize) -> u64 {
    (5 + payload + CHECK) as u64
}

/// The header: what a replay needs before the first event.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// [`crate::Terrain::content_hash`] of the data set.
    pub data_hash: [u8; 32],
    pub steps_per_second: u32,
    /// Ticks between checkpoints (1 ..= 100).
    pub checkpoint_interval: u32,
    /// The tick the world has reached where the recording starts (0 before version 3).
    pub start_tick: u64,
    /// The vehicles at the start tick.
    pub vehicles: Vec<(VehicleId, VehicleState)>,
}

/// What happened at a tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    Input {
        tick: u64,
        vehicle: VehicleId,
        keys: Keys,
    },
    Join {
        tick: u64,
        vehicle: VehicleId,
        state: VehicleState,
    },
    Leave {
        tick: u64,
        vehicle: VehicleId,
    },
    Checkpoint {
        tick: u64,
        digest: Digest,
    },
    /// The vehicle takes no step in step `tick + 1`.
    Wait {
        tick: u64,
        vehicle: VehicleId,
    },
    /// The vehicle takes two steps in step `tick + 1`, with these keys.
    Twice {
        tick: u64,
        vehicle: VehicleId,
        first: Keys,
        second: Keys,
    },
    End {
        tick: u64,
        digest: Digest,
    },
}

impl Event {
    pub fn tick(&self) -> u64 {
        match *self {
            Event::Input { tick, .. }
            | Event::Join { tick, .. }
            | Event::Leave { tick, .. }
            | Event::Checkpoint { tick, .. }
            | Event::Wait { tick, .. }
            | Event::Twice { tick, .. }
            | Event::End { tick, .. } => tick,
        }
    }
}

/// A parsed recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    pub header: Header,
    /// Every whole event record, in order (an end record, if any, is last).
    pub events: Vec<Event>,
    /// Where a partial record starts, when the file was cut inside one.
    pub truncated_at: Option<u64>,
}

/// Why bytes are not a recording.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FormatError {
    #[error("not a roam recording: the first 8 bytes should be \"roamrec\\n\"")]
    Magic,
    #[error(
        "recording format version {found}; this build reads versions {MIN_VERSION} to {VERSION}"
    )]
    Version { found: u32 },
    #[error("the file ends at byte {len}, inside the header (a recording that never started)")]
    TruncatedHeader { len: u64 },
    #[error("record at byte {offset}: {what}")]
    Corrupt { offset: u64, what: String },
}

fn corrupt(offset: usize, what: impl Into<String>) -> FormatError {
    FormatError::Corrupt {
        offset: offset as u64,
        what: what.into(),
    }
}

pub(crate) const HEADER: u8 = 1;
pub(crate) const INPUT: u8 = 2;
pub(crate) const JOIN: u8 = 3;
pub(crate) const LEAVE: u8 = 4;
pub(crate) const CHECKPOINT: u8 = 5;
pub(crate) const END: u8 = 6;
pub(crate) const WAIT: u8 = 7;
pub(crate) const TWICE: u8 = 8;

pub(crate) fn check(kind: u8, payload: &[u8]) -> [u8; CHECK] {
    let mut h = blake3::Hasher::new();
    h.update(&[kind]);
    h.update(&(payload.len() as u32).to_le_bytes());
    h.update(payload);
    let mut out = [0; CHECK];
    out.copy_from_slice(&h.finalize().as_bytes()[..CHECK]);
    out
}

pub(crate) fn put_state(out: &mut Vec<u8>, s: &VehicleState) {
    for bits in s.to_bits() {
        out.extend_from_slice(&bits.to_le_bytes());
    }
}

/// Reads fixed-size fields from a payload whose length was checked first.
struct Fields<'a> {
    bytes: &'a [u8],
}

impl Fields<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let (head, rest) = self.bytes.split_at(N);
        self.bytes = rest;
        head.try_into().expect("split_at(N) gives N bytes")
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn state(&mut self) -> VehicleState {
        VehicleState::from_bits([self.u64(), self.u64(), self.u64(), self.u64()])
    }
}

/// A framed record: its kind, its payload, and where the next record starts.
type Framed<'a> = (u8, &'a [u8], usize);

/// Why a record's kind and length cannot be a record's ([`length_ok`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
enum LengthError {
    /// A header's payload is `head` bytes plus 34 per vehicle, at most [`MAX_RECORD`].
    #[error("a header of {len} bytes (expected {head} plus 34 per vehicle, at most {MAX_RECORD})")]
    Header { len: usize, head: usize },
    #[error("unknown record kind {0}")]
    Kind(u8),
    #[error("a record of kind {kind} with {len} bytes, expected {expected}")]
    Record {
        kind: u8,
        len: usize,
        expected: usize,
    },
}

/// The payload length a record of `kind` must have in a file of `version` (a header:
/// 44 or 52 bytes plus 34 per vehicle), or why it cannot.
fn length_ok(kind: u8, len: usize, version: u32) -> Result<(), LengthError> {
    let expected = match kind {
        HEADER => {
            let head = header_fixed(version);
            return if len >= head && (len - head).is_multiple_of(2 + STATE) && len <= MAX_RECORD {
                Ok(())
            } else {
                Err(LengthError::Header { len, head })
            };
        }
        INPUT => 11,
        JOIN => 10 + STATE,
        LEAVE | WAIT => 10,
        TWICE => 12,
        CHECKPOINT | END => 40,
        other => return Err(LengthError::Kind(other)),
    };
    if len == expected {
        Ok(())
    } else {
        Err(LengthError::Record {
            kind,
            len,
            expected,
        })
    }
}

/// One framed record: `Ok(None)` when the bytes end inside it. The kind and length are
/// checked before the end of the bytes is, so a damaged length is an error, not a cut.
fn next_record(bytes: &[u8], at: usize, version: u32) -> Result<Option<Framed<'_>>, FormatError> {
    let Some(head) = bytes.get(at..at + 5) else {
        if let Some(&kind) = bytes.get(at) {
            // At least the kind is there: it must be one we know.
            if let Err(e @ LengthError::Kind(_)) = length_ok(kind, 0, version) {
                return Err(corrupt(at, e.to_string()));
            }
        }
        return Ok(None);
    };
    let kind = head[0];
    let len = u32::from_le_bytes([head[1], head[2], head[3], head[4]]) as usize;
    length_ok(kind, len, version).map_err(|e| corrupt(at, e.to_string()))?;
    let end = at + 5 + len + CHECK;
    let Some(whole) = bytes.get(at..end) else {
        return Ok(None);
    };
    let payload = &whole[5..5 + len];
    if whole[5 + len..] != check(kind, payload) {
        return Err(corrupt(at, "check bytes do not match the record"));
    }
    Ok(Some((kind, payload, end)))
}

/// A payload of exactly `n` bytes, or an error naming the record.
fn sized<'a>(
    payload: &'a [u8],
    n: usize,
    at: usize,
    what: &str,
) -> Result<Fields<'a>, FormatError> {
    if payload.len() != n {
        return Err(corrupt(
            at,
            format!("{what} record of {} bytes, expected {n}", payload.len()),
        ));
    }
    Ok(Fields { bytes: payload })
}

fn parse_header(payload: &[u8], at: usize, version: u32) -> Result<Header, FormatError> {
    let head = header_fixed(version);
    if payload.len() < head {
        return Err(corrupt(
            at,
            format!(
                "header of {} bytes, expected at least {head}",
                payload.len()
            ),
        ));
    }
    let mut f = Fields { bytes: payload };
    let data_hash = f.take::<32>();
    let steps_per_second = f.u32();
    let checkpoint_interval = f.u32();
    let start_tick = if version >= 3 { f.u64() } else { 0 };
    if start_tick > MAX_START_TICK {
        return Err(corrupt(
            at,
            format!("start tick {start_tick}, expected at most {MAX_START_TICK}"),
        ));
    }
    let count = f.u32() as usize;
    if f.bytes.len() as u64 != count as u64 * (2 + STATE) as u64 {
        return Err(corrupt(
            at,
            format!(
                "header lists {count} vehicles in {} bytes, expected {}",
                f.bytes.len(),
                count as u64 * (2 + STATE) as u64
            ),
        ));
    }
    if !(1..=MAX_CHECKPOINT_INTERVAL).contains(&checkpoint_interval) {
        return Err(corrupt(
            at,
            format!(
                "checkpoint interval {checkpoint_interval}, expected 1 ..= {MAX_CHECKPOINT_INTERVAL}"
            ),
        ));
    }
    let vehicles = (0..count).map(|_| (f.u16(), f.state())).collect();
    Ok(Header {
        data_hash,
        steps_per_second,
        checkpoint_interval,
        start_tick,
        vehicles,
    })
}

fn parse_event(kind: u8, payload: &[u8], at: usize) -> Result<Event, FormatError> {
    Ok(match kind {
        INPUT => {
            let mut f = sized(payload, 11, at, "input")?;
            let (tick, vehicle, bits) = (f.u64(), f.u16(), f.take::<1>()[0]);
            let keys = Keys::from_bits(bits)
                .ok_or_else(|| corrupt(at, format!("input keys {bits:#04x} have unknown bits")))?;
            Event::Input {
                tick,
                vehicle,
                keys,
            }
        }
        JOIN => {
            let mut f = sized(payload, 10 + STATE, at, "join")?;
            Event::Join {
                tick: f.u64(),
                vehicle: f.u16(),
                state: f.state(),
            }
        }
        LEAVE => {
            let mut f = sized(payload, 10, at, "leave")?;
            Event::Leave {
                tick: f.u64(),
                vehicle: f.u16(),
            }
        }
        CHECKPOINT | END => {
            let mut f = sized(payload, 40, at, "checkpoint")?;
            let (tick, digest) = (f.u64(), Digest(f.take()));
            if kind == END {
                Event::End { tick, digest }
            } else {
                Event::Checkpoint { tick, digest }
            }
        }
        WAIT => {
            let mut f = sized(payload, 10, at, "wait")?;
            Event::Wait {
                tick: f.u64(),
                vehicle: f.u16(),
            }
        }
        TWICE => {
            let mut f = sized(payload, 12, at, "twice")?;
            let (tick, vehicle) = (f.u64(), f.u16());
            let keys = |bits: u8| {
                Keys::from_bits(bits)
                    .ok_or_else(|| corrupt(at, format!("twice keys {bits:#04x} have unknown bits")))
            };
            let [a, b] = f.take::<2>();
            Event::Twice {
                tick,
                vehicle,
                first: keys(a)?,
                second: keys(b)?,
            }
        }
        HEADER => return Err(corrupt(at, "a second header")),
        other => return Err(corrupt(at, format!("unknown record kind {other}"))),
    })
}

/// Parses a recording. A file cut inside a record gives the whole records before it (and
/// says where the cut is); everything else wrong is an error with its byte offset.
pub fn parse(bytes: &[u8]) -> Result<Recording, FormatError> {
    let (recording, damaged) = parse_valid(bytes)?;
    match damaged {
        Some(e) => Err(e),
        None => Ok(recording),
    }
}

/// Parses a recording's valid part: the records before the first wrong one, and what is
/// wrong with that one (`None`: every whole record is right; a cut inside the last is
/// [`Recording::truncated_at`], as [`parse`] says it). A file whose header is wrong has no
/// valid part: that is the error.
pub fn parse_valid(bytes: &[u8]) -> Result<(Recording, Option<FormatError>), FormatError> {
    let mut reader = Reader::open(bytes)?;
    let mut events = Vec::new();
    let damaged = reader.read(&mut events).err();
    Ok((
        Recording {
            header: reader.header.clone(),
            events,
            truncated_at: reader.cut_at(),
        },
        damaged,
    ))
}

/// A recording read as it grows (a session still being written): its header, then its
/// event records as its bytes come ([`Reader::feed`]), each checked as [`parse`] checks
/// it. It holds the bytes read (a recording is at most [`MAX_FILE_BYTES`]).
#[derive(Clone, Debug)]
pub struct Reader {
    bytes: Vec<u8>,
    version: u32,
    header: Header,
    /// Where the next record starts.
    at: usize,
    /// The last checkpoint's tick (the start's before any).
    checkpointed: u64,
    last_tick: Option<u64>,
    ended: bool,
}

impl Reader {
    /// Reads the magic, the version and the header from `bytes` (the file so far), and
    /// keeps the rest for [`Reader::read`].
    pub fn open(bytes: &[u8]) -> Result<Reader, FormatError> {
        Reader::open_owned(bytes.to_vec())
    }

    /// [`Reader::open`] on the file's bytes read already, kept without a copy.
    pub fn open_owned(bytes: Vec<u8>) -> Result<Reader, FormatError> {
        let too_short = || FormatError::TruncatedHeader {
            len: bytes.len() as u64,
        };
        match bytes.get(..8) {
            Some(m) if m == MAGIC => {}
            Some(_) => return Err(FormatError::Magic),
            None if MAGIC.starts_with(&bytes) => return Err(too_short()),
            None => return Err(FormatError::Magic),
        }
        let version = bytes
            .get(8..12)
            .map(|v| u32::from_le_bytes([v[0], v[1], v[2], v[3]]))
            .ok_or_else(too_short)?;
        if !(MIN_VERSION..=VERSION).contains(&version) {
            return Err(FormatError::Version { found: version });
        }
        let (kind, payload, at) = next_record(&bytes, 12, version)?.ok_or_else(too_short)?;
        if kind != HEADER {
            return Err(corrupt(
                12,
                format!("the first record is of kind {kind}, not a header"),
            ));
        }
        let header = parse_header(payload, 12, version)?;
        Ok(Reader {
            bytes,
            version,
            checkpointed: header.start_tick,
            header,
            at,
            last_tick: None,
            ended: false,
        })
    }

    pub fn header(&self) -> &Header {
        &self.header
    }

    /// Bytes taken so far.
    pub fn len(&self) -> u64 {
        self.bytes.len() as u64
    }

    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Whether the end record has been read.
    pub fn ended(&self) -> bool {
        self.ended
    }

    /// Where a record the bytes end inside starts (`None`: they end between records).
    pub fn cut_at(&self) -> Option<u64> {
        (self.at < self.bytes.len()).then_some(self.at as u64)
    }

    /// Takes the file's next bytes and reads the whole records they complete into
    /// `events`; an error for the first wrong record (nothing after it is read).
    pub fn feed(&mut self, more: &[u8], events: &mut Vec<Event>) -> Result<(), FormatError> {
        self.bytes.extend_from_slice(more);
        self.read(events)
    }

    /// Reads the whole records not read yet into `events`, up to the end of the bytes (a
    /// cut inside the last record: [`Reader::cut_at`]) or the first wrong record (the
    /// error).
    pub fn read(&mut self, events: &mut Vec<Event>) -> Result<(), FormatError> {
        let interval = u64::from(self.header.checkpoint_interval);
        let start = self.header.start_tick;
        // The writer checkpoints every `interval` ticks: no event lies further than that
        // past the last checkpoint, which also bounds how far a replay steps per record.
        while self.at < self.bytes.len() {
            let at = self.at;
            if self.ended {
                return Err(corrupt(at, "bytes after the end record"));
            }
            let Some((kind, payload, end)) = next_record(&self.bytes, at, self.version)? else {
                break;
            };
            let event = parse_event(kind, payload, at)?;
            let tick = event.tick();
            if tick < start {
                return Err(corrupt(
                    at,
                    format!("tick {tick} comes before the recording's start (tick {start})"),
                ));
            }
            if let Some(last) = self.last_tick
                && tick < last
            {
                return Err(corrupt(at, format!("tick {tick} comes after tick {last}")));
            }
            let checkpointed = self.checkpointed;
            if tick > checkpointed + interval {
                return Err(corrupt(
                    at,
                    format!(
                        "tick {tick} is more than {interval} ticks past the last checkpoint (tick {checkpointed})"
                    ),
                ));
            }
            if let Event::Checkpoint { .. } = event {
                if tick != checkpointed + interval {
                    return Err(corrupt(
                        at,
                        format!(
                            "a checkpoint at tick {tick}, expected tick {}",
                            checkpointed + interval
                        ),
                    ));
                }
                self.checkpointed = tick;
            }
            self.ended = matches!(event, Event::End { .. });
            self.last_tick = Some(tick);
            events.push(event);
            self.at = end;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::{HEADER, INPUT, JOIN, LengthError, MAX_RECORD, TWICE, length_ok};

    /// Each kind's length, a header's by its version and vehicles, and what is wrong
    /// otherwise, in words a corrupt record's error carries.
    #[test]
    fn a_record_s_length_is_its_kind_s() {
        for (kind, len, version, want, words) in [
            (INPUT, 11, 3, Ok(()), ""),
            (JOIN, 42, 3, Ok(()), ""),
            (TWICE, 12, 1, Ok(()), ""),
            (HEADER, 52 + 2 * 34, 3, Ok(()), ""),
            (HEADER, 44, 2, Ok(()), ""),
            (
                INPUT,
                12,
                3,
                Err(LengthError::Record {
                    kind: INPUT,
                    len: 12,
                    expected: 11,
                }),
                "a record of kind 2 with 12 bytes, expected 11",
            ),
            (
                HEADER,
                53,
                3,
                Err(LengthError::Header { len: 53, head: 52 }),
                "a header of 53 bytes (expected 52 plus 34 per vehicle, at most 1048576)",
            ),
            (
                HEADER,
                52,
                2,
                Err(LengthError::Header { len: 52, head: 44 }),
                "a header of 52 bytes (expected 44 plus 34 per vehicle, at most 1048576)",
            ),
            (
                HEADER,
                MAX_RECORD + 2,
                3,
                Err(LengthError::Header {
                    len: MAX_RECORD + 2,
                    head: 52,
                }),
                "a header of 1048578 bytes (expected 52 plus 34 per vehicle, at most 1048576)",
            ),
            (
                0x7e,
                0,
                3,
                Err(LengthError::Kind(0x7e)),
                "unknown record kind 126",
            ),
        ] {
            let got = length_ok(kind, len, version);
            assert_eq!(got, want, "kind {kind}, {len} bytes");
            assert_eq!(got.err().map(|e| e.to_string()).unwrap_or_default(), words);
        }
    }
}
