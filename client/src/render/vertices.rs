//! What goes into vertex buffers: the terrain as world-space corners with normals (built on
//! the network thread, so the render thread only uploads), and the vehicle marker's model.
//!
//! **Following the cut** (issue 22): the viewer's [`LiveMesh`] gives each split diamond a
//! slot of four triangle places, and lists the slots a frame rewrote; [`TerrainVertices`]
//! lays the corners out by slot ([`SLOT_CORNERS`] a slot, a place without a triangle
//! written as a degenerate triangle at the origin, which draws nothing) and rewrites only
//! those slots, and the renderer uploads only them (`Renderer::upload_dirty`). A frame
//! then costs what it changed: before, every frame rebuilt every corner of the mesh
//! (65,536 triangles) and uploaded them all.
//!
//! **Normals** are a vertex's own: the height differences across its diamond's four
//! corners (a square's diagonal ones, a rotated diamond's axis ones, one-sided at the
//! map's edge; a map corner's from the two map corners beside it), which are vertices of
//! every cut the vertex is in. A vertex's normal so never changes while it is in the cut,
//! which is what lets a frame rewrite only the triangles it changed (an area-weighted
//! normal of the triangles around a vertex, as before, changed with every split or merge
//! near it, and so rewrote the corners of the triangles around the triangles changed);
//! it also does not flicker as detail comes and goes nearby, and it is the finite
//! difference at the scale the vertex is drawn at.

use std::collections::HashMap;

use roam_protocol::Grid;
use roam_protocol::mesh::{LiveMesh, NO_TRIANGLE, SLOT_TRIANGLES};

use super::Scene;
use super::math::{cross, normalize, sub};

/// One triangle corner: world position and a unit normal packed as signed 16-bit. A
/// corner's barycentric coordinate (for the wireframe) and its colour-map coordinate are
/// derived in the shader from the vertex index and the position, so a corner is 20 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Vertex {
    pub pos: [f32; 3],
    pub normal: [i16; 4],
}

/// Corners per [`LiveMesh`] slot.
pub const SLOT_CORNERS: usize = 3 * SLOT_TRIANGLES;

/// The corners of grid vertex `(x, z)` of height `y` on `scene`'s scales, its normal from
/// its diamond's corners' heights (`height(x, z)`, `None` for a vertex not held: taken as
/// level with the centre).
fn vertex(
    scene: &Scene,
    grid: &Grid,
    (x, z, y): (u32, u32, u16),
    lift: f32,
    height: impl Fn(u32, u32) -> Option<u16>,
) -> Vertex {
    let (hs, vs) = (scene.h_scale as f32, scene.v_scale as f32);
    let s = grid.size();
    let centre = f32::from(y);
    let at = |dx: i64, dz: i64| -> Option<f32> {
        let (cx, cz) = (i64::from(x) + dx, i64::from(z) + dz);
        let on = cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s);
        on.then(|| f32::from(height(cx as u32, cz as u32).unwrap_or(y)))
    };
    let corner = x.is_multiple_of(s) && z.is_multiple_of(s);
    let (m, square) = if corner {
        (grid.levels(), false)
    } else {
        grid.classify(x, z)
    };
    let d = 1i64 << m;
    // Height gradient in grid units: dH/dx, dH/dz.
    let (gx, gz) = if square {
        let h = |dx, dz| at(dx, dz).unwrap_or(centre);
        let (a, b, c, e) = (h(d, d), h(-d, -d), h(d, -d), h(-d, d));
        let span = 4.0 * d as f32;
        (((a + c) - (b + e)) / span, ((a + e) - (b + c)) / span)
    } else {
        let axis = |dx: i64, dz: i64| {
            let (p, q) = (at(dx, dz), at(-dx, -dz));
            let span = d as f32 * f32::from(u8::from(p.is_some()) + u8::from(q.is_some()));
            if span == 0.0 {
                0.0
            } else {
                (p.unwrap_or(centre) - q.unwrap_or(centre)) / span
            }
        };
        (axis(d, 0), axis(0, d))
    };
    let k = vs / hs;
    Vertex {
        pos: [x as f32 * hs, (centre + lift) * vs, z as f32 * hs],
        normal: pack(normalize([-gx * k, 1.0, -gz * k])),
    }
}

