//! The page's I/O: a WebTransport session to the server (HTTP/3, QUIC underneath) carrying
//! exactly the native protocol — the control stream the page opens (the hello, then the
//! welcome, colour windows and tiles, the page's budget and view), frames as datagrams or
//! a stream each, key datagrams every 10 ms — around the viewer's clock-free cores
//! ([`ClientCore`], [`KeyCore`], [`ColorCache`]: the native viewer's own). Everything runs
//! on the page's one thread: tasks are `spawn_local`, the state is one [`Live`] behind a
//! `RefCell`, never borrowed across an `await`.
//!
//! **Reconnecting** is the native viewer's: [`supervise`] drives the same clock-free
//! [`Supervisor`] (`roam_client::supervisor`, with its constants), handing it each
//! connection's [`End`] and each attempt's outcome with the time, and does what it says: a
//! connection lost (the browser says so) or silent ([`Patience::silence`], 10 s unless the
//! page's address says otherwise) is made again with the driver's ticket, backing off
//! from 100 ms to 2 s, for 35 s; a refusal, the server's goodbye, a frame the server could
//! not have sent, or the same edge silent twice with no frame between ends the session
//! for good, with the reason on the page.
//!
//! **Edges.** An edge server names the world's edges ([`WorldNews::Edges`]): their
//! WebTransport URLs, each with its certificate hashes to pin, join the page's rotation
//! after its own origin's ([`roam_client::edges::Addresses`]). A lost connection is made
//! again at the next edge in turn (wrapping), with the page's token; with other edges to
//! go to, a shorter silence is a loss, a handshake has a second, and an edge shutting
//! down is a loss too (another edge takes the page). The edge's word that its world is
//! gone (and back) is kept in [`Live::world`] for the page's message line.

use std::cell::RefCell;
use std::rc::Rc;

use bytes::Bytes;
use futures_channel::mpsc::{self, UnboundedReceiver, UnboundedSender};
use futures_util::StreamExt;
use roam_client::color_cache::ColorCache;
use roam_client::conversation::{self, ConversationError, TerrainId};
use roam_client::core::{ClientCore, Gaps, KeyCore, MAX_FRAME};
use roam_client::edges::{Addresses, WebEdge, World, web_edges};
use roam_client::supervisor::{End, Patience, SessionEnd, State, Supervisor};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Hello, Reason, ServerMessage, ViewChange, Welcome, WorldNews, close,
};
use wasm_bindgen_futures::spawn_local;
use web_time::{Duration, Instant};
use web_transport_wasm::{RecvStream, SendStream, Session};

use crate::page;
use crate::wire::{Reader, WireError, write};

mod join;
use join::end_of;
pub(crate) use join::{Joined, has_webtransport, join};

/// Frame streams read at once, at most: each may hold [`MAX_FRAME`] bytes.
const MAX_STREAMS: usize = 16;
/// How long a loss waits for a goodbye that may be behind it.
const GOODBYE_GRACE: Duration = Duration::from_millis(300);

/// What the tasks and the display share.
pub(crate) struct Live {
    pub core: ClientCore,
    pub keys: KeyCore,
    pub colors: ColorCache,
    pub welcome: Welcome,
    pub state: State,
    pub gaps: Gaps,
    /// Bumped with each connection: bytes of an older one are not offered to the new core.
    epoch: u64,
    heard: Instant,
    session: Option<Session>,
    control: Option<UnboundedSender<ClientMessage>>,
    /// A script's steps, last first; `None`: the keys pressed on the page.
    script: Option<Vec<KeyStep>>,
    /// Frame and colour bytes of the connections before this one.
    pub bytes_before: u64,
    pub color_bytes_before: u64,
    /// Frames that could not be decoded (a key frame was asked for).
    pub dropped: u64,
    /// Frames offered, every connection's (the supervisor's silence rule counts them).
    frames: u64,
    /// How long the page waits on the server (the supervisor's).
    patience: Patience,
    /// The newest camera told, for the next connection.
    view: Option<ViewChange>,
    /// Frame streams being read now (at most [`MAX_STREAMS`]).
    streams: usize,
    /// What the edge says of its world (gone, why).
    pub world: World,
    /// The edges the page connects to in turn: its own origin's, then those learned.
    pub edges: Addresses<WebEdge>,
    /// A watched recording's state, as the server last said it (`serve --replay`).
    pub replay: Option<roam_protocol::messages::ReplayStatus>,
}

