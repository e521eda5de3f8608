//! The bus's proofs as a world and its edges see them (a real `nats-server`): an edge with
//! another secret is never answered (and counted); a vehicle that no edge names is held,
//! then freed. (Attacks by a NATS client without the secret: `hostile_bus.rs`.)

use std::sync::Arc;
use std::time::Duration;

use roam_protocol::bus::{Answer, Ask};
use roam_server::Terrain;
use roam_server::net::bus::asker::Asker;
use roam_server::net::bus::edge::Remote;
use roam_server::net::bus::world::WorldServer;
use roam_server::net::bus::{BusError, BusOptions, BusSecret};
use roam_tests::fixtures::flat;
use roam_tests::nats::Nats;
use roam_tests::nats::cluster::{self, bus, capture, edge_and_remote, hand_made_edge, hello, when};

use crate::turn;

async fn start_world(terrain: &Arc<Terrain>, bus: &BusOptions, hold: Duration) -> WorldServer {
    cluster::start_world(terrain, bus, (hold, 64), None).await
}

async fn join(asker: &Asker) -> (u16, u64) {
    match asker.ask(&Ask::Join).await {
        Ok(Answer::Joined { vehicle, claim, .. }) => (vehicle, claim),
        other => panic!("{other:?}"),
    }
}

/// An edge holding another secret reaches NATS but never the world: its hellos do not
/// open there (counted as forged), so it gives up saying no world answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_edge_with_another_secret_is_never_answered() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "other-secret");
    let world = start_world(&terrain, &bus, Duration::from_secs(30)).await;
    let other = BusOptions {
        secret: Some(BusSecret::random()),
        ..bus.clone()
    };
    let err = Remote::connect(
        &other,
        terrain.content_hash(),
        "d",
        vec![],
        Duration::from_secs(3),
    )
    .await
    .err()
    .expect("not answered");
    assert!(matches!(err, BusError::NoWorld { .. }), "{err}");
    let refused = world.refused();
    assert!(refused.forged >= 1, "{refused:?}");
    // With the world's secret, the same edge is answered.
    Remote::connect(
        &bus,
        terrain.content_hash(),
        "d",
        vec![],
        Duration::from_secs(10),
    )
    .await
    .expect("the world answers an edge with its secret");
    world.shutdown().await.expect("the world stops");
}

/// A vehicle whose edge never names it in its hellos (its join's answer lost, say) is held
/// once the grace has passed, counted, and freed when its hold runs out; its sibling, named
/// in every hello, drives on untouched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_no_edge_names_is_held_then_freed() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "unnamed");
    // Held from its claim, 3 s before it is found unnamed: 2 s more held, then freed.
    let world = start_world(&terrain, &bus, Duration::from_secs(5)).await;
    let edge = hand_made_edge(&bus, &terrain, 31).await;
    let (named, claim) = join(&edge).await;
    let (unnamed, _) = join(&edge).await;
    // The edge's beat: every half second, naming only the first vehicle (at most 40).
    let beat = {
        let (edge, terrain) = (edge.clone(), terrain.clone());
        tokio::spawn(async move {
            let mut every = tokio::time::interval(Duration::from_millis(500));
            for _ in 0..40 {
                every.tick().await;
                let _ = edge.ask(&hello(&terrain, 31, vec![(named, claim)])).await;
            }
        })
    };
    let mut snaps = world.watch();
    let held = when(&mut snaps, 10, "the unnamed vehicle held", |s| {
        s.held.contains(&unnamed)
    })
    .await;
    assert!(!held.held.contains(&named), "the named one drives on");
    assert!(world.refused().unnamed >= 1, "{:?}", world.refused());
    let freed = when(&mut snaps, 10, "the unnamed vehicle freed", |s| {
        s.vehicles.iter().all(|v| v.id != unnamed)
    })
    .await;
    assert!(freed.vehicles.iter().any(|v| v.id == named));
    assert!(!freed.held.contains(&named));
    beat.abort();
    world.shutdown().await.expect("the world stops");
}

