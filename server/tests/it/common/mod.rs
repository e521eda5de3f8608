//! Helpers shared by the tests that run the `roam-server` binary.
#![allow(dead_code)] // each test file uses its own subset

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU32, Ordering};

/// The workspace root: commands run there, so `data/…` paths work as in the README.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the crate lives in the workspace")
        .to_path_buf()
}

/// Runs `roam-server args…` from the workspace root; asserts the exit code and that each of
/// `expected` occurs in stdout or stderr. Returns stdout.
pub fn check(args: &[&str], expected_exit: i32, expected: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_roam-server"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("run roam-server");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(
        out.status.code(),
        Some(expected_exit),
        "roam-server {args:?}\n--- stdout:\n{stdout}\n--- stderr:\n{stderr}"
    );
    for want in expected {
        assert!(
            stdout.contains(want) || stderr.contains(want),
            "roam-server {args:?}: {want:?} missing\n--- stdout:\n{stdout}\n--- stderr:\n{stderr}"
        );
    }
    if expected_exit != 0 {
        assert!(
            stderr.contains("error"),
            "roam-server {args:?}: a failure should say why on stderr, got {stderr:?}"
        );
    }
    stdout
}

/// A fresh directory under the system temp dir, removed on drop.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(name: &str) -> TempDir {
        static COUNTER: AtomicU32 = AtomicU32::new(0);
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let dir =
            std::env::temp_dir().join(format!("roam-cli-test-{}-{n}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).expect("create temp dir");
        TempDir(dir)
    }

    pub fn path(&self, file: &str) -> PathBuf {
        self.0.join(file)
    }

    pub fn str(&self) -> &str {
        self.0.to_str().expect("temp paths are UTF-8 here")
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// A recording of one vehicle holding Up on `terrain` for `ticks` ticks, with a checkpoint
/// every `interval` ticks whose digest is wrong from tick `bad_from` on: what a build with
/// other physics would have recorded.
pub fn diverged_recording(
    terrain: &std::sync::Arc<roam_server::Terrain>,
    ticks: u64,
    interval: u32,
    bad_from: u64,
) -> Vec<u8> {
    use roam_server::sim::physics::Keys;
    use roam_server::sim::recorder::Recorder;
    use roam_server::sim::recording::Header;
    use roam_server::sim::world::{self, Inputs, World};
    let mut world = World::new(terrain.clone());
    world
        .add(0, world::start_state(terrain, 0))
        .expect("the start is on the map");
    let header = Header {
        data_hash: terrain.content_hash(),
        steps_per_second: 100,
        checkpoint_interval: interval,
        start_tick: 0,
        vehicles: vec![(0, world.vehicles()[0].state)],
    };
    let mut rec = Recorder::new(Vec::new(), &header).expect("memory does not fail");
    let mut inputs = Inputs::new();
    inputs.set(0, Keys::UP);
    rec.input(0, 0, Keys::UP).expect("memory does not fail");
    for tick in 1..=ticks {
        world::step(&mut world, &inputs);
        if tick.is_multiple_of(u64::from(interval)) {
            let mut digest = world.digest();
            if tick >= bad_from {
                digest.0[31] ^= 1;
            }
            rec.checkpoint(tick, &digest).expect("memory does not fail");
        }
    }
    rec.finish(ticks, &world.digest())
        .expect("memory does not fail")
}

/// Runs `import SOURCE OUT extra…`, asserting the exit code and messages as [`check`]
/// does; returns the data set written (on success) and stdout.
pub fn import_file(
    source: &Path,
    out: &Path,
    extra: &[&str],
    exit: i32,
    expected: &[&str],
) -> (Option<roam_server::Terrain>, String) {
    let mut args = vec![
        "import",
        source.to_str().expect("a UTF-8 temp path"),
        out.to_str().expect("a UTF-8 temp path"),
    ];
    args.extend_from_slice(extra);
    let stdout = check(&args, exit, expected);
    let terrain = (exit == 0).then(|| {
        roam_server::terrain::dataset::load(out, &mut |_, _| {}).expect("load the data set")
    });
    (terrain, stdout)
}

/// Writes `bytes` as `name` in a fresh temp dir and runs [`import_file`] on it into
/// `out` there; returns the temp dir too.
pub fn import_bytes(
    name: &str,
    bytes: &[u8],
    extra: &[&str],
    exit: i32,
    expected: &[&str],
) -> (TempDir, Option<roam_server::Terrain>, String) {
    let dir = TempDir::new(name);
    let file = dir.path(name);
    fs::write(&file, bytes).expect("write source");
    let (terrain, stdout) = import_file(&file, &dir.path("out"), extra, exit, expected);
    (dir, terrain, stdout)
}

/// A PNG signature and an IHDR of `width × height` at `depth` bits, colour type `color`,
/// nothing after it: a file that claims more than it holds.
pub fn png_claiming(width: u32, height: u32, depth: u8, color: u8) -> Vec<u8> {
    let mut chunk = b"IHDR".to_vec();
    chunk.extend(width.to_be_bytes());
    chunk.extend(height.to_be_bytes());
    chunk.extend([depth, color, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend(13u32.to_be_bytes());
    out.extend(&chunk);
    out.extend(crc32(&chunk).to_be_bytes());
    out
}

/// The CRC-32 of a PNG chunk.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
