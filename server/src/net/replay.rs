//! Serving a recording (`serve --replay FILE`): the world thread plays a [`Watch`]
//! instead of running a [`crate::sim::world_core::WorldCore`], and publishes its
//! snapshots the same way, so every viewer task serves it as it serves a live world. Every
//! viewer is a spectator (a driver's hello is served as a spectator's); nothing is
//! recorded.
//!
//! **One clock, one holder of the controls.** The viewers share the replay's clock. The
//! controls ([`ReplayControl`]) are heeded from one viewer: with `--control`, the first
//! still connected that presented its token (nobody while none is there: the join token
//! alone never steers); without, the first to join still connected, then the next. Each
//! viewer is told the state ([`ReplayStatus`]: the valid part, the speed, paused, whether
//! it holds the controls and who does) at its welcome and whenever it changes other than
//! by the clock (the clock is each frame's tick).
//!
//! **The thread** wakes every 10 ms as the live world's does, takes the controls that came,
//! moves the clock by the speed, publishes the snapshot (the same one while paused: frames
//! keep flowing at each viewer's rate) and logs `replay ended at tick N, digest HEX` when
//! the clock reaches the valid part's end.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, Sender, TryRecvError};
use std::sync::{Arc, Mutex};

use roam_protocol::messages::{ReplayControl, ReplayStatus, ServerMessage};
use roam_protocol::sync::lock;
use tokio::sync::watch;

use super::conn::SendStream;
use super::world_loop::{Inbound, WorldStats};
use crate::Terrain;
use crate::sim::watch::{Control, Status, Watch};
use crate::sim::world::World;
use crate::sim::world_core::Snapshot;

/// A recording to serve, opened ([`crate::sim::watch::open_file`], or [`open_following`]
/// for one still being written), and the token whose viewer holds the controls
/// (`--control`).
pub struct Replaying {
    pub watch: Watch<Arc<Terrain>>,
    pub control_token: Option<String>,
    /// The file followed as it grows (`--follow`).
    pub follow: Option<Follower>,
}

impl Replaying {
    /// Opens `path` to serve: whole, or (`follow`) as it grows, from its newest tick
    /// ([`open_following`]); the viewer presenting `control_token` holds the controls.
    pub fn open(
        path: &std::path::Path,
        follow: bool,
        control_token: Option<String>,
        ground: Arc<Terrain>,
        data_hash: &[u8; 32],
    ) -> Result<Replaying, crate::sim::watch::OpenError> {
        let (watch, follow) = if follow {
            let (w, f) = open_following(path, ground, data_hash)?;
            (w, Some(f))
        } else {
            (crate::sim::watch::open_file(path, ground, data_hash)?, None)
        };
        Ok(Replaying {
            watch,
            control_token,
            follow,
        })
    }
}

/// How often a followed file is read for more, in world ticks (250 ms).
const FOLLOW_EVERY: u64 = 25;

/// Why a followed recording is no longer followed (its valid part stays watched).
#[derive(Debug, thiserror::Error)]
pub enum FollowError {
    #[error("reading {}: {error}", file.display())]
    Read {
        file: std::path::PathBuf,
        error: std::io::Error,
    },
    #[error(
        "{} grew past the {} bytes a recording may have",
        file.display(),
        crate::sim::recording::MAX_FILE_BYTES
    )]
    TooLarge { file: std::path::PathBuf },
}

/// A recording file followed as its server writes it: read for more every
/// [`FOLLOW_EVERY`] ticks, its whole records handed to the [`Watch`].
pub struct Follower {
    path: std::path::PathBuf,
    file: std::fs::File,
    reader: crate::sim::recording::Reader,
}

impl Follower {
    /// Reads what the file has gained and hands its whole records to `watch`. An error
    /// reading it ends the following (logged): the valid part stays what it was.
    fn poll(&mut self, watch: &mut Watch<Arc<Terrain>>) -> Result<(), FollowError> {
        use std::io::Read;
        let room = crate::sim::recording::MAX_FILE_BYTES.saturating_sub(self.reader.len());
        let mut more = Vec::new();
        (&mut self.file)
            .take(room + 1)
            .read_to_end(&mut more)
            .map_err(|error| FollowError::Read {
                file: self.path.clone(),
                error,
            })?;
        if more.is_empty() {
            return Ok(());
        }
        if more.len() as u64 > room {
            let file = self.path.clone();
            return Err(FollowError::TooLarge { file });
        }
        let mut events = Vec::new();
        let damaged = self.reader.feed(&more, &mut events).err();
        watch.append(&events, damaged, self.reader.cut_at());
        Ok(())
    }
}

