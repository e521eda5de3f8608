//! Length-prefixed messages on a QUIC stream: a `u32` length, then the message
//! ([`roam_protocol::messages`]). Shared by the server and the viewer.

use roam_protocol::messages::{self, Checked};
use serde::Serialize;
use serde::de::DeserializeOwned;

/// Why a message could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum WireError {
    #[error("the stream ended")]
    Closed,
    #[error("reading: {0}")]
    Read(#[from] quinn::ReadExactError),
    #[error("writing: {0}")]
    Write(#[from] quinn::WriteError),
    #[error("a message of {len} bytes, more than the {limit} allowed here")]
    TooLong { len: usize, limit: usize },
    #[error("decoding: {0}")]
    Decode(#[from] messages::DecodeError),
    #[error("encoding: {0}")]
    Encode(#[from] messages::EncodeError),
}

/// Reads one message of at most `limit` bytes.
pub async fn read<T: DeserializeOwned + Checked>(
    recv: &mut quinn::RecvStream,
    limit: usize,
) -> Result<T, WireError> {
    let mut len = [0u8; 4];
    match recv.read_exact(&mut len).await {
        Ok(()) => {}
        Err(quinn::ReadExactError::FinishedEarly(0)) => return Err(WireError::Closed),
        Err(e) => return Err(e.into()),
    }
    let len = u32::from_le_bytes(len) as usize;
    if len > limit {
        return Err(WireError::TooLong { len, limit });
    }
    let mut buf = vec![0u8; len];
    recv.read_exact(&mut buf).await?;
    Ok(messages::decode(&buf)?)
}

/// Writes one message.
pub async fn write<T: Serialize>(send: &mut quinn::SendStream, msg: &T) -> Result<(), WireError> {
    let mut buf = vec![0u8; 4];
    messages::encode(msg, &mut buf)?;
    let len = (buf.len() - 4) as u32;
    buf[..4].copy_from_slice(&len.to_le_bytes());
    send.write_all(&buf).await?;
    Ok(())
}
