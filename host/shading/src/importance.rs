//! Importance sampling of a material: [`Material::sample`] draws a light
//! direction wi for a view wo with a density close to the material's
//! f · cos θi, and [`Material::pdf`] gives that density, for a renderer's
//! path tracing and multiple importance sampling.
//!
//! **The distribution** (docs/material-format.md, "Importance sampling") is
//! a mixture: with probability s a cosine-weighted direction, otherwise a
//! half vector h drawn from a table of the view nearest wo, reflected:
//! wi = 2 (wo · h) h − wo. Each captured view j has a piecewise-constant
//! table of h over an N × N grid ([`GRID`]) on the square of Shirley and
//! Chiu's concentric map (square → disk, equal-area; disk → hemisphere by
//! z = √(1 − r²)). A table in half vectors keeps a lobe in place when wo
//! moves away from its view.
//!
//! A table is the mean of sixteen uv points' own distributions, each
//! normalised so that a dim or broad point counts as much as a bright,
//! narrow one; point k's weight of a cell is the luminance of f · cos θi at
//! one of the cell's 2 × 2 sub-points, times the Jacobian from the square
//! to wi. The four sub-points are seen from four directions around view j,
//! at the radius of its Voronoi region (the view directions nearer it than
//! any other view, which will use its table), so that the table covers
//! their half vectors too.
//! The cosine share s is the table's own: of [`SHARES`], the one under
//! which the uv points' samples would vary least (the sum of their
//! variances, each point left out of the table in turn); with a texel
//! model, at least the texel's diffuse part of its albedo at uv. Cosine
//! sampling covers what the table misses, so the density is positive
//! wherever cos θi is.
//!
//! Tables are built on first use, one view at a time (about 65 000 `eval`s
//! each), or all at once by [`Material::prepare_importance`]; after that no
//! query allocates.

use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::{Material, ShadeQuery, unit, unit_above};

/// Cells along each side of a view's table of half vectors.
pub const GRID: usize = 64;
/// The probabilities of a cosine-weighted direction rather than one from
/// the view's table that a table may choose from: the one under which its
/// uv points' samples vary least, each left out of the table in turn.
pub const SHARES: [f32; 8] = [0.02, 0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 1.0];
/// The share of a table that cannot choose (fewer than two uv points see
/// anything).
const DEFAULT_SHARE: f32 = 0.2;
/// The uv points a table averages over: a rank-1 lattice (generator 7) of
/// 16 points; sub-point s of a cell reads the four points i ≡ s (mod 4).
const UV_POINTS: usize = 16;

/// A direction drawn by [`Material::sample`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BsdfSample {
    /// Towards the light, sample-local, unit, above the horizon.
    pub wi: [f32; 3],
    /// f · cos θi at (uv, wi, wo): exactly [`Material::eval`]'s answer.
    pub f_cos: [f32; 3],
    /// The density of wi per unit solid angle: exactly
    /// [`Material::pdf`]`(uv, wi, wo)`, > 0.
    pub pdf: f32,
}

impl BsdfSample {
    /// The Monte Carlo weight f · cos θi / pdf.
    pub fn weight(&self) -> [f32; 3] {
        self.f_cos.map(|c| c / self.pdf)
    }
}

/// Every view's table, each built on first use.
#[derive(Clone)]
pub(crate) struct Importance {
    /// The captured views' unit directions (f32, as the shading has them).
    views: Vec<[f32; 3]>,
    /// Per view, the sine of how far from it the view directions that use
    /// its table lie (about); found with the first table.
    reach: OnceLock<Vec<f32>>,
    tables: Box<[OnceLock<Table>]>,
}

impl std::fmt::Debug for Importance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let built = self.tables.iter().filter(|t| t.get().is_some()).count();
        f.debug_struct("Importance")
            .field("views", &self.views.len())
            .field("built", &built)
            .finish()
    }
}

