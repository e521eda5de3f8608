//! Checks that a mesh is a valid split-only ROAM tessellation of a `size × size` map: it
//! covers the square exactly, every triangle is counter-clockwise seen from above, each
//! interior edge is shared by exactly two triangles (in opposite directions) and no vertex
//! lies inside another triangle's edge. Used by tests and by viewers checking what they
//! decode.

use crate::bintree::ccw;
use std::collections::{HashMap, HashSet};

/// What is wrong with a mesh.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum MeshError {
    #[error("index count {0} is not a multiple of 3")]
    Ragged(usize),
    #[error("triangle {tri}: index {index} out of range (only {vertices} vertices)")]
    Index {
        tri: usize,
        index: u32,
        vertices: usize,
    },
    #[error("vertex {index} at ({x}, {z}) lies off the {size}x{size} map")]
    OffMap {
        index: usize,
        x: u16,
        z: u16,
        size: u32,
    },
    #[error("triangle {tri} is degenerate or clockwise seen from above")]
    Orientation { tri: usize },
    #[error("triangles cover {got} (twice the area) instead of {want}")]
    Area { got: u64, want: u64 },
    #[error("edge ({a:?})-({b:?}) is used twice in the same direction")]
    Overlap { a: [u16; 2], b: [u16; 2] },
    #[error("interior edge ({a:?})-({b:?}) has a triangle on one side only (crack or T-junction)")]
    Crack { a: [u16; 2], b: [u16; 2] },
    #[error("vertex ({v:?}) lies inside edge ({a:?})-({b:?}): a T-junction")]
    TJunction {
        v: [u16; 2],
        a: [u16; 2],
        b: [u16; 2],
    },
    #[error("{0} triangles, over the budget of {1}")]
    Budget(usize, u32),
}

/// Checks the mesh structure described in the module docs.
pub fn check_mesh(vertices: &[[u16; 2]], indices: &[u32], size: u32) -> Result<(), MeshError> {
    if !indices.len().is_multiple_of(3) {
        return Err(MeshError::Ragged(indices.len()));
    }
    for (index, &[x, z]) in vertices.iter().enumerate() {
        if u32::from(x) > size || u32::from(z) > size {
            return Err(MeshError::OffMap { index, x, z, size });
        }
    }
    let mut area = 0u64;
    let mut edges: HashMap<([u16; 2], [u16; 2]), ()> = HashMap::new();
    for (tri, t) in indices.chunks_exact(3).enumerate() {
        let mut v = [[0u16; 2]; 3];
        for k in 0..3 {
            v[k] = *vertices.get(t[k] as usize).ok_or(MeshError::Index {
                tri,
                index: t[k],
                vertices: vertices.len(),
            })?;
        }
        let p = v.map(|[x, z]| (u32::from(x), u32::from(z)));
        let a2 = ccw(p[0], p[1], p[2]);
        if a2 <= 0 {
            return Err(MeshError::Orientation { tri });
        }
        area += a2 as u64;
        for k in 0..3 {
            let (a, b) = (v[k], v[(k + 1) % 3]);
            if edges.insert((a, b), ()).is_some() {
                return Err(MeshError::Overlap { a, b });
            }
        }
    }
    let want = 2 * u64::from(size) * u64::from(size);
    if area != want {
        return Err(MeshError::Area { got: area, want });
    }
    let on_boundary = |a: [u16; 2], b: [u16; 2]| {
        let s = size as u16;
        (a[0] == b[0] && (a[0] == 0 || a[0] == s)) || (a[1] == b[1] && (a[1] == 0 || a[1] == s))
    };
    let used: HashSet<[u16; 2]> = indices.iter().map(|&i| vertices[i as usize]).collect();
    for &(a, b) in edges.keys() {
        if !edges.contains_key(&(b, a)) && !on_boundary(a, b) {
            return Err(MeshError::Crack { a, b });
        }
        // Lattice points strictly inside the edge must not be vertices.
        let (dx, dz) = (
            i32::from(b[0]) - i32::from(a[0]),
            i32::from(b[1]) - i32::from(a[1]),
        );
        let g = gcd(dx.unsigned_abs(), dz.unsigned_abs()) as i32;
        for k in 1..g {
            let v = [
                (i32::from(a[0]) + dx / g * k) as u16,
                (i32::from(a[1]) + dz / g * k) as u16,
            ];
            if used.contains(&v) {
                return Err(MeshError::TJunction { v, a, b });
            }
        }
    }
    Ok(())
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 { a } else { gcd(b, a % b) }
}
