//! What goes into vertex buffers: the terrain as world-space corners with smooth normals
//! (built on the network thread, so the render thread only uploads), and the vehicle
//! marker's model.

use super::Scene;
use super::math::{cross, normalize, sub};

/// One triangle corner: world position and a unit normal packed as signed 16-bit. A
/// corner's barycentric coordinate (for the wireframe) and its colour-map coordinate are
/// derived in the shader from the vertex index and the position, so a corner is 20 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Vertex {
    pub pos: [f32; 3],
    pub normal: [i16; 4],
}

/// The terrain of one mesh, three corners per triangle, ready to upload.
#[derive(Clone, Debug, Default)]
pub struct TerrainVertices {
    pub corners: Vec<Vertex>,
    /// Scratch: per-vertex positions and normal sums, kept to avoid reallocating.
    world: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    packed: Vec<Vertex>,
}

impl TerrainVertices {
    pub fn triangles(&self) -> usize {
        self.corners.len() / 3
    }

    /// Rebuilds from `mesh` (grid vertices, height samples, triangles) on `scene`'s scales.
    /// Normals are smooth: each vertex's area-weighted face normals. A triangle with an
    /// index out of range (a decoder bug, never trusted) is skipped.
    pub fn build(&mut self, scene: &Scene, mesh: &roam_protocol::Mesh) {
        let (h, v) = (scene.h_scale as f32, scene.v_scale as f32);
        self.world.clear();
        self.world.extend(
            mesh.vertices
                .iter()
                .zip(&mesh.heights)
                .map(|(p, &y)| [f32::from(p[0]) * h, f32::from(y) * v, f32::from(p[1]) * h]),
        );
        let n = self.world.len();
        let ok = |t: &[u32]| t.iter().all(|&i| (i as usize) < n);
        self.normals.clear();
        self.normals.resize(n, [0.0; 3]);
        for t in mesh.indices.chunks_exact(3).filter(|t| ok(t)) {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| self.world[i as usize]);
            // Counter-clockwise seen from above: (b − a) × (c − a) points up.
            let f = cross(sub(b, a), sub(c, a));
            for &i in t {
                let m = &mut self.normals[i as usize];
                m[0] += f[0];
                m[1] += f[1];
                m[2] += f[2];
            }
        }
        // Each vertex packed once; corners copy it.
        self.packed.clear();
        self.packed.extend(
            self.world
                .iter()
                .zip(&self.normals)
                .map(|(&pos, &n)| Vertex {
                    pos,
                    normal: pack(normalize(n)),
                }),
        );
        self.corners.clear();
        self.corners.reserve(mesh.indices.len());
        for t in mesh.indices.chunks_exact(3).filter(|t| ok(t)) {
            self.corners
                .extend(t.iter().map(|&i| self.packed[i as usize]));
        }
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
