//! Analytic reference BRDFs, for generating MERL-format test tables and for
//! benchmarks: microfacet conductors with GGX or Beckmann normals, Schlick
//! Fresnel and separable Smith shadowing (exactly representable by NPF), a
//! Lambert base under a GGX dielectric coat, and a two-lobe GGX mixture.

use std::f64::consts::PI;

use super::{Brdf, Vec3};

/// A microfacet normal distribution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Ndf {
    /// GGX / Trowbridge–Reitz with roughness α.
    Ggx(f64),
    /// Beckmann with roughness α.
    Beckmann(f64),
}

/// erf, Abramowitz & Stegun 7.1.26 refined (|error| < 1.2e-7).
fn erf(x: f64) -> f64 {
    // Numerical Recipes erfc (Chebyshev), |relative error| < 1.2e-7.
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let r = t
        * (-z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87
                                        + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    if x >= 0.0 { 1.0 - r } else { r - 1.0 }
}

impl Ndf {
    /// D(θh) given cos θh (normalised: ∫ D cos θm dω = 1).
    pub fn d(&self, cos_h: f64) -> f64 {
        if cos_h <= 0.0 {
            return 0.0;
        }
        let c2 = cos_h * cos_h;
        let tan2 = (1.0 - c2) / c2;
        match *self {
            Ndf::Ggx(a) => {
                let a2 = a * a;
                a2 / (PI * c2 * c2 * (a2 + tan2).powi(2))
            }
            Ndf::Beckmann(a) => {
                let a2 = a * a;
                (-tan2 / a2).exp() / (PI * a2 * c2 * c2)
            }
        }
    }

    /// Smith G1 for a direction at cos θ (exact for both distributions).
    pub fn g1(&self, cos_t: f64) -> f64 {
        if cos_t <= 0.0 {
            return 0.0;
        }
        let tan2 = (1.0 - cos_t * cos_t).max(0.0) / (cos_t * cos_t);
        let lambda = match *self {
            Ndf::Ggx(a) => ((1.0 + a * a * tan2).sqrt() - 1.0) / 2.0,
            Ndf::Beckmann(a) => {
                if tan2 == 0.0 {
                    0.0
                } else {
                    let m = 1.0 / (a * tan2.sqrt());
                    ((erf(m) - 1.0) + (-m * m).exp() / (m * PI.sqrt())) / 2.0
                }
            }
        };
        1.0 / (1.0 + lambda)
    }
}

/// Schlick's Fresnel with normal reflectance `f0` at cos θd.
pub fn schlick(f0: f64, cos_d: f64) -> f64 {
    f0 + (1.0 - f0) * (1.0 - cos_d.clamp(0.0, 1.0)).powi(5)
}

fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// One microfacet lobe: D F G1 G1 / (4 cos θi cos θo).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lobe {
    /// Normal distribution.
    pub ndf: Ndf,
    /// Schlick F0 per channel.
    pub f0: [f64; 3],
    /// Scale per channel.
    pub weight: [f64; 3],
}

impl Lobe {
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        let (ci, co) = (wi[2], wo[2]);
        if ci <= 0.0 || co <= 0.0 {
            return [0.0; 3];
        }
        let h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
        let n = dot(h, h).sqrt();
        let h = [h[0] / n, h[1] / n, h[2] / n];
        let common = self.ndf.d(h[2]) * self.ndf.g1(ci) * self.ndf.g1(co) / (4.0 * ci * co);
        let cd = dot(wi, h);
        [0, 1, 2].map(|c| self.weight[c] * schlick(self.f0[c], cd) * common)
    }
}

/// Reference BRDFs.
#[derive(Debug, Clone, PartialEq)]
pub enum Analytic {
    /// A conductor: one lobe.
    Conductor(Lobe),
    /// A conductor whose Smith G1 is read the way the NPF model reads G —
    /// tabulated at the 90 bin centres, linear in between — so that the BRDF
    /// lies exactly in the NPF function space ("exactly representable").
    TabulatedG(Lobe),
    /// A Lambert base (albedo per channel) under a dielectric GGX coat with
    /// Schlick F0 = `coat_f0`: the base is seen through (1 − F(θi))(1 − F(θo)).
    CoatedDiffuse {
        /// Diffuse albedo.
        albedo: [f64; 3],
        /// Coat roughness.
        alpha: f64,
        /// Coat F0.
        coat_f0: f64,
    },
    /// A sum of lobes.
    Mixture(Vec<Lobe>),
}