pub(crate) type Shared = Rc<RefCell<Live>>;

impl Live {
    /// Sends the core's control messages, in order.
    /// (While reconnecting they wait in the core; the newest view and the budget go to
    /// the next connection anyway.)
    pub(crate) fn flush(&mut self) {
        let Some(tx) = &self.control else {
            return;
        };
        while let Some(msg) = self.core.poll_control() {
            let _ = tx.unbounded_send(msg);
        }
    }

    /// Tells the server the camera (this connection and the next).
    pub(crate) fn set_view(&mut self, view: ViewChange) {
        self.view = Some(view);
        self.core.set_view(view);
        self.flush();
    }

    /// The session ends with `why` (the first reason stands).
    pub(crate) fn end(&mut self, why: impl std::fmt::Display) {
        if !matches!(self.state, State::Ended(_)) {
            self.state = State::Ended(why.to_string());
        }
        if let Some(s) = self.session.take() {
            s.close(close::BYE, "bye");
        }
        self.control = None;
    }

    pub(crate) fn ended(&self) -> bool {
        matches!(self.state, State::Ended(_))
    }

    /// An edge's news of its world: the edges it names join the rotation; gone or back
    /// is kept for the page.
    fn news(&mut self, news: &WorldNews) {
        match news {
            WorldNews::Edges(edges) => {
                self.edges.learn(web_edges(edges));
            }
            other => {
                self.world.apply(other, Instant::now());
            }
        }
    }

    /// The server's frames follow vehicle `v` from now on (the next connection asks for
    /// it).
    fn following(&mut self, v: u16) {
        self.welcome.vehicle = v;
    }

    /// Sends a control message on the connection that is up (dropped while reconnecting).
    pub(crate) fn send(&mut self, msg: ClientMessage) {
        if let Some(tx) = &self.control {
            let _ = tx.unbounded_send(msg);
        }
    }

    pub(crate) fn bytes_in(&self) -> u64 {
        self.bytes_before + self.core.bytes_in()
    }

    pub(crate) fn color_bytes(&self) -> u64 {
        self.color_bytes_before + self.colors.bytes()
    }

    fn offer(&mut self, epoch: u64, bytes: &[u8]) {
        if epoch == self.epoch {
            self.heard = Instant::now();
            self.core.offer(bytes, Instant::now());
            self.frames += 1;
        }
    }

    /// One physics step's key datagram, sent on the connection that is up (numbered and
    /// repeated by the core, so a lost one costs nothing).
    pub(crate) fn send_keys(&mut self) {
        let step = match &mut self.script {
            Some(steps) => steps.pop().unwrap_or(KeyStep {
                held: Keys::NONE,
                pressed: Keys::NONE,
            }),
            None => self.keys.take_keys(),
        };
        let datagram = self.keys.key_datagram(step, Instant::now(), None);
        let mut bytes = Vec::new();
        if let Some(s) = &self.session
            && messages::encode(&datagram, &mut bytes).is_ok()
        {
            let _ = s.try_send_datagram(&bytes);
        }
    }

    /// The page is going away: the session closes at once with the goodbye's code (no
    /// time to write a message).
    pub(crate) fn leave(&mut self) {
        if let Some(s) = self.session.take() {
            s.close(close::BYE, "the page was closed");
        }
        self.state = State::Ended(SessionEnd::Quit.to_string());
        self.control = None;
    }

    /// Says goodbye (the server frees the vehicle at once) and closes.
    pub(crate) fn quit(&mut self) {
        if let Some(tx) = &self.control {
            let _ = tx.unbounded_send(ClientMessage::Bye(Reason::Quit));
        }
        self.state = State::Ended("quit".into());
        self.control = None; // the writer sends the goodbye, finishes and closes
    }
}

