//! Ground-truth samples: procedural spatially varying materials the
//! simulator renders and tests score the host against.
//!
//! Every material is a field of [`Texel`]s over the plane (millimetres),
//! **tileable** with period [`TILE_MM`] in both directions, so that a small
//! sample (25.4 mm) is a window of it and the ≈10× larger piece
//! ([`LARGE_PIECE_MM`] square, 9.9× the area) shows the pattern's
//! long-range variation that does not repeat within the small one.
//!
//! Shading model of a texel (sample-local frame, z = geometric normal):
//! Lambert diffuse plus a GGX microfacet lobe (height-correlated Smith G,
//! Schlick Fresnel with the specular albedo as F0), around the texel's
//! normal from its height map; cosines are taken against that normal.
//!
//! [`Sample::reflected_radiance`] is the **ground-truth API**: for tests and
//! benchmarks only; host code never calls it.

use std::f64::consts::PI;
use std::sync::Arc;

use glam::DVec3;

/// Period of every procedural material, mm.
pub const TILE_MM: f64 = 80.0;
/// Side of the large piece for the direct images (≈10× the small sample's area).
pub const LARGE_PIECE_MM: f64 = 80.0;
/// The largest side of a large piece ([`Sample::large`]): a texture set's
/// tile may be metres across, but a piece photographed for the direct
/// images is bounded, and so are the photographs', the direct images' and
/// the enlarged material's sizes (each grows with the piece's area).
pub const LARGE_PIECE_MAX_MM: f64 = 2.0 * LARGE_PIECE_MM;
/// Side of the small sample, mm.
pub const SAMPLE_MM: f64 = 25.4;

/// The reflectance parameters at one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Texel {
    /// Diffuse albedo (linear RGB).
    pub diffuse: [f64; 3],
    /// Specular albedo at normal incidence, F0 (linear RGB).
    pub specular: [f64; 3],
    /// GGX α.
    pub roughness: f64,
    /// Shading normal (sample-local, unit, z > 0).
    pub normal: DVec3,
}

impl Texel {
    /// BRDF f(ωi, ωo), 1/sr, for unit directions in the sample-local frame.
    pub fn brdf(&self, wi: DVec3, wo: DVec3) -> [f64; 3] {
        let n = self.normal;
        let (ci, co) = (n.dot(wi), n.dot(wo));
        if wi.z <= 0.0 || wo.z <= 0.0 || ci <= 0.0 || co <= 0.0 {
            return [0.0; 3];
        }
        let h = (wi + wo).normalize();
        if self.specular.iter().all(|&f0| f0 <= 0.0) {
            return self.diffuse.map(|a| a / PI);
        }
        let ch = n.dot(h).max(0.0);
        let a2 = self.roughness * self.roughness;
        let t = ch * ch * (a2 - 1.0) + 1.0;
        let d = a2 / (PI * t * t);
        let lambda = |c: f64| {
            let tan2 = (1.0 - c * c).max(0.0) / (c * c);
            0.5 * (-1.0 + (1.0 + a2 * tan2).sqrt())
        };
        let g = 1.0 / (1.0 + lambda(ci) + lambda(co));
        let schlick = (1.0 - wi.dot(h).clamp(0.0, 1.0)).powi(5);
        let common = d * g / (4.0 * ci * co);
        std::array::from_fn(|k| {
            let f0 = self.specular[k];
            self.diffuse[k] / PI + common * (f0 + (1.0 - f0) * schlick)
        })
    }

    /// Radiance reflected towards `wo` under unit irradiance (measured
    /// perpendicular to the light) from `wi`: f · cos θi.
    pub fn reflected(&self, wi: DVec3, wo: DVec3) -> [f64; 3] {
        let c = self.normal.dot(wi).max(0.0);
        self.brdf(wi, wo).map(|v| v * c)
    }
}

/// Where the built-in materials' small sample is cut, mm.
pub const SMALL_OFFSET_MM: [f64; 2] = [27.3, 31.9];

