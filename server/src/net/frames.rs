//! The frame clock: one task makes every viewer's frames, each pass serving every
//! [`Conversation`] that is due ([`Served`]), and hands what they say to send to quinn.
//! A viewer's own task ([`super::viewer`]) only reads its control stream and datagrams
//! into its conversation, writes colour, and ends the connection.
//!
//! **One clock.** Every conversation's frames fall on one grid, each viewer on one of 16
//! phases of its period in turn ([`super::clock::FrameClock::origin`], `origin +
//! k·period`, [`Conversation::new`]): at 60 Hz the clock wakes at most 960 times a second
//! whatever the number of viewers, each pass making the frames of the viewers on its
//! phase one after another. A timer and a task per viewer are gone; the phases keep a
//! pass to a sixteenth of the viewers (on one grid, 50 viewers' frames at 200 µs each
//! came in one burst of 10 ms, the last a tenth of a second late now and then).
//! Between passes it wakes only for what is due sooner: a small frame's second copy on a
//! lossy path, a viewer that joined (its first frame is due at once), a heavy frame back
//! (while it was away, the clock did not count on the viewer's next frame).
//!
//! **A pass in slices.** A pass lets the rest of the server run every [`PASS_SLICE`]: on
//! the one core a server is given, nothing is sent or read while the clock runs, and with
//! 64 viewers turning together a pass took 30 ms and more. Its first frames then waited in
//! quinn for its last, their streams were superseded before they left, the viewers took
//! none, fell behind and got key frames (the summary's `key_behind`: 20 to 55 in half a
//! second), which loaded the core more. Sliced (`scripts/capacity.sh --in-step 64`,
//! `FRAMES=1800`, 2026-12-07, in turn): the slowest viewer 42.2–43.2 → 51.7 frames/s, every
//! frame sent taken, the longest gap 937–992 → 131–168 ms, 207–213 → 151–153 µs a frame.
//!
//! What a viewer costs is mostly its cut: profiled (`perf`, 50 driving viewers on one core,
//! `data/kossou`, 2026-12-07), the coherent tessellator's update took about three fifths
//! of the server's CPU, the kernel's UDP and quinn a tenth, `malloc` and copies a tenth;
//! the clock changed the CPU a frame by a few per cent either way (within the noise).
//!
//! **Under load the cuts lag, not the frames.** After each pass the clock's [`Allowance`]
//! hears how late its frames started and says how many changes each cut may make a frame
//! (`Coherent::set_allowance`: past it only the splits above a bounded error go on). With
//! none, 100 viewers spread out took 50.5 frames/s on `data/kossou`, the core chasing
//! detail under a pixel through every turn; with it 57.5, and in step 37.2 → 52.7
//! (`scripts/capacity.sh`, 2026-12-07; the steep map gains little: docs/figures.md).
//!
//! **Heavy frames off the pass, but first frames in it.** A frame whose cut or coding is
//! heavy (a rebuild, a key frame's coding, many changes) comes out of the conversation as
//! a [`Job`], run on a blocking frame maker ([`super::makers`], at a lower priority than
//! the clock), then given back ([`Conversation::finish`]) and sent from there; the pass
//! goes on, so a heavy frame never delays the other viewers' frames. A viewer's first frame
//! (a key frame from scratch, 4.6 ms at 32,768 triangles) is the exception up to
//! [`INLINE_FIRST_BUDGET`]: the clock makes them itself, **one a pass, after the pass's
//! other frames**, the earliest joined first. A pass that leaves first frames waiting is
//! due again at once, so joins take what the served viewers leave of the core, and a served
//! viewer's frame waits for one first frame at most. The wait counts as lateness: while
//! viewers join, the served viewers' cuts are held back ([`Allowance`]) and their colour
//! waits, and while a pass leaves first frames waiting, each served viewer gets every other
//! frame ([`Conversation::pass_over`]: never two missed in a row), so the joins get the
//! core. Before, first frames were made in the pass's order, 4 ms apart counted from each
//! one's start: at 7.8 ms each, 40 joining at once were made back to back in one pass
//! while the viewers served before them waited (their frames up to 0.27 s late in the
//! server's summary; now at most 17 ms). With this order and the cheaper first frames
//! (docs/figures.md, "What a join costs"), `scripts/capacity.sh 40` (2026-12-07, the load
//! generator decoding no tile): the last first frame 175–298 ms after its join on
//! `data/kossou` (248–286 on the steep map), the longest gap after a first frame 29–53 ms
//! (31–47); with every other frame passed over, 165–206 ms (184–204), gaps 44–59 ms
//! (43–49). (Earlier ways, measured then: on a maker below the served frames, 40 had
//! their first frames up to 1.5 s after their joins; one a slice of the pass, 0.22–0.24 s
//! with gaps of 0.23–0.30 s.)
//!
//! **How bytes go.** A datagram is handed to quinn at once (refused after all, the
//! conversation puts the frame on a stream); a stream frame is written by a task of its
//! own, which a [`Transmit::Reset`] cancels (resetting the stream: quinn stops sending
//! and retransmitting it) before or after it is all written, until the viewer has it.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use roam_protocol::sync::lock;
use tokio::sync::oneshot;