/// A world restart is believed from the world's own answer only: an edge's world goes and
/// another process takes its place (the edge confirms it by a hello: one restart); the old
/// process's snapshots, captured and played again, are genuine but make no second restart
/// and are never taken (counted as replays or unconfirmed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_old_worlds_snapshots_played_again_restart_nothing() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "restart");
    let old = start_world(&terrain, &bus, Duration::from_secs(30)).await;
    // Served (its beat and its snapshots' subscriber run while it serves).
    let (edge, remote) = edge_and_remote(terrain.clone(), &bus).await;
    // The old world's snapshots, captured.
    let subjects = bus.subjects().expect("a valid name");
    let (snooper, captured) = capture(&nats, &subjects.snapshots, 50).await;
    old.shutdown().await.expect("the old world stops");
    let new = start_world(&terrain, &bus, Duration::from_secs(30)).await;
    let mut news = remote.news();
    tokio::time::timeout(Duration::from_secs(10), news.wait_for(|n| n.restarts == 1))
        .await
        .expect("the edge confirms the new world")
        .expect("the edge runs");
    let before = remote.refused();
    for payload in &captured {
        snooper
            .publish(subjects.snapshots.clone(), payload.clone())
            .await
            .expect("NATS takes it");
    }
    snooper.flush().await.expect("flushed");
    // Each played-again snapshot refused by the edge (looked at every 10 ms, 5 s at most).
    let refused = |r: roam_server::net::bus::Refused| r.replayed + r.unconfirmed;
    let mut look = tokio::time::interval(Duration::from_millis(10));
    for _ in 0..500 {
        look.tick().await;
        if refused(remote.refused()) - refused(before) >= 50 {
            break;
        }
    }
    let after = remote.refused();
    assert_eq!(
        refused(after) - refused(before),
        50,
        "{before:?} → {after:?}"
    );
    assert_eq!(
        remote.restarts(),
        1,
        "the old world's snapshots made no restart"
    );
    edge.server.shutdown().await.expect("the edge stops");
    new.shutdown().await.expect("the world stops");
}

/// The world's snapshots from before an edge subscribed (genuine, and never seen by it),
/// played again while its driver drives: each is older than the edge's newest, so none is
/// taken (the driver's vehicle is not in them: taken, it would have ended the session and
/// freed the vehicle); the drive goes on exactly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn snapshots_an_edge_never_saw_played_again_take_nothing_back() {
    let _turn = turn().await;
    let nats = Nats::start();
    let terrain = flat();
    let bus = bus(&nats, "unseen");
    let world = start_world(&terrain, &bus, Duration::from_secs(30)).await;
    // Snapshots of the empty world, before the edge exists.
    let subjects = bus.subjects().expect("a valid name");
    let (snooper, captured) = capture(&nats, &subjects.snapshots, 50).await;
    let (edge, remote) = edge_and_remote(terrain.clone(), &bus).await;
    let options = roam_client::headless::ViewerOptions {
        token: edge.token.clone(),
        role: roam_protocol::messages::Role::Driver,
        budget: 8_000,
        frames: 480,
        inputs: Some(
            roam_protocol::script::parse(roam_tests::fixtures::DRIVE).expect("a valid script"),
        ),
        ..Default::default()
    };
    let d = tokio::spawn(roam_client::headless::run(
        edge.server.addr,
        edge.fingerprint,
        options,
    ));
    // The vehicle in a snapshot the edge took (not only in the world's): the edge has a
    // newest, so each played-again one is older than it.
    let mut snaps = edge.server.watch();
    when(&mut snaps, 10, "the driver's vehicle at the edge", |s| {
        !s.vehicles.is_empty()
    })
    .await;
    let before = remote.refused();
    for payload in &captured {
        snooper
            .publish(subjects.snapshots.clone(), payload.clone())
            .await
            .expect("NATS takes it");
    }
    snooper.flush().await.expect("flushed");
    let stats = roam_tests::fixtures::bounded("the driver's session", d)
        .await
        .expect("the driver's task runs")
        .expect("the driver's session goes on to its last frame");
    assert_eq!(stats.frames, 480, "every frame taken");
    roam_tests::fixtures::assert_drive_exact(&terrain, stats.last, stats.last_tick);
    let after = remote.refused();
    assert_eq!(
        after.replayed - before.replayed,
        50,
        "{before:?} → {after:?}"
    );
    edge.server.shutdown().await.expect("the edge stops");
    world.shutdown().await.expect("the world stops");
}