impl Importance {
    pub(crate) fn new(views: Vec<[f32; 3]>) -> Importance {
        let tables = views.iter().map(|_| OnceLock::new()).collect();
        Importance { views, reach: OnceLock::new(), tables }
    }

    /// Each view's extent: the directions of a Fibonacci spiral over the
    /// hemisphere nearer it than any other view (its Voronoi region), as
    /// the radius of the disk with the same mean squared angle from it
    /// (√2 × the RMS), at most 45°; its sine.
    fn reach(&self) -> &[f32] {
        self.reach.get_or_init(|| {
            let views = &self.views;
            let (mut sum, mut count) = (vec![0.0f64; views.len()], vec![0usize; views.len()]);
            let n = 4096;
            for i in 0..n {
                let z = 1.0 - (i as f64 + 0.5) / n as f64;
                let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
                let r = (1.0 - z * z).sqrt();
                let d = [r * phi.cos(), r * phi.sin(), z].map(|x| x as f32);
                let (j, cos) = nearest(views, d);
                if !views.is_empty() {
                    sum[j] += (cos.clamp(-1.0, 1.0).acos() as f64).powi(2);
                    count[j] += 1;
                }
            }
            (sum.iter().zip(&count))
                .map(|(&s, &c)| {
                    let rms = if c > 0 { (s / c as f64).sqrt() } else { 0.0 };
                    ((2f64.sqrt() * rms).min(std::f64::consts::FRAC_PI_4).sin()) as f32
                })
                .collect()
        })
    }
}

/// The view nearest a unit direction d (the largest cosine) and that
/// cosine; (0, −∞) without views.
#[inline]
fn nearest(views: &[[f32; 3]], d: [f32; 3]) -> (usize, f32) {
    let mut best = (0, f32::NEG_INFINITY);
    for (j, v) in views.iter().enumerate() {
        let c = dot(*v, d);
        if c > best.1 {
            best = (j, c);
        }
    }
    best
}

/// One view's piecewise-constant distribution of half vectors over the
/// GRID × GRID cells, as pbrt's 2-D distributions are: the cumulative
/// probabilities of its rows, and per row those of its cells given the
/// row, each from 0 to exactly 1 (a probability is the difference of two
/// bounds). Two searches of 65 bounds touch a few cache lines where one of
/// 4 097 touched a dozen.
#[derive(Debug, Clone)]
struct Table {
    /// `[GRID + 1]`.
    rows: Box<[f32]>,
    /// `[GRID][GRID + 1]`.
    cells: Box<[f32]>,
    /// The probability of a cosine-weighted direction instead (one of
    /// [`SHARES`]).
    share: f32,
}

/// The bounds 0, …, 1 of the cumulative sums of `w` (≥ 0, finite) in
/// `out`; uniform if they are all 0. Returns their sum.
fn cumulative(w: &[f64], out: &mut Vec<f32>) -> f64 {
    let total: f64 = w.iter().sum();
    out.push(0.0);
    let mut run = 0.0f64;
    for (i, &x) in w.iter().enumerate() {
        run += if total > 0.0 { x / total } else { 1.0 / w.len() as f64 };
        out.push(if i + 1 == w.len() { 1.0 } else { run.min(1.0) as f32 });
    }
    total
}

/// The cell whose bounds (in `bounds`, from 0 to 1) hold x ∈ [0, 1) — never
/// an empty one, whose bounds are equal — and where x lies in it, in [0, 1).
#[inline]
fn find(bounds: &[f32], x: f32) -> (usize, f32) {
    let i = (bounds.partition_point(|&c| c <= x) - 1).min(bounds.len() - 2);
    let (lo, hi) = (bounds[i], bounds[i + 1]);
    (i, unit_interval((x - lo) / (hi - lo)))
}