impl Brdf for Analytic {
    fn eval(&self, wi: Vec3, wo: Vec3) -> [f64; 3] {
        if wi[2] <= 0.0 || wo[2] <= 0.0 {
            return [0.0; 3];
        }
        match self {
            Analytic::Conductor(lobe) => lobe.eval(wi, wo),
            Analytic::TabulatedG(lobe) => {
                let g = |c: f64| {
                    let (a, w) = super::coords::g_interp(c.acos());
                    let g1 = |k: usize| lobe.ndf.g1(super::coords::g_bin_centre(k).cos());
                    g1(a) * (1.0 - w) + g1(a + 1) * w
                };
                let exact = lobe.eval(wi, wo);
                let (gi, go) = (lobe.ndf.g1(wi[2]), lobe.ndf.g1(wo[2]));
                if gi <= 0.0 || go <= 0.0 {
                    return [0.0; 3];
                }
                let scale = g(wi[2]) * g(wo[2]) / (gi * go);
                exact.map(|v| v * scale)
            }
            Analytic::CoatedDiffuse { albedo, alpha, coat_f0 } => {
                let coat = Lobe { ndf: Ndf::Ggx(*alpha), f0: [*coat_f0; 3], weight: [1.0; 3] };
                let spec = coat.eval(wi, wo);
                let t = (1.0 - schlick(*coat_f0, wi[2])) * (1.0 - schlick(*coat_f0, wo[2]));
                [0, 1, 2].map(|c| spec[c] + albedo[c] / PI * t)
            }
            Analytic::Mixture(lobes) => lobes.iter().fold([0.0; 3], |acc, l| {
                let v = l.eval(wi, wo);
                [acc[0] + v[0], acc[1] + v[1], acc[2] + v[2]]
            }),
        }
    }
}

/// A GGX conductor (gold-like F0).
pub fn ggx_conductor(alpha: f64) -> Analytic {
    Analytic::Conductor(Lobe { ndf: Ndf::Ggx(alpha), f0: [0.95, 0.64, 0.27], weight: [1.0; 3] })
}

/// The conductor `c` with its G tabulated as NPF reads it.
pub fn exactly_representable(c: Analytic) -> Analytic {
    match c {
        Analytic::Conductor(lobe) => Analytic::TabulatedG(lobe),
        other => other,
    }
}

/// A Beckmann conductor (copper-like F0).
pub fn beckmann_conductor(alpha: f64) -> Analytic {
    Analytic::Conductor(Lobe {
        ndf: Ndf::Beckmann(alpha),
        f0: [0.95, 0.64, 0.54],
        weight: [1.0; 3],
    })
}

/// Lambert + GGX dielectric coat (a red plastic).
pub fn coated_plastic() -> Analytic {
    Analytic::CoatedDiffuse { albedo: [0.6, 0.12, 0.08], alpha: 0.12, coat_f0: 0.04 }
}

/// A two-lobe GGX mixture (a sharp and a hazy lobe).
pub fn two_lobe_ggx() -> Analytic {
    Analytic::Mixture(vec![
        Lobe { ndf: Ndf::Ggx(0.06), f0: [0.9, 0.9, 0.9], weight: [0.6, 0.6, 0.6] },
        Lobe { ndf: Ndf::Ggx(0.35), f0: [0.6, 0.45, 0.3], weight: [0.5, 0.5, 0.5] },
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫ D(m) cos θm dω = 1 and G1 is 1 at normal incidence.
    #[test]
    fn ndfs_are_normalised() {
        for ndf in [Ndf::Ggx(0.1), Ndf::Ggx(0.5), Ndf::Beckmann(0.1), Ndf::Beckmann(0.4)] {
            let n = 20_000;
            let mut sum = 0.0;
            for k in 0..n {
                let t = (k as f64 + 0.5) / n as f64 * PI / 2.0;
                sum += ndf.d(t.cos()) * t.cos() * t.sin() * (PI / 2.0 / n as f64) * 2.0 * PI;
            }
            assert!((sum - 1.0).abs() < 2e-3, "{ndf:?}: {sum}");
            assert!((ndf.g1(1.0) - 1.0).abs() < 1e-12);
            assert!(ndf.g1(0.1) < 1.0);
        }
        assert!((erf(0.5) - 0.520_499_877_8).abs() < 2e-7);
    }
}
