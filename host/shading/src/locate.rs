//! Direction → (captured direction, weight) pairs, the two interpolations of
//! docs/material-format.md ("Shading").
//!
//! - [`TriangleLocator`] (default): spherical barycentric weights over
//!   triangles of the calibrated directions, w = M⁻¹·d normalised to sum 1,
//!   M = [v₀ v₁ v₂]. A weight vanishes on the great circle through the other
//!   two vertices, so the weights are continuous across shared edges and
//!   exactly (1, 0, 0) at a vertex. A direction outside every triangle takes
//!   the nearest point of the triangulation's boundary (great-circle arcs):
//!   it clamps to the nearest covered direction.
//! - [`CellLocator`] (patent, Fig. 11A): a table over azimuth × polar angle
//!   whose cells list (direction, count / points) pairs.
//!
//! Both are built once when a material is opened; a lookup allocates nothing.

use crate::error::MaterialError;
use crate::format::CellTable;

type V3 = [f32; 3];

#[inline(always)]
fn dot(a: V3, b: V3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: V3, b: V3) -> V3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Up to three (direction index, weight) pairs.
pub type Weights3 = [(u16, f32); 3];

/// A triangle with the inverse of its vertex matrix.
#[derive(Debug, Clone)]
struct Tri {
    ids: [u16; 3],
    /// Rows of M⁻¹: wᵢ = inv[i] · d.
    inv: [V3; 3],
}

impl Tri {
    /// Barycentric weights of `d` (not normalised).
    #[inline(always)]
    fn raw(&self, d: V3) -> V3 {
        [dot(self.inv[0], d), dot(self.inv[1], d), dot(self.inv[2], d)]
    }
}

/// A boundary arc between two directions.
#[derive(Debug, Clone)]
struct Edge {
    ids: [u16; 2],
    a: V3,
    b: V3,
    /// Unit normal of the great circle through a and b.
    n: V3,
    /// n × a and b × n: d projects inside the arc iff d · na ≥ 0 and d · nb ≥ 0.
    na: V3,
    nb: V3,
    /// a · b.
    c: f32,
}

impl Edge {
    fn new(ids: [u16; 2], a: V3, b: V3) -> Option<Edge> {
        let n = cross(a, b);
        let len = dot(n, n).sqrt();
        (len > 1e-9).then(|| {
            let n = n.map(|x| x / len);
            Edge { ids, a, b, n, na: cross(n, a), nb: cross(b, n), c: dot(a, b) }
        })
    }

    /// The nearest point of the arc to `d`: (cosine of the angle to it,
    /// weights on the two ends).
    ///
    /// The projection p = d − (d·n) n of d on the arc's great circle lies
    /// within the arc iff (a × p) · n ≥ 0 and (p × b) · n ≥ 0, i.e.
    /// d · (n × a) ≥ 0 and d · (b × n) ≥ 0; and a · p = a · d, b · p = b · d
    /// since a and b are normal to n.
    #[inline]
    fn nearest(&self, d: V3) -> (f32, [f32; 2]) {
        let (da, db) = (dot(d, self.a), dot(d, self.b));
        if dot(d, self.na) >= 0.0 && dot(d, self.nb) >= 0.0 {
            let dn = dot(d, self.n);
            let plen = (dot(d, d) - dn * dn).max(0.0).sqrt();
            if plen > 1e-6 {
                let den = 1.0 - self.c * self.c;
                let (al, be) = ((da - self.c * db) / den, (db - self.c * da) / den);
                let (al, be) = (al.max(0.0), be.max(0.0));
                let s = al + be;
                if s > 0.0 {
                    return (plen, [al / s, be / s]);
                }
            }
        }
        if da >= db { (da, [1.0, 0.0]) } else { (db, [0.0, 1.0]) }
    }
}

/// Cells per side of the acceleration grid over the orthographic (x, y) of
/// a direction.
const GRID: usize = 64;
/// How far below zero a barycentric weight may be and still count as inside.
const INSIDE: f32 = -1e-6;

/// The default interpolation's lookup.
#[derive(Debug, Clone)]
pub struct TriangleLocator {
    dirs: Vec<V3>,
    tris: Vec<Tri>,
    edges: Vec<Edge>,
    /// Per grid cell: (start in `cands`, triangles, then edges).
    cells: Vec<(u32, u16, u16)>,
    cands: Vec<u16>,
}

