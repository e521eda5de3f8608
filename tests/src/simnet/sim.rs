//! What a test does with the simulated network and reads from it: a [`Sim`] made on a
//! terrain, viewers added over [`Path`]s, virtual time run step by step (each step: the
//! server's arrivals, the world's tick if due, each viewer's server side then client side,
//! the paths), the viewers steered and their paths broken, and what each took.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_client::core::{ClientCore, KeyCore, Received};
use roam_protocol::keys::KeyStep;
use roam_protocol::messages::{self, ClientMessage, Reason, Role, ViewChange, Welcome};
use roam_protocol::script::Script;
use roam_server::Terrain;
use roam_server::sim::world::{VehicleId, World};
use roam_server::sim::world_core::{Snapshot, WorldCore};
use roam_server::terrain::variance::VarianceTree;

use super::client::client_control;
use super::path::{InOrder, Path, SplitMix64, Wire};
use super::state::{
    ClientSide, FOV_Y_DEG, FRAME_RATE, STEP, ServerSide, ServerState, Sim, Stats, TICK, TakenFrame,
    TrackPoint, VIEWPORT, Viewer, ViewerId,
};

impl Sim {
    /// An empty world on `terrain`, no viewer yet, at virtual time 0.
    pub fn new(seed: u64, terrain: Arc<Terrain>) -> Sim {
        let variance = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
        let height_step = roam_protocol::height_step(terrain.heights.samples());
        let world = WorldCore::new(terrain.clone(), None).expect("no recording to fail");
        Sim {
            epoch: Instant::now(),
            now: Duration::ZERO,
            seed,
            scratch: roam_server::tessellate::Scratch::new(terrain.heights.side(), 1),
            terrain,
            variance,
            height_step,
            world,
            snapshot: Arc::new(Snapshot::default()),
            next_tick: TICK,
            viewers: Vec::new(),
        }
    }

    /// The virtual time.
    pub fn now(&self) -> Duration {
        self.now
    }

    pub(super) fn at(&self, t: Duration) -> Instant {
        self.epoch + t
    }

    /// A driver joins over `path`, asking for `budget` triangles, and drives `script`.
    pub fn add_driver(&mut self, script: &Script, budget: u32, path: Path) -> ViewerId {
        self.add(Role::Driver, Some(script.steps().collect()), budget, path)
    }

    /// A spectator joins over `path`, following `follow` (or the first vehicle).
    pub fn add_spectator(
        &mut self,
        follow: Option<VehicleId>,
        budget: u32,
        path: Path,
    ) -> ViewerId {
        self.add(Role::Spectator { follow }, None, budget, path)
    }

    fn add(
        &mut self,
        role: Role,
        steps: Option<Vec<KeyStep>>,
        budget: u32,
        path: Path,
    ) -> ViewerId {
        let id = self.viewers.len();
        let seed = |k: u64| {
            SplitMix64::new(self.seed ^ ((id as u64) << 32) ^ k.wrapping_mul(0x5851_f42d_4c95_7f2d))
                .next_u64()
        };
        let hello = roam_client::conversation::hello(
            role,
            "simnet".into(),
            VIEWPORT,
            FOV_Y_DEG,
            messages::clamp_budget(budget),
            FRAME_RATE,
            roam_client::render::native_max_texture(),
        );
        let mut v = Viewer {
            up: Wire::new(path.up, seed(1)),
            down: Wire::new(path.down, seed(2)),
            server: ServerSide {
                state: ServerState::Waiting,
                control_in: InOrder::default(),
                control_seq: 0,
                last_heard: self.now,
                joined: None,
            },
            client: ClientSide {
                hello: hello.clone(),
                core: None,
                welcome: None,
                steps,
                next_step: 0,
                next_key: Duration::ZERO,
                control_in: InOrder::default(),
                control_seq: 0,
                streams: BTreeMap::new(),
                early: VecDeque::new(),
                keys: KeyCore::default(),
                skip_decoding: 0,
                closed: None,
                last_heard: self.now,
            },
            stats: Stats::default(),
            taken: Vec::new(),
            track: Vec::new(),
            latest: None,
            dropped: Vec::new(),
        };
        let now = self.now;
        client_control(&mut v, now, &ClientMessage::Hello(hello));
        v.up.pump(now);
        self.viewers.push(v);
        id
    }

    /// Runs until the virtual time is `t`.
    pub fn run_until(&mut self, t: Duration) {
        while self.now < t {
            self.step();
        }
    }

    /// Runs for `d` of virtual time.
    pub fn run_for(&mut self, d: Duration) {
        self.run_until(self.now + d);
    }

