//! One viewer's connection: the handshake, its key datagrams and control messages, and its
//! frames, each tessellated for its own camera and sent on a stream of its own; a frame not
//! yet delivered when the next is ready is abandoned (latest frame wins).

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use roam_protocol::messages::{
    ClientMessage, Frame, KeyDatagram, Reason, Role, ServerMessage, VERSION, VehicleView,
    ViewChange, Welcome,
};
use roam_protocol::{BitSet, Grid, MeshEncoder};
use tokio::sync::oneshot;

use super::world_loop::{Event, Snapshot};
use super::{Shared, wire};
use crate::camera::Camera;
use crate::tessellate::{Limits, Mesh, Scales, Tessellator};
use crate::world::VehicleId;

/// The most triangles a viewer may ask for.
pub const MAX_BUDGET: u32 = 1 << 20;
/// Frames kept as possible bases, per viewer.
const BASES: usize = 16;
/// Key datagrams a driver may send per second, and in a burst (a viewer sends 100 a
/// second).
const KEY_RATE: f64 = 250.0;
const KEY_BURST: f64 = 50.0;
/// Colour-map bytes per chunk.
const CHUNK: usize = 64 << 10;

/// What the viewer's control messages change.
#[derive(Default)]
struct Control {
    budget: u32,
    /// The newest frame the viewer decoded.
    acked: Option<u64>,
    /// The viewer's camera, if it said how it differs from the default.
    view: Option<ViewChange>,
}

/// `camera` changed as the viewer asked; anything out of range is clamped, anything not a
/// number ignored.
fn apply_view(camera: &mut Camera, v: &ViewChange) {
    if v.pitch_deg.is_finite() {
        camera.pitch_deg = f64::from(v.pitch_deg).clamp(-89.0, 89.0);
    }
    // Slightly below the hover altitude too: the viewer's damped eye lags a climb.
    if v.eye_above.is_finite() {
        camera.eye[1] += f64::from(v.eye_above).clamp(-10.0, 1000.0);
    }
    camera.width = v.viewport[0].clamp(1, 16_384);
    camera.height = v.viewport[1].clamp(1, 16_384);
}

/// The close codes a connection ends with.
pub mod close {
    pub const SHUTDOWN: u32 = 1;
    pub const REFUSED: u32 = 2;
    pub const PROTOCOL: u32 = 3;
    pub const BYE: u32 = 4;
}

fn refuse(conn: &quinn::Connection, code: u32, why: &str) {
    conn.close(code.into(), why.as_bytes());
}

/// Sends a last message (a refusal, a goodbye) and gives it a moment to arrive before the
/// connection closes (closing drops what is unsent).
async fn last_word(send: &mut quinn::SendStream, msg: &ServerMessage) {
    if wire::write(send, msg).await.is_ok() && send.finish().is_ok() {
        let _ = tokio::time::timeout(Duration::from_millis(250), send.stopped()).await;
    }
}

