//! Bounded decoding: the serde `deserialize_with` functions the messages' variable-length
//! fields (strings, byte strings, lists) are read with ([`crate::messages`]). Each checks
//! the length the encoding claims against that field's limit before anything is
//! allocated, and reserves no more than the input has shown so far.
//!
//! Decisions:
//!
//! - bincode (standard configuration) writes a string, a byte string and a list alike: a
//!   varint length, then the items (a byte each for `u8`). Strings and bounded byte strings
//!   (the join token, a reason, a colour tile) are therefore read as a list of bytes,
//!   whose length the visitor sees (as the size hint) before one item is read: a claim past
//!   the limit is refused there. Reading them as bincode strings would borrow (or, decoding
//!   owned, allocate) the claimed bytes before the limit could be looked at.
//! - A list reserves at most [`PREALLOC`] bytes up front, then grows as its items decode,
//!   so an input claiming many items costs at most [`PREALLOC`] bytes more than the items
//!   it really holds (and at most three times those, while a `Vec` grows).
//! - The mesh, whose only limit is the message itself, is borrowed from the input and
//!   copied once ([`bytes`]): bincode refuses a length past the input's end before that.
//! - serde's errors are strings. So that the caller still gets the field, the length and
//!   the limit of a refusal as values ([`crate::messages::DecodeError::TooLong`]), the
//!   refusal is also kept in a thread-local cell, which [`take_refusal`] empties (a decode
//!   runs on one thread from start to end, and nothing in it recovers from an error).

use std::cell::Cell;
use std::fmt;
use std::marker::PhantomData;

use serde::Deserializer;
use serde::de::{self, Deserialize, SeqAccess, Visitor};

/// The most bytes a list reserves before its items arrive.
pub const PREALLOC: usize = 1 << 10;

/// A length past its limit: the field, the length claimed and the limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Refusal {
    pub what: &'static str,
    pub got: usize,
    pub limit: usize,
}

thread_local! {
    // Const-initialised, no destructor: setting it never allocates.
    static REFUSED: Cell<Option<Refusal>> = const { Cell::new(None) };
}

/// The refusal of the last decode on this thread, if it ended in one; empties the cell.
pub(crate) fn take_refusal() -> Option<Refusal> {
    REFUSED.take()
}

/// The error for `got` items of `what`, more than `limit`; kept for [`take_refusal`].
fn refuse<E: de::Error>(what: &'static str, got: usize, limit: usize) -> E {
    REFUSED.set(Some(Refusal { what, got, limit }));
    E::custom(format_args!("{what}: {got}, at most {limit}"))
}

/// A list of at most `limit` items of `T`.
struct List<T> {
    what: &'static str,
    limit: usize,
    item: PhantomData<T>,
}

impl<'de, T: Deserialize<'de>> Visitor<'de> for List<T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a list of at most {} {}", self.limit, self.what)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<T>, A::Error> {
        let claimed = seq.size_hint().unwrap_or(0);
        if claimed > self.limit {
            return Err(refuse(self.what, claimed, self.limit));
        }
        let mut out = Vec::with_capacity(claimed.min(PREALLOC / size_of::<T>().max(1)));
        while let Some(item) = seq.next_element()? {
            // For formats that give no length up front (bincode always does).
            if out.len() == self.limit {
                return Err(refuse(self.what, self.limit + 1, self.limit));
            }
            out.push(item);
        }
        Ok(out)
    }
}

/// Reads a list of at most `limit` items (`what` names them in an error).
pub(crate) fn list<'de, D, T>(d: D, what: &'static str, limit: usize) -> Result<Vec<T>, D::Error>
where
    D: Deserializer<'de>,
    T: Deserialize<'de>,
{
    d.deserialize_seq(List {
        what,
        limit,
        item: PhantomData,
    })
}

/// A UTF-8 string of at most `limit` bytes.
struct Text {
    what: &'static str,
    limit: usize,
}

impl<'de> Visitor<'de> for Text {
    type Value = String;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a string of at most {} {}", self.limit, self.what)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<String, A::Error> {
        let what = self.what;
        let bytes = List {
            what,
            limit: self.limit,
            item: PhantomData,
        }
        .visit_seq(seq)?;
        String::from_utf8(bytes).map_err(|e| {
            let at = e.utf8_error().valid_up_to();
            de::Error::custom(format_args!("{what}: not UTF-8 at byte {at}"))
        })
    }

    fn visit_str<E: de::Error>(self, s: &str) -> Result<String, E> {
        if s.len() > self.limit {
            return Err(refuse(self.what, s.len(), self.limit));
        }
        Ok(s.to_owned())
    }
}

/// Reads a string of at most `limit` bytes (`what` names them in an error).
pub(crate) fn string<'de, D>(d: D, what: &'static str, limit: usize) -> Result<String, D::Error>
where
    D: Deserializer<'de>,
{
    let text = Text { what, limit };
    if d.is_human_readable() {
        // Text formats write a string as a string (not the wire: tests and tools).
        d.deserialize_str(text)
    } else {
        // bincode: a length, then the bytes; see the module's header.
        d.deserialize_seq(text)
    }
}

/// A byte string, as long as the input holds.
struct Bytes;

impl<'de> Visitor<'de> for Bytes {
    type Value = Vec<u8>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("bytes")
    }

    fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<Vec<u8>, E> {
        Ok(v.to_vec())
    }

    fn visit_byte_buf<E: de::Error>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
        Ok(v)
    }

    fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<Vec<u8>, A::Error> {
        List {
            what: "bytes",
            limit: usize::MAX,
            item: PhantomData,
        }
        .visit_seq(seq)
    }
}

/// Reads a byte string borrowed from the input and copies it: what it allocates is what
/// the input holds (a length past the input's end is bincode's error, before any copy).
pub(crate) fn bytes<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
    d.deserialize_bytes(Bytes)
}
