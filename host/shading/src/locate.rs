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
    /// `n` or `−n`, whichever points away from every direction, if one
    /// does: the arc then supports the triangulation (it lies on the
    /// boundary of a convex set), and a direction beyond its great circle
    /// whose projection falls within the arc has that projection as its
    /// nearest covered point ([`Edge::answers`]).
    outward: Option<V3>,
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
            Edge { ids, a, b, n, outward: None, na: cross(n, a), nb: cross(b, n), c: dot(a, b) }
        })
    }

    /// Set [`Self::outward`] if every direction of `dirs` lies on one side
    /// of the arc's great circle (within float rounding).
    fn find_outward(&mut self, dirs: &[V3]) {
        const ON: f32 = 1e-6;
        let side = |s: f32| dirs.iter().all(|&d| s * dot(d, self.n) <= ON);
        self.outward = [1.0f32, -1.0].into_iter().find(|&s| side(s)).map(|s| self.n.map(|x| s * x));
    }

    /// Whether the arc alone answers `d`: it supports the triangulation,
    /// `d` lies beyond its great circle and projects within the arc. Then
    /// every covered direction is at least as far from `d` as the great
    /// circle is (a path from `d` to any of them crosses it), and the
    /// projection — covered — is exactly that far: no other arc is nearer.
    #[inline(always)]
    fn answers(&self, d: V3) -> bool {
        self.outward.is_some_and(|o| dot(d, o) > 0.0)
            && dot(d, self.na) >= 0.0
            && dot(d, self.nb) >= 0.0
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
/// Cells per side of the fast-path grid ([`TriangleLocator::primary`]).
const FINE: usize = 128;
/// No fast path for the cell ([`TriangleLocator::primary`]).
const NONE: u8 = u8::MAX;

/// The direction at grid position (gx, gy) ∈ [0, n]² (cell units) of a
/// grid of `n` cells per side over a direction's orthographic (x, y), and
/// whether it lies on the hemisphere; a position beyond the unit circle
/// maps to the horizon point of its azimuth.
fn grid_direction(n: usize, gx: f32, gy: f32) -> (V3, bool) {
    let (x, y) = (-1.0 + 2.0 * gx / n as f32, -1.0 + 2.0 * gy / n as f32);
    let r2 = x * x + y * y;
    if r2 < 1.0 {
        ([x, y, (1.0 - r2).sqrt()], true)
    } else {
        let r = r2.sqrt();
        ([x / r, y / r, 0.0], false)
    }
}

/// The default interpolation's lookup.
#[derive(Debug, Clone)]
pub struct TriangleLocator {
    dirs: Vec<V3>,
    tris: Vec<Tri>,
    edges: Vec<Edge>,
    /// Per grid cell: (start in `cands`, triangles, then edges).
    cells: Vec<(u32, u16, u16)>,
    cands: Vec<u16>,
    /// Per cell of a finer grid (`FINE` per side, same projection): the
    /// triangle `c`, or the supporting arc `c − tris.len()`, that answers
    /// most of the cell, or `NONE`. A lookup tries it first and keeps its
    /// answer only if its own test passes (inside the triangle;
    /// [`Edge::answers`]), so the table only decides how fast, never what.
    /// One byte per cell (16 KB; the material's random reads evict it from
    /// L1 all the same, and 2 bytes measured slower): the triangles and
    /// arcs past the 255th get no fast path.
    primary: Vec<u8>,
}

impl TriangleLocator {
    /// Check the triangles over `dirs` (unit vectors) and build the lookup.
    pub fn new(dirs: &[V3], tris: &[[u16; 3]], what: &str) -> Result<Self, MaterialError> {
        let bad = |s: String| Err(MaterialError::Value(format!("{what}: {s}")));
        let n = dirs.len();
        // Euler: a triangulation of n points on a sphere has 2n − 4
        // triangles, of a patch of it fewer. More would be overlapping
        // triangles — and would only make opening the file slow.
        let most = (2 * n).saturating_sub(4);
        if tris.len() > most {
            return bad(format!(
                "{} triangles over {n} directions: more than a triangulation has ({most})",
                tris.len()
            ));
        }
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
        let mut edges: Vec<Edge> = edge_list
            .iter()
            .filter_map(|&[p, q]| Edge::new([p, q], dirs[p as usize], dirs[q as usize]))
            .collect();
        for e in &mut edges {
            e.find_outward(dirs);
        }
        let mut loc = TriangleLocator {
            dirs: dirs.to_vec(),
            tris: out,
            edges,
            cells: Vec::new(),
            cands: Vec::new(),
            primary: Vec::new(),
        };
        loc.build_grid();
        loc.build_primary();
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
                        let at = |c: usize, s: usize| c as f32 + s as f32 / (SUB - 1) as f32;
                        let (d, _) = grid_direction(GRID, at(cx, sx), at(cy, sy));
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

    /// The fast-path table: per fine cell, the answer of most of 4 × 4
    /// points over it (found through the coarse grid), if it is a triangle
    /// or an arc that [`Edge::answers`] them.
    fn build_primary(&mut self) {
        const SUB: usize = 4;
        if self.dirs.len() < 3 {
            return;
        }
        let mut primary = Vec::with_capacity(FINE * FINE);
        // At most SUB² distinct answers per cell: one buffer for all cells.
        let mut votes: Vec<(u8, u32)> = Vec::with_capacity(SUB * SUB);
        for cy in 0..FINE {
            for cx in 0..FINE {
                votes.clear();
                for sy in 0..SUB {
                    for sx in 0..SUB {
                        let at = |c: usize, s: usize| c as f32 + (s as f32 + 0.5) / SUB as f32;
                        let (d, on_hemisphere) = grid_direction(FINE, at(cx, sx), at(cy, sy));
                        let Some(id) = on_hemisphere.then(|| self.answering(d)).flatten() else {
                            continue;
                        };
                        match votes.iter_mut().find(|v| v.0 == id) {
                            Some(v) => v.1 += 1,
                            None => votes.push((id, 1)),
                        }
                    }
                }
                let best = votes.iter().max_by_key(|v| v.1).map_or(NONE, |v| v.0);
                primary.push(best);
            }
        }
        self.primary = primary;
    }

    /// What answers `d` in [`Self::primary`]'s code: the triangle holding
    /// it, or `tris.len() + e` for a boundary arc `e` that
    /// [`Edge::answers`] it; `None` if neither or the code is too large.
    fn answering(&self, d: V3) -> Option<u8> {
        let (tris, arcs) = self.candidates(d);
        let mut scratch = [(0, 0.0); 3];
        let code = |i: usize| u8::try_from(i).ok().filter(|&c| c != NONE);
        if let Some(&t) =
            tris.iter().find(|&&t| self.tri_weights(&self.tris[t as usize], d, &mut scratch))
        {
            return code(t as usize);
        }
        arcs.iter()
            .find(|&&e| self.edges[e as usize].answers(d))
            .and_then(|&e| code(self.tris.len() + e as usize))
    }

    /// The coarse grid's candidate triangles and boundary arcs for `d`.
    #[inline(always)]
    fn candidates(&self, d: V3) -> (&[u16], &[u16]) {
        let (start, nt, ne) = self.cells[Self::cell(GRID, d)];
        let start = start as usize;
        self.cands[start..start + nt as usize + ne as usize].split_at(nt as usize)
    }

    /// The cell of direction `d` in a grid of `n` per side over its
    /// orthographic (x, y).
    #[inline(always)]
    fn cell(n: usize, d: V3) -> usize {
        let at = |c: f32| (((c + 1.0) * 0.5 * n as f32) as usize).min(n - 1);
        at(d[1]) * n + at(d[0])
    }

    /// The arc nearest to `d` among `among`: one that [`Edge::answers`] it
    /// if there is one (provably nearest, and no float tie with an arc
    /// that clamps to the shared end decides otherwise), else the one of
    /// the largest cosine.
    fn nearest_edge(&self, d: V3, among: impl Iterator<Item = usize>) -> Option<usize> {
        let mut best: Option<(f32, usize)> = None;
        for e in among {
            if self.edges[e].answers(d) {
                return Some(e);
            }
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
        // The fast path: the cell's usual answer, if its test passes.
        if let Some(&c) = self.primary.get(Self::cell(FINE, d)) {
            let c = c as usize;
            if let Some(t) = self.tris.get(c) {
                if self.tri_weights(t, d, out) {
                    return;
                }
            } else if c != NONE as usize {
                let e = c - self.tris.len();
                if self.edges[e].answers(d) {
                    return self.edge_weights(e, d, out);
                }
            }
        }
        let (tris, arcs) = self.candidates(d);
        for &t in tris {
            if self.tri_weights(&self.tris[t as usize], d, out) {
                return;
            }
        }
        if !arcs.is_empty() {
            let e = self.nearest_edge(d, arcs.iter().map(|&e| e as usize)).expect("a listed edge");
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
