//! One world, many machines: a real `nats-server` on loopback, a world
//! (`roam_server::net::bus::world`) and two edges (servers whose world is over NATS), with
//! headless viewers on both over real QUIC.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use roam_client::headless::{self, ViewerOptions, ViewerStats};
use roam_protocol::bus::{Answer, Ask};
use roam_protocol::messages::Role;
use roam_protocol::script;
use roam_server::Terrain;
use roam_server::net::bus::asker::Asker;
use roam_server::net::bus::edge::Remote;
use roam_server::net::bus::world::{WorldOptions, WorldServer};
use roam_server::net::bus::{BusError, BusOptions};
use roam_server::sim::record_files::RecordDir;
use roam_server::sim::session::{self, RecordOptions};
use roam_server::sim::world_core::Snapshot;
use roam_tests::fixtures::{self, Running, flat};
use roam_tests::nats::cluster::{self, bus, edge_and_remote, when};
use roam_tests::nats::{EdgeProcess, Nats};

use crate::turn;

/// A world of `terrain` on `bus`, recording to `record` if given.
async fn start_world(
    terrain: &Arc<Terrain>,
    bus: &BusOptions,
    record: Option<RecordOptions>,
) -> WorldServer {
    cluster::start_world(terrain, bus, (Duration::from_secs(30), 64), record).await
}

async fn edge(terrain: Arc<Terrain>, bus: &BusOptions) -> Running {
    edge_and_remote(terrain, bus).await.0
}

