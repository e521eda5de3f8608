//! One world, many machines: a real `nats-server` on loopback, a world
//! (`roam_server::net::bus::world`) and two edges (servers whose world is over NATS), with
//! headless viewers on both over real QUIC.

use std::sync::Arc;
use std::time::Duration;

use roam_client::headless::{self, ViewerOptions, ViewerStats};
use roam_protocol::messages::Role;
use roam_protocol::script;
use roam_server::Terrain;
use roam_server::net::Options;
use roam_server::net::bus::edge::Remote;
use roam_server::net::bus::world::{WorldOptions, WorldServer};
use roam_server::net::bus::{BusError, BusOptions};
use roam_server::sim::record_files::RecordDir;
use roam_server::sim::session::{self, RecordOptions};
use roam_server::sim::{recording, replay};
use roam_tests::fixtures::{self, Running, flat};
use roam_tests::nats::Nats;

/// Each test runs a world and edges with their threads: one at a time, so that on a
/// 2-core machine none starves another of the CPU.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

fn bus(nats: &Nats, world: &str) -> BusOptions {
    BusOptions {
        url: nats.url(),
        world: world.into(),
        creds: None,
        name: "roam-test".into(),
    }
}

/// A world of `terrain` on `bus`, recording to `record` if given.
async fn start_world(
    terrain: &Arc<Terrain>,
    bus: &BusOptions,
    record: Option<RecordOptions>,
) -> WorldServer {
    let options = WorldOptions {
        record,
        hold: Duration::from_secs(30),
        max_vehicles: 64,
    };
    WorldServer::start(terrain.clone(), terrain.content_hash(), options, bus)
        .await
        .expect("the world starts")
}

async fn edge(terrain: Arc<Terrain>, bus: &BusOptions) -> Running {
    let remote = Remote::connect(
        bus,
        terrain.content_hash(),
        "the test terrain",
        vec!["127.0.0.1:0".into()],
        Duration::from_secs(10),
    )
    .await
    .expect("the edge reaches the world");
    fixtures::serve(terrain, |o| Options {
        remote: Some(remote),
        ..o
    })
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
    let _turn = ONE_AT_A_TIME.lock().await;
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
    tokio::time::timeout(
        Duration::from_secs(10),
        snaps.wait_for(|s| !s.vehicles.is_empty()),
    )
    .await
    .expect("A's vehicle appears")
    .expect("the world runs");
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
    let want = fixtures::simulated_drive(&terrain);
    let got = sa.last.expect("a vehicle in the frames");
    assert_eq!(
        (got.x, got.z, got.speed, got.heading),
        (
            want.state.x,
            want.state.z,
            want.state.speed,
            want.state.heading
        ),
        "at tick {}",
        sa.last_tick
    );
    assert!(!sa.latencies_ms.is_empty(), "key changes were seen applied");
    a.server.shutdown().await.expect("edge A stops");
    b.server.shutdown().await.expect("edge B stops");
    // Both drivers said goodbye through their edges: the world let their vehicles go.
    tokio::time::timeout(
        Duration::from_secs(10),
        snaps.wait_for(|s| s.vehicles.is_empty()),
    )
    .await
    .expect("the vehicles leave")
    .expect("the world runs");
    // The world's recording, every driver's inputs in it, replays bit for bit.
    let final_world = world.shutdown().await.expect("the world stops");
    let files: Vec<_> = std::fs::read_dir(&dir)
        .expect("the recording directory")
        .map(|e| e.expect("a directory entry").path())
        .collect();
    assert_eq!(files.len(), 1, "one recording file: {files:?}");
    let bytes = std::fs::read(&files[0]).expect("the recording");
    let rec = recording::parse(&bytes).expect("parses");
    let out = replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays");
    assert!(out.ended, "closed cleanly");
    assert_eq!(out.tick, final_world.tick());
    assert_eq!(out.digest, final_world.digest());
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_with_another_data_set_is_refused_naming_both() {
    let _turn = ONE_AT_A_TIME.lock().await;
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
    let _turn = ONE_AT_A_TIME.lock().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "restart");
    let world = start_world(&terrain, &bus, None).await;
    let a = edge(terrain.clone(), &bus).await;
    let drive = driver(&a, 480, Some(fixtures::DRIVE));
    let d = tokio::spawn(headless::run(a.server.addr, a.fingerprint, drive));
    // Mid-drive (by the world's own ticks), the NATS server goes and comes back.
    let mut snaps = world.watch();
    let at = tokio::time::timeout(
        Duration::from_secs(20),
        snaps.wait_for(|s| !s.vehicles.is_empty() && s.tick >= 300),
    )
    .await
    .expect("the drive is under way")
    .expect("the world runs")
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
    assert_eq!(stats.reconnects, 0, "the viewer's own link never broke");
    // Key states lost with the bus are states the world waited for, then got again: the
    // drive is still exact.
    let (want, got) = (
        fixtures::simulated_drive(&terrain),
        stats.last.expect("a vehicle"),
    );
    assert_eq!(
        (got.x, got.z, got.speed, got.heading),
        (
            want.state.x,
            want.state.z,
            want.state.speed,
            want.state.heading
        )
    );
    assert_eq!(world.world_stats().dropped(), 0, "no world tick lost");
    a.server.shutdown().await.expect("the edge stops");
    world.shutdown().await.expect("the world stops");
}
