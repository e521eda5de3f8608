//! End to end, at the protocol: a real server on `127.0.0.1:0` streams a generated 257²
//! set's colour in tiles of 16 texels (5 levels: 16, 8, 4, 2 and 1 tiles a side) with
//! windows of 4 tiles. A viewer speaking the protocol directly (quinn) gets the welcome's
//! layout, the coarsest tile next and before any frame, then its normals, then the rest of
//! every level's window, each tile inside its window and equal to the pyramid's, each
//! followed at once by its normals, equal to the normal pyramid's (decoding to the
//! box-filtered texels and the averaged normals is `color_pyramid`'s and
//! `normal_pyramid`'s unit tests): as many normal tiles as colour tiles, never more.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use roam_client::headless;
use roam_link::wire;
use roam_protocol::messages::{ClientMessage, MAX_MESSAGE, Role, ServerMessage};
use roam_protocol::{colormap, normals};
use roam_server::net::Options;
use roam_tests::fixtures;

/// A safety bound on each wait: a regression fails, never hangs.
const BOUND: Duration = Duration::from_secs(30);
const TILE: u32 = 16;

async fn next(recv: &mut quinn::RecvStream) -> (ServerMessage, usize) {
    let msg = tokio::time::timeout(BOUND, wire::read::<ServerMessage>(recv, MAX_MESSAGE))
        .await
        .expect("a control message in time")
        .expect("a control message");
    let mut bytes = Vec::new();
    roam_protocol::messages::encode(&msg, &mut bytes).expect("it decoded, so it encodes");
    (msg, bytes.len() + 4)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_coarsest_tile_comes_before_the_first_frame_then_the_windows_fill() {
    let terrain = Arc::new(roam_server::terrain::generate::synthetic(257, 7));
    let pyramid = fixtures::pyramid(&terrain, TILE);
    let normal_tiles = fixtures::normals(&terrain, TILE);
    let r = fixtures::serve_tiled(terrain, TILE, |o| Options {
        color_rate: 100_000,
        color_window: 6,
        ..o
    });
    let (_endpoint, conn) = headless::connect(r.server.addr, r.fingerprint)
        .await
        .expect("connects");
    let (mut send, mut recv) = conn.open_bi().await.expect("a stream");
    // A window of 4, less than the server's 6 (the server uses the viewer's): the window
    // of a device whose textures are 4 tiles a side at most.
    let hello = roam_client::conversation::hello(
        Role::Driver,
        r.token.clone(),
        [1280, 720],
        60.0,
        4_000,
        30,
        4 * roam_protocol::tiles::DEFAULT_TILE,
    );
    assert_eq!(hello.color_window, 4);
    wire::write(&mut send, &ClientMessage::Hello(hello))
        .await
        .expect("sends");
    let (welcome, welcome_bytes) = next(&mut recv).await;
    let ServerMessage::Welcome(welcome) = welcome else {
        panic!("expected the welcome, got {welcome:?}");
    };
    let layout = welcome.color;
    assert_eq!(
        (layout.cells, layout.tile, layout.levels, layout.window),
        (256, TILE, 5, 4)
    );
    layout.check().expect("a valid layout");
    // The coarsest tile, next on the control stream: what the viewer draws with first.
    let (first, first_bytes) = next(&mut recv).await;
    let ServerMessage::ColorTile { level, x, z, data } = first else {
        panic!("expected the coarsest tile, got {first:?}");
    };
    assert_eq!((level, x, z), (4, 0, 0));
    assert_eq!(Some(data.as_slice()), pyramid.tile(4, 0, 0));
    let mut texels = Vec::new();
    colormap::decode(TILE, &data, &mut texels).expect("the coarsest tile decodes");
    // All the server sends before its first frame: the welcome and one tile.
    assert!(
        welcome_bytes + first_bytes <= 200 + colormap::max_len(TILE),
        "{welcome_bytes} + {first_bytes} bytes before the first frame"
    );
    // A frame comes (a datagram or a stream of its own).
    tokio::time::timeout(BOUND, async {
        tokio::select! {
            d = conn.read_datagram() => { d.expect("a frame datagram"); }
            s = conn.accept_uni() => { s.expect("a frame stream"); }
        }
    })
    .await
    .expect("a frame in time");
    // The coarsest tile's normals: the first tile after it (windows may move first).
    let mut origins = vec![(0u32, 0u32); usize::from(layout.levels)];
    let mut codes = Vec::new();
    // Windows may move first, a few times at most: bounded, so a missing tile fails.
    for n in 0.. {
        assert!(n < 100, "no normal tile in 100 control messages");
        match next(&mut recv).await.0 {
            ServerMessage::ColorWindow { level, x0, z0 } => {
                assert!(layout.origin_valid(level, x0, z0), "{level} ({x0}, {z0})");
                origins[usize::from(level)] = (x0, z0);
            }
            ServerMessage::NormalTile { level, x, z, data } => {
                assert_eq!((level, x, z), (4, 0, 0));
                assert_eq!(Some(data.as_slice()), normal_tiles.tile(4, 0, 0));
                normals::decode_tile(TILE, &data, &mut codes).expect("the normals decode");
                break;
            }
            other => panic!("expected the coarsest tile's normals, got {other:?}"),
        }
    }
    // Then the rest of every window: levels 3 (2 × 2) and 2 (4 × 4) whole, levels 1
    // and 0 the 4 × 4 around the vehicle (in the order the scheduler's tests check).
    let mut held = BTreeSet::from([(4u8, 0u32, 0u32)]);
    let want = 1 + 4 + 16 + 16 + 16;
    for _ in 0..500 {
        if held.len() == want {
            break;
        }
        match next(&mut recv).await.0 {
            ServerMessage::ColorWindow { level, x0, z0 } => {
                assert!(layout.windowed(level), "a window for level {level}");
                assert!(layout.origin_valid(level, x0, z0), "{level} ({x0}, {z0})");
                origins[usize::from(level)] = (x0, z0);
                held.retain(|&(l, x, z)| l != level || layout.in_window(l, (x0, z0), x, z));
            }
            ServerMessage::ColorTile { level, x, z, data } => {
                let origin = origins[usize::from(level)];
                assert!(layout.in_window(level, origin, x, z), "({level}, {x}, {z})");
                assert_eq!(Some(data.as_slice()), pyramid.tile(level, x, z));
                colormap::decode(layout.tile_side(level), &data, &mut texels)
                    .expect("a tile decodes");
                assert!(held.insert((level, x, z)), "({level}, {x}, {z}) twice");
                // Its normals, next.
                let ServerMessage::NormalTile {
                    level: l,
                    x: nx,
                    z: nz,
                    data,
                } = next(&mut recv).await.0
                else {
                    panic!("expected the normals of ({level}, {x}, {z})");
                };
                assert_eq!((l, nx, nz), (level, x, z));
                assert_eq!(Some(data.as_slice()), normal_tiles.tile(level, x, z));
                normals::decode_tile(layout.tile_side(level), &data, &mut codes)
                    .expect("the normals decode");
            }
            other => panic!("expected colour, got {other:?}"),
        }
    }
    assert_eq!(held.len(), want, "tiles held: {held:?}");
    // The vehicle is inside its finest window.
    let v = r.server.snapshot().vehicles[0].state;
    let at = |c: f64, o: u32| {
        let t = c / welcome.h_scale / f64::from(TILE);
        t >= f64::from(o) && t <= f64::from(o + 4)
    };
    assert!(
        at(v.x, origins[0].0) && at(v.z, origins[0].1),
        "{v:?} {origins:?}"
    );
    let counts = r.server.counts();
    assert_eq!(counts.color_tiles, want as u64);
    assert_eq!(counts.normal_tiles, counts.color_tiles);
    conn.close(0u32.into(), b"done");
    r.server.shutdown().await.expect("stops");
}