    /// One millisecond: arrivals at the server, the world's tick if due, frames due, arrivals
    /// at the viewers, the viewers' keys, takes and control messages, and the paths send.
    pub fn step(&mut self) {
        self.now += STEP;
        let now = self.now;
        self.server_receive(now);
        if now >= self.next_tick {
            self.tick();
            self.next_tick += TICK;
        }
        for i in 0..self.viewers.len() {
            self.server_frames(i, now);
        }
        for i in 0..self.viewers.len() {
            self.client_step(i, now);
        }
        for v in &mut self.viewers {
            v.up.pump(now);
            v.down.pump(now);
            v.stats.up = v.up.stats;
            v.stats.down = v.down.stats;
        }
    }

    // ---- What a test does ----

    /// Viewer `i`'s core, once welcomed (to change its budget or view: what it has to
    /// send leaves at the next step).
    pub fn client(&mut self, i: ViewerId) -> Option<&mut ClientCore> {
        self.viewers[i].client.core.as_mut()
    }

    /// The viewer asks for `budget` triangles.
    pub fn set_budget(&mut self, i: ViewerId, budget: u32) {
        if let Some(c) = self.client(i) {
            c.set_budget(budget);
        }
    }

    /// The viewer's camera changes.
    pub fn set_view(&mut self, i: ViewerId, view: ViewChange) {
        if let Some(c) = self.client(i) {
            c.set_view(view);
        }
    }

    /// The viewer takes its next `n` frames without decoding them (it acknowledges them
    /// all the same, and keeps no base of them).
    pub fn skip_decoding(&mut self, i: ViewerId, n: u32) {
        self.viewers[i].client.skip_decoding = n;
    }

    /// The viewer says goodbye on its control stream and stops.
    pub fn quit(&mut self, i: ViewerId) {
        let now = self.now;
        let v = &mut self.viewers[i];
        client_control(v, now, &ClientMessage::Bye(Reason::Quit));
        v.client.core = None;
        v.client.steps = None;
    }

    /// Viewer `i`'s path carries nothing (either way, packets on the way included) for `d`.
    pub fn cut_path(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
        v.down.down_until = v.down.down_until.max(until);
    }

    /// Viewer `i`'s path to the server carries nothing (packets on the way included) for
    /// `d`; the way back works.
    pub fn cut_up(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
    }

    /// Viewer `i`'s path carries nothing, ever again.
    pub fn kill_path(&mut self, i: ViewerId) {
        self.cut_path(i, Duration::MAX);
    }

    /// Viewer `i`'s path is now `path` (packets on the way keep their arrival times).
    pub fn set_path(&mut self, i: ViewerId, path: Path) {
        let v = &mut self.viewers[i];
        v.up.direction = path.up;
        v.down.direction = path.down;
    }

    // ---- What a test reads ----

    pub fn stats(&self, i: ViewerId) -> &Stats {
        &self.viewers[i].stats
    }

    /// Every frame the viewer took, in order.
    pub fn taken(&self, i: ViewerId) -> &[TakenFrame] {
        &self.viewers[i].taken
    }

    /// The newest frame the viewer took.
    pub fn latest(&self, i: ViewerId) -> Option<&Received> {
        self.viewers[i].latest.as_ref()
    }

    /// Why frames failed to decode, with when.
    pub fn decode_failures(&self, i: ViewerId) -> &[String] {
        &self.viewers[i].dropped
    }

    /// A driver's vehicle after each tick since it joined.
    pub fn track(&self, i: ViewerId) -> &[TrackPoint] {
        &self.viewers[i].track
    }

    /// The viewer's welcome, once it has one.
    pub fn welcome(&self, i: ViewerId) -> Option<&Welcome> {
        self.viewers[i].client.welcome.as_ref()
    }

    /// The vehicle the server gave (or let follow) viewer `i`, while it serves it.
    pub fn vehicle(&self, i: ViewerId) -> Option<VehicleId> {
        match &self.viewers[i].server.state {
            ServerState::Serving(s) => Some(s.conv.vehicle()),
            _ => None,
        }
    }

    /// Whether the server still serves viewer `i` (its core is alive).
    pub fn server_open(&self, i: ViewerId) -> bool {
        !matches!(self.viewers[i].server.state, ServerState::Closed)
    }

    /// Why the viewer's connection ended, if it has.
    pub fn client_closed(&self, i: ViewerId) -> Option<&str> {
        self.viewers[i].client.closed.as_deref()
    }

    /// The triangle budget the server's core for viewer `i` works to.
    pub fn server_budget(&self, i: ViewerId) -> Option<u32> {
        match &self.viewers[i].server.state {
            ServerState::Serving(s) => s.conv.core().map(|c| c.budget()),
            _ => None,
        }
    }

    /// The world now.
    pub fn world(&self) -> &World {
        self.world.world()
    }

    /// Whether the world has vehicle `id`.
    pub fn world_has(&self, id: VehicleId) -> bool {
        self.world().vehicle(id).is_some()
    }

    /// The newest snapshot.
    pub fn snapshot(&self) -> &Snapshot {
        &self.snapshot
    }
}
