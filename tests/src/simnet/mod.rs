//! A deterministic simulated network, in the spirit of `quinn-proto`'s `Pair` test harness:
//! the server's sans-IO cores ([`WorldCore`], and per viewer a [`Conversation`]) and the
//! viewer's sans-IO cores ([`ClientCore`] for frames, [`KeyCore`] for keys) driven together by virtual time, with no socket, task, thread or
//! clock. Tests add viewers over [`Path`]s, run virtual time, steer the viewers and break
//! their paths, and read what each viewer took ([`Stats`], [`TakenFrame`]s, a driver's
//! [`TrackPoint`]s) and what the world holds.
//!
//! **Time.** One `Instant` is read when a [`Sim`] is made (its epoch); from then on "now" is
//! the epoch plus a virtual [`Duration`] that [`Sim::step`] advances by 1 ms. Nothing reads
//! the clock again, so a run is a pure function of its seed and what the test does.
//! Packets arrive at nanosecond times, and are handled in the step that reaches them (a
//! step: arrivals at the server, the world's tick if due, frames due, arrivals at the
//! viewers, their keys, takes and control messages, then the paths send).
//!
//! **Composition** (as `net::viewer`, `net::frames` and `net::world_loop` do it):
//!
//! - The world ticks every 10 ms of virtual time; what arrived up to the tick belongs to
//!   it. Its newest snapshot is what frames show (the shell's `watch`, latest wins).
//! - A viewer sends its hello on the control stream; the server answers a driver's with a
//!   [`world_core::Event::Join`] (a spectator follows a vehicle of the snapshot) and a
//!   welcome, and from then on its [`Conversation`] (the one `net::frames` drives) makes a
//!   frame every `1 / frame_rate` s (60 here) for the followed vehicle's state in the
//!   newest snapshot, its heavy part run in place, and says how each goes: a change frame
//!   of at most [`MAX_DATAGRAM`] bytes as a datagram (twice, a few milliseconds apart,
//!   while the path loses packets), a larger one on a reliable stream of its own, reset
//!   when the next frame is made unless the viewer has acknowledged its frame; a key
//!   frame, whatever its size, on a reliable stream of its own that is not reset while it
//!   is pending ([`ViewerCore::pending_key`]). This harness only moves those transmits.
//! - Control messages and key datagrams arriving at the server go into the conversation
//!   (a goodbye, or a second hello, ends the connection; a driver's keys go on into the
//!   world).
//! - The viewer, once welcomed, sends a key datagram every 10 ms with its script's next
//!   step ([`roam_protocol::script::Script::steps`], then no keys) from its [`KeyCore`],
//!   offers every frame that arrives (datagrams, and each stream once complete, whatever
//!   streams after it have completed; those before the welcome wait for the welcome) to its
//!   [`ClientCore`], takes one frame a step when it has one (decoding it, and measuring key
//!   latencies with [`KeyCore::applied`]) and sends its control messages, in order. The
//!   harness checks each decoded mesh against the server's cut for that frame.
//! - Either side closes a connection it has heard nothing on for [`IDLE_TIMEOUT`] (quinn's
//!   `max_idle_timeout` in `link/src/tls.rs`); the server then tells the world the driver
//!   left and drops the viewer's core. A server that ends a connection itself (the
//!   viewer's goodbye, the followed vehicle gone, a refusal) gives its last word, if it
//!   has one, [`LAST_WORD`] to arrive, then closes: a close packet (which may be lost),
//!   and the driver's leave.
//!
//! **The path model**, per direction ([`Direction`]): a packet (at most [`MAX_DATAGRAM`] payload
//! bytes plus [`OVERHEAD`] bytes of headers) waits in a FIFO serialisation queue until the
//! direction is free (`rate_bytes_per_s`; none: it leaves at once), is dropped at the tail when
//! the queue holds more than `queue_bytes`, is lost with probability `loss`, and arrives
//! `delay` plus a uniform `[0, jitter]` after it left (so jitter reorders). Each direction
//! has its own seeded [`SplitMix64`]. A path can be cut for a while or for good
//! ([`Sim::cut_path`], [`Sim::kill_path`]): every packet that leaves or arrives meanwhile
//! is lost.
//!
//! - **Datagrams** (key datagrams, small frames, the close packet) are lost for good.
//! - **The control stream**, one per direction: each message is one packet with a
//!   sequence number; a lost one is sent again [`rto`] (2 × delay + 10 ms) after it left,
//!   as often as it takes; the receiver hands messages to the application in order (a lost
//!   one holds up those behind it).
//! - **Frame streams** (server to viewer): a frame's bytes in packets of [`MAX_DATAGRAM`],
//!   each retransmitted like a control message; the viewer offers the frame once every
//!   packet has arrived. A reset stream loses its packets still queued and is never sent
//!   again; packets already on the wire still arrive (the viewer reads streams as data
//!   comes, so a reset that follows them is too late to discard them), and the viewer
//!   forgets a reset stream once none of its packets is on the way (the reset arrives
//!   behind them).
//!
//! **What it does not model:** the QUIC handshake (a hello leaves when the viewer is
//! added), congestion control and pacing (only a fixed rate), transport acknowledgements
//! (free and never lost: a sender knows of a loss exactly `rto` after the packet left),
//! stream priorities (one FIFO for everything: the shell sends a key frame first, here it
//! waits its turn), flow control, keep-alives (a live
//! connection always has traffic here), the colour map (the welcome says 0 bytes of it),
//! the join token, the time the cores take (they run in zero virtual time), a window's
//! or a viewer's pacing of takes (a viewer takes a frame in the millisecond it arrives),
//! and key datagrams still reaching the world during a last word (dropped here).
//!
//! **Files**, lowest first (none refers to one above it; this one only declares them and
//! re-exports): `path.rs` (the path and packet model), `state.rs` (the [`Sim`]'s state:
//! each viewer's paths and sides, the constants), `server.rs` (the server's cores composed
//! as its shell composes them) and `client.rs` (the viewer's, as `session.rs` does), and
//! `sim.rs` (the harness: time, viewers, what a test does and reads).
//!
//! [`Conversation`]: roam_server::viewer::conversation::Conversation
//! [`ViewerCore::pending_key`]: roam_server::viewer::ViewerCore::pending_key
//! [`world_core::Event::Join`]: roam_server::sim::world_core::Event::Join
//! [`WorldCore`]: roam_server::sim::world_core::WorldCore
//! [`ClientCore`]: roam_client::core::ClientCore
//! [`KeyCore`]: roam_client::core::KeyCore
//! [`KeyCore::applied`]: roam_client::core::KeyCore::applied
//! [`Duration`]: std::time::Duration

mod client;
mod path;
mod server;
mod sim;
mod state;

pub use path::{Direction, OVERHEAD, Path, SplitMix64, WireStats, rto};
pub use state::{
    FOV_Y_DEG, FRAME_RATE, IDLE_TIMEOUT, LAST_WORD, MAX_DATAGRAM, STEP, Sim, Stats, TICK,
    TakenFrame, TrackPoint, VIEWPORT, ViewerId,
};
