//! The server's side of the simulated network, composed as the `net` shell composes its
//! sans-IO cores: arrivals at the server (key datagrams through the [`KeyGate`] into the
//! world, control messages in order into the [`Mailbox`]), the handshake, the world's
//! tick, and each viewer's frames (made by its [`ViewerCore`], sent as `net::viewer` sends
//! them), the idle timeout and the last word.

use std::collections::VecDeque;
use std::time::Duration;

use roam_protocol::messages::{self, ClientMessage, Reason, Role, ServerMessage, VERSION, Welcome};
use roam_server::Terrain;
use roam_server::sim::world::VehicleId;
use roam_server::sim::world_core;
use roam_server::tessellate::Mesh;
use roam_server::viewer::conversation::{Control, KeyGate, Mailbox, frame_message};
use roam_server::viewer::{Scene, ViewerCore, ViewerLimits};

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
                    if let Some(event) = s.gate.admit(&bytes, instant)
                        && s.driver
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
                if s.mailbox.push(msg) == Control::End {
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
                let core = ViewerCore::for_hello(
                    &self.terrain,
                    self.height_step,
                    &hello,
                    ViewerLimits::default(),
                );
                let rate = ViewerCore::frame_rate(&hello, ViewerLimits::default());
                v.server.state = ServerState::Serving(Box::new(Serving {
                    core,
                    mailbox: Mailbox::default(),
                    gate: KeyGate::new(vehicle),
                    vehicle,
                    driver,
                    seen: false,
                    period: Duration::from_secs_f64(1.0 / f64::from(rate)),
                    next_frame: now,
                    in_flight: None,
                    key_in_flight: None,
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
        self.snapshot = self.world.tick();
        for v in &mut self.viewers {
            let ServerState::Serving(s) = &v.server.state else {
                continue;
            };
            if !s.driver {
                continue;
            }
            if let Some(veh) = self.snapshot.vehicles.iter().find(|x| x.id == s.vehicle) {
                v.track.push(TrackPoint {
                    tick: self.snapshot.tick,
                    applied: self.snapshot.applied_by(s.vehicle),
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
        if now < s.next_frame {
            return;
        }
        // The shell's interval, missed ticks skipped.
        s.next_frame += s.period;
        while s.next_frame <= now {
            s.next_frame += s.period;
        }
        let Some(veh) = self.snapshot.vehicles.iter().find(|x| x.id == s.vehicle) else {
            if s.seen {
                let why = Reason::Unavailable("the vehicle followed has left".into());
                self.server_close(i, now, Some(ServerMessage::Bye(why)));
            }
            return; // a new driver's vehicle appears with the next tick
        };
        s.seen = true;
        for event in s.mailbox.drain() {
            s.core.handle(event);
        }
        let scene = Scene {
            terrain: &self.terrain,
            variance: &self.variance,
            scratch: &self.scratch,
        };
        let made = s.core.make_frame(&scene, &veh.state);
        let acked = s.core.acked();
        let pending_key = s.core.pending_key();
        let frame = made.frame;
        let key = made.base.is_none();
        let triangles = made.triangles as usize;
        let mut mesh = Mesh::default();
        s.core.mesh(&self.scratch, &mut mesh);
        s.made.push_back(MadeFrame {
            frame,
            key,
            triangles,
            mesh: mesh_hash(&mesh.vertices, &mesh.indices),
        });
        while s.made.len() > MADE_KEPT {
            s.made.pop_front();
        }
        v.stats.frames_made += 1;
        v.stats.key_frames_made += u64::from(key);
        let msg = frame_message(&self.terrain, &self.snapshot, made, s.vehicle, s.driver);
        let mut bytes = Vec::new();
        if messages::encode(&msg, &mut bytes).is_err() {
            let why = Reason::Unavailable("a frame over the message limit".into());
            self.server_close(i, now, Some(ServerMessage::Bye(why)));
            return;
        }
        // Latest frame wins: the change frame's stream in flight is reset unless its frame
        // was acknowledged; the key frame's only once it is no longer pending (superseded,
        // or another asked for) and unless acknowledged.
        let unacked = |sent: u64| acked.is_none_or(|a| a < sent);
        let key_done = s
            .key_in_flight
            .take_if(|&mut (_, sent)| pending_key != Some(sent));
        for (stream, sent) in key_done.into_iter().chain(s.in_flight.take()) {
            if unacked(sent) {
                v.down.reset(stream);
                v.stats.streams_reset += 1;
            }
        }
        v.stats.largest_frame = v.stats.largest_frame.max(bytes.len());
        // A change frame that fits goes as a datagram; a key frame always on a stream.
        if !key && bytes.len() <= MAX_DATAGRAM {
            v.stats.datagram_frames += 1;
            v.down.send(now, Payload::Datagram(bytes));
            return;
        }
        v.stats.stream_frames += 1;
        let stream = s.next_stream;
        s.next_stream += 1;
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
        if key {
            s.key_in_flight = Some((stream, frame));
        } else {
            s.in_flight = Some((stream, frame));
        }
    }
}

pub(super) fn server_control_send(v: &mut Viewer, now: Duration, msg: &ServerMessage) {
    v.down
        .send_control(now, &mut v.server.control_seq, encoded(msg));
}
