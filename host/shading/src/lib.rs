//! # scanner-shading
//!
//! What a renderer links to shade a scanned material: the material file
//! reader and its shading API. No serial or USB, no simulator, no scan or
//! image decoding, no command line — `safetensors`, `half`, `serde_json` and
//! `thiserror` only (scripts/check-deps.sh enforces it).
//!
//! ```no_run
//! use scanner_shading::Material;
//! let m = Material::open("woven-fabric.material".as_ref())?;
//! // Radiance towards wo per unit irradiance from wi: f · cos θi, linear RGB.
//! let rgb = m.eval([0.5, 0.5], [0.0, 0.5, 0.866], [0.3, 0.0, 0.954]);
//! # Ok::<(), scanner_shading::MaterialError>(())
//! ```
//!
//! **What `eval` returns.** f(uv, wi, wo) · cos θi — the reflected radiance
//! towards `wo` per unit irradiance arriving along `wi` at normal
//! incidence, i.e. the BRDF *times* the cosine of the light's angle, like
//! Mitsuba's `BSDF::eval` and unlike pbrt's `f()` (which excludes it).
//! Directions are in the sample's frame (docs/scanner-geometry.md): z along
//! the sample's normal, x along +u, y along +v, both pointing away from the
//! surface; they are normalised, and one shorter than 1e-6 or not finite
//! gives black.
//! Below the horizon (wi.z ≤ 0 or wo.z ≤ 0) the answer is 0. uv ∈ [0, 1]²
//! spans the material's extent (`Metadata::extent_mm`) and wraps outside
//! it, so a renderer may tile the material.
//!
//! **Sampling.** [`Material::sample`] draws wi for a view wo with a density
//! close to f · cos θi and returns it with `eval`'s answer and its density;
//! [`Material::pdf`] gives that density for any wi, for multiple
//! importance sampling ([`importance`] says how; call
//! [`Material::prepare_importance`] before rendering).
//!
//! ```no_run
//! # let m = scanner_shading::Material::open("m.material".as_ref())?;
//! m.prepare_importance();
//! let wo = [0.3, 0.0, 0.954];
//! if let Some(s) = m.sample([0.5, 0.5], wo, 0.42, [0.1, 0.7]) {
//!     let throughput = s.weight(); // f · cos θi / pdf
//!     assert_eq!(s.pdf, m.pdf([0.5, 0.5], s.wi, wo));
//! }
//! # Ok::<(), scanner_shading::MaterialError>(())
//! ```

pub mod error;
pub mod format;
pub mod importance;
pub mod locate;
pub mod texel;

use std::path::Path;

pub use error::MaterialError;
use format::DirectionTables;
pub use format::{Interpolation, MaterialData, Metadata};
pub use importance::BsdfSample;
use locate::{CellLocator, TriangleLocator};

/// One shading request for [`Material::eval_batch`]. Laid out as C's
/// `struct { float uv[2]; float wi[3]; float wo[3]; }` (the C API's
/// `ScannerShadeQuery`, scanner-shading-c).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ShadeQuery {
    /// Position in [0, 1]² over the material's extent (wraps outside).
    pub uv: [f32; 2],
    /// Direction towards the light, sample-local.
    pub wi: [f32; 3],
    /// Direction towards the viewer, sample-local.
    pub wo: [f32; 3],
}

/// The direction lookups of the file's interpolation.
// One per material, never in a collection: boxing the larger variant would
// only add a pointer to every lookup.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
enum Directions {
    /// Default: triangles, with the unit light directions and the
    /// half-vector shift β for the view shift.
    Triangles {
        views: TriangleLocator,
        lights: TriangleLocator,
        light_dirs: Vec<[f32; 3]>,
        view_dirs: Vec<[f32; 3]>,
        shift: f32,
    },
    /// The patent's cell tables.
    Cells { views: CellLocator, lights: CellLocator },
}