use super::clock::{FramesEnd, Served};
use super::conn::DatagramError;
use super::shared::Shared;
use crate::sim::world_core::Snapshot;
use crate::viewer::conversation::{Conversation, End, Job, Out, Sent, Step, Transmit};
use crate::viewer::{Allowance, KeyCause};

/// The largest budget whose first frame the clock makes itself (one a pass, after the
/// pass's other frames), rather than a blocking frame maker (the module's header says
/// why): a viewer's frame waits for one first frame at most, some 10 ms at this budget. It
/// borrows its tessellator from the makers' [`crate::tessellate::Scratch`] (no map-sized
/// state is added), waiting for a maker's job to return one if all are lent.
const INLINE_FIRST_BUDGET: u32 = 65_536;

/// Longest sleep between passes with nothing due (a viewer's first frame wakes it).
const IDLE: Duration = Duration::from_millis(250);

/// The longest a pass runs before it lets the rest of the server run (quinn's connections
/// send the frames made so far and read what came in, the frame writers write), then goes
/// on. On the one core a server is given, a pass of 64 viewers turning together took 30 ms
/// and more, with nothing sent or read meanwhile: the frames made first waited for the
/// last, their streams were superseded before they left, and with no frame taken the
/// viewers fell behind and got key frames.
const PASS_SLICE: Duration = Duration::from_millis(2);

/// Serves every viewer's frames until the server shuts down.
pub(super) async fn run(shared: Arc<Shared>) {
    // What each cut may change a frame, from how late the passes' frames start.
    let mut allowance = Allowance::default();
    // Whether the last pass left first frames waiting: the served viewers then get every
    // other frame ([`Conversation::pass_over`]), and the joins the core that frees.
    let mut joins_waiting = false;
    loop {
        let now = Instant::now();
        let viewers: Vec<Arc<Served>> = {
            let mut v = lock(&shared.clock.viewers);
            v.retain(|s| !s.ended());
            v.clone()
        };
        let snap: Arc<Snapshot> = shared.snapshots.borrow().clone();
        let mut next = now + IDLE;
        let mut slice = Instant::now();
        let mut latest: Option<Duration> = None;
        // The viewers whose first frame is due, in the order they joined: one is made a
        // pass, after the others' frames.
        let mut joining: Vec<&Arc<Served>> = Vec::new();
        let p = Pass {
            now,
            snap: &snap,
            allowance: &allowance,
            joins_waiting,
        };
        for s in &viewers {
            if slice.elapsed() >= PASS_SLICE {
                tokio::task::yield_now().await;
                slice = Instant::now();
            }
            let (at, first_due) = turn(&shared, s, &p, &mut latest, false);
            if first_due {
                joining.push(s);
            } else if let Some(at) = at {
                next = next.min(at);
            }
        }
        let mut left = joining.into_iter();
        for s in left.by_ref() {
            let (at, waiting) = turn(&shared, s, &p, &mut latest, true);
            if let Some(at) = at {
                next = next.min(at);
            }
            if !waiting {
                break; // made (or away on a maker): the next one waits for the next pass
            }
        }
        joins_waiting = left.next().is_some();
        if joins_waiting {
            next = now; // first frames still wait: the next pass at once
        }
        if viewers.is_empty() {
            allowance = Allowance::default();
        }
        allowance.pass(latest);
        if latest.is_some() {
            shared.stats.allowance(allowance.level());
        }
        if next <= Instant::now() {
            // Due again at once (a frame come due during the pass): the rest of the server
            // (quinn's connections, the readers, colour) runs first.
            tokio::task::yield_now().await;
        }
        tokio::select! {
            _ = tokio::time::sleep_until(next.into()) => {}
            _ = shared.clock.wake.notified() => {}
            _ = shared.shutting_down() => return,
        }
    }
}

/// What a pass's turns share: when it began, the world it shows, the cuts' allowance, and
/// whether first frames were left waiting by the pass before.
struct Pass<'a> {
    now: Instant,
    snap: &'a Arc<Snapshot>,
    allowance: &'a Allowance,
    joins_waiting: bool,
}