impl TriangleLocator {
    /// Check the triangles over `dirs` (unit vectors) and build the lookup.
    pub fn new(dirs: &[V3], tris: &[[u16; 3]], what: &str) -> Result<Self, MaterialError> {
        let bad = |s: String| Err(MaterialError::Value(format!("{what}: {s}")));
        let n = dirs.len();
        let mut out = Vec::with_capacity(tris.len());
        let mut uses: std::collections::BTreeMap<(u16, u16), u32> = Default::default();
        for t in tris {
            if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] || t.iter().any(|&i| i as usize >= n) {
                return bad(format!("triangle {t:?} is not three distinct directions of {n}"));
            }
            let [a, b, c] = t.map(|i| dirs[i as usize].map(f64::from));
            // M = [a b c] as columns; M⁻¹ rows are (b×c, c×a, a×b) / det.
            let cr = |x: [f64; 3], y: [f64; 3]| {
                [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]]
            };
            let (bc, ca, ab) = (cr(b, c), cr(c, a), cr(a, b));
            let det = a[0] * bc[0] + a[1] * bc[1] + a[2] * bc[2];
            if det.abs() < 1e-9 {
                return bad(format!("triangle {t:?} is degenerate"));
            }
            let row = |r: [f64; 3]| r.map(|x| (x / det) as f32);
            out.push(Tri { ids: *t, inv: [row(bc), row(ca), row(ab)] });
            for k in 0..3 {
                let (p, q) = (t[k], t[(k + 1) % 3]);
                *uses.entry((p.min(q), p.max(q))).or_default() += 1;
            }
        }
        if let Some(((p, q), u)) = uses.iter().find(|&(_, &u)| u > 2) {
            return bad(format!("edge {p}–{q} is shared by {u} triangles"));
        }
        let mut edge_list: Vec<[u16; 2]> =
            uses.iter().filter(|&(_, &u)| u == 1).map(|(&(p, q), _)| [p, q]).collect();
        if tris.is_empty() {
            // One or two directions: the arc between them is the whole set.
            match n {
                1 => {}
                2 => edge_list.push([0, 1]),
                _ => return bad(format!("{n} directions but no triangles")),
            }
        }
        let edges: Vec<Edge> = edge_list
            .iter()
            .filter_map(|&[p, q]| Edge::new([p, q], dirs[p as usize], dirs[q as usize]))
            .collect();
        let mut loc = TriangleLocator {
            dirs: dirs.to_vec(),
            tris: out,
            edges,
            cells: Vec::new(),
            cands: Vec::new(),
        };
        loc.build_grid();
        Ok(loc)
    }

    /// The grid: per cell, every triangle that contains one of 5 × 5 points
    /// over the cell, and its edge neighbours; where a point is outside
    /// them all, the nearest boundary arcs and their neighbours.
    fn build_grid(&mut self) {
        const SUB: usize = 5;
        let mut tri_nb: Vec<Vec<usize>> = vec![Vec::new(); self.tris.len()];
        for (i, a) in self.tris.iter().enumerate() {
            for (j, b) in self.tris.iter().enumerate() {
                let shared = a.ids.iter().filter(|x| b.ids.contains(x)).count();
                if i != j && shared == 2 {
                    tri_nb[i].push(j);
                }
            }
        }
        for cy in 0..GRID {
            for cx in 0..GRID {
                let mut tris: Vec<usize> = Vec::new();
                let mut edges: Vec<usize> = Vec::new();
                for sy in 0..SUB {
                    for sx in 0..SUB {
                        let x =
                            -1.0 + 2.0 * (cx as f32 + sx as f32 / (SUB - 1) as f32) / GRID as f32;
                        let y =
                            -1.0 + 2.0 * (cy as f32 + sy as f32 / (SUB - 1) as f32) / GRID as f32;
                        let r2 = x * x + y * y;
                        let d = if r2 < 1.0 {
                            [x, y, (1.0 - r2).sqrt()]
                        } else {
                            let r = r2.sqrt();
                            [x / r, y / r, 0.0]
                        };
                        let before = tris.len();
                        tris.extend(
                            (0..self.tris.len())
                                .filter(|&t| self.tris[t].raw(d).iter().all(|&w| w >= INSIDE)),
                        );
                        if tris.len() == before
                            && let Some(e) = self.nearest_edge(d, 0..self.edges.len())
                        {
                            edges.push(e);
                        }
                    }
                }
                tris.sort_unstable();
                tris.dedup();
                let near: Vec<usize> = tris.iter().flat_map(|&t| tri_nb[t].clone()).collect();
                tris.extend(near.into_iter().filter(|t| !tris.contains(t)).collect::<Vec<_>>());
                edges.sort_unstable();
                edges.dedup();
                let all_edges = &self.edges;
                let near: Vec<usize> = edges
                    .iter()
                    .flat_map(|&e| {
                        let ids = all_edges[e].ids;
                        (0..all_edges.len())
                            .filter(move |&f| all_edges[f].ids.iter().any(|x| ids.contains(x)))
                    })
                    .collect();
                edges.extend(near);
                edges.sort_unstable();
                edges.dedup();
                self.cells.push((self.cands.len() as u32, tris.len() as u16, edges.len() as u16));
                self.cands.extend(tris.iter().chain(&edges).map(|&i| i as u16));
            }
        }
    }

    fn nearest_edge(&self, d: V3, among: impl Iterator<Item = usize>) -> Option<usize> {
        let mut best: Option<(f32, usize)> = None;
        for e in among {
            let (s, _) = self.edges[e].nearest(d);
            if best.is_none_or(|(b, _)| s > b) {
                best = Some((s, e));
            }
        }
        best.map(|(_, e)| e)
    }

    #[inline(always)]
    fn tri_weights(&self, t: &Tri, d: V3, out: &mut Weights3) -> bool {
        let w = t.raw(d);
        if w[0] < INSIDE || w[1] < INSIDE || w[2] < INSIDE {
            return false;
        }
        // Weights below 10⁻⁵ (float noise at a vertex or an edge) are
        // dropped, so a captured direction reads one image, an edge two.
        let w = w.map(|x| if x < 1e-5 { 0.0 } else { x });
        let s = w[0] + w[1] + w[2];
        if s <= 0.0 {
            return false;
        }
        // Divided, not multiplied by 1/s: exactly 1 at a vertex.
        *out = [(t.ids[0], w[0] / s), (t.ids[1], w[1] / s), (t.ids[2], w[2] / s)];
        true
    }

    fn edge_weights(&self, e: usize, d: V3, out: &mut Weights3) {
        let edge = &self.edges[e];
        let (_, w) = edge.nearest(d);
        *out = [(edge.ids[0], w[0]), (edge.ids[1], w[1]), (0, 0.0)];
    }

    /// The weights of unit direction `d` (z > 0), in `out` (unused slots
    /// have weight 0).
    pub fn weights(&self, d: V3, out: &mut Weights3) {
        if self.dirs.len() == 1 {
            *out = [(0, 1.0), (0, 0.0), (0, 0.0)];
            return;
        }
        let cell = |c: f32| (((c + 1.0) * 0.5 * GRID as f32) as usize).min(GRID - 1);
        let (start, nt, ne) = self.cells[cell(d[1]) * GRID + cell(d[0])];
        let cands = &self.cands[start as usize..start as usize + nt as usize + ne as usize];
        for &t in &cands[..nt as usize] {
            if self.tri_weights(&self.tris[t as usize], d, out) {
                return;
            }
        }
        if ne > 0 {
            let e = self
                .nearest_edge(d, cands[nt as usize..].iter().map(|&e| e as usize))
                .expect("a listed edge");
            return self.edge_weights(e, d, out);
        }
        // Not where the grid expected it (within float rounding of an
        // edge): search everything.
        self.weights_exhaustive(d, out);
    }

    /// [`Self::weights`] without the grid: every triangle, then every
    /// boundary arc (the reference the grid is tested against).
    pub fn weights_exhaustive(&self, d: V3, out: &mut Weights3) {
        if self.dirs.len() == 1 {
            *out = [(0, 1.0), (0, 0.0), (0, 0.0)];
            return;
        }
        for t in &self.tris {
            if self.tri_weights(t, d, out) {
                return;
            }
        }
        match self.nearest_edge(d, 0..self.edges.len()) {
            Some(e) => self.edge_weights(e, d, out),
            None => *out = [(0, 1.0), (0, 0.0), (0, 0.0)],
        }
    }
}