/// Opens `path` to watch as it grows (`--follow`): its valid part so far, and the
/// [`Follower`] that reads the rest as it comes.
pub fn open_following(
    path: &std::path::Path,
    ground: Arc<Terrain>,
    data_hash: &[u8; 32],
) -> Result<(Watch<Arc<Terrain>>, Follower), crate::sim::watch::OpenError> {
    let (mut watch, file, reader) = crate::sim::watch::open_file_reading(path, ground, data_hash)?;
    watch.follow();
    // Watched live: from the newest whole tick, on as the file grows.
    watch.seek(watch.status().end);
    Ok((
        watch,
        Follower {
            path: path.to_path_buf(),
            file,
            reader,
        },
    ))
}

/// Where a replay's controls go: its thread here, or the world over the bus (an edge of
/// `world --replay`).
enum Controls {
    Here(Mutex<Sender<Control>>),
    World(Arc<super::bus::edge::Remote>),
}

/// What the viewer tasks share of a replay.
pub struct ReplayShared {
    controls: Controls,
    status: watch::Receiver<Status>,
    /// An edge's: whether its world serves a recording now (a `serve --replay`'s always).
    active: watch::Receiver<bool>,
    /// The viewers in the order they joined: an id, the peer in words, whether it
    /// presented the control token.
    viewers: Mutex<Vec<(u64, String, bool)>>,
    /// The viewer holding the controls (0: none).
    holder: watch::Sender<u64>,
    pub(super) control_token: Option<String>,
    /// The vehicle a viewer follows when none is in the world yet: the first the
    /// recording has (`None`: it has none).
    pub(super) first_vehicle: Option<u16>,
    next_id: AtomicU64,
}

/// A viewer's place among those watching: it leaves the list when dropped.
pub struct Seat {
    shared: Arc<ReplayShared>,
    pub(super) id: u64,
}

impl Drop for Seat {
    fn drop(&mut self) {
        let mut v = lock(&self.shared.viewers);
        v.retain(|(id, ..)| *id != self.id);
        self.shared.elect(&v);
    }
}

impl ReplayShared {
    /// A viewer (`peer`, and whether it presented the control token) starts watching.
    pub(super) fn enter(self: &Arc<Self>, peer: String, controller: bool) -> Seat {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed) + 1;
        let mut v = lock(&self.viewers);
        v.push((id, peer, controller));
        self.elect(&v);
        Seat {
            shared: self.clone(),
            id,
        }
    }

    /// The holder: with a control token, the first viewer that presented it (none while
    /// none there); without, the first.
    fn elect(&self, viewers: &[(u64, String, bool)]) {
        let holder = match self.control_token {
            Some(_) => viewers.iter().find(|v| v.2),
            None => viewers.first(),
        }
        .map_or(0, |v| v.0);
        self.holder
            .send_if_modified(|h| std::mem::replace(h, holder) != holder);
    }

    /// Whether viewers are served a recording now (an edge's world may be a live one).
    pub(super) fn active(&self) -> bool {
        *self.active.borrow()
    }

    /// Takes viewer `id`'s control: heeded only from the holder.
    pub(super) fn control(&self, id: u64, c: ReplayControl) -> bool {
        if *self.holder.borrow() != id {
            return false;
        }
        match &self.controls {
            Controls::Here(_) => self.control_here(c),
            Controls::World(remote) => {
                let remote = remote.clone();
                tokio::spawn(async move {
                    if let Err(why) = remote.replay_control(c).await {
                        tracing::info!("a replay control not taken by the world: {why}");
                    }
                });
                true
            }
        }
    }

    /// Takes a control for the replay's thread here, whoever it comes from (an edge of
    /// `world --replay`, which heeds only its own holder's).
    pub(super) fn control_here(&self, c: ReplayControl) -> bool {
        let Controls::Here(tx) = &self.controls else {
            return false;
        };
        let tx = lock(tx);
        tx.send(c).is_ok()
    }

    /// The clock as the bus carries it (`world --replay`'s snapshots).
    pub(super) fn wire_status(&self) -> roam_protocol::bus::Replay {
        let s = *self.status.borrow();
        roam_protocol::bus::Replay {
            start: s.start,
            end: s.end,
            speed: s.speed,
            paused: s.paused,
        }
    }

    /// An edge's share of its world's replay: active while the world's snapshots say it
    /// serves a recording (`replay`: their clock, from [`super::bus::edge::Remote`]), the
    /// controls sent to the world. Each edge has its holder (its first viewer).
    pub(super) fn for_edge(
        remote: Arc<super::bus::edge::Remote>,
        mut replay: watch::Receiver<Option<roam_protocol::bus::Replay>>,
    ) -> Arc<ReplayShared> {
        let (status_tx, status) = watch::channel(Status::default());
        let (active_tx, active) = watch::channel(replay.borrow().is_some());
        tokio::spawn(async move {
            loop {
                let now = *replay.borrow_and_update();
                active_tx
                    .send_if_modified(|a| std::mem::replace(a, now.is_some()) != now.is_some());
                if let Some(r) = now {
                    status_tx.send_if_modified(|s| {
                        let new = Status {
                            tick: s.tick,
                            start: r.start,
                            end: r.end,
                            speed: r.speed,
                            paused: r.paused,
                        };
                        std::mem::replace(s, new) != new
                    });
                }
                if replay.changed().await.is_err() {
                    return;
                }
            }
        });
        Arc::new(ReplayShared {
            controls: Controls::World(remote),
            status,
            active,
            viewers: Mutex::new(Vec::new()),
            holder: watch::Sender::new(0),
            control_token: None,
            first_vehicle: None,
            next_id: AtomicU64::new(0),
        })
    }

    /// The state as viewer `id` is told it.
    pub(super) fn status_for(&self, id: u64) -> ReplayStatus {
        let s = *self.status.borrow();
        let holder = *self.holder.borrow();
        let controller = lock(&self.viewers)
            .iter()
            .find(|v| v.0 == holder)
            .map_or_else(|| "nobody".to_string(), |v| v.1.clone());
        ReplayStatus {
            tick: s.tick,
            start: s.start,
            end: s.end,
            speed: s.speed,
            paused: s.paused,
            control: holder == id,
            controller,
        }
    }
}