/// What changed in a [`TerrainVertices`] since the last update taken: the network thread's
/// vertices, sent to the render thread's copy ([`TerrainVertices::apply`]).
#[derive(Clone, Debug, Default)]
pub struct TerrainUpdate {
    /// Corners in all.
    pub len: usize,
    pub triangles: usize,
    /// Every corner (`data` is all of them), rather than the slots listed.
    pub full: bool,
    pub slots: Vec<u32>,
    /// [`SLOT_CORNERS`] per slot listed, or every corner.
    pub data: Vec<Vertex>,
}

impl TerrainUpdate {
    /// `self`, then `newer`, as one update; `None` when it would carry more than a full
    /// one (the caller sends a full one instead).
    pub fn then(mut self, newer: TerrainUpdate) -> Option<TerrainUpdate> {
        if newer.full {
            return Some(newer);
        }
        if self.full {
            self.data.resize(newer.len, Vertex::default());
            for (k, &slot) in newer.slots.iter().enumerate() {
                let at = slot as usize * SLOT_CORNERS;
                self.data[at..at + SLOT_CORNERS]
                    .copy_from_slice(&newer.data[k * SLOT_CORNERS..(k + 1) * SLOT_CORNERS]);
            }
        } else {
            if self.data.len() + newer.data.len() > newer.len {
                return None;
            }
            self.slots.extend_from_slice(&newer.slots);
            self.data.extend_from_slice(&newer.data);
        }
        self.len = newer.len;
        self.triangles = newer.triangles;
        Some(self)
    }
}

/// The terrain of one mesh, three corners per triangle, ready to upload: built whole from
/// a [`roam_protocol::Mesh`] ([`TerrainVertices::build`]), or kept up to date slot by slot
/// from a [`LiveMesh`] ([`TerrainVertices::update`]).
#[derive(Clone, Debug, Default)]
pub struct TerrainVertices {
    pub corners: Vec<Vertex>,
    triangles: usize,
    /// Laid out by [`LiveMesh`] slot.
    slotted: bool,
    /// Slots rewritten and not yet uploaded or taken, each once.
    dirty: Vec<u32>,
    is_dirty: Vec<bool>,
    /// Every corner is to be uploaded.
    all: bool,
    /// Scratch: the slots a [`LiveMesh`] rewrote.
    slots: Vec<u32>,
}

impl TerrainVertices {
    pub fn triangles(&self) -> usize {
        self.triangles
    }

    /// Rebuilds from `mesh` (grid vertices, height samples, triangles) on `scene`'s scales.
    /// A triangle with an index out of range (a decoder bug, never trusted) is skipped.
    pub fn build(&mut self, scene: &Scene, mesh: &roam_protocol::Mesh) {
        let Some(grid) = Grid::new(scene.levels) else {
            return;
        };
        let held: HashMap<(u32, u32), u16> = mesh
            .vertices
            .iter()
            .zip(&mesh.heights)
            .map(|(p, &y)| ((u32::from(p[0]), u32::from(p[1])), y))
            .collect();
        let packed: Vec<Vertex> = mesh
            .vertices
            .iter()
            .zip(&mesh.heights)
            .map(|(p, &y)| {
                let (x, z) = (u32::from(p[0]), u32::from(p[1]));
                vertex(scene, &grid, (x, z, y), 0.0, |x, z| {
                    held.get(&(x, z)).copied()
                })
            })
            .collect();
        let n = packed.len();
        self.corners.clear();
        self.corners.reserve(mesh.indices.len());
        for t in mesh.indices.chunks_exact(3) {
            if t.iter().all(|&i| (i as usize) < n) {
                self.corners.extend(t.iter().map(|&i| packed[i as usize]));
            }
        }
        self.triangles = self.corners.len() / 3;
        self.slotted = false;
        self.clear_dirty();
        self.all = true;
    }

