//! Joining a server from the page (the part of [`super`] before a session runs): the
//! WebTransport handshake within its deadline, the hello, the welcome and the colour
//! messages up to the coarsest tile ([`join`]), and how a session's end reads
//! ([`ending`], [`end_of`]: worth connecting again, the server shutting down, or final).

use roam_client::color_cache::{ColorCache, Keep};
use roam_client::conversation::{self, ConversationError, Joining};
use roam_client::edges::WebEdge;
use roam_client::supervisor::{End, JOIN_TIMEOUT, secs};
use roam_protocol::messages::{ClientMessage, Hello, ServerMessage, Welcome, WorldNews, close};
use web_time::Duration;
use web_transport_wasm::{ClientBuilder, SendStream, Session};

use super::{GOODBYE_GRACE, with_timeout};
use crate::page;
use crate::wire::{Reader, write};

/// Why a join failed, and whether another attempt may succeed.
#[derive(Debug)]
pub(crate) struct JoinError {
    pub lost: bool,
    pub message: String,
}

/// A connection that has joined, and the news of the world that came with it.
pub(crate) struct Joined {
    pub(super) session: Session,
    pub(super) send: SendStream,
    pub(super) recv: Reader,
    pub welcome: Welcome,
    pub colors: ColorCache,
    pub(super) news: Vec<WorldNews>,
}

/// Whether the browser has WebTransport at all.
pub(crate) fn has_webtransport() -> bool {
    js_sys::Reflect::has(&page::window(), &"WebTransport".into()).unwrap_or(false)
}

/// How a session's end reads, and whether it is worth connecting again: a close by the
/// server on purpose (a goodbye, a refusal, shutting down) is final.
pub(super) fn ending(e: &web_transport_wasm::Error) -> (bool, String) {
    match e {
        web_transport_wasm::Error::Session { code, reason } => {
            let purpose = match *code {
                close::SHUTDOWN => "the server is shutting down",
                close::REFUSED => "the server refused this viewer",
                close::PROTOCOL => "the server saw a protocol error",
                close::BYE => "the server said goodbye",
                _ => "",
            };
            if purpose.is_empty() {
                (
                    true,
                    format!("the connection was lost: code {code} {reason}"),
                )
            } else {
                (false, format!("{purpose}: {reason}"))
            }
        }
        other => (true, format!("the connection was lost: {other}")),
    }
}

/// How a session ended, for the supervisor: the server shutting down (its close code says
/// so), lost, or final ([`ending`]).
pub(super) fn end_of(e: &web_transport_wasm::Error) -> End {
    if let web_transport_wasm::Error::Session { code, .. } = e
        && *code == close::SHUTDOWN
    {
        return End::Shutdown(ending(e).1);
    }
    match ending(e) {
        (true, why) => End::Lost { why, silent: false },
        (false, why) => End::Final(why),
    }
}

/// Connects to `edge`, says `hello`, and reads the welcome and the coarsest colour tile:
/// the handshake within `handshake` (the supervisor's: `HANDSHAKE`, or `HANDSHAKE_MANY`
/// with other edges to go to), the rest within [`JOIN_TIMEOUT`]. A session that does not
/// join is closed (the goodbye's code when it was refused or broke the protocol; else 0,
/// so that a vehicle it took back stays held for the next attempt).
pub(crate) async fn join(
    edge: &WebEdge,
    hello: Hello,
    handshake: Duration,
) -> Result<Joined, JoinError> {
    let fatal = |message: String| JoinError {
        lost: false,
        message,
    };
    let url =
        url::Url::parse(&edge.url).map_err(|e| fatal(format!("the address {}: {e}", edge.url)))?;
    let hashes = page::hash_bytes(&edge.hashes).map_err(|e| fatal(e.to_string()))?;
    let builder = ClientBuilder::new().with_unreliable(true);
    let client = if hashes.is_empty() {
        builder.with_system_roots()
    } else {
        builder.with_server_certificate_hashes(hashes)
    };
    let session = with_timeout(client.connect(url.clone()), handshake)
        .await
        .ok_or_else(|| JoinError {
            lost: true,
            message: format!(
                "connecting to {url}: no handshake within {}",
                secs(handshake)
            ),
        })?
        .map_err(|e| JoinError {
            lost: true,
            message: format!("connecting to {url}: {e}"),
        })?;
    let joined = match with_timeout(greet(&session, hello), JOIN_TIMEOUT).await {
        Some(r) => r,
        None => Err(JoinError {
            lost: true,
            message: format!(
                "no welcome and coarsest colour tile within {} s",
                JOIN_TIMEOUT.as_secs()
            ),
        }),
    };
    match joined {
        Ok((send, recv, welcome, colors, news)) => Ok(Joined {
            session,
            send,
            recv,
            welcome,
            colors,
            news,
        }),
        Err(e) => {
            session.close(if e.lost { 0 } else { close::BYE }, "did not join");
            Err(e)
        }
    }
}

/// What a join reads: the control stream's ends, the welcome, the coarsest colour and the
/// news of the world among them.
type Greeted = (SendStream, Reader, Welcome, ColorCache, Vec<WorldNews>);

/// The hello on a new session, the welcome and the colour messages up to the coarsest tile.
async fn greet(session: &Session, hello: Hello) -> Result<Greeted, JoinError> {
    let fatal = |e: ConversationError| JoinError {
        lost: false,
        message: e.to_string(),
    };
    let asked = hello.color_window;
    let (mut send, recv) = match session.open_bi().await {
        Ok(streams) => streams,
        Err(e) => return Err(failed_on(session, format!("opening the control stream: {e}")).await),
    };
    if let Err(e) = write(&mut send, &ClientMessage::Hello(hello)).await {
        return Err(failed_on(session, format!("sending the hello: {e}")).await);
    }
    let mut recv = Reader {
        stream: recv,
        buf: Vec::new(),
    };
    let welcome = match recv.message::<ServerMessage>().await {
        Ok(Some(msg)) => conversation::welcome_of(msg).map_err(fatal)?,
        Ok(None) => return Err(failed_on(session, "the control stream ended".into()).await),
        Err(e) => return Err(failed_on(session, format!("reading the welcome: {e}")).await),
    };
    let mut joining = Joining::new(&welcome, asked, Keep::Texels).map_err(fatal)?;
    loop {
        let msg = match recv.message::<ServerMessage>().await {
            Ok(Some(m)) => m,
            Ok(None) => return Err(failed_on(session, "the control stream ended".into()).await),
            Err(e) => return Err(failed_on(session, e.to_string()).await),
        };
        if let Some(cache) = joining.apply(&msg).map_err(fatal)? {
            return Ok((send, recv, welcome, cache, joining.take_news()));
        }
    }
}

/// A join step that failed on `session`: the session's own end, if it comes within a
/// moment (a refusal's close may overtake its message), says what happened and whether to
/// try again; else the connection was lost.
async fn failed_on(session: &Session, message: String) -> JoinError {
    match with_timeout(session.closed(), GOODBYE_GRACE).await {
        Some(e) => {
            let (lost, why) = ending(&e);
            JoinError {
                lost,
                message: format!("{message} ({why})"),
            }
        }
        None => JoinError {
            lost: true,
            message,
        },
    }
}