/// Tells viewer `id` the replay's state when it changes (the clock's running aside); ends
/// when the control stream fails.
pub(super) async fn tell(
    send: Arc<tokio::sync::Mutex<SendStream>>,
    shared: Arc<ReplayShared>,
    id: u64,
) {
    let mut status = shared.status.clone();
    let mut holder = shared.holder.subscribe();
    let mut last: Option<ReplayStatus> = None;
    loop {
        let now = shared.status_for(id);
        let same = last.as_ref().is_some_and(|l| {
            ReplayStatus {
                tick: now.tick,
                ..l.clone()
            } == now
        });
        if !same {
            let msg = ServerMessage::Replay(now.clone());
            let mut s = send.lock().await;
            if s.write_msg(&msg).await.is_err() {
                return;
            }
            last = Some(now);
        }
        tokio::select! {
            r = status.changed() => if r.is_err() { return },
            r = holder.changed() => if r.is_err() { return },
        }
    }
}

/// The world thread of a replay, started: plays `replaying` (see the module docs) until
/// `inbox` closes; returns the shared state the viewer tasks (or `world --replay`'s
/// answers to its edges) use.
pub(crate) fn start(
    replaying: Replaying,
    inbox: Receiver<Inbound>,
    snapshots: watch::Sender<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
) -> std::io::Result<(std::thread::JoinHandle<World>, Arc<ReplayShared>)> {
    let Replaying {
        mut watch,
        control_token,
        mut follow,
    } = replaying;
    let first_vehicle = watch
        .world()
        .vehicles()
        .first()
        .map(|v| v.id)
        .or_else(|| watch.marks().iter().find(|m| m.join).map(|m| m.vehicle));
    let (controls, controls_rx) = std::sync::mpsc::channel();
    let (status_tx, status) = watch::channel(watch.status());
    snapshots.send_replace(Arc::new(watch.snapshot()));
    let shared = Arc::new(ReplayShared {
        controls: Controls::Here(Mutex::new(controls)),
        status,
        active: watch::channel(true).1,
        viewers: Mutex::new(Vec::new()),
        holder: watch::Sender::new(0),
        control_token,
        first_vehicle,
        next_id: AtomicU64::new(0),
    });
    let handle = std::thread::Builder::new()
        .name("roam-replay".into())
        .spawn(move || {
            let mut pacer = super::world_loop::Pacer::new();
            let mut ticks = 0u64;
            loop {
                ticks += 1;
                if ticks.is_multiple_of(FOLLOW_EVERY)
                    && watch.growing()
                    && let Some(f) = follow.as_mut()
                    && let Err(why) = f.poll(&mut watch)
                {
                    tracing::warn!("no longer following the recording: {why}");
                    watch.unfollow();
                    follow = None;
                }
                pacer.wait();
                // Nothing comes on the inbox from spectators; its closing stops the thread.
                loop {
                    match inbox.try_recv() {
                        Ok(_) => {}
                        Err(TryRecvError::Empty) => break,
                        Err(TryRecvError::Disconnected) => return watch.world().clone(),
                    }
                }
                pacer.begin(&stats);
                let mut told = false;
                while let Ok(c) = controls_rx.try_recv() {
                    watch.control(c);
                    told = true;
                }
                watch.advance();
                if let Some((tick, digest)) = watch.take_ended() {
                    tracing::info!("replay ended at tick {tick}, digest {digest}");
                }
                snapshots.send_replace(Arc::new(watch.snapshot()));
                let now = watch.status();
                status_tx.send_if_modified(|s| {
                    let changed = told
                        || (s.start, s.end, s.speed, s.paused)
                            != (now.start, now.end, now.speed, now.paused);
                    *s = now;
                    changed
                });
                pacer.made(&stats);
            }
        })?;
    Ok((handle, shared))
}