/// A scanned material, ready to shade. `Send + Sync`: share one between
/// threads; no query allocates (no sampling query either, once
/// [`Material::prepare_importance`] has run).
#[derive(Debug, Clone)]
pub struct Material {
    meta: Metadata,
    size: usize,
    colours: usize,
    groups: usize,
    lights: usize,
    /// `[V][L][K]`: f (the palette divided by the captured light's cos θi).
    palettes: Vec<[f32; 3]>,
    /// `[V][S][S][G]`.
    indices: Vec<u8>,
    light_groups: Vec<u8>,
    directions: Directions,
    /// `[S][S]` stored texel-model values ([`texel::STORED`] each), or empty.
    texels: Vec<[f32; texel::STORED]>,
    /// `[2S][2S][1 + R]`: per texel the shared detail factor, then the
    /// light components' log factors (one lookup's values together), or
    /// empty.
    detail: Vec<[f32; 3]>,
    /// The detail layer's light components R (0: none).
    components: usize,
    /// `[L][R]` each light's coefficients on them.
    detail_coefficients: Vec<f32>,
    /// The views' tables of half vectors for [`Material::sample`].
    importance: importance::Importance,
    /// Fig. 9's enlargement map (version 5), or none.
    enlargement: Option<UvMap>,
}

/// An enlargement map ready to look up (docs/material-format.md,
/// "Enlargement").
#[derive(Debug, Clone)]
struct UvMap {
    columns: usize,
    rows: usize,
    /// `[rows][columns]`: the scanned sample's uv at the texel's centre.
    centres: Vec<[f32; 2]>,
    /// One map texel's side in the scanned sample's uv, along u and v.
    scale: [f32; 2],
}

impl UvMap {
    fn new(meta: &Metadata, map: &[[u16; 2]]) -> Option<UvMap> {
        let e = meta.enlargement.as_ref()?;
        let (columns, rows) = (e.columns as usize, e.rows as usize);
        let units = format::ENLARGEMENT_UNITS as f32;
        let scale = [
            (meta.extent_mm[0] / columns as f64 / meta.sample_size_mm) as f32,
            (meta.extent_mm[1] / rows as f64 / meta.sample_size_mm) as f32,
        ];
        let centres = map.iter().map(|m| m.map(|x| (x as f32 + 0.5) / units)).collect();
        Some(UvMap { columns, rows, centres, scale })
    }

    /// The scanned sample's uv for a finite uv over the large piece
    /// (wrapped into [0, 1)): its map texel's match, moved by the uv's
    /// offset from that texel's centre, within the sample.
    #[inline(always)]
    fn scanned(&self, uv: [f32; 2]) -> [f32; 2] {
        let at = |u: f32, n: usize| {
            let x = (u - u.floor()) * n as f32;
            let i = (x as usize).min(n - 1);
            (i, x - i as f32 - 0.5)
        };
        let (c, dx) = at(uv[0], self.columns);
        let (r, dy) = at(uv[1], self.rows);
        let m = self.centres[r * self.columns + c];
        let below_one = 1.0 - f32::EPSILON;
        [
            (m[0] + dx * self.scale[0]).clamp(0.0, below_one),
            (m[1] + dy * self.scale[1]).clamp(0.0, below_one),
        ]
    }
}

/// The detail layer's factor at a point (docs/material-format.md, "Detail
/// layer"): the shared factor `shared` times e to the light components'
/// sum `log`, within [1 / [`format::DETAIL_RANGE`],
/// [`format::DETAIL_RANGE`]].
#[inline]
pub fn detail_factor(shared: [f32; 3], log: [f32; 3]) -> [f32; 3] {
    let r = format::DETAIL_RANGE;
    std::array::from_fn(|k| {
        let f = shared[k] * log[k].exp();
        if f.is_nan() { shared[k] } else { f.clamp(1.0 / r, r) }
    })
}

