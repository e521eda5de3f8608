//! The server's side of the simulated network, composed as the `net` shell composes its
//! sans-IO cores: arrivals at the server (key datagrams and control messages into each
//! viewer's [`Conversation`], its key events into the world), the handshake, the world's
//! tick, and each viewer's frames (the conversation's, every decision of how they go its
//! own: this file only moves its transmits onto the simulated paths), the idle timeout and
//! the last word.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use roam_protocol::messages::{self, ClientMessage, Reason, Role, ServerMessage, VERSION, Welcome};
use roam_server::Terrain;
use roam_server::sim::world::VehicleId;
use roam_server::sim::world_core;
use roam_server::tessellate::Mesh;
use roam_server::viewer::conversation::{
    Conversation, End, Event, Handled, Role as ConvRole, Step, Transmit,
};
use roam_server::viewer::{Scene, ViewerLimits};

use super::path::Payload;
use super::state::{
    IDLE_TIMEOUT, LAST_WORD, MADE_KEPT, MAX_DATAGRAM, MadeFrame, ServerState, Serving, Sim,
    TrackPoint, Viewer, ViewerId, encoded, mesh_hash,
};

pub(super) fn welcome(terrain: &Terrain, vehicle: VehicleId, tick: u64) -> Welcome {
    let color = roam_protocol::ColorLayout::new(
        terrain.heights.size(),
        roam_protocol::tiles::DEFAULT_TILE,
        roam_protocol::tiles::DEFAULT_WINDOW,
    )
    .expect("the test terrains' colour maps are powers of two");
    roam_server::viewer::conversation::welcome(
        terrain,
        vehicle,
        tick,
        color,
        ViewerLimits::default(),
    )
}

impl Sim {
    /// Everything that reached the server by `now`, in the order it arrived (over all
    /// viewers).
    pub(super) fn server_receive(&mut self, now: Duration) {
        let mut arrivals = Vec::new();
        for (i, v) in self.viewers.iter_mut().enumerate() {
            for (k, (at, p)) in v.up.arrived(now).into_iter().enumerate() {
                arrivals.push((at, i, k, p));
            }
        }
        arrivals.sort_by_key(|(at, i, k, _)| (*at, *i, *k));
        for (at, i, _, payload) in arrivals {
            let instant = self.at(at);
            let v = &mut self.viewers[i];
            if matches!(v.server.state, ServerState::Closed) {
                continue;
            }
            v.server.last_heard = at;
            if matches!(v.server.state, ServerState::Closing(_)) {
                continue;
            }
            match payload {
                Payload::Datagram(bytes) => {
                    let ServerState::Serving(s) = &mut v.server.state else {
                        continue;
                    };
                    if let Some(Handled::World(event)) =
                        s.conv.handle(instant, Event::Datagram(&bytes))
                    {
                        self.world.handle(event);
                    }
                }
                Payload::Control { seq, bytes } => {
                    for msg in v.server.control_in.accept(seq, bytes) {
                        self.server_control(i, now, &msg);
                    }
                }
                Payload::Chunk { .. } => {}
                Payload::Close => self.server_close(i, now, None),
            }
        }
    }

    /// A control message in order at the server.
    pub(super) fn server_control(&mut self, i: ViewerId, now: Duration, bytes: &[u8]) {
        let Ok(msg) = messages::decode::<ClientMessage>(bytes) else {
            self.server_close(i, now, None); // not the protocol: the stream ends
            return;
        };
        let v = &mut self.viewers[i];
        match &mut v.server.state {
            ServerState::Closed | ServerState::Closing(_) => {}
            ServerState::Serving(s) => {
                if matches!(msg, ClientMessage::KeyFrame) {
                    v.stats.key_frame_requests += 1;
                }
                if s.conv.handle(self.epoch + now, Event::Control(msg)) == Some(Handled::Goodbye) {
                    self.server_close(i, now, None);
                }
            }
            ServerState::Waiting => {
                let ClientMessage::Hello(hello) = msg else {
                    self.server_close(i, now, None);
                    return;
                };
                if hello.version != VERSION {
                    let refused = ServerMessage::Refused(Reason::Version { server: VERSION });
                    self.server_close(i, now, Some(refused));
                    return;
                }
                let (vehicle, driver) = match hello.role {
                    Role::Driver => match self.world.handle(world_core::Event::Join) {
                        Some(id) => {
                            v.server.joined = Some(id);
                            (id, true)
                        }
                        None => {
                            let why = Reason::Unavailable("no room".into());
                            self.server_close(i, now, Some(ServerMessage::Refused(why)));
                            return;
                        }
                    },
                    Role::Spectator { follow } => {
                        let target = match follow {
                            Some(id) => self.snapshot.vehicles.iter().find(|v| v.id == id),
                            None => self.snapshot.vehicles.first(),
                        };
                        match target {
                            Some(t) => (t.id, false),
                            None => {
                                let why = Reason::Unavailable("no vehicle to follow".into());
                                self.server_close(i, now, Some(ServerMessage::Refused(why)));
                                return;
                            }
                        }
                    }
                };
                let w = welcome(&self.terrain, vehicle, self.snapshot.tick);
                server_control_send(v, now, &ServerMessage::Welcome(w));
                let role = ConvRole {
                    vehicle,
                    driver,
                    replay: false,
                };
                let now_i = self.epoch + now;
                let conv = Conversation::new(
                    &self.terrain,
                    self.height_step,
                    &hello,
                    ViewerLimits::default(),
                    role,
                    (now_i, self.epoch),
                );
                v.server.state = ServerState::Serving(Box::new(Serving {
                    conv,
                    streams: Vec::new(),
                    next_stream: 0,
                    made: VecDeque::new(),
                }));
            }
        }
    }