impl Table {
    /// The table from its cells' weights (≥ 0, finite, row-major); uniform
    /// if they are all 0.
    fn from_weights(w: &[f64], share: f32) -> Table {
        let mut cells = Vec::with_capacity(GRID * (GRID + 1));
        let sums: Vec<f64> = w.chunks(GRID).map(|row| cumulative(row, &mut cells)).collect();
        let mut rows = Vec::with_capacity(GRID + 1);
        cumulative(&sums, &mut rows);
        Table { rows: rows.into(), cells: cells.into(), share }
    }

    #[inline]
    fn probability(&self, x: usize, y: usize) -> f32 {
        let row = &self.cells[y * (GRID + 1)..][..GRID + 1];
        (self.rows[y + 1] - self.rows[y]) * (row[x + 1] - row[x])
    }

    /// The density of a unit half vector above the horizon per unit solid
    /// angle: P(cell) · N² on the square (area 1), over π on the disk
    /// (area π), times cos θh onto the hemisphere.
    #[inline]
    fn density(&self, h: [f32; 3]) -> f32 {
        let [x, y] = disk_to_square([h[0], h[1]]);
        let cell = |t: f32| ((t * GRID as f32) as usize).min(GRID - 1);
        let p = self.probability(cell(x), cell(y));
        p * (GRID * GRID) as f32 * h[2] / PI
    }

    /// A half vector: the row whose bounds hold `uc`, the cell of that row
    /// whose bounds hold where uc lies in the row, and `u` within the cell.
    #[inline]
    fn sample(&self, uc: f32, u: [f32; 2]) -> [f32; 3] {
        let (cy, within) = find(&self.rows, uc);
        let (cx, _) = find(&self.cells[cy * (GRID + 1)..][..GRID + 1], within);
        let p = [(cx as f32 + u[0]) / GRID as f32, (cy as f32 + u[1]) / GRID as f32];
        hemisphere(square_to_disk(p))
    }
}

/// Shirley and Chiu's concentric map from [0, 1]² onto the unit disk
/// (equal-area up to the factor π/4).
#[inline]
pub fn square_to_disk(p: [f32; 2]) -> [f32; 2] {
    let (a, b) = (2.0 * p[0] - 1.0, 2.0 * p[1] - 1.0);
    if a == 0.0 && b == 0.0 {
        return [0.0, 0.0];
    }
    let (r, phi) = if a.abs() > b.abs() {
        (a, FRAC_PI_4 * (b / a))
    } else {
        (b, FRAC_PI_2 - FRAC_PI_4 * (a / b))
    };
    [r * phi.cos(), r * phi.sin()]
}

/// The inverse of [`square_to_disk`], for a point in the closed disk.
#[inline]
pub fn disk_to_square(d: [f32; 2]) -> [f32; 2] {
    let r = (d[0] * d[0] + d[1] * d[1]).sqrt();
    let mut phi = d[1].atan2(d[0]);
    if phi < -FRAC_PI_4 {
        phi += 2.0 * PI;
    }
    let k = 1.0 / FRAC_PI_4;
    let (a, b) = if phi < FRAC_PI_4 {
        (r, phi * r * k)
    } else if phi < 3.0 * FRAC_PI_4 {
        ((FRAC_PI_2 - phi) * r * k, r)
    } else if phi < 5.0 * FRAC_PI_4 {
        (-r, (phi - PI) * -r * k)
    } else {
        ((3.0 * FRAC_PI_2 - phi) * -r * k, -r)
    };
    [((a + 1.0) * 0.5).clamp(0.0, 1.0), ((b + 1.0) * 0.5).clamp(0.0, 1.0)]
}

/// The mixture's cosine-weighted direction (density cos θi / π) from
/// u ∈ [0, 1)²: the concentric disk lifted onto the hemisphere. z is 0 only
/// on the disk's rim.
#[inline]
pub fn cosine_direction(u: [f32; 2]) -> [f32; 3] {
    hemisphere(square_to_disk(u))
}

