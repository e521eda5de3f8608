//! Length-prefixed messages on a QUIC stream: a `u32` length, then the message
//! ([`roam_protocol::messages`]). Shared by the server and the viewer.
//!
//! A length past the reader's limit is refused before anything is allocated; within it,
//! the buffer grows as the bytes arrive ([`READ_CHUNK`] first, then doubling), so a peer
//! that claims a long message and sends little costs little. Reading is over a
//! [`Source`]: a QUIC stream, or bytes in memory (what the fuzzing test feeds it).

use std::future::Future;

use quinn::ReadExactError;
use roam_protocol::messages::{self, Checked};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// The most bytes [`read`] reserves before they arrive.
pub const READ_CHUNK: usize = 64 << 10;

/// Why a message could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("the stream ended")]
    Closed,
    #[error("reading: {0}")]
    Read(#[from] ReadExactError),
    #[error("writing: {0}")]
    Write(#[from] quinn::WriteError),
    #[error("a message of {len} bytes, more than the {limit} allowed here")]
    TooLong { len: usize, limit: usize },
    #[error("decoding: {0}")]
    Decode(#[from] messages::DecodeError),
    #[error("encoding: {0}")]
    Encode(#[from] messages::EncodeError),
}

/// Where messages are read from.
pub trait Source {
    /// Fills `buf`, or fails saying how many bytes came before the stream's end.
    fn read_exact(
        &mut self,
        buf: &mut [u8],
    ) -> impl Future<Output = Result<(), ReadExactError>> + Send;
}

impl Source for quinn::RecvStream {
    fn read_exact(
        &mut self,
        buf: &mut [u8],
    ) -> impl Future<Output = Result<(), ReadExactError>> + Send {
        quinn::RecvStream::read_exact(self, buf)
    }
}

/// Bytes in memory, consumed from the front: ready at once.
impl Source for &[u8] {
    fn read_exact(
        &mut self,
        buf: &mut [u8],
    ) -> impl Future<Output = Result<(), ReadExactError>> + Send {
        let n = buf.len().min(self.len());
        let (head, rest) = self.split_at(n);
        buf[..n].copy_from_slice(head);
        *self = rest;
        std::future::ready(if n == buf.len() {
            Ok(())
        } else {
            Err(ReadExactError::FinishedEarly(n))
        })
    }
}

/// Reads one message of at most `limit` bytes.
pub async fn read<T: DeserializeOwned + Checked>(
    recv: &mut impl Source,
    limit: usize,
) -> Result<T, WireError> {
    let mut len = [0u8; 4];
    match recv.read_exact(&mut len).await {
        Ok(()) => {}
        Err(ReadExactError::FinishedEarly(0)) => return Err(WireError::Closed),
        Err(e) => return Err(e.into()),
    }
    let len = u32::from_le_bytes(len) as usize;
    if len > limit {
        return Err(WireError::TooLong { len, limit });
    }
    let mut buf = Vec::new();
    while buf.len() < len {
        let at = buf.len();
        buf.resize(at + (len - at).min(at.max(READ_CHUNK)), 0);
        match recv.read_exact(&mut buf[at..]).await {
            Ok(()) => {}
            Err(ReadExactError::FinishedEarly(n)) => {
                return Err(ReadExactError::FinishedEarly(at + n).into());
            }
            Err(e) => return Err(e.into()),
        }
    }
    Ok(messages::decode(&buf)?)
}

/// Writes one message.
pub async fn write<T: Serialize>(send: &mut quinn::SendStream, msg: &T) -> Result<(), WireError> {
    send.write_all(&frame(msg)?).await?;
    Ok(())
}

/// One message as it goes on a stream (its length, then its bytes): for a writer that is
/// not a [`quinn::SendStream`] (the server's WebTransport streams).
pub fn frame<T: Serialize>(msg: &T) -> Result<Vec<u8>, WireError> {
    Ok(messages::frame(msg)?)
}