/// The default interpolation's weights (docs/material-format.md,
/// "Shading"): `pair(view, light, weight)` for every contributing captured
/// pair of query (wi, wo) — unit vectors above the horizon. Light weights
/// by `lights` (whose direction `i` is `light_dirs[i]`); for each light,
/// the view direction moved from wo by `shift` (0…1) towards the light
/// reflected about the half vector, weighted by `views`.
#[inline]
pub fn default_pairs(
    lights: &TriangleLocator,
    light_dirs: &[[f32; 3]],
    views: &TriangleLocator,
    shift: f32,
    wi: [f32; 3],
    wo: [f32; 3],
    mut pair: impl FnMut(u16, u16, f32),
) {
    let (mut lb, mut vb) = ([(0u16, 0f32); 3], [(0u16, 0f32); 3]);
    lights.weights(wi, &mut lb);
    // Without a shift every light reads the views of wo itself: one lookup.
    let h = if shift > 0.0 {
        Some(unit([wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]]).unwrap_or([0.0, 0.0, 1.0]))
    } else {
        views.weights(wo, &mut vb);
        None
    };
    for &(li, wl) in &lb {
        if wl == 0.0 {
            continue;
        }
        if let Some(h) = h {
            let l = light_dirs[li as usize];
            let k = 2.0 * (h[0] * l[0] + h[1] * l[1] + h[2] * l[2]);
            let r = [k * h[0] - l[0], k * h[1] - l[1], k * h[2] - l[2]];
            let mut v: [f32; 3] = std::array::from_fn(|i| (1.0 - shift) * wo[i] + shift * r[i]);
            // Below the horizon: the horizon point of its azimuth.
            v[2] = v[2].max(1e-4);
            views.weights(unit(v).unwrap_or(wo), &mut vb);
        }
        for &(vi, wv) in &vb {
            if wv != 0.0 {
                pair(vi, li, wv * wl);
            }
        }
    }
}

/// `d` normalised, or `None` if it is shorter than 1e-6 or not finite.
#[inline]
pub fn unit(d: [f32; 3]) -> Option<[f32; 3]> {
    let l2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    if l2.is_finite() && l2 > 1e-12 {
        let r = 1.0 / l2.sqrt();
        Some(d.map(|x| x * r))
    } else {
        unit_rescaled(d)
    }
}

/// [`unit`] of a direction whose squared length over- or underflows f32:
/// scaled by its largest component first.
#[cold]
fn unit_rescaled(d: [f32; 3]) -> Option<[f32; 3]> {
    let big = d.iter().fold(0.0f32, |m, c| m.max(c.abs()));
    if !big.is_finite() || !d.iter().all(|c| c.is_finite()) || big == 0.0 {
        return None;
    }
    let s = d.map(|c| c / big);
    let len = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
    (big * len > 1e-6).then(|| s.map(|c| c / len))
}

/// Both directions normalised ([`unit`]), or `None` if either cannot be or
/// lies on or below the horizon (black).
#[inline(always)]
fn unit_above(wi: [f32; 3], wo: [f32; 3]) -> Option<([f32; 3], [f32; 3])> {
    let (wi, wo) = (unit(wi)?, unit(wo)?);
    (wi[2] > 0.0 && wo[2] > 0.0).then_some((wi, wo))
}

/// Model evaluations per query: the query itself and up to 3 × 3 mixed
/// pairs, padded to a multiple of 4 lanes.
const MODEL_SLOTS: usize = 12;

/// The directions at which a query evaluates the texel model, structure
/// of arrays: slot 0 the query, then the mixed pairs with their weights
/// divided by their light's cos θi; unused slots point straight up with
/// weight 0.
#[derive(Debug, Clone, Copy)]
struct ModelLanes {
    wi: [[f32; MODEL_SLOTS]; 3],
    wo: [[f32; MODEL_SLOTS]; 3],
    weight: [f32; MODEL_SLOTS],
    used: usize,
}

impl Default for ModelLanes {
    fn default() -> Self {
        let mut up = [[0.0; MODEL_SLOTS]; 3];
        up[2] = [1.0; MODEL_SLOTS];
        ModelLanes { wi: up, wo: up, weight: [0.0; MODEL_SLOTS], used: 1 }
    }
}

impl ModelLanes {
    #[inline(always)]
    fn push(&mut self, wi: [f32; 3], wo: [f32; 3], weight: f32) {
        // Never more than 9 pairs (3 light × 3 view weights); a guard all the same.
        if self.used < MODEL_SLOTS {
            let k = self.used;
            for a in 0..3 {
                self.wi[a][k] = wi[a];
                self.wo[a][k] = wo[a];
            }
            self.weight[k] = weight;
            self.used += 1;
        }
    }

    #[inline(always)]
    fn set_query(&mut self, wi: [f32; 3], wo: [f32; 3]) {
        for a in 0..3 {
            self.wi[a][0] = wi[a];
            self.wo[a][0] = wo[a];
        }
    }
}

/// Bilinear taps of a coordinate in [0, 1) over `n` pixel centres, clamped
/// at the borders: (low, high, weight of high).
#[inline]
fn taps(n: usize, u: f32) -> (usize, usize, f32) {
    let x = u * n as f32 - 0.5;
    let f = x.floor();
    let t = x - f;
    let i = f as isize;
    let last = n as isize - 1;
    ((i.clamp(0, last)) as usize, ((i + 1).clamp(0, last)) as usize, t)
}