/// A spatially varying material over the plane.
pub trait Material: Send + Sync + std::fmt::Debug {
    /// Short name (`woven-fabric`, …).
    fn name(&self) -> &str;
    /// The texel at `p` (mm).
    fn texel(&self, p: [f64; 2]) -> Texel;
    /// Period of the pattern, mm: the large piece is one tile.
    fn tile_mm(&self) -> f64 {
        TILE_MM
    }
    /// Where the 25.4 mm small sample is cut, mm.
    fn sample_offset_mm(&self) -> [f64; 2] {
        SMALL_OFFSET_MM
    }
}

/// A physical piece of a material: a `size_mm` square window of it, cut at
/// `offset_mm`. Its uv runs from 0 to 1 across the piece (u along +x, v
/// along the sample's bitangent, world −y).
#[derive(Debug, Clone)]
pub struct Sample {
    /// The material.
    pub material: Arc<dyn Material>,
    /// Where the window starts in the material, mm.
    pub offset_mm: [f64; 2],
    /// Side of the piece, mm.
    pub size_mm: f64,
}

impl Sample {
    /// The 25.4 mm sample of `material`, cut at its sample offset.
    pub fn small(material: Arc<dyn Material>) -> Sample {
        let offset_mm = material.sample_offset_mm();
        Sample { material, offset_mm, size_mm: SAMPLE_MM }
    }

    /// The large piece of the same material: the smallest square of whole
    /// tiles at least [`LARGE_PIECE_MM`] across — one tile of a library material
    /// or of a texture set of 80 mm or more, a smaller tile repeated (a
    /// piece is larger than its pattern's repeat and than the 25.4 mm
    /// sample cut from it). It contains the small sample, periodically.
    /// A tile larger than [`LARGE_PIECE_MAX_MM`] gives a piece of that
    /// side cut from it, centred on the small sample.
    pub fn large(material: Arc<dyn Material>) -> Sample {
        let tile = material.tile_mm();
        if tile > LARGE_PIECE_MAX_MM {
            let margin = (LARGE_PIECE_MAX_MM - SAMPLE_MM) / 2.0;
            let offset_mm = material.sample_offset_mm().map(|o| o - margin);
            return Sample { material, offset_mm, size_mm: LARGE_PIECE_MAX_MM };
        }
        // 1e-9: a tile that divides 80 mm up to rounding is not one more.
        let tiles = (LARGE_PIECE_MM / tile - 1e-9).ceil().max(1.0);
        Sample { material, offset_mm: [0.0, 0.0], size_mm: tiles * tile }
    }

    /// Material coordinates of uv.
    pub fn point(&self, uv: [f64; 2]) -> [f64; 2] {
        [self.offset_mm[0] + uv[0] * self.size_mm, self.offset_mm[1] + uv[1] * self.size_mm]
    }

    /// The texel at uv.
    pub fn texel(&self, uv: [f64; 2]) -> Texel {
        self.material.texel(self.point(uv))
    }

    /// **Ground truth (tests and benchmarks only):** radiance reflected at
    /// `uv` towards `view` under unit irradiance from `light` (unit vectors,
    /// sample-local frame, z = sample normal).
    pub fn reflected_radiance(&self, uv: [f64; 2], view: DVec3, light: DVec3) -> [f64; 3] {
        self.texel(uv).reflected(light, view)
    }
}

/// The calibration and material library by name.
pub fn by_name(name: &str) -> Option<Arc<dyn Material>> {
    Some(match name {
        "checkerboard" => Arc::new(Checkerboard::default()),
        "diffuse-white" => Arc::new(DiffuseWhite::default()),
        "glossy-black" => Arc::new(GlossyBlack::default()),
        "woven-fabric" => Arc::new(WovenFabric),
        "leather" => Arc::new(Leather),
        "painted-wood" => Arc::new(PaintedWood),
        "rough-metal" => Arc::new(RoughMetal),
        _ => return None,
    })
}

