//! Geometry of the triangle bintree, diamond by diamond.
//!
//! Grid coordinates run `0..=size` on both axes (`size = side - 1 = 2^N`); `x` is the column
//! (east), `z` the row (south). Splitting a bintree triangle bisects its hypotenuse; the two
//! triangles sharing a hypotenuse form a *diamond*, and in a conforming split-only mesh they
//! are always split together. Every grid vertex except the four corners is the centre (split
//! vertex) of exactly one diamond, so a mesh is fully described by the set of split
//! ("active") diamonds, and per-diamond data needs about one slot per sample.
//!
//! Two shapes alternate with depth, `h = 2^m` being the half-size:
//! - **square**: centre `(x, z)` with `x ≡ z ≡ h (mod 2h)`; its triangles are the two halves
//!   of the `2h` cell around it, cut along one diagonal (the hypotenuse); the other two cell
//!   corners are the apices, i.e. the centres of its two *parent* diamonds. Which diagonal
//!   alternates cell by cell (the seed's alternating-diagonal pattern).
//! - **rotated**: centre on the midpoint of an axis-aligned cell edge of length `2h`; that edge
//!   is the hypotenuse, the apices (parents) lie `h` away on either side of it. On the map's
//!   boundary only one triangle (one parent) exists.
//!
//! The root diamond is the square one at the map's centre (`h = size / 2`): the two root
//! triangles share the NW–SE diagonal and have no parents.

/// Grid vertex `(x, z)`.
pub type Vertex = (u32, u32);

/// A bintree triangle: right angle at `apex`, hypotenuse from `left` to `right`, and
/// `apex → left → right` counter-clockwise seen from above (+Y), so face normals point up.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Triangle {
    pub apex: Vertex,
    pub left: Vertex,
    pub right: Vertex,
}

impl Triangle {
    /// The two root triangles of a `size × size` map.
    pub fn roots(size: u32) -> [Triangle; 2] {
        [
            Triangle {
                apex: (size, 0),
                left: (0, 0),
                right: (size, size),
            },
            Triangle {
                apex: (0, size),
                left: (size, size),
                right: (0, 0),
            },
        ]
    }

    /// Midpoint of the hypotenuse, if it is a grid vertex (else the triangle is a leaf of the
    /// full-resolution bintree).
    pub fn split_vertex(&self) -> Option<Vertex> {
        let (sx, sz) = (self.left.0 + self.right.0, self.left.1 + self.right.1);
        (sx % 2 == 0 && sz % 2 == 0).then_some((sx / 2, sz / 2))
    }

    /// The two halves, in bintree order (left child first). `None` at full resolution.
    pub fn children(&self) -> Option<[Triangle; 2]> {
        let m = self.split_vertex()?;
        Some([
            Triangle {
                apex: m,
                left: self.apex,
                right: self.left,
            },
            Triangle {
                apex: m,
                left: self.right,
                right: self.apex,
            },
        ])
    }

    /// The triangle's vertices in counter-clockwise order.
    pub fn vertices(&self) -> [Vertex; 3] {
        [self.apex, self.left, self.right]
    }
}

/// The two diamond shapes; see the module docs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Shape {
    Square,
    /// Hypotenuse along `x` (`horizontal`) or along `z`.
    Rotated {
        horizontal: bool,
    },
}

/// A diamond, named by its centre.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Diamond {
    pub x: u32,
    pub z: u32,
    /// `h = 2^m`.
    pub m: u32,
    pub shape: Shape,
}

impl Diamond {
    /// The diamond centred at `(x, z)` on a `size × size` map; `None` for corners and
    /// points outside the map.
    pub fn at(x: u32, z: u32, size: u32) -> Option<Diamond> {
        if x > size || z > size || (x.is_multiple_of(size) && z.is_multiple_of(size)) {
            return None;
        }
        let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
        Some(if tx == tz {
            Diamond {
                x,
                z,
                m: tx,
                shape: Shape::Square,
            }
        } else {
            Diamond {
                x,
                z,
                m: tx.min(tz),
                shape: Shape::Rotated {
                    horizontal: tx < tz,
                },
            }
        })
    }

    /// The root diamond of a `size × size` map.
    pub fn root(size: u32) -> Diamond {
        Diamond {
            x: size / 2,
            z: size / 2,
            m: size.trailing_zeros() - 1,
            shape: Shape::Square,
        }
    }

    pub fn h(&self) -> u32 {
        1 << self.m
    }

    pub fn centre(&self) -> Vertex {
        (self.x, self.z)
    }

    /// Depth in the bintree of the diamond's triangles (the root diamond is 0, the finest
    /// diamonds `2N - 1`).
    pub fn depth(&self, size: u32) -> u32 {
        let n = size.trailing_zeros();
        match self.shape {
            Shape::Square => 2 * (n - 1 - self.m),
            Shape::Rotated { .. } => 2 * (n - self.m) - 1,
        }
    }

    /// Whether this is the map's root diamond.
    pub fn is_root(&self, size: u32) -> bool {
        self.shape == Shape::Square && self.h() * 2 == size
    }

