//! The tessellator does no heap allocation per frame once warm: a counting global allocator
//! watches the frames that follow a short warm-up.
//!
//! Only allocations made on the thread that switched counting on are counted, into that
//! thread's own counters: the test harness runs other threads (and tests) beside it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;

use roam_protocol::validate::check_mesh;
use roam_server::terrain::dataset;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Limits, Mesh, Scales, Tessellator};
use roam_server::{Heightfield, Terrain};

struct Counting;

thread_local! {
    // Const-initialised and without destructors, so touching them from inside the
    // allocator never allocates.
    /// Counting is on for this thread.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    /// Allocations (`alloc`, `alloc_zeroed`, `realloc`) counted on this thread.
    static ALLOCS: Cell<usize> = const { Cell::new(0) };
    /// Deallocations counted on this thread.
    static DEALLOCS: Cell<usize> = const { Cell::new(0) };
}

/// Adds one to `counter` when counting is on for this thread.
fn bump(counter: &'static std::thread::LocalKey<Cell<usize>>) {
    if COUNTING.try_with(Cell::get).unwrap_or(false) {
        let _ = counter.try_with(|c| c.set(c.get() + 1));
    }
}

// SAFETY: every call is forwarded unchanged to `System`; the counters have no effect on
// the memory handed out.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS);
        // SAFETY: the caller upholds `GlobalAlloc::alloc`'s contract, passed on as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS);
        // SAFETY: as for `alloc`.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        bump(&ALLOCS);
        // SAFETY: as for `alloc`; `ptr` came from this allocator, hence from `System`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        bump(&DEALLOCS);
        // SAFETY: as for `realloc`.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Allocations and deallocations made by `f` on this thread.
fn count<R>(f: impl FnOnce() -> R) -> (R, usize, usize) {
    let (a0, d0) = (ALLOCS.with(Cell::get), DEALLOCS.with(Cell::get));
    COUNTING.with(|c| c.set(true));
    let r = f();
    COUNTING.with(|c| c.set(false));
    (
        r,
        ALLOCS.with(Cell::get) - a0,
        DEALLOCS.with(Cell::get) - d0,
    )
}

fn load() -> (Terrain, VarianceTree) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/synth-257");
    let terrain = dataset::load(&dir, &mut |_, _| {}).expect("the bundled data set loads");
    let vt = VarianceTree::build(&terrain.heights, 2, &mut |_, _| {});
    (terrain, vt)
}

/// Camera number `i` of a deterministic walk over the map: varied positions, heights,
/// headings and pitches, all looking at some of the terrain.
fn camera(t: &Terrain, i: u32) -> Camera {
    let hf: &Heightfield = &t.heights;
    let size = hf.size();
    let f = f64::from(i);
    // Grid position on a Lissajous path, kept a little inside the map.
    let gx = (0.5 + 0.42 * (f * 0.71).sin()) * f64::from(size);
    let gz = (0.5 + 0.42 * (f * 0.37 + 1.0).cos()) * f64::from(size);
    let (cx, cz) = (gx.round() as u32, gz.round() as u32);
    let ground = f64::from(hf.get(cx, cz)) * t.map.v_scale;
    Camera {
        eye: [
            gx * t.map.h_scale,
            ground + 5.0 + 40.0 * f64::from(i % 5),
            gz * t.map.h_scale,
        ],
        yaw_deg: f * 47.0 % 360.0,
        pitch_deg: -5.0 - f64::from(i % 7) * 6.0,
        fov_y_deg: 60.0,
        width: 1920,
        height: 1080,
    }
}

/// Bytes reserved by a mesh's buffers.
fn mesh_bytes(m: &Mesh) -> usize {
    m.vertices.capacity() * 4 + m.indices.capacity() * 4
}

#[test]
fn warm_tessellator_does_not_allocate() {
    let (terrain, vt) = load();
    let hf = &terrain.heights;
    let scales = Scales {
        h: terrain.map.h_scale,
        v: terrain.map.v_scale,
    };
    let limits = Limits {
        budget: 20_000,
        threshold_px: 0.0,
        // The map's fog: the fog-aware priority allocates nothing either.
        fog_density: terrain.map.fog_density as f32,
        guard_deg: 0.0,
    };
    let mut tess = Tessellator::new(hf.side());
    let mut mesh = Mesh::default();

    // Warm-up: a few frames from different cameras, same budget.
    for i in 0..4 {
        tess.tessellate(hf, &vt, scales, &camera(&terrain, i), limits, &mut mesh);
    }
    let warm_bytes = tess.heap_bytes();

    let mut triangles = Vec::new();
    for i in 100..120 {
        let cam = camera(&terrain, i);
        let before = (tess.heap_bytes(), mesh_bytes(&mesh));
        let ((), allocs, deallocs) =
            count(|| tess.tessellate(hf, &vt, scales, &cam, limits, &mut mesh));
        assert_eq!(
            (allocs, deallocs),
            (0, 0),
            "frame {i} ({cam:?}): {allocs} allocations, {deallocs} deallocations once warm; \
             (tessellator, mesh) bytes {before:?} before, {:?} after",
            (tess.heap_bytes(), mesh_bytes(&mesh))
        );
        // The frame did real work, within the budget, and produced a valid mesh.
        let n = mesh.triangle_count();
        assert!(
            n > 2 && n <= limits.budget as usize,
            "frame {i}: {n} triangles"
        );
        check_mesh(&mesh.vertices, &mesh.indices, hf.size())
            .unwrap_or_else(|e| panic!("frame {i}: {e:?}"));
        triangles.push(n);
    }
    assert_eq!(tess.heap_bytes(), warm_bytes, "pools grew after warm-up");
    // The cameras differ enough to give different meshes.
    triangles.sort_unstable();
    triangles.dedup();
    assert!(
        triangles.len() > 1 || triangles[0] == limits.budget as usize,
        "all frames gave {triangles:?} triangles"
    );

    // A smaller budget fits in the pools sized for the larger one.
    let small = Limits {
        budget: 1_000,
        ..limits
    };
    for i in [3, 100, 200] {
        let cam = camera(&terrain, i);
        let ((), allocs, deallocs) =
            count(|| tess.tessellate(hf, &vt, scales, &cam, small, &mut mesh));
        assert_eq!(
            (allocs, deallocs),
            (0, 0),
            "frame {i} with budget {}: {allocs} allocations, {deallocs} deallocations",
            small.budget
        );
        assert!(mesh.triangle_count() <= small.budget as usize);
        check_mesh(&mesh.vertices, &mesh.indices, hf.size())
            .unwrap_or_else(|e| panic!("small frame {i}: {e:?}"));
    }
}

#[test]
fn the_counter_sees_allocations() {
    // Guards the test above against a counter that never counts.
    let (v, allocs, _) = count(|| std::hint::black_box(vec![1u8; 64]));
    assert_eq!(v.len(), 64);
    assert!(allocs >= 1, "a Vec allocation went uncounted");
    let (_, allocs, deallocs) = count(|| drop(v));
    assert_eq!((allocs, deallocs), (0, 1), "dropping the Vec");
    let (_, allocs, deallocs) = count(|| ());
    assert_eq!((allocs, deallocs), (0, 0));
}