/// Why a material could not be had.
#[derive(Debug, thiserror::Error)]
pub enum MaterialError {
    /// Neither a library name nor a directory (a usage error).
    #[error("unknown material {0:?} (one of {names}, or a texture-set directory)", names = MATERIAL_NAMES.join(", "))]
    Unknown(String),
    /// A texture-set directory that is not valid (a bad input file).
    #[error("texture set: {0}")]
    TextureSet(#[from] crate::texture_set::TextureSetError),
}

/// A library material by name ([`by_name`]), or the texture set in the
/// directory `name` names (docs/texture-set.md).
pub fn lookup(name: &str) -> Result<Arc<dyn Material>, MaterialError> {
    if let Some(m) = by_name(name) {
        return Ok(m);
    }
    let path = std::path::Path::new(name);
    if path.is_dir() || name.contains(std::path::MAIN_SEPARATOR) {
        return Ok(Arc::new(crate::texture_set::TextureSet::load(path)?));
    }
    Err(MaterialError::Unknown(name.to_string()))
}

/// Names [`by_name`] knows.
pub const MATERIAL_NAMES: [&str; 7] = [
    "checkerboard",
    "diffuse-white",
    "glossy-black",
    "woven-fabric",
    "leather",
    "painted-wood",
    "rough-metal",
];

/// The spatially varying materials (not the calibration targets).
pub const SVBRDF_NAMES: [&str; 4] = ["woven-fabric", "leather", "painted-wood", "rough-metal"];

// ---------------------------------------------------------------------------
// Calibration targets

/// A matte printed checkerboard: `squares` × `squares` over the small
/// sample, the first (at uv = 0) white.
#[derive(Debug, Clone, Copy)]
pub struct Checkerboard {
    /// Squares across the sample.
    pub squares: u32,
    /// Albedo of the light squares.
    pub white: f64,
    /// Albedo of the dark squares.
    pub black: f64,
}

impl Default for Checkerboard {
    fn default() -> Checkerboard {
        Checkerboard { squares: 8, white: 0.85, black: 0.04 }
    }
}

impl Material for Checkerboard {
    fn name(&self) -> &str {
        "checkerboard"
    }
    fn texel(&self, p: [f64; 2]) -> Texel {
        // The pattern is laid out relative to the small sample's window.
        let o = SMALL_OFFSET_MM;
        let pitch = SAMPLE_MM / self.squares as f64;
        let i = ((p[0] - o[0]) / pitch).floor() as i64;
        let j = ((p[1] - o[1]) / pitch).floor() as i64;
        let a = if (i + j).rem_euclid(2) == 0 { self.white } else { self.black };
        flat([a; 3], [0.0; 3], 1.0)
    }
}

/// A pure diffuse white (Spectralon-like).
#[derive(Debug, Clone, Copy)]
pub struct DiffuseWhite {
    /// Albedo.
    pub albedo: f64,
}

impl Default for DiffuseWhite {
    fn default() -> DiffuseWhite {
        DiffuseWhite { albedo: 0.98 }
    }
}

impl Material for DiffuseWhite {
    fn name(&self) -> &str {
        "diffuse-white"
    }
    fn texel(&self, _p: [f64; 2]) -> Texel {
        flat([self.albedo; 3], [0.0; 3], 1.0)
    }
}

/// A glossy black tile (black glass or lacquer): no diffuse part, a narrow
/// dielectric GGX lobe. The simulator's beam is perfectly collimated, so
/// the lobe's width stands in for both the surface's and the real source's
/// angular spread (an LED collimator spreads its beam by about a degree).
/// Its highlights locate the lights (docs/calibration-format.md).
#[derive(Debug, Clone, Copy)]
pub struct GlossyBlack {
    /// Specular reflectance at normal incidence (glass: 0.04).
    pub f0: f64,
    /// GGX α.
    pub alpha: f64,
}

impl Default for GlossyBlack {
    fn default() -> GlossyBlack {
        GlossyBlack { f0: 0.04, alpha: 0.02 }
    }
}

impl Material for GlossyBlack {
    fn name(&self) -> &str {
        "glossy-black"
    }
    fn texel(&self, _p: [f64; 2]) -> Texel {
        flat([0.0; 3], [self.f0; 3], self.alpha)
    }
}

fn flat(diffuse: [f64; 3], specular: [f64; 3], roughness: f64) -> Texel {
    Texel { diffuse, specular, roughness, normal: DVec3::Z }
}

// ---------------------------------------------------------------------------
// Periodic noise (tile = TILE_MM)

fn hash(x: i64, y: i64, seed: u64) -> u64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 33;
    h = h.wrapping_mul(0xC4CE_B9FE_1A85_EC53);
    h ^ (h >> 33)
}