/// The patent's lookup: cells of `360°/columns × 90°/rows`.
#[derive(Debug, Clone)]
pub struct CellLocator {
    columns: usize,
    rows: usize,
    offsets: Vec<u32>,
    pairs: Vec<(u16, f32)>,
}

impl CellLocator {
    /// From a checked table (docs/material-format.md).
    pub fn new(t: &CellTable, columns: u32, rows: u32, points: u32) -> CellLocator {
        CellLocator {
            columns: columns as usize,
            rows: rows as usize,
            offsets: t.offsets.clone(),
            pairs: t
                .mirrors
                .iter()
                .zip(&t.counts)
                .map(|(&m, &c)| (m, c as f32 / points as f32))
                .collect(),
        }
    }

    /// The cell of unit direction `d`: (row, column).
    pub fn cell(columns: usize, rows: usize, d: V3) -> (usize, usize) {
        let mut phi = d[1].atan2(d[0]);
        if phi < 0.0 {
            phi += std::f32::consts::TAU;
        }
        let theta = d[2].clamp(-1.0, 1.0).acos();
        let col = ((phi / std::f32::consts::TAU * columns as f32) as usize).min(columns - 1);
        let row = ((theta / std::f32::consts::FRAC_PI_2 * rows as f32) as usize).min(rows - 1);
        (row, col)
    }

    /// The (direction, weight) pairs of unit direction `d`.
    pub fn weights(&self, d: V3) -> &[(u16, f32)] {
        let (r, c) = Self::cell(self.columns, self.rows, d);
        let i = r * self.columns + c;
        &self.pairs[self.offsets[i] as usize..self.offsets[i + 1] as usize]
    }
}