/// The first connection's state: joined at `edge`, the page's own; the server may be
/// silent for `silence` ([`Patience::silence`]).
pub(crate) fn live(
    joined: &mut Joined,
    edge: WebEdge,
    budget: u32,
    script: Option<Vec<KeyStep>>,
    silence: Duration,
) -> Result<Shared, ConversationError> {
    let levels = joined.welcome.levels;
    let mut core =
        ClientCore::new(&joined.welcome, budget).ok_or(ConversationError::Levels { levels })?;
    // The page draws with geomorphs, as the window does.
    core.set_morph(roam_client::render::MORPH_TICKS);
    let fresh = joined.colors.fresh();
    Ok(Rc::new(RefCell::new(Live {
        core,
        keys: KeyCore::default(),
        colors: std::mem::replace(&mut joined.colors, fresh),
        welcome: joined.welcome.clone(),
        state: State::Connected,
        gaps: Gaps::default(),
        epoch: 0,
        heard: Instant::now(),
        session: None,
        control: None,
        script,
        bytes_before: 0,
        color_bytes_before: 0,
        dropped: 0,
        frames: 0,
        patience: Patience {
            silence,
            ..Patience::default()
        },
        view: None,
        streams: 0,
        world: World::default(),
        edges: Addresses::new([edge]).expect("one edge is an edge to connect to"),
        replay: None,
    })))
}

/// Runs the session: the connection `joined`, then each reconnection the supervisor asks
/// for, until it ends.
pub(crate) async fn supervise(live: Shared, hello: Hello, mut joined: Joined) {
    // The first connection's terrain, which every later one must show (its colour cache
    // went to `live`).
    let first = TerrainId::of(&joined.welcome, live.borrow().colors.coarsest());
    let mut supervisor = Supervisor::new(live.borrow().patience, first);
    let mut hello = conversation::next_hello(hello, &joined.welcome);
    loop {
        let end = serve(&live, joined).await;
        let verdict = {
            let l = live.borrow();
            supervisor.ended(
                end,
                &l.edges.current().url,
                l.edges.index(),
                l.edges.many(),
                l.frames,
                Instant::now(),
            )
        };
        if let Err(why) = verdict {
            live.borrow_mut().end(why);
            return;
        }
        if live.borrow().ended() {
            return;
        }
        // The budget and viewport asked now, not at the page's load.
        {
            let l = live.borrow();
            hello.budget = l.core.budget();
            if let Some(v) = l.view {
                hello.viewport = v.viewport;
            }
        }
        match reconnect(&live, &mut supervisor, &hello).await {
            Ok(j) => {
                hello = conversation::next_hello(hello, &j.welcome);
                joined = j;
            }
            Err(why) => {
                live.borrow_mut().end(why);
                return;
            }
        }
    }
}

/// Connects again, each attempt at the next edge in turn, as the supervisor says, until
/// one joins (showing the same terrain), the page quits, or the supervisor gives up.
async fn reconnect(
    live: &Shared,
    supervisor: &mut Supervisor,
    hello: &Hello,
) -> Result<Joined, SessionEnd> {
    let mut lost_at = Some(Instant::now());
    loop {
        let (edge, attempt) = {
            let mut l = live.borrow_mut();
            if l.ended() {
                return Err(SessionEnd::Quit);
            }
            let edge = l.edges.after_loss().clone();
            let attempt = supervisor.attempt(l.edges.many());
            if let Some(at) = lost_at.take() {
                l.gaps.lost(at);
            }
            l.state = supervisor.state();
            (edge, attempt)
        };
        let joined = join(&edge, hello.clone(), attempt.handshake).await;
        if live.borrow().ended() {
            // Quit (or the page closed) meanwhile: nothing comes back.
            if let Ok(j) = joined {
                j.session.close(close::BYE, "quit");
            }
            return Err(SessionEnd::Quit);
        }
        let e = match joined {
            Ok(j) => {
                let found = TerrainId::of(&j.welcome, j.colors.coarsest());
                return match supervisor.joined(&found) {
                    Ok(()) => Ok(j),
                    Err(why) => {
                        j.session.close(close::BYE, "another terrain");
                        Err(why)
                    }
                };
            }
            Err(e) => e,
        };
        let pause = supervisor.failed(&edge.url, e.lost, &e.message, Instant::now())?;
        page::sleep(ms(pause)).await;
    }
}

