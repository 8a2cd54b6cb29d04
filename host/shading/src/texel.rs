//! The texel model a material may carry beside its captured images
//! (docs/material-format.md, "Texel model"): per texel, Lambert diffuse
//! plus a GGX microfacet lobe with height-correlated Smith G and Schlick
//! Fresnel, around the texel's own normal, cosines taken against that
//! normal. The shading uses it to carry the captured images' residuals
//! between the captured directions (highlights then move with the query
//! instead of cross-fading between mirrors); the builder fits it. This is
//! the one copy of its formula.

use std::f32::consts::PI;

/// One texel's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TexelParams {
    /// Diffuse albedo ρd, linear RGB.
    pub diffuse: [f32; 3],
    /// Specular reflectance at normal incidence F0, linear RGB.
    pub specular: [f32; 3],
    /// GGX α (> 0).
    pub alpha: f32,
    /// Unit shading normal, sample-local, z > 0.
    pub normal: [f32; 3],
}

impl Default for TexelParams {
    fn default() -> Self {
        TexelParams { diffuse: [0.0; 3], specular: [0.0; 3], alpha: 1.0, normal: [0.0, 0.0, 1.0] }
    }
}

/// The model's terms for one pair of unit directions (wi towards the light,
/// wo towards the viewer), with `a2 = α²`: the reflected radiance per unit
/// irradiance f · cos θi (cos against the texel normal) is, per channel,
/// `ρd · t[0] + F0 · t[1] + t[2]`. Zero where either direction is below the
/// sample or the texel's horizon. Branch-free, so loops over many pairs
/// vectorise.
///
/// Written for f32 near a narrow lobe's peak: GGX's denominator
/// (n·h)² (α² − 1) + 1 is taken as sin²θh + α² cos²θh, with sin²θh from
/// |n × h|² rather than 1 − (n·h)²: the usual form subtracts numbers near
/// 1 and, at α = 0.01, loses three of f32's seven digits of D there.
#[inline(always)]
pub fn terms(n: [f32; 3], a2: f32, wi: [f32; 3], wo: [f32; 3]) -> [f32; 3] {
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (ci, co) = (dot(n, wi), dot(n, wo));
    let valid = wi[2] > 0.0 && wo[2] > 0.0 && ci > 0.0 && co > 0.0;
    let (ci, co) = (ci.max(1e-6), co.max(1e-6));
    let hs = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
    let inv2 = 1.0 / dot(hs, hs).max(1e-12);
    let inv = inv2.sqrt();
    let nh = dot(n, hs);
    let ch = (nh * inv).max(0.0);
    let nxh =
        [n[1] * hs[2] - n[2] * hs[1], n[2] * hs[0] - n[0] * hs[2], n[0] * hs[1] - n[1] * hs[0]];
    // sin²θh; 1 where h is not in front of n (then the pair is not valid).
    let sh = if nh > 0.0 { dot(nxh, nxh) * inv2 } else { 1.0 };
    let t = sh + a2 * ch * ch;
    let d = a2 / (PI * t * t);
    // Λ(c) = (√(1 + α² tan²) − 1) / 2: small where it cancels, so G = 1 / (1
    // + Λi + Λo) keeps f32's precision all the same.
    let lambda = |c: f32| 0.5 * ((1.0 + a2 * ((1.0 - c * c).max(0.0) / (c * c))).sqrt() - 1.0);
    let g = 1.0 / (1.0 + lambda(ci) + lambda(co));
    let x = 1.0 - (dot(wi, hs) * inv).clamp(0.0, 1.0);
    let x2 = x * x;
    let s = x2 * x2 * x;
    // D G F / (4 ci co) · ci.
    let common = d * g / (4.0 * co);
    let m = if valid { 1.0 } else { 0.0 };
    [m * ci / PI, m * common * (1.0 - s), m * common * s]
}

/// [`terms`] for N pairs at once, structure of arrays (`wi[axis][pair]`),
/// so that the compiler evaluates several pairs per vector instruction:
/// `out[term][pair]`.
#[inline(always)]
pub fn terms_batch<const N: usize>(
    n: [f32; 3],
    a2: f32,
    wi: &[[f32; N]; 3],
    wo: &[[f32; N]; 3],
) -> [[f32; N]; 3] {
    let mut out = [[0.0; N]; 3];
    for k in 0..N {
        let t = terms(n, a2, [wi[0][k], wi[1][k], wi[2][k]], [wo[0][k], wo[1][k], wo[2][k]]);
        out[0][k] = t[0];
        out[1][k] = t[1];
        out[2][k] = t[2];
    }
    out
}

/// f · cos θi of a texel (cos against its normal) for unit directions.
#[inline]
pub fn reflected(p: &TexelParams, wi: [f32; 3], wo: [f32; 3]) -> [f32; 3] {
    let t = terms(p.normal, p.alpha * p.alpha, wi, wo);
    std::array::from_fn(|c| p.diffuse[c] * t[0] + p.specular[c] * t[1] + t[2])
}

/// Values stored per texel in the material file: ρd (3), F0 (3), α, and
/// the normal's x and y (z = √(1 − x² − y²)).
pub const STORED: usize = 9;

impl TexelParams {
    /// From the file's [`STORED`] values (checked by the reader).
    pub fn from_stored(v: &[f32]) -> TexelParams {
        let (x, y) = (v[7], v[8]);
        TexelParams {
            diffuse: [v[0], v[1], v[2]],
            specular: [v[3], v[4], v[5]],
            alpha: v[6],
            normal: [x, y, (1.0 - x * x - y * y).max(0.0).sqrt()],
        }
    }

    /// The file's [`STORED`] values.
    pub fn to_stored(&self) -> [f32; STORED] {
        let d = &self.diffuse;
        let s = &self.specular;
        [d[0], d[1], d[2], s[0], s[1], s[2], self.alpha, self.normal[0], self.normal[1]]
    }

    /// Why stored values cannot be a texel: ρd and F0 in [0, 1], α in
    /// [10⁻³, 1], the normal's x, y within the unit disc with z ≥ 0.1.
    pub fn check_stored(v: &[f32]) -> Result<(), String> {
        let unit = |x: f32| (0.0..=1.0).contains(&x);
        if !v[..6].iter().all(|&x| unit(x)) {
            return Err(format!("albedo or F0 {:?} outside [0, 1]", &v[..6]));
        }
        if !(1e-3..=1.0).contains(&v[6]) {
            return Err(format!("α {} outside [0.001, 1]", v[6]));
        }
        let r2 = v[7] * v[7] + v[8] * v[8];
        if !(r2.is_finite() && r2 <= 0.99) {
            return Err(format!("normal ({}, {}) is not above the sample", v[7], v[8]));
        }
        Ok(())
    }
}
