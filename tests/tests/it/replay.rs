//! Watching a recording end to end (`serve --replay`): a real server on loopback playing a
//! recorded three-driver session, headless viewers over QUIC. Every frame shows the
//! recorded world at its tick; a driver's hello is served as a spectator's; the first
//! viewer holds the controls and the second is told so; pause holds the clock while frames
//! flow; a seek lands on the recorded world; a spectator follows another vehicle.

use std::sync::Arc;

use roam_client::session::{KeySource, Session};
use roam_protocol::messages::{ReplayControl, VehicleView};
use roam_server::Terrain;
use roam_server::net::Options;
use roam_server::net::replay::Replaying;
use roam_server::sim::physics::Keys;
use roam_server::sim::recorder::RecordedWorld;
use roam_server::sim::watch;
use roam_server::sim::world::{self, Inputs, Vehicle, World};
use roam_tests::fixtures::{self, frame, status_when};

const TICKS: u64 = 3000;

/// Three drivers, one joining late and one leaving, recorded; and the world at every tick
/// (after that many steps, before that tick's joins and leaves).
fn session(terrain: &Arc<Terrain>) -> (Vec<u8>, Vec<Vec<Vehicle>>) {
    let mut w = World::new(terrain.clone());
    w.add(0, world::start_state(terrain, 0))
        .expect("on the map");
    w.add(1, world::start_state(terrain, 1))
        .expect("on the map");
    let mut rec = RecordedWorld::start(w, Vec::new(), terrain.content_hash(), 100)
        .expect("memory does not fail");
    let pattern = [Keys::UP, Keys::UP.union(Keys::LEFT), Keys::UP, Keys::DOWN];
    let mut inputs = Inputs::new();
    let mut worlds = Vec::new();
    for tick in 0..TICKS {
        worlds.push(rec.world().vehicles().to_vec());
        match tick {
            600 => rec.join(2, world::start_state(terrain, 2)).expect("joins"),
            2000 => rec.leave(1).expect("leaves"),
            _ => {}
        }
        for v in rec.world().vehicles() {
            inputs.set(v.id, pattern[(tick / 90 + u64::from(v.id)) as usize % 4]);
        }
        rec.step(&inputs).expect("memory does not fail");
    }
    worlds.push(rec.world().vehicles().to_vec());
    let (_, bytes) = rec.finish().expect("memory does not fail");
    (bytes, worlds)
}