impl Material {
    /// Open and check a material file (docs/material-format.md).
    pub fn open(path: &Path) -> Result<Material, MaterialError> {
        let name = || path.display().to_string();
        let io = |source| MaterialError::Io { path: name(), source };
        let in_file = |e| MaterialError::File { path: name(), source: Box::new(e) };
        let md = std::fs::metadata(path).map_err(io)?;
        if !md.is_file() {
            return Err(in_file(MaterialError::Container("not a regular file".into())));
        }
        let bytes = std::fs::read(path).map_err(io)?;
        Material::from_bytes(&bytes).map_err(in_file)
    }

    /// A material from a file's bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Material, MaterialError> {
        Material::from_data(MaterialData::from_bytes(bytes)?)
    }

    /// A material from its (checked) content.
    pub fn from_data(d: MaterialData) -> Result<Material, MaterialError> {
        let m = &d.meta;
        let (nl, nv) = (m.lights.len(), m.views.len());
        let k = m.colours as usize;
        // Normalised in f32 as a query's directions are, so that a query
        // at a captured direction (the file's, in f64 or f32) has the same
        // bits: the texel model then cancels exactly at a captured pair.
        let dirs = |l: &[format::Mirror]| -> Vec<[f32; 3]> {
            l.iter()
                .map(|x| {
                    let d = x.direction.map(|c| c as f32);
                    unit(d).unwrap_or(d)
                })
                .collect()
        };
        let (ld, vd) = (dirs(&m.lights), dirs(&m.views));
        let importance = importance::Importance::new(vd.clone());
        let mut palettes = vec![[0.0f32; 3]; d.palettes.len()];
        for li in 0..nl {
            let inv_cos = 1.0 / ld[li][2];
            for vi in 0..nv {
                let src = &d.palettes[(li * nv + vi) * k..][..k];
                let dst = &mut palettes[(vi * nl + li) * k..][..k];
                for (o, i) in dst.iter_mut().zip(src) {
                    *o = i.map(|x| x * inv_cos);
                }
            }
        }
        let directions = match &d.tables {
            DirectionTables::Triangles { views, lights } => Directions::Triangles {
                views: TriangleLocator::new(&vd, views, "view_triangles")?,
                lights: TriangleLocator::new(&ld, lights, "light_triangles")?,
                light_dirs: ld,
                view_dirs: vd,
                shift: m.half_vector_shift as f32,
            },
            DirectionTables::Patent { views, lights } => {
                let Interpolation::Patent { columns, rows, points } = m.interpolation else {
                    return Err(MaterialError::Metadata(
                        "cell tables without patent interpolation".into(),
                    ));
                };
                Directions::Cells {
                    views: CellLocator::new(views, columns, rows, points),
                    lights: CellLocator::new(lights, columns, rows, points),
                }
            }
        };
        Ok(Material {
            size: m.resolution as usize,
            colours: k,
            groups: d.groups(),
            lights: nl,
            palettes,
            indices: d.indices,
            light_groups: d.light_groups,
            directions,
            texels: d.texels.iter().map(|p| p.to_stored()).collect(),
            detail: {
                let (r, n) = (m.detail_components as usize, d.detail.len());
                (0..n * (1 + r))
                    .map(|i| match i % (1 + r) {
                        0 => d.detail[i / (1 + r)],
                        c => d.detail_bases[(c - 1) * n + i / (1 + r)],
                    })
                    .collect()
            },
            components: m.detail_components as usize,
            detail_coefficients: d.detail_coefficients,
            importance,
            enlargement: UvMap::new(&d.meta, &d.enlargement),
            meta: d.meta,
        })
    }

    /// Where on the scanned sample `uv` is shaded, as uv over the sample:
    /// `uv` itself (the lookups wrap it) or, for an enlarged material, its
    /// match through the enlargement map, within [0, 1). Not finite:
    /// unchanged (black).
    #[inline(always)]
    pub fn scanned_uv(&self, uv: [f32; 2]) -> [f32; 2] {
        match &self.enlargement {
            Some(m) if uv[0].is_finite() && uv[1].is_finite() => m.scanned(uv),
            _ => uv,
        }
    }

    /// The file's metadata.
    pub fn metadata(&self) -> &Metadata {
        &self.meta
    }

    /// f(uv, wi, wo) · cos θi, linear RGB (see the crate documentation).
    #[inline]
    pub fn eval(&self, uv: [f32; 2], wi: [f32; 3], wo: [f32; 3]) -> [f32; 3] {
        match &self.directions {
            Directions::Triangles { .. } => {
                let mut s = Staged::default();
                self.stage(uv, wi, wo, &mut s, false);
                self.gather(&mut s);
                self.finish(&s)
            }
            Directions::Cells { views, lights } => {
                let uv = self.scanned_uv(uv);
                let Some((wi, wo, at)) = self.footprint(uv, wi, wo) else {
                    return [0.0; 3];
                };
                let mut acc = [0.0f32; 3];
                let lw = lights.weights(wi);
                let mut light_weights = [(0u16, 0f32); format::MAX_CELL_PAIRS];
                let mut n = 0;
                for &(vi, wv) in views.weights(wo) {
                    for &(li, wl) in lw {
                        let w = wv * wl;
                        if w != 0.0 {
                            let p = self.pair(vi, li, w);
                            let idx = self.indices_at(&p, &at);
                            let c = bilinear(self.palette(&p), idx, &at);
                            for k in 0..3 {
                                acc[k] += w * c[k];
                            }
                        }
                    }
                }
                if self.components > 0 {
                    // The light cells' weights.
                    for &(li, wl) in lw {
                        if wl != 0.0 && n < light_weights.len() {
                            light_weights[n] = (li, wl);
                            n += 1;
                        }
                    }
                }
                let d = self.detail_at(&Footprint::on(2 * self.size, uv), &light_weights[..n]);
                std::array::from_fn(|k| acc[k] * wi[2] * d[k])
            }
        }
    }

    /// [`Self::eval`] over many queries: `out[i]` answers `queries[i]`.
    ///
    /// With the default interpolation the queries go through in blocks:
    /// first every query of a block finds its pairs and asks the memory for
    /// their index bytes, then reads them and asks for the palette colours,
    /// then sums — so the cache misses of a block overlap instead of
    /// following one another (docs/benchmarks.md, "Shading speed").
    /// A query whose wi and wo are those of the query before it (the same
    /// bits) reuses its direction lookup: put the queries that share
    /// directions one after another — an image under one light seen from
    /// one direction, a uv grid per pair — and they cost little more than
    /// their texel reads. The answers are the same in any order.
    ///
    /// # Panics
    /// If the slices' lengths differ.
    pub fn eval_batch(&self, queries: &[ShadeQuery], out: &mut [[f32; 3]]) {
        assert_eq!(queries.len(), out.len(), "one answer per query");
        if let Directions::Cells { .. } = self.directions {
            for (q, o) in queries.iter().zip(out) {
                *o = self.eval(q.uv, q.wi, q.wo);
            }
            return;
        }
        let mut staged = [Staged::default(); BLOCK];
        for (qs, os) in queries.chunks(BLOCK).zip(out.chunks_mut(BLOCK)) {
            for (k, q) in qs.iter().enumerate() {
                // The entry staged just before (at the end of the previous
                // block for the first; before any query, one without a
                // key): its lookup serves if it has the same directions.
                let p = (k + BLOCK - 1) % BLOCK;
                let reuse = staged[p].dirs.key == Some(Lookup::key(q.wi, q.wo));
                if reuse {
                    staged[k].dirs = staged[p].dirs;
                }
                self.stage(q.uv, q.wi, q.wo, &mut staged[k], reuse);
            }
            for s in &mut staged[..qs.len()] {
                self.gather(s);
            }
            for (s, o) in staged.iter().zip(os) {
                *o = self.finish(s);
            }
        }
    }

    /// Unit directions above the horizon and the bilinear footprint of uv,
    /// or `None` for black.
    #[inline(always)]
    fn footprint(
        &self,
        uv: [f32; 2],
        wi: [f32; 3],
        wo: [f32; 3],
    ) -> Option<([f32; 3], [f32; 3], Footprint)> {
        let (wi, wo) = unit_above(wi, wo)?;
        Some((wi, wo, self.texels_at(uv)?))
    }

    /// The bilinear footprint of uv (wrapped into [0, 1)), or `None` if uv
    /// is not finite.
    #[inline(always)]
    fn texels_at(&self, uv: [f32; 2]) -> Option<Footprint> {
        if !uv[0].is_finite() || !uv[1].is_finite() {
            return None;
        }
        Some(Footprint::on(self.size, uv))
    }

    /// The detail layer's factors at its footprint `at` (on its 2S × 2S
    /// grid) for a query whose lights are `lights` (light, weight): the
    /// light components' coefficients are the lights' weighted mean. 1
    /// without a layer.
    #[inline(always)]
    fn detail_at(&self, at: &Footprint, lights: &[(u16, f32)]) -> [f32; 3] {
        if self.detail.is_empty() {
            return [1.0; 3];
        }
        let r = self.components;
        let d = at.texel.map(|t| self.detail[t as usize * (1 + r)]);
        let shared = std::array::from_fn(|k| (0..4).map(|i| at.w[i] * d[i][k]).sum());
        if r == 0 {
            return shared;
        }
        let mut log = [0.0f32; 3];
        let mut coef = [0.0f32; format::MAX_DETAIL_COMPONENTS as usize];
        let mut total = 0.0f32;
        for &(l, w) in lights {
            let row = &self.detail_coefficients[l as usize * r..][..r];
            for (c, x) in coef.iter_mut().zip(row) {
                *c += w * x;
            }
            total += w;
        }
        if total > 0.0 {
            for i in 0..4 {
                let at_i = &self.detail[at.texel[i] as usize * (1 + r) + 1..][..r];
                for (b, c) in at_i.iter().zip(&coef) {
                    let cw = c * at.w[i] / total;
                    for k in 0..3 {
                        log[k] += cw * b[k];
                    }
                }
            }
        }
        detail_factor(shared, log)
    }

    /// The texel model at a footprint, its parameters interpolated
    /// bilinearly (the file has a model).
    #[inline(always)]
    fn texel_at(&self, at: &Footprint) -> texel::TexelParams {
        let tx = at.texel.map(|t| &self.texels[t as usize]);
        let w = at.w;
        let v: [f32; texel::STORED] = std::array::from_fn(|i| {
            w[0] * tx[0][i] + w[1] * tx[1][i] + w[2] * tx[2][i] + w[3] * tx[3][i]
        });
        texel::TexelParams::from_stored(&v)
    }

    /// Where (view, light)'s index bytes and palette start.
    #[inline(always)]
    fn pair(&self, view: u16, light: u16, w: f32) -> Pair {
        let image = view as usize * self.size * self.size * self.groups
            + self.light_groups[light as usize] as usize;
        let palette = (view as usize * self.lights + light as usize) * self.colours;
        Pair { image, palette, w, view, light }
    }

    /// A pair's palette.
    #[inline(always)]
    fn palette(&self, p: &Pair) -> &[[f32; 3]] {
        &self.palettes[p.palette..][..self.colours]
    }

    /// The palette indices of a pair at the footprint's four texels.
    #[inline(always)]
    fn indices_at(&self, p: &Pair, at: &Footprint) -> [u8; 4] {
        let img = &self.indices[p.image..];
        let [t0, t1, t2, t3] = at.texel.map(|t| t as usize * self.groups);
        [img[t0], img[t1], img[t2], img[t3]]
    }

    /// The direction half of stage 1 (default interpolation): the unit
    /// directions and captured pairs of (wi, wo), which do not depend on uv,
    /// into `l`, prefetching each pair's index bytes at `at` as it is found.
    #[inline(always)]
    fn look_up(&self, wi: [f32; 3], wo: [f32; 3], l: &mut Lookup, at: &Footprint) {
        let Directions::Triangles { views, lights, light_dirs, shift, .. } = &self.directions
        else {
            unreachable!("staged only with the default interpolation")
        };
        l.key = Some(Lookup::key(wi, wo));
        l.pairs = 0;
        let Some((wi, wo)) = unit_above(wi, wo) else {
            return;
        };
        (l.wi, l.wo) = (wi, wo);
        default_pairs(lights, light_dirs, views, *shift, wi, wo, |vi, li, w| {
            // Never more than 9 pairs (3 light × 3 view weights); a guard all the same.
            if l.pairs < MAX_PAIRS {
                let p = self.pair(vi, li, w);
                self.prefetch_indices(&p, at);
                l.pair[l.pairs] = p;
                l.pairs += 1;
            }
        });
    }

    /// Ask the memory for a pair's index bytes at a footprint.
    #[inline(always)]
    fn prefetch_indices(&self, p: &Pair, at: &Footprint) {
        for t in at.texel {
            prefetch(&self.indices[p.image + t as usize * self.groups]);
        }
    }

    /// Stage 1 (default interpolation): directions, footprint and pairs;
    /// prefetches the pairs' index bytes and the texel model. With `reuse`,
    /// `s.dirs` already holds the lookup of these directions (the query
    /// before it had the same).
    #[inline(always)]
    fn stage(&self, uv: [f32; 2], wi: [f32; 3], wo: [f32; 3], s: &mut Staged, reuse: bool) {
        let uv = self.scanned_uv(uv);
        let Some(at) = self.texels_at(uv) else {
            s.dirs.pairs = 0;
            s.dirs.key = None;
            return;
        };
        if reuse {
            for p in &s.dirs.pair[..s.dirs.pairs] {
                self.prefetch_indices(p, &at);
            }
        } else {
            self.look_up(wi, wo, &mut s.dirs, &at);
        }
        s.at = at;
        if s.dirs.pairs > 0 && !self.detail.is_empty() {
            s.fine = Footprint::on(2 * self.size, uv);
            // Its two rows (each pair of taps shares a line, or nearly).
            for t in [s.fine.texel[0], s.fine.texel[2]] {
                prefetch(&self.detail[t as usize * (1 + self.components)]);
            }
        }
        if s.dirs.pairs > 0 && !self.texels.is_empty() {
            for t in at.texel {
                prefetch(&self.texels[t as usize]);
            }
        }
    }

    /// Stage 2: the pairs' palette indices; prefetches their colours.
    #[inline(always)]
    fn gather(&self, s: &mut Staged) {
        for k in 0..s.dirs.pairs {
            let p = s.dirs.pair[k];
            let idx = self.indices_at(&p, &s.at);
            s.idx[k] = idx;
            let pal = self.palette(&p);
            for i in idx {
                prefetch(&pal[i as usize]);
            }
        }
    }

    /// Stage 3: the sum over the pairs, with the texel model if the file
    /// has one.
    #[inline(always)]
    fn finish(&self, s: &Staged) -> [f32; 3] {
        if s.dirs.pairs == 0 {
            return [0.0; 3];
        }
        let mut acc = [0.0f32; 3];
        for k in 0..s.dirs.pairs {
            let p = &s.dirs.pair[k];
            let c = bilinear(self.palette(p), s.idx[k], &s.at);
            for ch in 0..3 {
                acc[ch] += p.w * c[ch];
            }
        }
        let Directions::Triangles { light_dirs, view_dirs, .. } = &self.directions else {
            unreachable!("staged only with the default interpolation")
        };
        let d = if self.components > 0 {
            let mut lights = [(0u16, 0f32); MAX_PAIRS];
            for (l, p) in lights.iter_mut().zip(&s.dirs.pair[..s.dirs.pairs]) {
                *l = (p.light, p.w);
            }
            self.detail_at(&s.fine, &lights[..s.dirs.pairs])
        } else {
            self.detail_at(&s.fine, &[])
        };
        if self.texels.is_empty() {
            return std::array::from_fn(|c| acc[c] * s.dirs.wi[2] * d[c]);
        }
        let p = self.texel_at(&s.at);
        // M(wi, wo) + cos θi · Σ (f_k − M_k / cos θi(l_k)) w_k: the query's
        // directions in slot 0, each mixed pair's in the next, weighted by
        // w / cos θi(light); evaluated together.
        let mut lanes = ModelLanes::default();
        lanes.set_query(s.dirs.wi, s.dirs.wo);
        for p in &s.dirs.pair[..s.dirs.pairs] {
            let (l, v) = (light_dirs[p.light as usize], view_dirs[p.view as usize]);
            lanes.push(l, v, p.w / l[2]);
        }
        let t = texel::terms_batch(p.normal, p.alpha * p.alpha, &lanes.wi, &lanes.wo);
        let (mut sd, mut ss, mut so) = (0.0, 0.0, 0.0);
        for (k, &w) in lanes.weight.iter().enumerate().skip(1) {
            sd += w * t[0][k];
            ss += w * t[1][k];
            so += w * t[2][k];
        }
        std::array::from_fn(|c| {
            let m = p.diffuse[c] * t[0][0] + p.specular[c] * t[1][0] + t[2][0];
            let mixed = p.diffuse[c] * sd + p.specular[c] * ss + so;
            ((acc[c] - mixed) * s.dirs.wi[2] + m).max(0.0) * d[c]
        })
    }
}

