//! Measured isotropic BRDFs and the non-parametric factor microfacet model
//! (NPF; spec/npf-brdf.md).
//!
//! Conventions (stated once, pbrt style): directions are unit vectors in the
//! local shading frame with the normal along +z, `wi` towards the light, `wo`
//! towards the viewer; [`Brdf::eval`] returns the BRDF value f(wi, wo) in sr⁻¹
//! **without** the cosine factor, and 0 when either direction is below the
//! horizon.
//!
//! - [`coords`]: the (θh, θd, φd) half/difference parameterisation and its
//!   MERL binning.
//! - [`merl`]: reading and writing MERL binary tables.
//! - [`measurements`]: scattered measurements as CSV.
//! - [`npf`]: the NPF model, its JSON file and the naive D·F·H model.
//! - [`fit`]: alternating weighted least squares (AWLS) fitting.
//! - [`smith`]: the Smith shadowing-masking term derived from a tabulated D.
//! - [`render`]: the rendered-sphere comparison (the one PSNR definition).
//! - [`analytic`]: reference analytic BRDFs (GGX, Beckmann, coats, mixtures)
//!   for tests and benchmarks.

pub mod analytic;
pub mod coords;
pub mod fit;
pub mod measurements;
pub mod merl;
pub mod npf;
pub mod render;
pub mod smith;

/// A 3-vector.
pub type Vec3 = [f64; 3];

/// An isotropic BRDF in the local frame, RGB.
pub trait Brdf: Sync {
    /// f(wi, wo) per channel, sr⁻¹, cosine excluded.
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3];
}

/// Number of bins of every NPF factor table.
pub const BINS: usize = 90;

/// Largest BRDF value any reader or the fit accepts, sr⁻¹ (a mirror-like
/// MERL material peaks near 10⁴): a MERL cell, a measurement, an NPF
/// model's ρd and ρs. Beyond it the units are wrong, and the fit's single
/// precision and a rendered sphere's radiance would overflow.
pub const MAX_VALUE: f64 = 1e8;