    /// Follows `live` (the slots it rewrote since its last update, or every slot when
    /// these vertices were built otherwise), with heights from `height` (a grid index's,
    /// `None` for one not in the cut), each vertex drawn `lift(i)` samples above its
    /// height (a geomorph's, [`super::Morph`]; the normals are the heights'):
    /// O(slots rewritten).
    pub fn update(
        &mut self,
        scene: &Scene,
        live: &mut LiveMesh,
        height: impl Fn(u32) -> Option<u16>,
        lift: impl Fn(u32) -> f32,
    ) {
        let Some(grid) = Grid::new(scene.levels) else {
            return;
        };
        self.slots.clear();
        live.take_dirty(&mut self.slots);
        if !self.slotted {
            self.slotted = true;
            self.clear_dirty();
            self.all = true;
            self.corners.clear();
            self.slots.clear();
            self.slots.extend(0..live.slots() as u32);
        }
        self.corners
            .resize(live.slots() * SLOT_CORNERS, Vertex::default());
        self.is_dirty.resize(live.slots(), false);
        let look = |x: u32, z: u32| height(grid.index(x, z));
        for k in 0..self.slots.len() {
            let slot = self.slots[k];
            let at = slot as usize * SLOT_CORNERS;
            for (j, t) in live.slot(slot).iter().enumerate() {
                let out = &mut self.corners[at + 3 * j..at + 3 * j + 3];
                if *t == NO_TRIANGLE {
                    out.fill(Vertex::default());
                    continue;
                }
                for (c, &i) in out.iter_mut().zip(t) {
                    let (x, z) = grid.coords(i);
                    let y = height(i).unwrap_or(0);
                    *c = vertex(scene, &grid, (x, z, y), lift(i), look);
                }
            }
            self.mark(slot);
        }
        self.triangles = live.triangle_count();
    }

    fn mark(&mut self, slot: u32) {
        if !self.all && !self.is_dirty[slot as usize] {
            self.is_dirty[slot as usize] = true;
            self.dirty.push(slot);
        }
    }

    /// Forgets what changed (a viewer that builds the vertices and uploads nothing).
    pub fn forget_changes(&mut self) {
        self.clear_dirty();
    }

    fn clear_dirty(&mut self) {
        for &s in &self.dirty {
            self.is_dirty[s as usize] = false;
        }
        self.dirty.clear();
        self.all = false;
    }

    /// What to upload: every corner, or the byte ranges of the slots rewritten (adjacent
    /// slots merged), as `(first corner, corners)`; then nothing is pending.
    pub fn take_ranges(&mut self, mut f: impl FnMut(usize, &[Vertex])) {
        if self.all || !self.slotted {
            f(0, &self.corners);
        } else {
            self.dirty.sort_unstable();
            let mut k = 0;
            while k < self.dirty.len() {
                let first = self.dirty[k] as usize;
                let mut end = first + 1;
                k += 1;
                while k < self.dirty.len() && self.dirty[k] as usize == end {
                    end += 1;
                    k += 1;
                }
                let (a, b) = (first * SLOT_CORNERS, end * SLOT_CORNERS);
                f(a, &self.corners[a..b.min(self.corners.len())]);
            }
        }
        self.clear_dirty();
    }

    /// What changed since the last update taken, for a copy on another thread.
    pub fn take_update(&mut self) -> TerrainUpdate {
        let full = self.all || !self.slotted;
        let mut u = TerrainUpdate {
            len: self.corners.len(),
            triangles: self.triangles,
            full,
            ..TerrainUpdate::default()
        };
        if full {
            u.data.extend_from_slice(&self.corners);
        } else {
            for &slot in &self.dirty {
                let at = slot as usize * SLOT_CORNERS;
                u.slots.push(slot);
                u.data
                    .extend_from_slice(&self.corners[at..at + SLOT_CORNERS]);
            }
        }
        self.clear_dirty();
        u
    }