fn unit(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Smooth value noise in [0, 1] with `cells` lattice cells per tile in each
/// direction (periodic over the tile).
fn value_noise(p: [f64; 2], cells: [i64; 2], seed: u64) -> f64 {
    let x = p[0] / TILE_MM * cells[0] as f64;
    let y = p[1] / TILE_MM * cells[1] as f64;
    let (xi, yi) = (x.floor(), y.floor());
    let (fx, fy) = (fade(x - xi), fade(y - yi));
    // The cell and the next one, wrapped periodically (one division each).
    let wrap = |i: f64, n: i64| {
        let i = (i as i64).rem_euclid(n);
        [i, if i + 1 == n { 0 } else { i + 1 }]
    };
    let (xs, ys) = (wrap(xi, cells[0]), wrap(yi, cells[1]));
    let v = |dx: usize, dy: usize| unit(hash(xs[dx], ys[dy], seed));
    let (v00, v10, v01, v11) = (v(0, 0), v(1, 0), v(0, 1), v(1, 1));
    let a = v00 + (v10 - v00) * fx;
    let b = v01 + (v11 - v01) * fx;
    a + (b - a) * fy
}

/// Fractal sum of `octaves` value noises from `cells` cells per tile,
/// normalised to [0, 1].
fn fbm(p: [f64; 2], cells: i64, octaves: u32, seed: u64) -> f64 {
    let (mut sum, mut norm, mut amp, mut c) = (0.0, 0.0, 1.0, cells);
    for o in 0..octaves {
        sum += amp * value_noise(p, [c, c], seed.wrapping_add(o as u64 * 7919));
        norm += amp;
        amp *= 0.5;
        c *= 2;
    }
    sum / norm
}

/// Periodic Worley noise: distance (in cell units) to the nearest feature
/// point of a `cells` × `cells` jittered grid per tile, and that point's hash.
fn worley(p: [f64; 2], cells: i64, seed: u64) -> (f64, u64) {
    let x = p[0] / TILE_MM * cells as f64;
    let y = p[1] / TILE_MM * cells as f64;
    let (xi, yi) = (x.floor() as i64, y.floor() as i64);
    // The cells before, at and after, wrapped periodically (one division).
    let wrap = |i: i64| {
        let r = i.rem_euclid(cells);
        [if r == 0 { cells - 1 } else { r - 1 }, r, if r + 1 == cells { 0 } else { r + 1 }]
    };
    let (xs, ys) = (wrap(xi), wrap(yi));
    let mut best = (f64::INFINITY, 0);
    for dy in -1..=1 {
        for dx in -1..=1 {
            let (cx, cy) = (xi + dx, yi + dy);
            let h = hash(xs[(dx + 1) as usize], ys[(dy + 1) as usize], seed);
            let fx = cx as f64 + unit(h);
            let fy = cy as f64 + unit(h.rotate_left(29));
            let d = ((fx - x).powi(2) + (fy - y).powi(2)).sqrt();
            if d < best.0 {
                best = (d, h);
            }
        }
    }
    best
}

fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn mix3(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t)
}

fn scale3(a: [f64; 3], s: f64) -> [f64; 3] {
    a.map(|v| (v * s).clamp(0.0, 1.0))
}