/// The vehicles as a frame shows them.
fn seen(vehicles: &[Vehicle], terrain: &Terrain) -> Vec<VehicleView> {
    vehicles
        .iter()
        .map(|v| VehicleView {
            id: v.id,
            x: v.state.x,
            z: v.state.z,
            y: roam_server::sim::physics::altitude(terrain, v.state.x, v.state.z),
            speed: v.state.speed,
            heading: v.state.heading,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recorded_session_watched_as_recorded_with_its_controls() {
    let terrain = fixtures::flat();
    let (bytes, worlds) = session(&terrain);
    let w = watch::open_bytes(&bytes, terrain.clone(), &terrain.content_hash()).expect("opens");
    let r = fixtures::serve(terrain.clone(), |o| Options {
        replay: Some(Replaying {
            watch: w,
            control_token: None,
            follow: None,
        }),
        ..o
    });
    let hello = fixtures::driver_hello(&r.token);
    let s = Session::join(r.server.addr, r.fingerprint, hello, KeySource::None)
        .await
        .expect("joins");
    assert_eq!(
        s.welcome().ticket,
        None,
        "a driver's hello is served as a spectator's"
    );
    let status = status_when(&s, "the replay's status", |st| st.replay.is_some()).await;
    let rs = status.replay.expect("waited for");
    assert_eq!((rs.start, rs.end, rs.speed), (0, TICKS, 4));
    assert!(rs.control, "the first viewer holds the controls");
    // Every frame is the recorded world at its tick.
    let mut ticks = Vec::new();
    for _ in 0..40 {
        let f = frame(&s).await;
        assert_eq!(
            f.vehicles,
            seen(&worlds[f.tick as usize], &terrain),
            "tick {}",
            f.tick
        );
        ticks.push(f.tick);
    }
    assert!(
        ticks.windows(2).all(|t| t[0] <= t[1]),
        "the clock runs forward"
    );
    // Paused: frames keep coming, at one tick.
    s.replay_control(ReplayControl::Pause);
    let st = status_when(&s, "paused", |st| {
        st.replay.as_ref().is_some_and(|r| r.paused)
    })
    .await;
    // The clock where it stopped (frames made before the pause may still come first).
    let stopped = st.replay.expect("waited for").tick;
    until_tick(&s, stopped).await;
    for _ in 0..10 {
        assert_eq!(frame(&s).await.tick, stopped, "paused");
    }
    // A seek, paused: the frames show the recorded world there.
    for target in [2500, 700, 1999, 2000, 5] {
        let f = seek_to(&s, target).await;
        assert_eq!(f.vehicles, seen(&worlds[target as usize], &terrain));
    }
    // A second viewer is told who holds the controls.
    let hello = fixtures::driver_hello(&r.token);
    let other = Session::join(r.server.addr, r.fingerprint, hello, KeySource::None)
        .await
        .expect("joins");
    let st = status_when(&other, "the replay's status", |st| st.replay.is_some()).await;
    let theirs = st.replay.expect("waited for");
    assert!(!theirs.control);
    assert!(theirs.paused, "one clock");
    assert!(
        theirs.controller.starts_with("127.0.0.1:"),
        "{}",
        theirs.controller
    );
    // To the next join, then a spectator follows the vehicle that joined.
    s.replay_control(ReplayControl::SeekMark { forward: true });
    let f = until_tick(&s, 600).await;
    assert_eq!(f.vehicles.len(), 2, "the join shows from the next tick");
    seek_to(&s, 601).await;
    assert_ne!(s.vehicle(), 2);
    s.follow(2);
    status_when(&s, "following vehicle 2", |st| st.welcome.vehicle == 2).await;
    assert_eq!(s.vehicle(), 2);
    for _ in 0..5 {
        let f = frame(&s).await;
        assert!(f.vehicles.iter().any(|v| v.id == 2));
    }
    // Resumed at 8× to the end: the last state is held.
    s.replay_control(ReplayControl::Speed(32));
    s.replay_control(ReplayControl::Seek(TICKS - 100));
    s.replay_control(ReplayControl::Resume);
    let f = until_tick(&s, TICKS).await;
    assert_eq!(f.vehicles, seen(&worlds[TICKS as usize], &terrain));
    let outcome = roam_server::sim::replay::replay(
        &roam_server::sim::recording::parse(&bytes).expect("whole"),
        terrain.clone(),
        &terrain.content_hash(),
    )
    .expect("replays");
    assert_eq!(f.vehicles, seen(&outcome.vehicles, &terrain));
    other.quit().await;
    s.quit().await;
    r.server.shutdown().await.expect("stops");
}

/// A session still being written (`--follow`): watched up to its newest whole tick, and on
/// as the file grows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_growing_recording_is_followed() {
    use std::io::Write;
    let terrain = fixtures::flat();
    let (bytes, worlds) = session(&terrain);
    let dir = std::env::temp_dir().join(format!("roam-follow-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a temp dir");
    let path = dir.join("growing.rec");
    let half = bytes.len() / 2 + 7; // inside a record
    std::fs::write(&path, &bytes[..half]).expect("written");
    let (w, follow) =
        roam_server::net::replay::open_following(&path, terrain.clone(), &terrain.content_hash())
            .expect("opens");
    let r = fixtures::serve(terrain.clone(), |o| Options {
        replay: Some(Replaying {
            watch: w,
            control_token: None,
            follow: Some(follow),
        }),
        ..o
    });
    let hello = fixtures::driver_hello(&r.token);
    let s = Session::join(r.server.addr, r.fingerprint, hello, KeySource::None)
        .await
        .expect("joins");
    let st = status_when(&s, "the replay's status", |st| st.replay.is_some()).await;
    let end = st.replay.expect("waited for").end;
    assert!(end > 0 && end < TICKS, "part of the session: {end}");
    s.replay_control(ReplayControl::Pause);
    let f = seek_to(&s, end - 1).await;
    assert_eq!(f.vehicles, seen(&worlds[end as usize - 1], &terrain));
    // The rest is written: the valid part grows to the end.
    let mut file = std::fs::OpenOptions::new()
        .append(true)
        .open(&path)
        .expect("opens");
    file.write_all(&bytes[half..]).expect("written");
    drop(file);
    status_when(&s, "the whole session", |st| {
        st.replay.as_ref().is_some_and(|r| r.end == TICKS)
    })
    .await;
    let f = seek_to(&s, TICKS - 1).await;
    assert_eq!(f.vehicles, seen(&worlds[TICKS as usize - 1], &terrain));
    s.quit().await;
    r.server.shutdown().await.expect("stops");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Asks for a seek to `target` and waits for the frame showing it.
async fn seek_to(s: &Session, target: u64) -> roam_client::session::Received {
    s.replay_control(ReplayControl::Seek(target));
    until_tick(s, target).await
}

/// The first frame showing `tick`, within 10 s of frames.
async fn until_tick(s: &Session, tick: u64) -> roam_client::session::Received {
    for _ in 0..600 {
        let f = frame(s).await;
        if f.tick == tick {
            return f;
        }
    }
    panic!("no frame showed tick {tick}");
}
