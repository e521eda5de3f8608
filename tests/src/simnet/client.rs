//! The viewer's side of the simulated network, composed as `session.rs` composes the
//! viewer's sans-IO cores: frames offered to its [`ClientCore`] as they arrive (datagrams,
//! and each stream once read to its end), its [`KeyCore`]'s key datagram every 10 ms, the
//! frame taken (each decoded mesh checked against the server's cut for that frame), and its
//! control messages, in order.

use std::time::{Duration, Instant};

use roam_client::core::{ClientCore, Taken};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{self, ClientMessage, ServerMessage};

use super::path::Payload;
use super::state::{
    Assembly, EARLY_BYTES, IDLE_TIMEOUT, ServerState, Sim, TICK, TakenFrame, Viewer, ViewerId,
    encoded, mesh_hash,
};

impl Sim {
    /// Viewer `i`'s client side at `now`: arrivals, the idle timeout, keys, a take, and
    /// control messages.
    pub(super) fn client_step(&mut self, i: ViewerId, now: Duration) {
        let epoch = self.epoch;
        let v = &mut self.viewers[i];
        let arrivals = v.down.arrived(now);
        if v.client.closed.is_some() {
            return;
        }
        for (at, payload) in arrivals {
            v.client.last_heard = at;
            match payload {
                Payload::Datagram(bytes) => client_offer(v, epoch + at, bytes),
                Payload::Chunk {
                    stream,
                    index,
                    count,
                    bytes,
                } => {
                    let a = v.client.streams.entry(stream).or_insert_with(|| Assembly {
                        parts: vec![None; count as usize],
                        have: 0,
                    });
                    let Some(slot) = a.parts.get_mut(index as usize) else {
                        continue;
                    };
                    if slot.is_none() {
                        *slot = Some(bytes);
                        a.have += 1;
                    }
                    if a.have == a.parts.len() {
                        let a = v.client.streams.remove(&stream).expect("just found");
                        let whole: Vec<u8> = a.parts.into_iter().flatten().flatten().collect();
                        v.stats.streams_completed += 1;
                        client_offer(v, epoch + at, whole);
                    }
                }
                Payload::Control { seq, bytes } => {
                    for msg in v.client.control_in.accept(seq, bytes) {
                        match messages::decode::<ServerMessage>(&msg) {
                            Ok(ServerMessage::Welcome(w)) => {
                                let mut core = ClientCore::new(&w, v.client.hello.budget)
                                    .expect("the welcome's grid is one the protocol has");
                                // A driver acknowledges its frames in its key datagrams,
                                // as `roam-client` does.
                                if v.client.steps.is_some() {
                                    core.set_acks_in_datagrams();
                                }
                                v.client.core = Some(core);
                                v.client.welcome = Some(w);
                                v.client.next_key = now;
                                for bytes in std::mem::take(&mut v.client.early) {
                                    client_offer(v, epoch + at, bytes);
                                }
                            }
                            // Colour, an edge's news and a replay's (`serve`'s live
                            // cores send none).
                            Ok(
                                ServerMessage::ColorTile { .. }
                                | ServerMessage::NormalTile { .. }
                                | ServerMessage::ColorWindow { .. }
                                | ServerMessage::World(_)
                                | ServerMessage::Following(_)
                                | ServerMessage::Replay(_),
                            ) => {}
                            Ok(ServerMessage::Refused(r) | ServerMessage::Bye(r)) => {
                                v.client.closed = Some(format!("{r:?}"));
                            }
                            Err(e) => v.client.closed = Some(format!("control stream: {e}")),
                        }
                    }
                }
                Payload::Close => {
                    v.client
                        .closed
                        .get_or_insert_with(|| "the server closed the connection".into());
                }
            }
        }
        // A stream the server reset that can no longer complete (none of its packets is on
        // the way) ends: its reset arrives behind its last packet.
        let down = &v.down;
        v.client.streams.retain(|&s, _| !down.abandoned(s));
        if v.client.closed.is_none() && now.saturating_sub(v.client.last_heard) >= IDLE_TIMEOUT {
            v.client.closed = Some("idle timeout".into());
        }
        if v.client.closed.is_some() {
            v.up.close();
            return;
        }
        let Some(core) = v.client.core.as_mut() else {
            return;
        };
        // A key datagram every 10 ms.
        if let Some(steps) = &v.client.steps {
            while v.client.next_key <= now {
                let step = steps.get(v.client.next_step).copied().unwrap_or(KeyStep {
                    held: Keys::NONE,
                    pressed: Keys::NONE,
                });
                v.client.next_step += 1;
                let acked = core.acks_in_datagrams().then(|| core.acked()).flatten();
                let datagram = v.client.keys.key_datagram(step, epoch + now, acked);
                v.up.send(now, Payload::Datagram(encoded(&datagram)));
                v.stats.key_datagrams += 1;
                v.client.next_key += TICK;
            }
        }
        if core.has_frame() {
            let decode = v.client.skip_decoding == 0;
            v.client.skip_decoding = v.client.skip_decoding.saturating_sub(1);
            match core.take(decode) {
                Ok(Taken::Frame(mut r)) => {
                    if let Some(seq) = r.input_seq {
                        r.latencies_ms = v.client.keys.applied(seq, r.arrived);
                        v.stats.key_latencies_ms.extend(&r.latencies_ms);
                    }
                    let made = match &v.server.state {
                        ServerState::Serving(s) => {
                            s.made.iter().find(|m| m.frame == r.frame).copied()
                        }
                        _ => None,
                    };
                    let key = made.is_some_and(|m| m.key);
                    if decode && let Some(m) = made {
                        let mesh = core.mesh();
                        v.stats.meshes_checked += 1;
                        let same = mesh.triangle_count() == m.triangles
                            && mesh_hash(&mesh.vertices, &mesh.indices) == m.mesh;
                        v.stats.mesh_mismatches += u64::from(!same);
                    }
                    let st = &mut v.stats;
                    st.frames += 1;
                    st.key_frames += u64::from(key);
                    st.max_triangles = st.max_triangles.max(r.triangles);
                    if let Some(last) = st.last_frame_at {
                        st.largest_gap = st.largest_gap.max(now - last);
                    }
                    st.first_frame_at.get_or_insert(now);
                    st.last_frame_at = Some(now);
                    v.taken.push(TakenFrame {
                        at: now,
                        frame: r.frame,
                        tick: r.tick,
                        triangles: r.triangles,
                        key,
                        decoded: decode,
                    });
                    v.latest = Some(r);
                }
                Ok(Taken::Nothing) => {}
                Ok(Taken::Dropped(why)) => {
                    v.stats.decode_errors += 1;
                    v.dropped.push(format!("{now:?}: {why}"));
                }
                Err(e) => {
                    v.stats.inconsistent += 1;
                    v.dropped.push(format!("{now:?}: {e}"));
                }
            }
        }
        client_flush(v, now);
    }
}

/// Viewer `v`'s frame bytes arrived at `at`: to the core, or kept until the welcome.
pub(super) fn client_offer(v: &mut Viewer, at: Instant, bytes: Vec<u8>) {
    match v.client.core.as_mut() {
        Some(core) => core.offer(&bytes, at),
        None => {
            v.client.early.push_back(bytes);
            while v.client.early.iter().map(Vec::len).sum::<usize>() > EARLY_BYTES {
                v.client.early.pop_front();
            }
        }
    }
}

/// The viewer sends what its core has for the control stream.
pub(super) fn client_flush(v: &mut Viewer, now: Duration) {
    while let Some(m) = v.client.core.as_mut().and_then(ClientCore::poll_control) {
        client_control(v, now, &m);
    }
}

pub(super) fn client_control(v: &mut Viewer, now: Duration, msg: &ClientMessage) {
    v.up.send_control(now, &mut v.client.control_seq, encoded(msg));
}