/// A disk point lifted onto the upper hemisphere.
#[inline]
fn hemisphere(d: [f32; 2]) -> [f32; 3] {
    [d[0], d[1], (1.0 - d[0] * d[0] - d[1] * d[1]).max(0.0).sqrt()]
}

#[inline]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// wo mirrored about the unit vector h.
#[inline]
fn reflect(wo: [f32; 3], h: [f32; 3]) -> [f32; 3] {
    let k = 2.0 * dot(wo, h);
    std::array::from_fn(|i| k * h[i] - wo[i])
}

/// A uniform number in [0, 1) from a renderer's: NaN and below 0 give 0,
/// 1 and above the largest float below 1.
#[inline]
fn unit_interval(x: f32) -> f32 {
    if x >= 0.0 { x.min(1.0 - f32::EPSILON / 2.0) } else { 0.0 }
}

impl Material {
    /// Draw a direction towards the light for the view `wo` at `uv`, with
    /// uniform numbers `uc` (which part of the mixture, then which cell)
    /// and `u` (where): see the module documentation. `None` if wo is not
    /// a direction above the horizon, uv is not finite, or the draw falls
    /// on or below the horizon (a renderer counts it as a zero sample).
    /// Builds the table of wo's view on its first use.
    pub fn sample(
        &self,
        uv: [f32; 2],
        given: [f32; 3],
        uc: f32,
        u: [f32; 2],
    ) -> Option<BsdfSample> {
        let wo = unit(given)?;
        if wo[2] <= 0.0 || !uv.iter().all(|x| x.is_finite()) {
            return None;
        }
        let (uc, u) = (unit_interval(uc), u.map(unit_interval));
        let table = self.importance_table(wo);
        let share = self.share_at(table, uv);
        let wi = if uc < share {
            cosine_direction(u)
        } else {
            let h = table.sample(unit_interval((uc - share) / (1.0 - share)), u);
            unit(reflect(wo, h))?
        };
        if wi[2] <= 0.0 {
            return None;
        }
        // As `pdf` and `eval` compute them from this wi and the caller's wo
        // (normalised again), so that a renderer asking them gets the same
        // bits; wo's view is the same.
        let (wi_again, _) = unit_above(wi, given)?;
        let pdf = mixture_pdf(table, share, wi_again, wo);
        (pdf > 0.0).then(|| BsdfSample { wi, f_cos: self.eval(uv, wi, given), pdf })
    }

    /// The density per unit solid angle with which [`Self::sample`] draws
    /// wi for the view wo at uv; 0 if either is not a direction above the
    /// horizon or uv is not finite. Builds the table of wo's view on its
    /// first use.
    pub fn pdf(&self, uv: [f32; 2], wi: [f32; 3], wo: [f32; 3]) -> f32 {
        match unit_above(wi, wo) {
            Some((wi, wo)) if uv.iter().all(|x| x.is_finite()) => {
                let table = self.importance_table(wo);
                mixture_pdf(table, self.share_at(table, uv), wi, wo)
            }
            _ => 0.0,
        }
    }

    /// The cosine share at uv: the table's, or with a texel model at least
    /// the texel's diffuse part of its albedo, ρd / (ρd + F0) over the
    /// channels' sums (its parameters bilinear at uv), so that a dull texel
    /// among glossy ones is not sampled as they are. uv finite.
    #[inline]
    fn share_at(&self, table: &Table, uv: [f32; 2]) -> f32 {
        if self.texels.is_empty() {
            return table.share;
        }
        let p = self.texel_at(&crate::Footprint::on(self.size, self.scanned_uv(uv)));
        let (d, f) = (p.diffuse.iter().sum::<f32>(), p.specular.iter().sum::<f32>());
        let diffuse = if d + f > 0.0 { d / (d + f) } else { 0.0 };
        if diffuse.is_finite() { table.share.max(diffuse.min(1.0)) } else { table.share }
    }