/// One viewer's turn in a pass, under its lock ([`pass`]): when it is due next, and
/// whether it is still waiting for its first frame with its core at hand (left for the
/// pass's end when `may_first` is false; not made when true: its vehicle is not in the
/// world yet). The latest lateness of a frame made goes into `latest`.
fn turn(
    shared: &Arc<Shared>,
    s: &Arc<Served>,
    p: &Pass,
    latest: &mut Option<Duration>,
    may_first: bool,
) -> (Option<Instant>, bool) {
    let mut c = lock(&s.conv);
    // A frame that could not be made ends its viewer, never the clock.
    c.set_allowance(p.allowance.changes());
    let made = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        pass(shared, s, &mut c, p, may_first)
    }));
    match made {
        Ok(Some(late)) => *latest = (*latest).max(Some(late)),
        Ok(None) => {}
        Err(_) => s.stop(FramesEnd::Failed("the frame maker failed")),
    }
    let waiting = !s.ended() && c.frames() == 0 && c.core().is_some();
    let first_due = waiting && (may_first || c.frame_due(p.now));
    (c.poll_timeout(), first_due)
}

/// One viewer's frame if due, and whatever is due to send. A first frame is made only when
/// `may_first` says so (the pass's end). Returns how late a frame started for want of the
/// core (`None`: none was made, or a first one: [`Conversation::late`]). A wait behind the
/// clock's own first frames counts: while viewers join, the cuts of those served are held
/// back ([`Allowance`]) and the joins get the core they leave.
fn pass(
    shared: &Arc<Shared>,
    s: &Arc<Served>,
    c: &mut Conversation,
    p: &Pass,
    may_first: bool,
) -> Option<Duration> {
    let (now, snap) = (p.now, p.snap);
    if s.ended() {
        return None;
    }
    let mut made = None;
    if p.joins_waiting && c.pass_over(now) {
        shared.stats.add(&shared.stats.passed_over, 1);
        transmit(s, c, now);
        return None;
    }
    if c.frame_due(now) && (c.frames() > 0 || may_first) {
        let started = Instant::now();
        // A frame that starts behind holds every viewer's colour back, a first frame
        // waiting its turn too (the joins want the core more than colour does).
        shared.color.frame_started(c.due_at(), started);
        // A first frame's wait is its join's (the viewer reports it), not a served viewer's.
        if c.frames() > 0 {
            shared
                .stats
                .frame_late(started.saturating_duration_since(c.due_at()));
        }
        made = c.late(started);
        path(s, c, now);
        let step = {
            let mut grant = lock(&s.grant);
            c.frame(now, &shared.scene(), snap, &mut **grant)
        };
        let step = match step {
            Step::Heavy(job) if job.first() && job.budget() <= INLINE_FIRST_BUDGET => {
                let done = job.run(&shared.scene(), || shared.snapshots.borrow().clone());
                c.finish(Instant::now(), &shared.terrain, done)
            }
            other => other,
        };
        match step {
            Step::Idle => {}
            Step::Sent(sent) => counted(shared, s, c, sent, started),
            Step::Heavy(job) => {
                if !job.first() {
                    shared.stats.add(&shared.stats.heavy, 1);
                }
                tokio::spawn(heavy(shared.clone(), s.clone(), job));
            }
            Step::End(why) => {
                s.stop(ended(why));
                return made;
            }
        }
        tell(shared, s, c);
    }
    transmit(s, c, now);
    made
}

/// A frame's heavy part on a blocking maker, then sent.
async fn heavy(shared: Arc<Shared>, s: Arc<Served>, job: Box<Job>) {
    // The permit goes with the job: held until it ends, even if this task is dropped.
    let Ok(permit) = shared.makers.acquire(job.first()).await else {
        return s.stop(FramesEnd::Failed("the server is shutting down"));
    };
    if s.ended() {
        return; // the viewer left while the job waited
    }
    let started = Instant::now();
    let shared2 = shared.clone();
    let done = tokio::task::spawn_blocking(move || {
        let _permit = permit;
        // Below the async workers: frames first ([`super::makers`]).
        super::makers::lower_this_thread();
        job.run(&shared2.scene(), || shared2.snapshots.borrow().clone())
    })
    .await;
    let Ok(done) = done else {
        return s.stop(FramesEnd::Failed("the frame maker failed"));
    };
    let now = Instant::now();
    let mut c = lock(&s.conv);
    path(&s, &mut c, now);
    match c.finish(now, &shared.terrain, done) {
        Step::Sent(sent) => counted(&shared, &s, &c, sent, started),
        Step::End(why) => return s.stop(ended(why)),
        Step::Idle | Step::Heavy(_) => {}
    }
    tell(&shared, &s, &mut c);
    transmit(&s, &mut c, now);
    drop(c);
    // The clock may be asleep past this viewer's next frame (it did not count on it).
    shared.clock.wake.notify_one();
}