/// Texel with the normal of height field `height` (mm) at `p`, by central
/// differences over `eps` mm.
fn with_height(
    p: [f64; 2],
    eps: f64,
    height: impl Fn([f64; 2]) -> f64,
    diffuse: [f64; 3],
    specular: [f64; 3],
    roughness: f64,
) -> Texel {
    let dx = (height([p[0] + eps, p[1]]) - height([p[0] - eps, p[1]])) / (2.0 * eps);
    let dy = (height([p[0], p[1] + eps]) - height([p[0], p[1] - eps])) / (2.0 * eps);
    Texel { diffuse, specular, roughness, normal: DVec3::new(-dx, -dy, 1.0).normalize() }
}

// ---------------------------------------------------------------------------
// Spatially varying materials

/// Plain-weave cotton: indigo warp, ecru weft, 1 mm thread pitch, fading.
#[derive(Debug, Clone, Copy)]
pub struct WovenFabric;

impl WovenFabric {
    const PITCH: f64 = 1.0;

    /// (height mm, warp on top).
    fn weave(p: [f64; 2]) -> (f64, bool) {
        let (x, y) = (p[0] / Self::PITCH, p[1] / Self::PITCH);
        let prof = |f: f64| (1.0 - ((f - 0.5) / 0.45).powi(2)).max(0.0).sqrt();
        let (i, j) = (x.floor(), y.floor());
        let warp = 0.09 * prof(x - i) * (0.75 + 0.25 * (PI * (y + i)).sin());
        let weft = 0.09 * prof(y - j) * (0.75 - 0.25 * (PI * (x + j)).sin());
        (warp.max(weft), warp >= weft)
    }
}

impl Material for WovenFabric {
    fn name(&self) -> &str {
        "woven-fabric"
    }
    fn texel(&self, p: [f64; 2]) -> Texel {
        let (h, warp) = Self::weave(p);
        let fading = 0.8 + 0.4 * fbm(p, 4, 3, 11);
        let (colour, thread) = if warp {
            let i = (p[0] / Self::PITCH).floor() as i64;
            ([0.05, 0.08, 0.24], value_noise([p[1], i as f64], [20, 80], 5))
        } else {
            let j = (p[1] / Self::PITCH).floor() as i64;
            ([0.72, 0.66, 0.55], value_noise([p[0], j as f64], [20, 80], 6))
        };
        // Shadowed gaps between threads are darker.
        let ao = 0.35 + 0.65 * smoothstep(0.0, 0.05, h);
        let diffuse = scale3(colour, fading * (0.85 + 0.3 * thread) * ao);
        with_height(p, 0.02, |q| Self::weave(q).0, diffuse, [0.04; 3], 0.45)
    }
}

/// Full-grain leather: pores, wrinkles, uneven tanning.
#[derive(Debug, Clone, Copy)]
pub struct Leather;

impl Leather {
    fn height(p: [f64; 2]) -> f64 {
        let (f1, _) = worley(p, 110, 21);
        let pore = -0.03 * (1.0 - smoothstep(0.0, 0.22, f1));
        let grain = 0.02 * f1;
        let wrinkles = 0.12 * (fbm(p, 16, 4, 22) - 0.5);
        pore + grain + wrinkles
    }
}

impl Material for Leather {
    fn name(&self) -> &str {
        "leather"
    }
    fn texel(&self, p: [f64; 2]) -> Texel {
        let tan = fbm(p, 5, 3, 23);
        let (f1, _) = worley(p, 110, 21);
        let crease = fbm(p, 16, 4, 22);
        let base = mix3([0.20, 0.09, 0.04], [0.42, 0.23, 0.11], tan);
        let shade = (0.7 + 0.3 * smoothstep(0.05, 0.3, f1)) * (0.8 + 0.4 * crease);
        let rough = 0.25 + 0.2 * fbm(p, 10, 2, 24);
        with_height(p, 0.02, Self::height, scale3(base, shade), [0.045; 3], rough)
    }
}

/// Plain-sawn wood painted teal, the paint worn through along the grain.
#[derive(Debug, Clone, Copy)]
pub struct PaintedWood;

impl PaintedWood {
    /// Growth-ring phase in [0, 1): 40 rings per tile across y, warped.
    fn ring(p: [f64; 2]) -> f64 {
        let warp = 1.6 * (fbm(p, 4, 3, 31) - 0.5) + 0.3 * (fbm(p, 16, 2, 32) - 0.5);
        let r = p[1] / TILE_MM * 40.0 + warp;
        r - r.floor()
    }