/// Serves one connection to its end.
pub async fn serve(conn: quinn::Connection, shared: Arc<Shared>) {
    let accepted = tokio::time::timeout(Duration::from_secs(5), conn.accept_bi()).await;
    let Ok(Ok((mut send, mut recv))) = accepted else {
        refuse(&conn, close::PROTOCOL, "no control stream within 5 s");
        return;
    };
    let hello = match tokio::time::timeout(
        Duration::from_secs(5),
        wire::read::<ClientMessage>(&mut recv, 4096),
    )
    .await
    {
        Ok(Ok(ClientMessage::Hello(h))) => h,
        _ => {
            refuse(&conn, close::PROTOCOL, "expected a hello");
            return;
        }
    };
    let reply = |reason: Reason| ServerMessage::Refused(reason);
    if hello.version != VERSION {
        last_word(&mut send, &reply(Reason::Version { server: VERSION })).await;
        refuse(&conn, close::REFUSED, "protocol version");
        return;
    }
    if !constant_time_eq(hello.token.as_bytes(), shared.token.as_bytes()) {
        last_word(&mut send, &reply(Reason::WrongToken)).await;
        refuse(&conn, close::REFUSED, "wrong token");
        return;
    }
    // A driver gets a vehicle; a spectator follows one.
    let (vehicle, driver) = match hello.role {
        Role::Driver => {
            let (tx, rx) = oneshot::channel();
            if shared.events.send(Event::Join { reply: tx }).is_err() {
                refuse(&conn, close::SHUTDOWN, "shutting down");
                return;
            }
            match rx.await {
                Ok(id) => (id, true),
                Err(_) => {
                    refuse(&conn, close::SHUTDOWN, "shutting down");
                    return;
                }
            }
        }
        Role::Spectator { follow } => {
            let snap = shared.snapshots.borrow().clone();
            let target = match follow {
                Some(id) => snap.vehicles.iter().find(|v| v.id == id),
                None => snap.vehicles.first(),
            };
            match target {
                Some(v) => (v.id, false),
                None => {
                    let why = Reason::Unavailable("no vehicle to follow".into());
                    last_word(&mut send, &reply(why)).await;
                    refuse(&conn, close::REFUSED, "no vehicle to follow");
                    return;
                }
            }
        }
    };
    let leave = Leave {
        events: shared.events.clone(),
        vehicle: driver.then_some(vehicle),
    };
    if welcome(&mut send, &shared, vehicle).await.is_err() {
        return;
    }
    let control = Arc::new(Mutex::new(Control {
        budget: hello.budget.clamp(2, MAX_BUDGET),
        acked: None,
        view: None,
    }));
    let keys = tokio::spawn(read_keys(conn.clone(), shared.clone(), vehicle, driver));
    let ctl = tokio::spawn(read_control(recv, control.clone()));
    let fov = f64::from(hello.fov_y_deg);
    let camera = Camera {
        eye: [0.0; 3],
        yaw_deg: 0.0,
        pitch_deg: crate::flyover::PITCH_DEG,
        // A field of view that is not a number is taken as the usual 60°.
        fov_y_deg: if fov.is_finite() {
            fov.clamp(1.0, 179.0)
        } else {
            60.0
        },
        width: hello.viewport[0].clamp(1, 16_384),
        height: hello.viewport[1].clamp(1, 16_384),
    };
    let rate = hello.frame_rate.clamp(1, 240);
    tokio::select! {
        end = frames(&conn, &shared, control, camera, rate, vehicle, driver) => {
            let why = match end {
                FramesEnd::ConnectionLost => None,
                FramesEnd::VehicleLeft => Some("the vehicle followed has left"),
                FramesEnd::Failed(why) => Some(why),
            };
            if let Some(why) = why {
                let bye = ServerMessage::Bye(Reason::Unavailable(why.into()));
                last_word(&mut send, &bye).await;
                conn.close(close::BYE.into(), why.as_bytes());
            }
        }
        _ = ctl => conn.close(close::BYE.into(), b"bye"),
        _ = conn.closed() => {}
        _ = shared.shutting_down() => {
            last_word(&mut send, &ServerMessage::Bye(Reason::Shutdown)).await;
            conn.close(close::SHUTDOWN.into(), b"the server is shutting down");
        }
    }
    keys.abort();
    drop(leave);
}

/// Tells the world a driver left, however the connection ended.
struct Leave {
    events: std::sync::mpsc::Sender<Event>,
    vehicle: Option<VehicleId>,
}