fn ended(why: End) -> FramesEnd {
    match why {
        End::VehicleLeft => FramesEnd::VehicleLeft,
        End::Failed(why) => FramesEnd::Failed(why),
    }
}

/// The server's counts for a frame made, and the viewer's.
fn counted(shared: &Shared, s: &Served, c: &Conversation, sent: Sent, started: Instant) {
    let stats = &shared.stats;
    stats.add(&stats.make_ns, started.elapsed().as_nanos() as u64);
    stats.add(&stats.frames, 1);
    let tx = s.conn.quic().stats().udp_tx.bytes;
    let before = s.bytes_out.swap(tx, Ordering::Relaxed);
    stats.add(&stats.bytes_out, tx.saturating_sub(before));
    stats.add(&stats.short, u64::from(sent.short));
    stats.add(&stats.key_frames, u64::from(sent.key.is_some()));
    match sent.key {
        Some(KeyCause::Asked) => stats.add(&stats.key_asked, 1),
        Some(KeyCause::Behind) => stats.add(&stats.key_behind, 1),
        Some(KeyCause::Larger) => stats.add(&stats.key_larger, 1),
        Some(KeyCause::First) | None => {}
    }
    s.sent.send_replace(c.frames());
}

/// What the conversation tells the shell: whom it follows, a replay's controls.
fn tell(shared: &Shared, s: &Served, c: &mut Conversation) {
    while let Some(out) = c.poll_event() {
        match out {
            Out::Following(to) => {
                s.follow.send_replace(to);
            }
            Out::Replay(control) => {
                if let (Some(r), Some(id)) = (&shared.replay, s.replay) {
                    r.control(id, control);
                }
            }
        }
    }
}

/// Tells the conversation the path's figures (before a frame: how it goes depends on them).
fn path(s: &Served, c: &mut Conversation, now: Instant) {
    let stats = s.conn.quic().stats();
    let path = crate::viewer::conversation::Event::Path {
        max_datagram: s.conn.max_datagram_size(),
        lost: stats.path.lost_packets,
        sent: stats.path.sent_packets,
    };
    c.handle(now, path);
}

/// Hands quinn what the conversation says to send by `now`.
fn transmit(s: &Arc<Served>, c: &mut Conversation, now: Instant) {
    while let Some(t) = c.poll_transmit(now) {
        match t {
            Transmit::Datagram { frame, bytes } => {
                match s.conn.send_datagram(bytes.clone().into()) {
                    Ok(()) => {}
                    Err(DatagramError::Lost) => return s.stop(FramesEnd::ConnectionLost),
                    Err(DatagramError::Refused) => {
                        let refused = crate::viewer::conversation::Event::Refused { frame, bytes };
                        c.handle(now, refused);
                    }
                }
            }
            Transmit::Reset { frame } => {
                let mut streams = lock(&s.streams);
                if let Some(i) = streams.iter().position(|(f, _)| *f == frame) {
                    let _ = streams.swap_remove(i).1.send(());
                }
            }
            Transmit::Stream {
                frame,
                priority,
                bytes,
            } => {
                let (cancel, cancelled) = oneshot::channel();
                let mut streams = lock(&s.streams);
                streams.retain(|(_, tx)| !tx.is_closed());
                streams.push((frame, cancel));
                tokio::spawn(write_frame(s.clone(), priority, bytes, cancelled));
            }
        }
    }
}

/// Writes a frame on a stream of its own; resets it if cancelled before the viewer has it.
async fn write_frame(
    s: Arc<Served>,
    priority: i32,
    bytes: Vec<u8>,
    mut cancelled: oneshot::Receiver<()>,
) {
    // Superseded before the viewer gave it a stream (a slow or silent viewer): it goes.
    let opened = tokio::select! {
        o = s.conn.open_uni() => o,
        Ok(()) = &mut cancelled => return,
    };
    let Some(mut stream) = opened else {
        return s.stop(FramesEnd::ConnectionLost);
    };
    stream.set_priority(priority);
    let written = tokio::select! {
        r = stream.write_all(&bytes) => r.is_ok() && stream.finish(),
        Ok(()) = &mut cancelled => false,
    };
    if !written {
        stream.reset(0);
        return;
    }
    // Handed to quinn: a finished stream still waits in the send buffer on a slow path,
    // so a cancel resets it until the viewer has read it all.
    tokio::select! {
        () = stream.stopped() => {}
        Ok(()) = cancelled => stream.reset(0),
    }
}