/// Queries per block of [`Material::eval_batch`] (more than one: a query
/// reuses the lookup of the entry staged before it, which must be another).
const BLOCK: usize = 32;
const _: () = assert!(BLOCK > 1);
/// Pairs per query of the default interpolation: 3 light × 3 view weights.
const MAX_PAIRS: usize = 9;

/// The bilinear colour of a pair from its palette and four indices.
#[inline(always)]
fn bilinear(pal: &[[f32; 3]], idx: [u8; 4], at: &Footprint) -> [f32; 3] {
    let c =
        [pal[idx[0] as usize], pal[idx[1] as usize], pal[idx[2] as usize], pal[idx[3] as usize]];
    std::array::from_fn(|k| {
        at.w[0] * c[0][k] + at.w[1] * c[1][k] + at.w[2] * c[2][k] + at.w[3] * c[3][k]
    })
}

/// A captured pair of a query: where its index bytes (image and light
/// group) and palette start, its weight and its directions.
#[derive(Debug, Clone, Copy, Default)]
struct Pair {
    image: usize,
    palette: usize,
    w: f32,
    view: u16,
    light: u16,
}

/// The four texels of a bilinear lookup (`y · S + x`) and their weights.
#[derive(Debug, Clone, Copy, Default)]
struct Footprint {
    texel: [u32; 4],
    w: [f32; 4],
}

