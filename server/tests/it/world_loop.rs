//! The real world loop (`net::world_loop::run`, on its own thread as the server runs it),
//! recording to a disk that fails early: the world keeps ticking with no tick dropped, a
//! driver can still join, the failure is logged naming the file, the join after it is
//! logged as unrecorded, and the file left replays. (Its own test binary: no other test
//! shares the CPU with the 100 Hz loop while it is timed.)

use crate::disk;

use std::io::Write;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use disk::Disk;
use roam_protocol::sync::lock;
use roam_server::net::world_loop::{self, Inbound, WorldStats};
use roam_server::sim::recording::{self, record_len};
use roam_server::sim::replay;
use roam_server::sim::session::{DEFAULT_MAX_BYTES, RecordOptions};
use roam_server::sim::world::VehicleId;
use roam_server::sim::world_core::{Event, Snapshot, WorldCore};
use tokio::sync::{oneshot, watch};

/// Log lines, as the world thread writes them.
#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<u8>>>);

impl Write for Log {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        lock(&self.0).extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Log {
    fn text(&self) -> String {
        String::from_utf8_lossy(&lock(&self.0)).into_owned()
    }
}

/// Asks the world for a vehicle.
async fn join(inbox: &Sender<Inbound>) -> VehicleId {
    let (tx, rx) = oneshot::channel();
    inbox
        .send((Event::Join, Some(tx)))
        .expect("the world thread runs");
    tokio::time::timeout(Duration::from_secs(30), rx)
        .await
        .expect("answered in time")
        .expect("a vehicle")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_world_loop_keeps_ticking_after_the_recording_fails() {
    let terrain = Arc::new(roam_server::terrain::generate::synthetic(65, 3));
    // The disk takes the first header and 20 bytes more: the first hand-over of records
    // (at the checkpoint at tick 100, by when a join and waits are pending) fails.
    let header = record_len(52) + 12;
    let disk = Disk::failing_after(header + 20);
    let record = RecordOptions::new(disk.clone(), DEFAULT_MAX_BYTES);
    let core = WorldCore::new(terrain.clone(), Some(record)).expect("the first file starts");
    let (inbox, inbox_rx) = std::sync::mpsc::channel();
    let (snap_tx, mut snapshots) = watch::channel(Arc::new(Snapshot::default()));
    let stats = Arc::new(WorldStats::default());
    let log = Log::default();
    let thread = {
        let stats = stats.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_ansi(false)
            .with_writer({
                let log = log.clone();
                move || log.clone()
            })
            .finish();
        std::thread::spawn(move || {
            tracing::subscriber::with_default(subscriber, || {
                world_loop::run(core, inbox_rx, snap_tx, &stats)
            })
        })
    };
    let a = join(&inbox).await;
    let failure = 100;
    tokio::time::timeout(
        Duration::from_secs(60),
        snapshots.wait_for(|s| s.tick > failure + 200),
    )
    .await
    .expect("the world ticks on")
    .expect("the world thread runs");
    assert!(disk.refused() > 0, "the disk failed");
    let b = join(&inbox).await;
    assert_ne!(a, b, "a driver joins after the failure");
    assert_eq!(stats.dropped(), 0, "no tick dropped");
    assert!(stats.ticks() > failure + 200);
    drop(inbox);
    let world = tokio::task::spawn_blocking(move || thread.join())
        .await
        .expect("joined")
        .expect("the world thread ends without a panic");
    let ids: Vec<VehicleId> = world.vehicles().iter().map(|v| v.id).collect();
    assert_eq!(ids, [a, b]);
    let text = log.text();
    assert!(
        text.contains("ERROR") && text.contains("recording to mem-001.rec failed"),
        "{text}"
    );
    assert!(
        text.contains("WARN") && text.contains(&format!("vehicle {b} joined unrecorded")),
        "{text}"
    );
    // What is left is the header, whole: it replays (to an empty world at tick 0).
    let files = disk.files();
    assert_eq!(files.len(), 1);
    assert_eq!(files[0].1.len() as u64, header);
    let rec = recording::parse(&files[0].1).expect("parses");
    assert_eq!(rec.truncated_at, None);
    let out = replay::replay(&rec, terrain.clone(), &terrain.content_hash()).expect("replays");
    assert_eq!((out.tick, out.ended), (0, false));
}