/// Two edge processes (`roam-test-edge`, with the page if `web`) of world `name`, sharing
/// one fresh state directory (one identity), and that directory, for the test to remove.
fn edge_processes(nats: &Nats, name: &str, web: bool) -> (EdgeProcess, EdgeProcess, PathBuf) {
    let state = std::env::temp_dir().join(format!("roam-edges-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&state);
    let exe = env!("CARGO_BIN_EXE_roam-test-edge");
    let start = if web {
        EdgeProcess::start_web
    } else {
        EdgeProcess::start
    };
    let a = start(exe, nats, name, &state);
    let b = start(exe, nats, name, &state);
    (a, b, state)
}

/// A world `name` on `nats`, an edge, and a driver on it driving [`fixtures::DRIVE`] for
/// 480 frames (its task, to await).
async fn driving(
    nats: &Nats,
    name: &str,
) -> (
    Arc<Terrain>,
    BusOptions,
    WorldServer,
    Running,
    tokio::task::JoinHandle<anyhow::Result<ViewerStats>>,
) {
    let terrain = flat();
    let bus = bus(nats, name);
    let world = start_world(&terrain, &bus, None).await;
    let a = edge(terrain.clone(), &bus).await;
    let drive = driver(&a, 480, Some(fixtures::DRIVE));
    let d = tokio::spawn(headless::run(a.server.addr, a.fingerprint, drive));
    (terrain, bus, world, a, d)
}

fn driver(r: &Running, frames: u64, drive: Option<&str>) -> ViewerOptions {
    ViewerOptions {
        token: r.token.clone(),
        role: Role::Driver,
        budget: 8_000,
        frames,
        inputs: drive.map(|d| script::parse(d).expect("valid")),
        ..ViewerOptions::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn drivers_on_two_edges_share_one_world_and_it_replays() {
    let _turn = turn().await;
    let nats = Nats::start();
    let dir = std::env::temp_dir().join(format!("roam-cluster-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    let terrain = flat();
    let bus = bus(&nats, "two-edges");
    let files = RecordDir::new(dir.clone(), roam_server::net::world_loop::unix_seconds);
    let world = start_world(
        &terrain,
        &bus,
        Some(RecordOptions::new(files, session::DEFAULT_MAX_BYTES)),
    )
    .await;
    let (a, b) = (
        edge(terrain.clone(), &bus).await,
        edge(terrain.clone(), &bus).await,
    );
    // The driver on edge A joins first (vehicle 0, at the first start slot), then the
    // driver on B (vehicle 1) once A's vehicle is in the world.
    let da = tokio::spawn(headless::run(
        a.server.addr,
        a.fingerprint,
        driver(&a, 330, Some(fixtures::DRIVE)),
    ));
    let mut snaps = world.watch();
    when(&mut snaps, 10, "A's vehicle appears", |s| {
        !s.vehicles.is_empty()
    })
    .await;
    let db = tokio::spawn(headless::run(
        b.server.addr,
        b.fingerprint,
        driver(&b, 200, None),
    ));
    let (sa, sb): (ViewerStats, ViewerStats) = (
        da.await.expect("joins").expect("A's driver runs"),
        db.await.expect("joins").expect("B's driver runs"),
    );
    for s in [&sa, &sb] {
        assert_eq!(s.decode_errors, 0);
        assert_eq!(s.vehicles_max, 2, "each edge's driver sees both vehicles");
    }
    assert_eq!((sa.vehicle, sb.vehicle), (0, 1));
    // The drive through edge A and the bus ends exactly where the script, simulated, ends.
    fixtures::assert_drive_exact(&terrain, sa.last, sa.last_tick);
    assert!(!sa.latencies_ms.is_empty(), "key changes were seen applied");
    a.server.shutdown().await.expect("edge A stops");
    b.server.shutdown().await.expect("edge B stops");
    // Both drivers said goodbye through their edges: the world let their vehicles go.
    when(&mut snaps, 10, "the vehicles leave", |s| {
        s.vehicles.is_empty()
    })
    .await;
    // The world's recording, every driver's inputs in it, replays bit for bit.
    let final_world = world.shutdown().await.expect("the world stops");
    fixtures::assert_replays(&dir, &terrain, &final_world);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_with_another_data_set_is_refused_naming_both() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "data-check");
    let world = start_world(&terrain, &bus, None).await;
    let mut other = terrain.content_hash();
    other[0] ^= 1;
    let err = Remote::connect(&bus, other, "/data/other", vec![], Duration::from_secs(10))
        .await
        .err()
        .expect("refused");
    assert!(matches!(err, BusError::DataSet { .. }), "{err}");
    let text = err.to_string();
    for part in [
        roam_link::tls::hex(&terrain.content_hash()),
        roam_link::tls::hex(&other),
        "/data/other".to_string(),
        "\"data-check\"".to_string(),
    ] {
        assert!(text.contains(&part), "{text} names {part}");
    }
    // No world by that name: said, after the wait.
    let none = BusOptions {
        world: "nobody".into(),
        ..bus.clone()
    };
    let err = Remote::connect(&none, other, "d", vec![], Duration::from_millis(500))
        .await
        .err()
        .expect("no world answers");
    assert!(matches!(err, BusError::NoWorld { .. }), "{err}");
    world.shutdown().await.expect("the world stops");
}

/// The NATS server restarted mid-drive: the world ticks on (none dropped), the edge and the
/// world reconnect and resubscribe, and the driver's frames pause, then go on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nats_restart_mid_drive_loses_no_tick_and_the_drive_goes_on() {
    let _turn = turn().await;
    let nats = Nats::start();
    let (terrain, _, world, a, d) = driving(&nats, "restart").await;
    // Mid-drive (by the world's own ticks), the NATS server goes and comes back.
    let mut snaps = world.watch();
    let at = when(&mut snaps, 20, "the drive is under way", |s| {
        !s.vehicles.is_empty() && s.tick >= 300
    })
    .await
    .tick;
    let port = nats.kill();
    let _back = Nats::on(port);
    let stats = d.await.expect("joins").expect("the driver runs");
    assert_eq!(stats.frames, 480);
    assert!(stats.last_tick > at, "frames after the restart");
    assert!(
        stats.gap_max_s <= 3.0,
        "the longest pause between frames: {} s",
        stats.gap_max_s
    );
    assert_eq!(
        stats.reconnects, 0,
        "the viewer's own connection never broke"
    );
    // Key states lost with the bus are states the world waited for, then got again: the
    // drive is still exact.
    fixtures::assert_drive_exact(&terrain, stats.last, stats.last_tick);
    assert_eq!(world.world_stats().dropped(), 0, "no world tick lost");
    a.server.shutdown().await.expect("the edge stops");
    world.shutdown().await.expect("the world stops");
}

/// An edge killed (`kill -9`) mid-drive: its driver, given both edges' addresses, moves to
/// the other one after a second's silence and gets its vehicle back with its ticket.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_killed_mid_drive_its_driver_resumes_on_the_other() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let name = "edge-killed";
    let bus = bus(&nats, name);
    let world = start_world(&terrain, &bus, None).await;
    let (a, b, state) = edge_processes(&nats, name, false);
    assert_eq!(
        a.fingerprint, b.fingerprint,
        "one state directory, one identity"
    );
    let drive = ViewerOptions {
        token: fixtures::TOKEN.to_string(),
        role: Role::Driver,
        budget: 8_000,
        frames: 600,
        inputs: Some(script::parse(fixtures::DRIVE).expect("valid")),
        ..ViewerOptions::default()
    };
    let (addrs, fingerprint) = ([a.addr, b.addr], a.fingerprint);
    let mover =
        tokio::spawn(async move { headless::measure_any(&addrs, fingerprint, drive).await });
    let mut snaps = world.watch();
    let started = when(&mut snaps, 10, "the vehicle appears", |s| {
        !s.vehicles.is_empty()
    })
    .await
    .tick;
    let at = when(&mut snaps, 20, "the drive is under way", |s| {
        s.tick >= started + 200
    })
    .await
    .tick;
    a.kill();
    let moved = mover.await.expect("runs").expect("joins");
    assert_eq!(moved.error, None, "the session went on");
    assert_eq!(moved.frames, 600);
    assert_eq!(moved.vehicle, 0, "the same vehicle");
    assert_eq!(
        (moved.reconnects, moved.resumed),
        (1, 1),
        "moved once, resumed"
    );
    assert!(moved.last_tick > at, "frames from B after A died");
    // The figure the README gives (run with --nocapture).
    eprintln!("edge killed: longest frame gap {:.3} s", moved.gap_max_s);
    assert!(
        moved.gap_max_s <= 3.0,
        "the longest pause between frames: {} s",
        moved.gap_max_s
    );
    drop(b);
    world.shutdown().await.expect("the world stops");
    let _ = std::fs::remove_dir_all(&state);
}

/// A stuck edge (a subscriber that stopped reading: its TCP window full) slows neither the
/// world nor the other edges: nats-server buffers for it, then cuts it off as a slow
/// consumer, while the world ticks on (none dropped) and a driver on another edge drives
/// exactly. Sixty vehicles make the snapshots big enough to fill its buffers within the
/// drive.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stuck_edge_slows_neither_the_world_nor_the_other_edges() {
    let _turn = turn().await;
    let nats = Nats::with_config("max_pending: 1048576\nwrite_deadline: \"1s\"\n");
    // The driver first (the first start slot, where the offline drive starts).
    let (terrain, bus, world, a, d) = driving(&nats, "stuck").await;
    let mut snaps = world.watch();
    when(&mut snaps, 20, "the driver's vehicle", |s| {
        !s.vehicles.is_empty()
    })
    .await;
    let subjects = bus.subjects().expect("a valid name");
    let client = bus.connect().await.expect("reaches NATS");
    // Sixty joins by an edge of the test's making (they are held 3 s later, as no edge
    // names them, and stay in the world, held, for the drive).
    let counts = Arc::new(roam_server::net::bus::seal::RefusedCounts::default());
    let asker = Asker::start(client, &subjects, bus.key().as_ref(), 8, counts)
        .await
        .expect("subscribes to its answers");
    let hello = Ask::Hello {
        data: terrain.content_hash(),
        edge: 8,
        addresses: vec![],
        vehicles: vec![],
    };
    match asker.ask(&hello).await.expect("the world answers") {
        Answer::Hello { world, .. } => asker.set_world(world),
        other => panic!("{other:?}"),
    }
    for _ in 0..60 {
        let answer = asker.ask(&Ask::Join).await.expect("the world answers");
        assert!(matches!(answer, Answer::Joined { .. }), "{answer:?}");
    }
    // The stuck edge: subscribed to the snapshots, then never reading again.
    let mut stuck = std::net::TcpStream::connect(("127.0.0.1", nats.port)).expect("connects");
    {
        use std::io::{BufRead, Write};
        let subscribe = format!(
            "CONNECT {{\"verbose\":false,\"pedantic\":false}}\r\nSUB {} 1\r\nPING\r\n",
            subjects.snapshots
        );
        stuck.write_all(subscribe.as_bytes()).expect("subscribes");
        let mut lines = std::io::BufReader::new(stuck.try_clone().expect("a second handle"));
        let mut line = String::new();
        for _ in 0..4 {
            line.clear();
            lines.read_line(&mut line).expect("nats-server answers");
            if line.starts_with("PONG") {
                break;
            }
        }
        assert!(line.starts_with("PONG"), "subscribed: {line:?}");
    }
    let stats = d.await.expect("joins").expect("the driver runs");
    let cut = nats.logged("Slow Consumer", Duration::from_secs(30));
    assert!(cut.is_some(), "nats-server found the stuck edge out");
    assert_eq!(stats.frames, 480);
    assert_eq!(
        stats.vehicles_max,
        roam_server::viewer::conversation::MAX_SHOWN,
        "the other edge's driver sees as many vehicles as a frame shows, the nearest of 61"
    );
    let known = a.server.snapshot().vehicles.len();
    assert!(known >= 60, "the other edge knows the whole world: {known}");
    fixtures::assert_drive_exact(&terrain, stats.last, stats.last_tick);
    assert_eq!(world.world_stats().dropped(), 0, "no world tick lost");
    drop(stuck);
    a.server.shutdown().await.expect("the edge stops");
    world.shutdown().await.expect("the world stops");
}

/// The world's side of an edge's death, spoken over NATS as an edge would: a vehicle whose
/// edge falls silent is held (not freed), given back when that edge is heard again; a
/// leave or hold naming an older claim (a retry, or an edge whose driver has since moved)
/// changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_world_holds_a_silent_edges_vehicles_and_ignores_stale_claims() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "silent-edge");
    let world = start_world(&terrain, &bus, None).await;
    // An edge of its own making (name 7), sealing as a real edge does.
    let client = bus.connect().await.expect("reaches NATS");
    let subjects = bus.subjects().expect("a valid name");
    let counts = Arc::new(roam_server::net::bus::seal::RefusedCounts::default());
    let asker = Asker::start(client, &subjects, bus.key().as_ref(), 7, counts)
        .await
        .expect("subscribes to its answers");
    let asker = &asker;
    let ask = |a: Ask| async move { asker.ask(&a).await.expect("the world answers") };
    let joined = |a: Answer| match a {
        Answer::Joined { vehicle, claim, .. } => (vehicle, claim),
        other => panic!("{other:?}"),
    };
    let hello = |vehicles: Vec<(u16, u64)>| Ask::Hello {
        data: terrain.content_hash(),
        edge: 7,
        addresses: vec!["10.0.0.7:4433".into()],
        vehicles,
    };
    // A first hello names the world process; requests are for it from then on.
    match ask(hello(vec![])).await {
        Answer::Hello { world, .. } => asker.set_world(world),
        other => panic!("{other:?}"),
    }
    let (v, claim) = joined(ask(Ask::Join).await);
    let (w, w_claim) = joined(ask(Ask::Join).await);
    match ask(hello(vec![(v, claim), (w, w_claim)])).await {
        Answer::Hello { edges, .. } => assert_eq!(edges, vec!["10.0.0.7:4433".to_string()]),
        other => panic!("{other:?}"),
    }
    // A stale claim changes nothing; the newest one does.
    assert_eq!(
        ask(Ask::Leave {
            vehicle: w,
            claim: w_claim + 100
        })
        .await,
        Answer::Done
    );
    let mut snaps = world.watch();
    let with_both = |s: &Arc<Snapshot>| s.vehicles.len() == 2;
    when(&mut snaps, 5, "both vehicles stay", with_both).await;
    assert_eq!(
        ask(Ask::Leave {
            vehicle: w,
            claim: w_claim
        })
        .await,
        Answer::Done
    );
    when(&mut snaps, 5, "the left vehicle goes", |s| {
        s.vehicles.iter().all(|x| x.id != w)
    })
    .await;
    // Edge 7 goes silent: its vehicle is held, not freed.
    let held = when(&mut snaps, 15, "held once the edge is silent", |s| {
        s.held.contains(&v)
    })
    .await
    .clone();
    assert!(held.vehicles.iter().any(|x| x.id == v), "held, not freed");
    // Heard again, naming it: given back.
    ask(hello(vec![(v, claim)])).await;
    when(&mut snaps, 5, "given back to its edge", |s| {
        !s.held.contains(&v) && s.vehicles.iter().any(|x| x.id == v)
    })
    .await;
    world.shutdown().await.expect("the world stops");
}

/// A NATS server that wants a token: given in a file (`--nats-creds`), the world and an
/// edge connect; a wrong one is refused at once, naming the URL, not retried for ever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_credentials_from_a_file_are_used_and_a_wrong_one_is_said() {
    let _turn = turn().await;
    let nats = Nats::with_token("s3cret-token");
    let dir = std::env::temp_dir().join(format!("roam-creds-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let (good, bad) = (dir.join("good"), dir.join("bad"));
    std::fs::write(&good, "s3cret-token\n").expect("written");
    std::fs::write(&bad, "wrong-token\n").expect("written");
    let terrain = flat();
    let with = |file: &std::path::Path| BusOptions {
        creds: Some(file.to_owned()),
        ..bus(&nats, "creds")
    };
    let world = start_world(&terrain, &with(&good), None).await;
    let data = terrain.content_hash();
    Remote::connect(&with(&good), data, "d", vec![], Duration::from_secs(10))
        .await
        .expect("an edge with the token reaches the world");
    let err = Remote::connect(&with(&bad), data, "d", vec![], Duration::from_secs(10))
        .await
        .err()
        .expect("a wrong token is refused");
    assert!(matches!(err, BusError::Connect { .. }), "{err}");
    assert!(err.to_string().contains(&nats.url()), "{err}");
    world.shutdown().await.expect("the world stops");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The world gone from under an edge: the edge tells its viewers why (frames go on), and
/// keeps asking; when another world process answers, its driver, whose vehicle that world
/// never knew, is told and let go.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_world_gone_is_told_and_a_restarted_world_lets_drivers_go() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "world-gone");
    let world = start_world(&terrain, &bus, None).await;
    let (a, remote) = edge_and_remote(terrain.clone(), &bus).await;
    let d = tokio::spawn(headless::measure(
        a.server.addr,
        a.fingerprint,
        driver(&a, 1_000_000, None),
    ));
    let mut snaps = world.watch();
    when(&mut snaps, 10, "the vehicle appears", |s| {
        !s.vehicles.is_empty()
    })
    .await;
    world.shutdown().await.expect("the world stops");
    let mut news = remote.news();
    let gone = tokio::time::timeout(Duration::from_secs(10), news.wait_for(|n| n.gone.is_some()))
        .await
        .expect("the edge finds the world gone")
        .expect("the edge runs")
        .clone();
    let why = gone.gone.expect("waited for it");
    assert!(why.contains("\"world-gone\" has not answered"), "{why}");
    assert!(!d.is_finished(), "the driver stays while the world is away");
    let again = start_world(&terrain, &bus, None).await;
    let stats = tokio::time::timeout(Duration::from_secs(20), d)
        .await
        .expect("the driver is let go")
        .expect("runs")
        .expect("joined");
    let error = stats.error.expect("the session ended");
    assert!(error.contains("the world restarted"), "{error}");
    assert!(
        stats.world_gone_s > 0.0,
        "the viewer was told: {}",
        stats.world_gone_s
    );
    assert_eq!(remote.news().borrow().gone, None, "the world answers again");
    a.server.shutdown().await.expect("the edge stops");
    again.shutdown().await.expect("the world stops");
}

/// `world --replay`: the world serves a recording to its edges. A viewer on an edge (a
/// driver's hello) watches it as a spectator: the replay's clock reaches the edge with the
/// snapshots, the edge's first viewer holds its controls, and its seek, sent over the bus,
/// lands every edge's frames on the recorded world; a join asked of the world is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_world_serving_a_recording_is_watched_through_its_edge() {
    use roam_client::session::{KeySource, Session, Taken};
    use roam_protocol::messages::ReplayControl;
    use roam_server::sim::physics::Keys;
    use roam_server::sim::recorder::RecordedWorld;
    use roam_server::sim::world::{self, Inputs, Vehicle, World};
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    // Two drivers for 2,000 ticks, recorded, and the world at every tick.
    let mut w = World::new(terrain.clone());
    w.add(0, world::start_state(&terrain, 0))
        .expect("on the map");
    w.add(1, world::start_state(&terrain, 1))
        .expect("on the map");
    let mut rec = RecordedWorld::start(w, Vec::new(), terrain.content_hash(), 100)
        .expect("memory does not fail");
    let mut inputs = Inputs::new();
    let mut worlds: Vec<Vec<Vehicle>> = Vec::new();
    for tick in 0..2000u32 {
        worlds.push(rec.world().vehicles().to_vec());
        inputs.set(
            0,
            if tick % 300 < 200 {
                Keys::UP
            } else {
                Keys::UP.union(Keys::LEFT)
            },
        );
        inputs.set(1, Keys::UP.union(Keys::RIGHT));
        rec.step(&inputs).expect("memory does not fail");
    }
    let (_, bytes) = rec.finish().expect("memory does not fail");
    let watch =
        roam_server::sim::watch::open_bytes(&bytes, terrain.clone(), &terrain.content_hash())
            .expect("opens");
    let bus = bus(&nats, "watched");
    let options = WorldOptions {
        record: None,
        hold: Duration::from_secs(30),
        max_vehicles: 64,
        replay: Some(roam_server::net::replay::Replaying {
            watch,
            control_token: None,
            follow: None,
        }),
    };
    let world = WorldServer::start(terrain.clone(), terrain.content_hash(), options, &bus)
        .await
        .expect("the world starts");
    let (a, remote) = edge_and_remote(terrain.clone(), &bus).await;
    assert!(remote.join().await.is_err(), "no driving a recording");
    // Until the edge has the world's snapshots, it does not know it serves a recording.
    let mut clock = remote.replay_clock();
    tokio::time::timeout(Duration::from_secs(10), clock.wait_for(|c| c.is_some()))
        .await
        .expect("the clock within 10 s")
        .expect("the edge runs");
    let hello = fixtures::driver_hello(&a.token);
    let s = Session::join(a.server.addr, a.fingerprint, hello, KeySource::None)
        .await
        .expect("joins");
    assert_eq!(s.welcome().ticket, None, "served as a spectator");
    let st = fixtures::status_when(&s, "the replay's status", |st| st.replay.is_some()).await;
    let rs = st.replay.expect("waited for");
    assert_eq!((rs.start, rs.end), (0, 2000));
    assert!(rs.control, "the edge's first viewer holds its controls");
    let seen = |tick: u64| -> Vec<(u16, f64, f64)> {
        worlds[tick as usize]
            .iter()
            .map(|v| (v.id, v.state.x, v.state.z))
            .collect()
    };
    // The frames show the recorded world at their ticks.
    for _ in 0..20 {
        let f = fixtures::frame(&s).await;
        let got: Vec<(u16, f64, f64)> = f.vehicles.iter().map(|v| (v.id, v.x, v.z)).collect();
        assert_eq!(got, seen(f.tick), "tick {}", f.tick);
    }
    // Paused and sought through the bus: the world's clock, every edge's frames.
    s.replay_control(ReplayControl::Pause);
    s.replay_control(ReplayControl::Seek(1500));
    let mut shown = None;
    for _ in 0..600 {
        if let Ok(Taken::Frame(f)) = s.next_frame(true).await
            && f.tick == 1500
        {
            shown = Some(f);
            break;
        }
    }
    let f = shown.expect("a frame at tick 1500 within 600");
    let got: Vec<(u16, f64, f64)> = f.vehicles.iter().map(|v| (v.id, v.x, v.z)).collect();
    assert_eq!(got, seen(1500));
    let mut snaps = world.watch();
    when(&mut snaps, 5, "the world's clock at 1500", |w| {
        w.tick == 1500
    })
    .await;
    s.quit().await;
    a.server.shutdown().await.expect("the edge stops");
    world.shutdown().await.expect("the world stops");
}

/// The tests that also open the page in Chromium (`needs_browser`, as the modules of the
/// tests that need one are named: the fast tier and `scripts/test`'s first pass leave them
/// out by that name).
mod needs_browser {
    use roam_tests::browser::{self, Browser, GpuPath};

    use super::*;
    use crate::alone;

    /// The page one edge served learns the world's other edges from it; when that edge is
    /// killed (`kill -9`), the page moves to the other edge, trusting that edge's own
    /// certificate (its hashes came with its address), and gets its vehicle back.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_page_moves_to_another_edge_when_its_edge_is_killed() {
        let _turn = alone().await;
        let nats = Nats::start();
        let terrain = flat();
        let name = "page-moves";
        let world = start_world(&terrain, &bus(&nats, name), None).await;
        let (a, b, state) = edge_processes(&nats, name, true);
        let (a_web, b_web) = (a.web.expect("serves the page"), b.web.expect("the page"));
        let (report, mut reports) = browser::reports().await;
        let url = format!(
            "https://127.0.0.1:{}/#token={}&gpu=webgl&frames=10&report=http://{report}/report&script={}",
            a_web.port(),
            fixtures::TOKEN,
            "150%20U%0A3000%20UL%0A",
        );
        let _browser = Browser::open(&url, GpuPath::WebGl2);
        let on = |r: &serde_json::Value, port: u16| {
            r["edge"]
                .as_str()
                .is_some_and(|e| e.starts_with(&format!("https://127.0.0.1:{port}/")))
        };
        let first = browser::numbers(&mut reports).await;
        assert!(on(&first, a_web.port()), "on A first: {first}");
        let vehicle = first["vehicle"].clone();
        // A names B as soon as the world has heard of both: in the numbers, or a report after.
        let mut known = first;
        for _ in 0..8 {
            if known["edges"].as_u64() >= Some(2) {
                break;
            }
            known = browser::next(&mut reports).await;
            assert_eq!(known["state"], "connected", "{known}");
        }
        assert!(known["edges"].as_u64() >= Some(2), "B learned: {known}");
        a.kill();
        let mut r = browser::next(&mut reports).await;
        for _ in 0..16 {
            if r["state"] != "reconnecting" {
                break;
            }
            r = browser::next(&mut reports).await;
        }
        assert_eq!(r["state"], "connected", "{r}");
        assert!(on(&r, b_web.port()), "on B now: {r}");
        assert_eq!(
            (&r["reconnects"], &r["resumed"]),
            (&1.into(), &1.into()),
            "{r}"
        );
        assert_eq!(r["vehicle"], vehicle, "its vehicle back: {r}");
        let mut snaps = world.watch();
        let s = when(&mut snaps, 10, "the vehicle driven again", |s| {
            s.held.is_empty()
        })
        .await;
        assert_eq!(s.vehicles.len(), 1, "no second vehicle");
        drop(b);
        world.shutdown().await.expect("the world stops");
        let _ = std::fs::remove_dir_all(&state);
    }
}