    /// Paint coverage in [0, 1].
    fn paint(p: [f64; 2]) -> f64 {
        let late = smoothstep(0.55, 0.8, Self::ring(p));
        let wear = fbm(p, 8, 4, 33);
        1.0 - smoothstep(0.55, 0.65, wear + 0.35 * late)
    }

    fn height(p: [f64; 2]) -> f64 {
        let late = smoothstep(0.55, 0.8, Self::ring(p));
        -0.02 * late + 0.012 * Self::paint(p)
    }
}

impl Material for PaintedWood {
    fn name(&self) -> &str {
        "painted-wood"
    }
    fn texel(&self, p: [f64; 2]) -> Texel {
        let late = smoothstep(0.55, 0.8, Self::ring(p));
        let wood = mix3([0.55, 0.36, 0.19], [0.33, 0.19, 0.09], late);
        let paint = Self::paint(p);
        let teal = scale3([0.06, 0.36, 0.33], 0.9 + 0.2 * fbm(p, 20, 2, 34));
        let diffuse = mix3(wood, teal, paint);
        let specular = mix3([0.03; 3], [0.05; 3], paint);
        let rough = 0.45 + (0.12 - 0.45) * paint;
        with_height(p, 0.02, Self::height, diffuse, specular, rough)
    }
}

/// Hammered copper, lightly tarnished, with fine scratches.
#[derive(Debug, Clone, Copy)]
pub struct RoughMetal;

impl RoughMetal {
    fn height(p: [f64; 2]) -> f64 {
        let (f1, _) = worley(p, 32, 41);
        let dents = 0.06 * f1 * f1;
        let scratches = 0.002 * value_noise(p, [8, 600], 42);
        dents + scratches
    }
}

impl Material for RoughMetal {
    fn name(&self) -> &str {
        "rough-metal"
    }
    fn texel(&self, p: [f64; 2]) -> Texel {
        let tarnish = smoothstep(0.55, 0.8, fbm(p, 6, 4, 43));
        let copper = [0.95, 0.64, 0.54];
        let specular = mix3(copper, [0.45, 0.30, 0.24], tarnish);
        let diffuse = mix3([0.0; 3], [0.05, 0.03, 0.02], tarnish);
        let rough = 0.16 + 0.1 * fbm(p, 12, 3, 44) + 0.15 * tarnish;
        with_height(p, 0.02, Self::height, diffuse, specular, rough)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The large piece: whole tiles from 80 mm, at most 160 mm; a larger
    /// tile (a texture set may be metres across) gives 160 mm of it around
    /// the small sample, so that the photographs, direct images and the
    /// enlarged material the demo makes of it stay bounded.
    #[test]
    fn a_large_piece_is_whole_tiles_up_to_its_largest_side() {
        #[derive(Debug)]
        struct Tiled(f64);
        impl Material for Tiled {
            fn name(&self) -> &str {
                "tiled"
            }
            fn texel(&self, p: [f64; 2]) -> Texel {
                by_name("leather").unwrap().texel(p)
            }
            fn tile_mm(&self) -> f64 {
                self.0
            }
            fn sample_offset_mm(&self) -> [f64; 2] {
                [4000.0, -10.0]
            }
        }
        let piece = |tile: f64| Sample::large(Arc::new(Tiled(tile)));
        for (tile, side) in
            [(16.0, 80.0), (30.0, 90.0), (79.0, 158.0), (80.0, 80.0), (160.0, 160.0)]
        {
            let p = piece(tile);
            assert_eq!((p.size_mm, p.offset_mm), (side, [0.0, 0.0]), "a {tile} mm tile");
        }
        for tile in [160.5, 300.0, 10_000.0] {
            let p = piece(tile);
            assert_eq!(p.size_mm, LARGE_PIECE_MAX_MM, "a {tile} mm tile");
            // The small sample in the middle of the piece.
            let small = Sample::small(p.material.clone());
            let centre = |s: &Sample| s.point([0.5, 0.5]);
            let (a, b) = (centre(&p), centre(&small));
            assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9, "{a:?} {b:?}");
        }
    }