    /// Every corner, as an update (what [`TerrainUpdate::then`] falls back to).
    pub fn full_update(&self) -> TerrainUpdate {
        TerrainUpdate {
            len: self.corners.len(),
            triangles: self.triangles,
            full: true,
            slots: Vec::new(),
            data: self.corners.clone(),
        }
    }

    /// Applies an update taken from another [`TerrainVertices`], marking what it changed.
    pub fn apply(&mut self, u: &TerrainUpdate) {
        self.is_dirty.resize(u.len / SLOT_CORNERS, false);
        if u.full {
            self.corners.clear();
            self.corners.extend_from_slice(&u.data);
            self.clear_dirty();
            self.all = true;
        } else {
            self.corners.resize(u.len, Vertex::default());
            for (k, &slot) in u.slots.iter().enumerate() {
                let at = slot as usize * SLOT_CORNERS;
                if at + SLOT_CORNERS <= self.corners.len() {
                    self.corners[at..at + SLOT_CORNERS]
                        .copy_from_slice(&u.data[k * SLOT_CORNERS..(k + 1) * SLOT_CORNERS]);
                    self.mark(slot);
                }
            }
        }
        self.slotted = true;
        self.triangles = u.triangles;
    }
}

/// A unit vector as signed 16-bit normalised integers.
pub fn pack(n: [f32; 3]) -> [i16; 4] {
    let q = |v: f32| (v.clamp(-1.0, 1.0) * 32767.0).round() as i16;
    [q(n[0]), q(n[1]), q(n[2]), 0]
}