    /// Build every view's table now, on all cores, rather than on first
    /// use — before rendering, so that no sample waits or allocates.
    pub fn prepare_importance(&self) {
        let n = self.importance.tables.len();
        let next = AtomicUsize::new(0);
        let threads = std::thread::available_parallelism().map_or(1, |t| t.get()).min(n);
        std::thread::scope(|s| {
            for _ in 0..threads {
                s.spawn(|| {
                    loop {
                        let j = next.fetch_add(1, Ordering::Relaxed);
                        if j >= n {
                            break;
                        }
                        self.table_of_view(j);
                    }
                });
            }
        });
    }

    /// The table of the view nearest the unit direction wo.
    #[inline]
    fn importance_table(&self, wo: [f32; 3]) -> &Table {
        self.table_of_view(nearest(&self.importance.views, wo).0)
    }

    fn table_of_view(&self, j: usize) -> &Table {
        let imp = &self.importance;
        imp.tables[j].get_or_init(|| self.build_table(around(imp.views[j], imp.reach()[j])))
    }

    /// A view's table from its four surrounding directions (see the
    /// module documentation).
    fn build_table(&self, views: [[f32; 3]; 4]) -> Table {
        let uv: [[f32; 2]; UV_POINTS] = std::array::from_fn(|i| {
            let y = ((7 * i) % UV_POINTS) as f32;
            [(i as f32 + 0.5) / UV_POINTS as f32, (y + 0.5) / UV_POINTS as f32]
        });
        let per_point = UV_POINTS / 4;
        // `[cell][sub-point][its uv points]`.
        let mut point = vec![0.0f32; GRID * GRID * UV_POINTS];
        let mut queries = Vec::with_capacity(GRID * UV_POINTS);
        let mut jacobian = Vec::with_capacity(GRID * 4);
        // Per cell, cosine sampling's density on the square (area 1): the
        // mean of its sub-points' cos θi / π · dωi/dsquare, which is
        // 4 cos θi (wo · h) / cos θh each.
        let mut cosine = vec![0.0f64; GRID * GRID];
        let mut out = vec![[0.0f32; 3]; GRID * UV_POINTS];
        // A row of cells at a time.
        for cy in 0..GRID {
            queries.clear();
            jacobian.clear();
            for cx in 0..GRID {
                for (s, &wo) in views.iter().enumerate() {
                    let p = [
                        (cx as f32 + 0.25 + 0.5 * (s % 2) as f32) / GRID as f32,
                        (cy as f32 + 0.25 + 0.5 * (s / 2) as f32) / GRID as f32,
                    ];
                    let h = hemisphere(square_to_disk(p));
                    let wi = reflect(wo, h);
                    let ok = h[2] > 1e-6 && wi[2] > 0.0 && dot(wo, h) > 0.0;
                    jacobian.push(if ok { dot(wo, h) / h[2] } else { 0.0 });
                    if ok {
                        // 4 × … / 4 sub-points.
                        cosine[cy * GRID + cx] += (wi[2] * dot(wo, h) / h[2]) as f64;
                    }
                    // Below the horizon: straight up, weighted 0.
                    let wi = if ok { wi } else { [0.0, 0.0, 1.0] };
                    for k in (s..UV_POINTS).step_by(4) {
                        queries.push(ShadeQuery { uv: uv[k], wi, wo });
                    }
                }
            }
            self.eval_batch(&queries, &mut out);
            let row = &mut point[cy * GRID * UV_POINTS..][..GRID * UV_POINTS];
            for (i, (w, rgb)) in row.iter_mut().zip(&out).enumerate() {
                let lum = (rgb[0] + rgb[1] + rgb[2]) / 3.0 * jacobian[i / per_point];
                *w = if lum.is_finite() { lum.max(0.0) } else { 0.0 };
            }
        }
        // Each point's distribution over the cells (`p[k][cell]`), of the
        // points that see anything.
        let k_of = |i: usize| (i % per_point) * 4 + i / per_point;
        let mut p = vec![vec![0.0f64; GRID * GRID]; UV_POINTS];
        for (c, cell) in point.chunks(UV_POINTS).enumerate() {
            for (i, &w) in cell.iter().enumerate() {
                p[k_of(i)][c] = w as f64;
            }
        }
        let mut totals = Vec::with_capacity(UV_POINTS);
        p.retain_mut(|pk| {
            let total: f64 = pk.iter().sum();
            let seen = total > 0.0 && total.is_finite();
            if seen {
                pk.iter_mut().for_each(|x| *x /= total);
                totals.push(total);
            }
            seen
        });
        let n = p.len() as f64;
        let weights: Vec<f64> =
            (0..GRID * GRID).map(|c| p.iter().map(|pk| pk[c]).sum::<f64>() / n).collect();
        let share =
            if p.len() < 2 { DEFAULT_SHARE } else { choose_share(&p, &totals, &weights, &cosine) };
        Table::from_weights(&weights, share)
    }
}