    /// Centres of the parent diamonds (the apices of its triangles), those that exist.
    pub fn parents(&self, size: u32) -> [Option<Vertex>; 2] {
        let (x, z, h) = (self.x, self.z, self.h());
        match self.shape {
            Shape::Square if self.is_root(size) => [None, None],
            Shape::Square => {
                if ((x + h) / (2 * h) + (z + h) / (2 * h)) % 2 == 1 {
                    [Some((x + h, z + h)), Some((x - h, z - h))]
                } else {
                    [Some((x + h, z - h)), Some((x - h, z + h))]
                }
            }
            Shape::Rotated { horizontal: true } => [
                (z >= h).then(|| (x, z - h)),
                (z + h <= size).then(|| (x, z + h)),
            ],
            Shape::Rotated { horizontal: false } => [
                (x >= h).then(|| (x - h, z)),
                (x + h <= size).then(|| (x + h, z)),
            ],
        }
    }

    /// Ends of the shared hypotenuse.
    pub fn hypotenuse(&self, size: u32) -> [Vertex; 2] {
        let (x, z, h) = (self.x, self.z, self.h());
        match self.shape {
            Shape::Square => {
                if self.is_root(size) || ((x + h) / (2 * h) + (z + h) / (2 * h)) % 2 == 0 {
                    [(x - h, z - h), (x + h, z + h)]
                } else {
                    [(x + h, z - h), (x - h, z + h)]
                }
            }
            Shape::Rotated { horizontal: true } => [(x - h, z), (x + h, z)],
            Shape::Rotated { horizontal: false } => [(x, z - h), (x, z + h)],
        }
    }

    /// The diamond's triangles (one on the map's boundary, else two), counter-clockwise.
    pub fn triangles(&self, size: u32) -> Vec<Triangle> {
        let [p, q] = self.hypotenuse(size);
        let apices: Vec<Vertex> = if self.is_root(size) {
            vec![(size, 0), (0, size)]
        } else {
            self.parents(size).into_iter().flatten().collect()
        };
        apices
            .into_iter()
            .map(|apex| {
                let t = Triangle {
                    apex,
                    left: p,
                    right: q,
                };
                if ccw(t.apex, t.left, t.right) > 0 {
                    t
                } else {
                    Triangle {
                        apex,
                        left: q,
                        right: p,
                    }
                }
            })
            .collect()
    }

    /// Centres of the child diamonds that exist (four inside the map, fewer on its edge,
    /// none at full resolution).
    pub fn children(&self, size: u32) -> Vec<Vertex> {
        let (x, z, h) = (self.x as i64, self.z as i64, self.h() as i64);
        let offsets: Vec<(i64, i64)> = match self.shape {
            Shape::Square => vec![(h, 0), (-h, 0), (0, h), (0, -h)],
            Shape::Rotated { .. } if h == 1 => vec![],
            Shape::Rotated { .. } => {
                let k = h / 2;
                vec![(k, k), (-k, k), (k, -k), (-k, -k)]
            }
        };
        let s = size as i64;
        offsets
            .into_iter()
            .map(|(dx, dz)| (x + dx, z + dz))
            .filter(|&(cx, cz)| (0..=s).contains(&cx) && (0..=s).contains(&cz))
            .map(|(cx, cz)| (cx as u32, cz as u32))
            .collect()
    }
}

/// Twice the signed area of `a, b, c` seen from above: positive when counter-clockwise with
/// `x` east and `z` south (the y component of `(b - a) × (c - a)`).
pub fn ccw(a: Vertex, b: Vertex, c: Vertex) -> i64 {
    let (ax, az) = (a.0 as i64, a.1 as i64);
    let (bx, bz) = (b.0 as i64 - ax, b.1 as i64 - az);
    let (cx, cz) = (c.0 as i64 - ax, c.1 as i64 - az);
    bz * cx - bx * cz
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_non_corner_vertex_is_one_diamond() {
        let size = 16;
        let mut count = 0;
        for z in 0..=size {
            for x in 0..=size {
                match Diamond::at(x, z, size) {
                    None => assert!(x.is_multiple_of(size) && z.is_multiple_of(size)),
                    Some(d) => {
                        count += 1;
                        // Its triangles are children of its parents' triangles and split at
                        // its centre.
                        for t in d.triangles(size) {
                            assert_eq!(t.split_vertex(), Some((x, z)), "{d:?}");
                            assert!(ccw(t.apex, t.left, t.right) > 0);
                        }
                        for p in d.parents(size).into_iter().flatten() {
                            let pd = Diamond::at(p.0, p.1, size).expect("parents are diamonds");
                            assert!(pd.children(size).contains(&(x, z)), "{pd:?} -> {d:?}");
                            assert_eq!(pd.depth(size) + 1, d.depth(size));
                        }
                        for c in d.children(size) {
                            let cd = Diamond::at(c.0, c.1, size).expect("children are diamonds");
                            assert!(cd.parents(size).contains(&Some((x, z))));
                        }
                    }
                }
            }
        }
        assert_eq!(count, 17 * 17 - 4);
    }

    #[test]
    fn triangles_of_a_diamond_are_children_of_its_parents_triangles() {
        let size = 16;
        // Walk the bintree from the roots; every triangle must be one of its diamond's.
        let mut stack = Triangle::roots(size).to_vec();
        let mut seen = 0;
        while let Some(t) = stack.pop() {
            if let Some(m) = t.split_vertex() {
                let d = Diamond::at(m.0, m.1, size).expect("split vertices are diamonds");
                assert!(d.triangles(size).contains(&t), "{t:?} not in {d:?}");
                seen += 1;
                stack.extend(t.children().expect("split vertex exists"));
            }
        }
        // Interior triangles of a full bintree of depth 2N: 2 * (4^N - 1).
        assert_eq!(seen, 2 * (256 - 1));
    }
}