    /// The server ends viewer `i`'s connection: its core goes, and (once a last word, a
    /// refusal or a goodbye, if any, has had [`LAST_WORD`] to arrive) the connection closes and the world is told
    /// its driver left.
    pub(super) fn server_close(&mut self, i: ViewerId, now: Duration, last: Option<ServerMessage>) {
        let v = &mut self.viewers[i];
        match (&v.server.state, last) {
            (ServerState::Closed, _) => {}
            (ServerState::Closing(until), _) if now < *until => {}
            (ServerState::Waiting | ServerState::Serving(_), Some(msg)) => {
                v.server.state = ServerState::Closing(now + LAST_WORD);
                server_control_send(v, now, &msg);
            }
            _ => {
                v.server.state = ServerState::Closed;
                v.down.close();
                v.down.send(now, Payload::Close);
                if let Some(id) = v.server.joined.take() {
                    self.world.handle(world_core::Event::Leave(id));
                }
            }
        }
    }

    pub(super) fn tick(&mut self) {
        self.snapshot = Arc::new(self.world.tick());
        for v in &mut self.viewers {
            let ServerState::Serving(s) = &v.server.state else {
                continue;
            };
            if !s.conv.driver() {
                continue;
            }
            let vehicle = s.conv.vehicle();
            if let Some(veh) = self.snapshot.vehicles.iter().find(|x| x.id == vehicle) {
                v.track.push(TrackPoint {
                    tick: self.snapshot.tick,
                    applied: self.snapshot.applied_by(vehicle),
                    state: veh.state,
                });
            }
        }
    }

    /// Viewer `i`'s server side at `now`: the idle timeout, and a frame if one is due.
    pub(super) fn server_frames(&mut self, i: ViewerId, now: Duration) {
        let v = &mut self.viewers[i];
        let idle = now.saturating_sub(v.server.last_heard) >= IDLE_TIMEOUT;
        match v.server.state {
            ServerState::Closed => return,
            ServerState::Closing(until) if now >= until => {
                self.server_close(i, now, None);
                return;
            }
            _ if idle => {
                self.server_close(i, now, None);
                return;
            }
            _ => {}
        }
        let ServerState::Serving(s) = &mut v.server.state else {
            return;
        };
        let instant = self.epoch + now;
        let down = v.down.stats;
        s.conv.handle(
            instant,
            Event::Path {
                max_datagram: Some(MAX_DATAGRAM),
                lost: down.lost + down.dropped,
                sent: down.packets,
            },
        );
        let scene = Scene {
            terrain: &self.terrain,
            variance: &self.variance,
            scratch: &self.scratch,
        };
        // Heavy parts run in place: the cores take no virtual time.
        let step = match s.conv.frame(instant, &scene, &self.snapshot, &mut |b| b) {
            Step::Heavy(job) => {
                let done = job.run(&scene, || self.snapshot.clone());
                s.conv.finish(instant, &self.terrain, done)
            }
            other => other,
        };
        match step {
            Step::Idle | Step::Heavy(_) => {}
            Step::End(why) => {
                let why = match why {
                    End::VehicleLeft => "the vehicle followed has left",
                    End::Failed(why) => why,
                };
                let bye = ServerMessage::Bye(Reason::Unavailable(why.into()));
                self.server_close(i, now, Some(bye));
                return;
            }
            Step::Sent(sent) => {
                let mut mesh = Mesh::default();
                if let Some(core) = s.conv.core() {
                    core.mesh(&self.scratch, &mut mesh);
                }
                s.made.push_back(MadeFrame {
                    frame: sent.frame,
                    key: sent.key.is_some(),
                    triangles: sent.triangles as usize,
                    mesh: mesh_hash(&mesh.vertices, &mesh.indices),
                });
                while s.made.len() > MADE_KEPT {
                    s.made.pop_front();
                }
                v.stats.frames_made += 1;
                v.stats.key_frames_made += u64::from(sent.key.is_some());
                v.stats.largest_frame = v.stats.largest_frame.max(sent.bytes);
            }
        }
        while let Some(t) = s.conv.poll_transmit(instant) {
            match t {
                Transmit::Datagram { bytes, .. } => {
                    v.stats.datagram_frames += 1;
                    v.down.send(now, Payload::Datagram(bytes));
                }
                Transmit::Reset { frame } => {
                    if let Some(k) = s.streams.iter().position(|(f, _)| *f == frame) {
                        v.down.reset(s.streams.swap_remove(k).1);
                        v.stats.streams_reset += 1;
                    }
                }
                Transmit::Stream { frame, bytes, .. } => {
                    v.stats.stream_frames += 1;
                    let stream = s.next_stream;
                    s.next_stream += 1;
                    // Streams of frames long superseded are of no more use to reset.
                    s.streams.retain(|(f, _)| f + 64 > frame);
                    s.streams.push((frame, stream));
                    let count = bytes.len().div_ceil(MAX_DATAGRAM) as u32;
                    for (index, chunk) in bytes.chunks(MAX_DATAGRAM).enumerate() {
                        v.down.send(
                            now,
                            Payload::Chunk {
                                stream,
                                index: index as u32,
                                count,
                                bytes: chunk.to_vec(),
                            },
                        );
                    }
                }
            }
        }
    }
}

pub(super) fn server_control_send(v: &mut Viewer, now: Duration, msg: &ServerMessage) {
    v.down
        .send_control(now, &mut v.server.control_seq, encoded(msg));
}