    #[test]
    fn materials_tile_with_the_tile_period() {
        for name in SVBRDF_NAMES {
            let m = by_name(name).unwrap();
            for &(x, y) in &[(1.3, 2.7), (40.1, 77.7), (79.9, 0.05)] {
                let a = m.texel([x, y]);
                let b = m.texel([x + TILE_MM, y - TILE_MM]);
                for k in 0..3 {
                    assert!((a.diffuse[k] - b.diffuse[k]).abs() < 1e-9, "{name}");
                }
                assert!((a.normal - b.normal).length() < 1e-6, "{name}");
            }
        }
    }

    /// The noises wrap their lattice once an axis; the same values as
    /// wrapping every cell they read, at points in the tile's last and
    /// first cells, on both sides of its edges and far away.
    #[test]
    fn noises_wrap_their_cells_as_each_cell_wrapped_alone() {
        let value_ref = |p: [f64; 2], cells: [i64; 2], seed: u64| {
            let x = p[0] / TILE_MM * cells[0] as f64;
            let y = p[1] / TILE_MM * cells[1] as f64;
            let (xi, yi) = (x.floor(), y.floor());
            let (fx, fy) = (fade(x - xi), fade(y - yi));
            let (xi, yi) = (xi as i64, yi as i64);
            let v = |dx: i64, dy: i64| {
                unit(hash((xi + dx).rem_euclid(cells[0]), (yi + dy).rem_euclid(cells[1]), seed))
            };
            let a = v(0, 0) + (v(1, 0) - v(0, 0)) * fx;
            let b = v(0, 1) + (v(1, 1) - v(0, 1)) * fx;
            a + (b - a) * fy
        };
        let worley_ref = |p: [f64; 2], cells: i64, seed: u64| {
            let x = p[0] / TILE_MM * cells as f64;
            let y = p[1] / TILE_MM * cells as f64;
            let (xi, yi) = (x.floor() as i64, y.floor() as i64);
            let mut best = (f64::INFINITY, 0);
            for (dx, dy) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (dx, dy))) {
                let (cx, cy) = (xi + dx, yi + dy);
                let h = hash(cx.rem_euclid(cells), cy.rem_euclid(cells), seed);
                let fx = cx as f64 + unit(h);
                let fy = cy as f64 + unit(h.rotate_left(29));
                let d = ((fx - x).powi(2) + (fy - y).powi(2)).sqrt();
                if d < best.0 {
                    best = (d, h);
                }
            }
            best
        };
        let coords =
            [-160.3, -80.0, -79.99, -0.01, 0.0, 0.3, 39.7, 79.5, 79.99, 80.0, 80.2, 1e4 + 0.7];
        for &x in &coords {
            for &y in &coords {
                let p = [x, y];
                for cells in [[1, 1], [4, 4], [20, 80], [110, 3]] {
                    assert_eq!(
                        value_noise(p, cells, 5).to_bits(),
                        value_ref(p, cells, 5).to_bits()
                    );
                }
                for cells in [1, 2, 110] {
                    let (d, h) = worley(p, cells, 21);
                    let (dr, hr) = worley_ref(p, cells, 21);
                    assert_eq!((d.to_bits(), h), (dr.to_bits(), hr), "{p:?} {cells}");
                }
            }
        }
    }

    #[test]
    fn white_is_lambertian_and_energy_conserving() {
        let w = DiffuseWhite::default().texel([0.0, 0.0]);
        let wi = DVec3::new(0.3, 0.1, 0.9).normalize();
        let wo = DVec3::new(-0.5, 0.2, 0.6).normalize();
        let f = w.brdf(wi, wo);
        assert!((f[0] - 0.98 / PI).abs() < 1e-12);
        assert_eq!(w.brdf(DVec3::new(0.0, 0.0, -1.0), wo), [0.0; 3]);
    }
}