/// Four view directions around unit `wo`, `reach` (a sine) from it at
/// right angles to one another, kept above the horizon: a table built
/// from them serves every view direction nearer `wo` than any other view.
fn around(wo: [f32; 3], reach: f32) -> [[f32; 3]; 4] {
    // A frame about wo.
    let t = unit([-wo[1], wo[0], 0.0]).unwrap_or([1.0, 0.0, 0.0]);
    let b = [wo[1] * t[2] - wo[2] * t[1], wo[2] * t[0] - wo[0] * t[2], wo[0] * t[1] - wo[1] * t[0]];
    let c = (1.0 - reach * reach).max(0.0).sqrt();
    std::array::from_fn(|s| {
        let (x, y) = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][s];
        let mut d: [f32; 3] = std::array::from_fn(|i| c * wo[i] + reach * (x * t[i] + y * b[i]));
        d[2] = d[2].max(0.02);
        unit(d).unwrap_or(wo)
    })
}

/// The share of cosine sampling whose samples vary least at the uv points:
/// drawn from the mixture of `cosine` (the density on the square) and the
/// table of the other points (`mean` without it), point k — distribution
/// `p[k]`, integral `totals[k]` — has a variance of
/// totals[k]² (Σ_cells p_k² / (area · density) − 1); the share whose sum
/// over the points (a render's squared error) is least.
fn choose_share(p: &[Vec<f64>], totals: &[f64], mean: &[f64], cosine: &[f64]) -> f32 {
    let n = p.len() as f64;
    let area = 1.0 / mean.len() as f64;
    let variance = |share: f64| -> f64 {
        p.iter()
            .zip(totals)
            .map(|(pk, t)| {
                let mut v = 0.0;
                for c in 0..mean.len() {
                    if pk[c] > 0.0 {
                        let others = (n * mean[c] - pk[c]).max(0.0) / (n - 1.0);
                        let q = share * cosine[c] + (1.0 - share) * others / area;
                        v += if q > 0.0 { pk[c] * pk[c] / (area * q) } else { f64::INFINITY };
                    }
                }
                (v - 1.0) * t * t
            })
            .sum::<f64>()
    };
    let mut best = (DEFAULT_SHARE, f64::INFINITY);
    for s in SHARES {
        let v = variance(s as f64);
        if v < best.1 {
            best = (s, v);
        }
    }
    best.0
}

/// The mixture's density of unit wi (above the horizon) for unit wo, with
/// cosine share `share`.
#[inline]
fn mixture_pdf(table: &Table, share: f32, wi: [f32; 3], wo: [f32; 3]) -> f32 {
    let cosine = wi[2] / PI;
    if share >= 1.0 {
        return cosine;
    }
    let half = match unit([wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]]) {
        Some(h) if h[2] > 0.0 => table.density(h) / (4.0 * dot(wo, h)),
        _ => 0.0,
    };
    share * cosine + (1.0 - share) * half
}
