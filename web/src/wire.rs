//! The control stream's framing on the page: length-prefixed messages (a `u32` length,
//! little-endian, then the message, as `roam-link`'s `wire` on the native side), read
//! with the limit checked before anything is kept ([`Reader`]) and written ([`write`]).

use roam_protocol::messages::{self, Checked, ClientMessage};
use serde::de::DeserializeOwned;
use web_transport_wasm::{RecvStream, SendStream};

/// Why the control stream gave no message, or took none.
#[derive(Debug, thiserror::Error)]
pub(crate) enum WireError {
    /// The stream failed (the session's end says why).
    #[error("reading the control stream: {0}")]
    Read(web_transport_wasm::Error),
    #[error("the control stream ended inside a message's length")]
    EndedInLength,
    #[error(
        "a message of {len} bytes, more than the {} allowed",
        messages::MAX_MESSAGE
    )]
    TooLong { len: usize },
    #[error("the control stream ended inside a message")]
    EndedInMessage,
    #[error("decoding: {0}")]
    Decode(messages::DecodeError),
    /// A message that cannot be framed.
    #[error(transparent)]
    Frame(messages::EncodeError),
    #[error(transparent)]
    Write(web_transport_wasm::Error),
}

/// Length-prefixed messages (a `u32` length, little-endian, then the message) read from a
/// stream: a length past the limit is refused before anything is kept.
pub(crate) struct Reader {
    pub stream: RecvStream,
    pub buf: Vec<u8>,
}

impl Reader {
    /// Until `n` bytes are buffered; `false` at the stream's end.
    async fn fill(&mut self, n: usize) -> Result<bool, WireError> {
        while self.buf.len() < n {
            match self.stream.read(n - self.buf.len()).await {
                Ok(Some(chunk)) => self.buf.extend_from_slice(&chunk),
                Ok(None) => return Ok(false),
                Err(e) => return Err(WireError::Read(e)),
            }
        }
        Ok(true)
    }

    /// The next message; `None` when the stream ends between messages.
    pub(crate) async fn message<T: DeserializeOwned + Checked>(
        &mut self,
    ) -> Result<Option<T>, WireError> {
        if !self.fill(4).await? {
            return if self.buf.is_empty() {
                Ok(None)
            } else {
                Err(WireError::EndedInLength)
            };
        }
        let len = u32::from_le_bytes([self.buf[0], self.buf[1], self.buf[2], self.buf[3]]) as usize;
        if len > messages::MAX_MESSAGE {
            return Err(WireError::TooLong { len });
        }
        if !self.fill(4 + len).await? {
            return Err(WireError::EndedInMessage);
        }
        let msg = messages::decode(&self.buf[4..4 + len]).map_err(WireError::Decode);
        self.buf.drain(..4 + len);
        msg.map(Some)
    }
}

pub(crate) async fn write(send: &mut SendStream, msg: &ClientMessage) -> Result<(), WireError> {
    let buf = messages::frame(msg).map_err(WireError::Frame)?;
    send.write(&buf).await.map_err(WireError::Write)
}