impl Drop for Leave {
    fn drop(&mut self) {
        if let Some(vehicle) = self.vehicle {
            let _ = self.events.send(Event::Leave { vehicle });
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn welcome(
    send: &mut quinn::SendStream,
    shared: &Shared,
    vehicle: VehicleId,
) -> Result<(), wire::WireError> {
    let t = &shared.terrain;
    let m = &t.map;
    let snap = shared.snapshots.borrow().clone();
    let w = Welcome {
        version: VERSION,
        levels: t.heights.levels() as u8,
        h_scale: m.h_scale,
        v_scale: m.v_scale,
        sun_dir: m.sun_dir.map(|v| v as f32),
        sun_color: m.sun_color,
        fog_density: m.fog_density as f32,
        fog_color: m.fog_color,
        water_level: m.water_level.map(|v| v as f32),
        vehicle,
        color_cells: t.color.cells(),
        color_bytes: shared.color_map.len() as u32,
        tick: snap.tick,
    };
    wire::write(send, &ServerMessage::Welcome(w)).await?;
    for (k, chunk) in shared.color_map.chunks(CHUNK).enumerate() {
        let msg = ServerMessage::ColorMap {
            offset: (k * CHUNK) as u32,
            data: chunk.to_vec(),
        };
        wire::write(send, &msg).await?;
    }
    Ok(())
}

/// Key datagrams to the world; anything that is not one is ignored. A driver may send
/// [`KEY_RATE`] a second (a burst of [`KEY_BURST`]); more are dropped here, so one flooding
/// viewer cannot crowd the others out of the world's key backlog.
async fn read_keys(conn: quinn::Connection, shared: Arc<Shared>, vehicle: VehicleId, driver: bool) {
    let mut tokens = KEY_BURST;
    let mut refilled = tokio::time::Instant::now();
    while let Ok(bytes) = conn.read_datagram().await {
        let now = tokio::time::Instant::now();
        tokens = (tokens + (now - refilled).as_secs_f64() * KEY_RATE).min(KEY_BURST);
        refilled = now;
        if tokens < 1.0 {
            continue;
        }
        tokens -= 1.0;
        let Ok(d) = roam_protocol::messages::decode::<KeyDatagram>(&bytes) else {
            continue;
        };
        if driver {
            // A full backlog drops this datagram; its states come again in later ones.
            let _ = shared.keys.try_send((vehicle, d.states));
        }
    }
}

/// Control messages until the viewer says goodbye or sends something that is not one.
async fn read_control(mut recv: quinn::RecvStream, control: Arc<Mutex<Control>>) {
    while let Ok(msg) = wire::read::<ClientMessage>(&mut recv, 4096).await {
        let mut c = control.lock().unwrap_or_else(|e| e.into_inner());
        match msg {
            ClientMessage::Budget(b) => c.budget = b.clamp(2, MAX_BUDGET),
            ClientMessage::Ack { frame } => c.acked = Some(c.acked.map_or(frame, |a| a.max(frame))),
            ClientMessage::KeyFrame => c.acked = None,
            ClientMessage::View(v) => c.view = Some(v),
            ClientMessage::Bye(_) | ClientMessage::Hello(_) => return,
        }
    }
}

/// The viewer's tessellation state, moved to a blocking thread for each frame.
struct Maker {
    tess: Tessellator,
    mesh: Mesh,
    encoder: MeshEncoder,
    grid: Grid,
    bases: VecDeque<(u64, BitSet)>,
}

impl Maker {
    /// Tessellates for `camera` and codes the mesh against the newest acknowledged base.
    fn make(
        &mut self,
        shared: &Shared,
        camera: &Camera,
        budget: u32,
        acked: Option<u64>,
        frame: u64,
    ) -> (Option<u64>, Vec<u8>) {
        let t = &shared.terrain;
        let scales = Scales {
            h: t.map.h_scale,
            v: t.map.v_scale,
        };
        let limits = Limits {
            budget,
            threshold_px: 0.0,
        };
        self.tess.tessellate(
            &t.heights,
            &shared.variance,
            scales,
            camera,
            limits,
            &mut self.mesh,
        );
        let mut split = BitSet::default();
        self.tess.split_set(&self.grid, &mut split);
        let base = acked.and_then(|a| self.bases.iter().find(|(f, _)| *f == a));
        let mut payload = Vec::new();
        self.encoder
            .encode(
                &split,
                t.heights.samples(),
                base.map(|(_, b)| b),
                &mut payload,
            )
            .expect("the tessellator's meshes are conforming");
        let base = base.map(|(f, _)| *f);
        self.bases.push_back((frame, split));
        if self.bases.len() > BASES {
            self.bases.pop_front();
        }
        (base, payload)
    }
}

/// Why a viewer's frames stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FramesEnd {
    /// The vehicle it followed (or drove) is gone.
    VehicleLeft,
    /// The connection can take no more streams.
    ConnectionLost,
    /// The server could not make a frame: said to the viewer, never a panic.
    Failed(&'static str),
}

async fn frames(
    conn: &quinn::Connection,
    shared: &Arc<Shared>,
    control: Arc<Mutex<Control>>,
    mut camera: Camera,
    rate: u16,
    vehicle: VehicleId,
    driver: bool,
) -> FramesEnd {
    let grid = Grid::new(shared.terrain.heights.levels()).expect("data sets have 1 ..= 15 levels");
    let mut maker = Some(Maker {
        tess: Tessellator::new(shared.terrain.heights.side()),
        mesh: Mesh::default(),
        encoder: MeshEncoder::with_step(grid, shared.height_step),
        grid,
        bases: VecDeque::new(),
    });
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / f64::from(rate)));
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    type InFlight = (
        oneshot::Sender<()>,
        tokio::task::JoinHandle<Option<quinn::SendStream>>,
        u64,
    );
    let mut in_flight: Option<InFlight> = None;
    let mut seen = false;
    let mut frame = 0u64;
    loop {
        interval.tick().await;
        let snap: Arc<Snapshot> = shared.snapshots.borrow().clone();
        let Some(v) = snap.vehicles.iter().find(|v| v.id == vehicle) else {
            if seen {
                return FramesEnd::VehicleLeft;
            }
            continue; // a new driver's vehicle appears with the next tick
        };
        seen = true;
        let altitude =
            |s: &crate::physics::VehicleState| crate::physics::altitude(&*shared.terrain, s.x, s.z);
        camera.eye = [v.state.x, altitude(&v.state), v.state.z];
        camera.yaw_deg = v.state.heading;
        let (budget, acked, view) = {
            let c = control.lock().unwrap_or_else(|e| e.into_inner());
            (c.budget, c.acked, c.view)
        };
        let mut cam = camera;
        if let Some(v) = &view {
            apply_view(&mut cam, v);
        }
        let (mut m, shared2) = (maker.take().expect("put back below"), shared.clone());
        let Ok((m, base, mesh)) = tokio::task::spawn_blocking(move || {
            let (base, mesh) = m.make(&shared2, &cam, budget, acked, frame);
            (m, base, mesh)
        })
        .await
        else {
            return FramesEnd::Failed("the frame maker failed");
        };
        maker = Some(m);
        let msg = Frame {
            frame,
            base,
            tick: snap.tick,
            vehicles: snap
                .vehicles
                .iter()
                .map(|v| VehicleView {
                    id: v.id,
                    x: v.state.x,
                    z: v.state.z,
                    y: altitude(&v.state),
                    speed: v.state.speed,
                    heading: v.state.heading,
                })
                .collect(),
            input_seq: driver
                .then(|| {
                    snap.applied
                        .iter()
                        .find(|(id, _)| *id == vehicle)
                        .map(|&(_, s)| s)
                })
                .flatten(),
            mesh,
        };
        let mut bytes = Vec::new();
        if roam_protocol::messages::encode(&msg, &mut bytes).is_err() {
            return FramesEnd::Failed("a frame over the message limit");
        }
        // Latest frame wins: the previous frame's stream is reset unless the viewer has
        // acknowledged it, whether it is still being written or already handed to quinn
        // (a finished stream still waits in the send buffer on a slow link).
        if let Some((cancel, task, sent)) = in_flight.take() {
            if task.is_finished() {
                if let Ok(Some(mut stream)) = task.await
                    && acked.is_none_or(|a| a < sent)
                {
                    let _ = stream.reset(0u32.into());
                }
            } else {
                let _ = cancel.send(());
            }
        }
        let Ok(mut stream) = conn.open_uni().await else {
            return FramesEnd::ConnectionLost;
        };
        let _ = stream.set_priority(frame as i32);
        let (cancel, cancelled) = oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            tokio::select! {
                r = stream.write_all(&bytes) => {
                    if r.is_ok() && stream.finish().is_ok() {
                        return Some(stream);
                    }
                    None
                }
                _ = cancelled => {
                    let _ = stream.reset(0u32.into());
                    None
                }
            }
        });
        in_flight = Some((cancel, task, frame));
        frame += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_view_change_is_clamped_and_nan_ignored() {
        let base = Camera {
            eye: [10.0, 20.0, 30.0],
            yaw_deg: 0.0,
            pitch_deg: crate::flyover::PITCH_DEG,
            fov_y_deg: 60.0,
            width: 1280,
            height: 720,
        };
        let check = |v: ViewChange, pitch: f64, eye_y: f64, size: (u32, u32)| {
            let mut c = base;
            apply_view(&mut c, &v);
            assert_eq!(
                (c.pitch_deg, c.eye[1], (c.width, c.height)),
                (pitch, eye_y, size)
            );
        };
        let v = |pitch_deg, eye_above, viewport| ViewChange {
            pitch_deg,
            eye_above,
            viewport,
        };
        check(v(12.0, 1.5, [800, 600]), 12.0, 21.5, (800, 600));
        check(
            v(f32::NAN, f32::INFINITY, [0, 99_999]),
            base.pitch_deg,
            20.0,
            (1, 16_384),
        );
        check(v(-500.0, -30.0, [640, 480]), -89.0, 10.0, (640, 480));
    }
}
