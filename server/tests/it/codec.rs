//! The mesh codec on the tessellator's real meshes: a viewer decodes exactly the server's
//! triangles and heights, key frames and deltas, with frames lost in between.

use std::sync::Arc;

use roam_protocol::mesh;
use roam_protocol::script::{self, DRIVE_SCRIPT};
use roam_protocol::{BitSet, Grid, MeshDecoder, MeshEncoder};
use roam_server::Terrain;
use roam_server::sim::flyover;
use roam_server::terrain::dataset;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator};

fn load(name: &str) -> Arc<Terrain> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name);
    Arc::new(dataset::load(&dir, &mut |_, _| {}).expect("bundled"))
}

/// Tessellates along the benchmark's drive and checks every frame through the codec:
/// returns the bytes per triangle of each frame.
fn drive(name: &str, budget: u32, skip: usize) -> Vec<f64> {
    let terrain = load(name);
    let vt = VarianceTree::build(&terrain.heights, 2, &mut |_, _| {});
    let script = script::parse(DRIVE_SCRIPT).expect("valid");
    let cameras = flyover::drive(&terrain, &script, 60);
    let grid = Grid::new(terrain.heights.levels()).expect("valid");
    let step = roam_protocol::height_step(terrain.heights.samples());
    let (mut enc, mut dec) = (MeshEncoder::with_step(grid, step), MeshDecoder::new(grid));
    let mut tess = Tessellator::new(terrain.heights.side());
    let scales = Scales {
        h: terrain.map.h_scale,
        v: terrain.map.v_scale,
    };
    let limits = Limits {
        budget,
        threshold_px: 0.0,
        fog_density: 0.0,
        guard_deg: 0.0,
    };
    let (mut server, mut viewer) = (Mesh::default(), mesh::Mesh::default());
    let mut acked: Option<BitSet> = None;
    let mut sizes = Vec::new();
    for (k, cam) in cameras.iter().enumerate().step_by(4) {
        tess.tessellate(&terrain.heights, &vt, scales, cam, limits, &mut server);
        let mut split = BitSet::default();
        tess.split_set(&grid, &mut split);
        let mut payload = Vec::new();
        enc.encode(
            &split,
            terrain.heights.samples(),
            acked.as_ref(),
            &mut payload,
        )
        .expect("the tessellator's meshes are conforming");
        // Every `skip`-th frame is lost: never decoded, never a base.
        if skip > 0 && k % (4 * skip) == 4 {
            continue;
        }
        let mut decoded = BitSet::default();
        let info = dec
            .decode(&payload, acked.as_ref(), budget, &mut decoded)
            .unwrap_or_else(|e| panic!("frame {k}: {e}"));
        mesh::emit(&grid, &decoded, dec.heights(), &mut viewer);
        assert_eq!(decoded, split, "frame {k}");
        assert_eq!(viewer.vertices, server.vertices, "frame {k}");
        assert_eq!(viewer.indices, server.indices, "frame {k}");
        for (v, &h) in viewer.vertices.iter().zip(&viewer.heights) {
            assert_eq!(h, terrain.heights.get(u32::from(v[0]), u32::from(v[1])));
        }
        assert_eq!(info.triangles as usize, server.triangle_count());
        sizes.push(payload.len() as f64 / server.triangle_count() as f64);
        acked = Some(split);
    }
    sizes
}

#[test]
fn real_meshes_decode_exactly_and_small() {
    let sizes = drive("kossou", 65_536, 0);
    // The must: a key frame ≤ 2 bytes per triangle, steady driving ≤ 0.5.
    assert!(sizes[0] <= 2.0, "first frame {} B/tri", sizes[0]);
    let worst = sizes[1..].iter().copied().fold(0.0, f64::max);
    assert!(worst <= 0.5, "a delta frame of {worst} B/tri");
}

#[test]
fn lost_frames_do_not_corrupt_the_next() {
    drive("synth-257", 20_000, 3);
}