/// The vehicle marker: a hovercraft-like wedge, nose along +Z, 4 m long, lit with flat
/// normals. Corners in metres.
pub fn marker_model() -> Vec<Vertex> {
    let nose = [0.0, 0.6, 2.2];
    let left = [-1.4, 0.5, -1.6];
    let right = [1.4, 0.5, -1.6];
    let top = [0.0, 1.5, -1.0];
    let skirt_l = [-1.6, 0.0, -1.8];
    let skirt_r = [1.6, 0.0, -1.8];
    let skirt_n = [0.0, 0.0, 2.4];
    let faces: [[[f32; 3]; 3]; 8] = [
        [nose, top, left],
        [nose, right, top],
        [left, top, right],
        [nose, left, skirt_l],
        [nose, skirt_l, skirt_n],
        [nose, skirt_r, right],
        [nose, skirt_n, skirt_r],
        [left, right, skirt_r],
    ];
    let mut out = Vec::with_capacity(faces.len() * 3);
    for f in faces {
        let mut n = normalize(cross(sub(f[1], f[0]), sub(f[2], f[0])));
        // Faces are listed either way round; light them from outside.
        let centre = [
            (f[0][0] + f[1][0] + f[2][0]) / 3.0,
            (f[0][1] + f[1][1] + f[2][1]) / 3.0 - 0.6,
            (f[0][2] + f[1][2] + f[2][2]) / 3.0,
        ];
        if n[0] * centre[0] + n[1] * centre[1] + n[2] * centre[2] < 0.0 {
            n = [-n[0], -n[1], -n[2]];
        }
        for p in f {
            out.push(Vertex {
                pos: p,
                normal: pack(n),
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> Scene {
        crate::render::test_scene(1, 10.0, 0.5)
    }

    #[test]
    fn flat_mesh_has_upward_normals_and_world_positions() {
        let mesh = roam_protocol::Mesh {
            vertices: vec![[0, 0], [2, 0], [0, 2], [2, 2]],
            heights: vec![4, 4, 4, 4],
            indices: vec![0, 2, 1, 1, 2, 3],
        };
        let mut t = TerrainVertices::default();
        t.build(&scene(), &mesh);
        assert_eq!(t.triangles(), 2);
        assert_eq!(t.corners[1].pos, [0.0, 2.0, 20.0]);
        for c in &t.corners {
            assert_eq!(c.normal, [0, 32767, 0, 0]);
        }
    }

    /// A corner triple as bits, rotated to start at its least (for comparing as sets).
    fn triangle_set(corners: &[Vertex]) -> std::collections::BTreeSet<Vec<u32>> {
        corners
            .chunks_exact(3)
            .filter(|t| t[0] != Vertex::default() || t[1] != Vertex::default())
            .map(|t| {
                let key: Vec<Vec<u32>> = t
                    .iter()
                    .map(|v| {
                        let mut k: Vec<u32> = v.pos.iter().map(|p| p.to_bits()).collect();
                        k.extend(v.normal.iter().map(|&n| n as u16 as u32));
                        k
                    })
                    .collect();
                let m = (0..3).min_by_key(|&j| key[j].clone()).unwrap_or(0);
                (0..3).flat_map(|j| key[(m + j) % 3].clone()).collect()
            })
            .collect()
    }

    /// Slot by slot, the vertices follow random cuts: after each, they are the vertices
    /// built whole from the same mesh (as sets of triangles), and a copy kept by the
    /// updates taken is the same corner for corner.
    #[test]
    fn updates_follow_the_cut_as_a_whole_build_does() {
        use roam_protocol::{BitSet, Grid, LiveMesh};
        let scene = crate::render::test_scene(6, 10.0, 0.5);
        let grid = Grid::new(6).expect("a grid");
        let height = |i: u32| (i.wrapping_mul(2_654_435_761) >> 20) as u16;
        let mut live = LiveMesh::new(&grid);
        let (mut terrain, mut copy) = (TerrainVertices::default(), TerrainVertices::default());
        let mut before = BitSet::new(grid.vertices());
        let mut seed = 7u64;
        for round in 0..40 {
            let mut now = BitSet::new(grid.vertices());
            for _ in 0..(round % 7) * 5 {
                seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
                let (x, z) = ((seed >> 33) as u32 % 65, (seed >> 45) as u32 % 65);
                grid.split_closed(&mut now, x, z);
            }
            let toggled: Vec<u32> = (0..grid.vertices() as u32)
                .filter(|&i| now.contains(i) != before.contains(i))
                .collect();
            live.update(&grid, toggled.into_iter(), |i| now.contains(i));
            let held = |i: u32| {
                let (x, z) = grid.coords(i);
                let corner = x % 64 == 0 && z % 64 == 0;
                (corner || now.contains(i)).then(|| height(i))
            };
            terrain.update(&scene, &mut live, held, |_| 0.0);
            copy.apply(&terrain.take_update());
            assert_eq!(copy.corners, terrain.corners, "round {round}");
            assert_eq!(copy.triangles(), live.triangle_count());
            let mut whole = TerrainVertices::default();
            whole.build(&scene, &live.to_mesh(&grid, held));
            assert_eq!(whole.triangles(), live.triangle_count());
            assert_eq!(triangle_set(&terrain.corners), triangle_set(&whole.corners));
            before = now;
        }
    }

    #[test]
    fn out_of_range_indices_are_skipped() {
        let mesh = roam_protocol::Mesh {
            vertices: vec![[0, 0], [2, 0], [0, 2]],
            heights: vec![0, 0, 0],
            indices: vec![0, 2, 1, 0, 2, 9],
        };
        let mut t = TerrainVertices::default();
        t.build(&scene(), &mesh);
        assert_eq!(t.triangles(), 1);
    }

    #[test]
    fn marker_faces_point_outwards() {
        let m = marker_model();
        assert_eq!(m.len(), 24);
        let up = m.iter().filter(|v| v.normal[1] > 0).count();
        assert!(up >= 9, "the top faces are lit from above: {up}");
    }
}