/// `d` in whole milliseconds, for the browser's timers.
fn ms(d: Duration) -> i32 {
    i32::try_from(d.as_millis()).unwrap_or(i32::MAX)
}

/// `fut`, or `None` after `d`.
async fn with_timeout<T>(fut: impl std::future::Future<Output = T>, d: Duration) -> Option<T> {
    use futures_util::future::{Either, select};
    let fut = std::pin::pin!(fut);
    let timer = std::pin::pin!(page::sleep(ms(d)));
    match select(fut, timer).await {
        Either::Left((v, _)) => Some(v),
        Either::Right(_) => None,
    }
}

/// Serves one connection: its readers and writer, until it ends.
async fn serve(live: &Shared, joined: Joined) -> End {
    let Joined {
        session,
        send,
        recv,
        welcome,
        colors,
        news,
    } = joined;
    let (control, outgoing) = mpsc::unbounded();
    let (ends, mut ended) = mpsc::unbounded::<End>();
    let epoch = {
        let mut l = live.borrow_mut();
        if l.ended() {
            session.close(close::BYE, "quit");
            return End::Final("quit".into());
        }
        let reconnected = l.epoch > 0 || l.session.is_some();
        if reconnected {
            // A fresh core and colour cache; the counts go on.
            l.bytes_before += l.core.bytes_in();
            l.color_bytes_before += l.colors.bytes();
            let budget = l.core.budget();
            let morph = l.core.morph_ticks();
            let replay = l.core.is_replay();
            match ClientCore::new(&welcome, budget) {
                Some(core) => {
                    l.core = core;
                    if let Some(ticks) = morph {
                        l.core.set_morph(ticks);
                    }
                    // A watched recording stays one across a reconnection.
                    if replay {
                        l.core.set_replay();
                    }
                }
                None => {
                    session.close(close::BYE, "another grid");
                    return End::Final("the server's grid changed".into());
                }
            }
            // The camera told so far goes to the new connection too.
            if let Some(view) = l.view {
                l.core.set_view(view);
            }
            l.colors = colors;
            l.gaps
                .reconnected(welcome.ticket.is_some() && welcome.resumed);
            // This edge says so if its world is gone too.
            l.world.back(Instant::now());
        }
        for n in &news {
            l.news(n);
        }
        l.epoch += 1;
        l.welcome = welcome;
        l.session = Some(session.clone());
        l.control = Some(control);
        l.state = State::Connected;
        l.heard = Instant::now();
        l.flush();
        l.epoch
    };
    spawn_local(write_control(send, outgoing, session.clone()));
    spawn_local(read_control(recv, live.clone(), epoch, ends.clone()));
    spawn_local(read_datagrams(session.clone(), live.clone(), epoch));
    spawn_local(read_streams(session.clone(), live.clone(), epoch));
    {
        let (session, ends) = (session.clone(), ends.clone());
        spawn_local(async move {
            let e = session.closed().await;
            let _ = ends.unbounded_send(end_of(&e));
        });
    }
    spawn_local(watch_silence(live.clone(), epoch, ends));
    let mut end = ended.next().await.unwrap_or_else(|| End::Lost {
        why: "the connection's tasks ended".into(),
        silent: false,
    });
    if matches!(end, End::Lost { .. }) {
        // A goodbye read just before the connection closed says more than the loss (a
        // busy page may see the close first): give the control reader a moment.
        if let Some(Some(fin @ (End::Final(_) | End::Shutdown(_)))) =
            with_timeout(ended.next(), GOODBYE_GRACE).await
        {
            end = fin;
        }
    }
    let mut l = live.borrow_mut();
    if l.epoch == epoch {
        l.session = None;
        l.control = None;
    }
    if end.worth_reconnecting(l.edges.many()) {
        // Not a goodbye: the server holds the vehicle for the reconnection (should this
        // close reach it through a path that came back).
        session.close(0, "lost; reconnecting");
    } else {
        session.close(close::BYE, "bye");
    }
    end
}