impl Footprint {
    /// The bilinear footprint of a finite uv (wrapped into [0, 1)) on an
    /// n × n grid of texel centres.
    #[inline(always)]
    fn on(n: usize, uv: [f32; 2]) -> Footprint {
        let (texel, w) = bilinear_footprint(n, uv);
        Footprint { texel, w }
    }
}

/// How the shading interpolates every per-texel table (index images, texel
/// model, detail layer): the four texels (`y · n + x`) around a finite uv
/// (wrapped into [0, 1)) on an n × n grid of texel centres, clamped at the
/// borders, and their bilinear weights.
#[inline(always)]
pub fn bilinear_footprint(n: usize, uv: [f32; 2]) -> ([u32; 4], [f32; 4]) {
    let (x0, x1, tx) = taps(n, uv[0] - uv[0].floor());
    let (y0, y1, ty) = taps(n, uv[1] - uv[1].floor());
    let texel = [y0 * n + x0, y0 * n + x1, y1 * n + x0, y1 * n + x1].map(|t| t as u32);
    let w = [(1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty];
    (texel, w)
}

/// A query between the stages of the default interpolation.
#[derive(Debug, Clone, Copy, Default)]
struct Staged {
    /// Its unit directions and pairs (none: black).
    dirs: Lookup,
    at: Footprint,
    /// The uv's footprint on the detail layer's 2S × 2S grid (with a layer).
    fine: Footprint,
    /// Each pair's palette indices at the footprint.
    idx: [[u8; 4]; MAX_PAIRS],
}

/// Directions looked up ([`Material::look_up`]) and what they gave: their
/// unit vectors and captured pairs (none: black).
#[derive(Debug, Clone, Copy, Default)]
struct Lookup {
    /// The bits of the (wi, wo) looked up; `None` if not these directions'
    /// lookup (not yet made, or a query black for its uv).
    key: Option<[[u32; 3]; 2]>,
    wi: [f32; 3],
    wo: [f32; 3],
    pairs: usize,
    pair: [Pair; MAX_PAIRS],
}

impl Lookup {
    /// What identifies a lookup: the bits of the directions as given.
    #[inline(always)]
    fn key(wi: [f32; 3], wo: [f32; 3]) -> [[u32; 3]; 2] {
        [wi, wo].map(|d| d.map(f32::to_bits))
    }
}

/// Ask the memory for the cache line holding `x` (a hint; no effect on
/// results).
#[inline(always)]
fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch never faults, and `x` is a valid reference anyway.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T1, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T1>((x as *const T).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

#[cfg(test)]
mod tests;