/// Lost when the server says nothing for as long as the supervisor's patience allows
/// ([`Patience::allowed_silence`]: shorter with other edges to go to), checked ten times a
/// second.
async fn watch_silence(live: Shared, epoch: u64, ends: UnboundedSender<End>) {
    loop {
        page::sleep(100).await;
        let l = live.borrow();
        if l.epoch != epoch || l.ended() {
            return;
        }
        let silence = l.patience.allowed_silence(l.edges.many());
        if l.heard.elapsed() >= silence {
            let _ = ends.unbounded_send(End::silence(silence));
            return;
        }
    }
}

/// Writes the core's control messages in order; a goodbye finishes the stream and closes
/// the session once the server has had a moment to hear it.
async fn write_control(
    mut send: SendStream,
    mut outgoing: UnboundedReceiver<ClientMessage>,
    session: Session,
) {
    while let Some(msg) = outgoing.next().await {
        let bye = matches!(msg, ClientMessage::Bye(_));
        if write(&mut send, &msg).await.is_err() {
            return;
        }
        if bye {
            let _ = send.finish();
            let _ = with_timeout(session.closed(), Duration::from_secs(1)).await;
            session.close(close::BYE, "bye");
            return;
        }
    }
}

/// The server's control messages after the join: colour windows and tiles into the colour
/// cache; a goodbye (the server shutting down, or for good) or anything else ends the
/// connection.
async fn read_control(mut recv: Reader, live: Shared, epoch: u64, ends: UnboundedSender<End>) {
    let mut rgb = Vec::new();
    let end = loop {
        let msg = match recv.message::<ServerMessage>().await {
            Ok(Some(m)) => m,
            // The stream or the session ended: the session tells why.
            Ok(None) => return,
            Err(WireError::Read(_)) => return,
            Err(e) => break End::Final(format!("the server's control stream: {e}")),
        };
        {
            let mut l = live.borrow_mut();
            if l.epoch != epoch {
                return;
            }
            l.heard = Instant::now();
        }
        let colors = || std::cell::RefMut::map(live.borrow_mut(), |l| &mut l.colors);
        match conversation::take_control(&msg, &mut rgb, colors) {
            Ok(None) => {}
            Ok(Some(conversation::Told::News(news))) => live.borrow_mut().news(news),
            Ok(Some(conversation::Told::Following(v))) => live.borrow_mut().following(v),
            Ok(Some(conversation::Told::Replay(s))) => {
                let mut l = live.borrow_mut();
                l.core.set_replay();
                l.replay = Some(s.clone());
            }
            Err(why @ ConversationError::Goodbye(Reason::Shutdown)) => {
                break End::Shutdown(why.to_string());
            }
            Err(why) => break End::Final(why.to_string()),
        }
    };
    let _ = ends.unbounded_send(end);
}

async fn read_datagrams(session: Session, live: Shared, epoch: u64) {
    while let Ok(bytes) = session.recv_datagram().await {
        let mut l = live.borrow_mut();
        if l.epoch != epoch {
            return;
        }
        l.offer(epoch, &bytes);
    }
}

async fn read_streams(session: Session, live: Shared, epoch: u64) {
    while let Ok(mut stream) = session.accept_uni().await {
        let mut l = live.borrow_mut();
        if l.epoch != epoch {
            return;
        }
        // A bound on what a server can make the page hold (as the native viewer's).
        if l.streams >= MAX_STREAMS {
            stream.stop(0);
            continue;
        }
        l.streams += 1;
        drop(l);
        let live = live.clone();
        spawn_local(async move {
            read_stream(stream, live.clone(), epoch).await;
            live.borrow_mut().streams -= 1;
        });
    }
}

/// One frame's stream, read to its end (at most [`MAX_FRAME`] bytes) and offered; every
/// chunk is news of the server (a large frame on a slow path is not silence).
async fn read_stream(mut stream: RecvStream, live: Shared, epoch: u64) {
    let mut bytes: Vec<u8> = Vec::new();
    loop {
        match stream.read(MAX_FRAME).await {
            Ok(Some(chunk)) => {
                live.borrow_mut().heard = Instant::now();
                if bytes.len() + chunk.len() > MAX_FRAME {
                    stream.stop(0);
                    return;
                }
                bytes.extend_from_slice(&chunk);
            }
            Ok(None) => break,
            Err(_) => return,
        }
    }
    live.borrow_mut().offer(epoch, &Bytes::from(bytes));
}
