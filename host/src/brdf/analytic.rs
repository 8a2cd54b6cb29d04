//! Analytic reference BRDFs, for generating MERL-format test tables and for
//! benchmarks: microfacet conductors with GGX or Beckmann normals, Schlick
//! Fresnel and separable Smith shadowing (exactly representable by NPF), a
//! Lambert base under a GGX dielectric coat (energy-coupled, or seen through
//! the smooth-interface Fresnel transmission), and a two-lobe GGX mixture.

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
    /// Schlick F0 = `coat_f0`; how much light the coat lets through to the
    /// base and back out is `transmission`.
    CoatedDiffuse {
        /// Diffuse albedo.
        albedo: [f64; 3],
        /// Coat roughness.
        alpha: f64,
        /// Coat F0.
        coat_f0: f64,
        /// The coupling between the coat and the base.
        transmission: Transmission,
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
            Analytic::CoatedDiffuse { albedo, alpha, coat_f0, transmission } => {
                let coat = coat_lobe(*alpha, *coat_f0);
                let spec = coat.eval(wi, wo);
                let t = match transmission {
                    Transmission::Fresnel => {
                        (1.0 - schlick(*coat_f0, wi[2])) * (1.0 - schlick(*coat_f0, wo[2]))
                    }
                    Transmission::Coupled(e) => {
                        (1.0 - e.at(wi[2])) * (1.0 - e.at(wo[2])) / (1.0 - e.mean)
                    }
                };
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

/// How a coat lets light through to the diffuse base and back.
#[derive(Debug, Clone, PartialEq)]
pub enum Transmission {
    /// The smooth-interface approximation: (1 − F(θi))(1 − F(θo)) with
    /// Schlick's F at the angles to the macro normal. At grazing angles it
    /// removes the base entirely (F → 1), more than a rough coat reflects.
    Fresnel,
    /// Energy coupling (Kelemen & Szirmay-Kalos 2001; the same form as
    /// Kulla & Conty's energy compensation): the base sees what the coat's
    /// own GGX lobe does not reflect,
    /// (1 − E(θi))(1 − E(θo)) / (1 − Ē), where E(θ) is the lobe's directional
    /// albedo and Ē = 2∫ E(θ) cos θ sin θ dθ its cosine-weighted mean, so a
    /// base of albedo 1 returns exactly the energy the coat lets through.
    Coupled(DirectionalAlbedo),
}

/// The directional albedo E(θ) = ∫ f_spec(ω, ωo) cos θo dωo of a microfacet
/// lobe, tabulated uniformly in θ and read by linear interpolation.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectionalAlbedo {
    table: Vec<f64>,
    /// Ē = 2∫ E(θ) cos θ sin θ dθ.
    pub mean: f64,
}

/// Steps of the E(θ) table over [0, π/2].
const ALBEDO_STEPS: usize = 90;

impl DirectionalAlbedo {
    /// E(θ) of `lobe` (first channel), integrated over half vectors:
    /// with o = reflect(i, h), dωo = 4 (i·h) dωh, so
    /// E(θi) = ∫ f(i, o) cos θo · 4 (i·h) dωh over the h with i·h > 0 and o
    /// above the horizon; θh = (π/2)u² concentrates the midpoint samples on
    /// the peak, as MERL's θh′ does.
    pub fn of(lobe: &Lobe) -> DirectionalAlbedo {
        use rayon::prelude::*;
        const NU: usize = 384;
        const NPHI: usize = 192;
        let table: Vec<f64> = (0..=ALBEDO_STEPS)
            .into_par_iter()
            .map(|k| {
                // The last entry is the limit at grazing incidence.
                let theta = (k as f64 / ALBEDO_STEPS as f64).min(0.9999) * PI / 2.0;
                let i = [theta.sin(), 0.0, theta.cos()];
                let mut sum = 0.0;
                for a in 0..NU {
                    let u = (a as f64 + 0.5) / NU as f64;
                    let th = PI / 2.0 * u * u;
                    let (sh, ch) = th.sin_cos();
                    // dωh = sin θh dθh dφ, dθh = π u du; φ over [0, π], × 2.
                    let dw = sh * PI * u / NU as f64 * (PI / NPHI as f64) * 2.0;
                    for b in 0..NPHI {
                        let phi = (b as f64 + 0.5) / NPHI as f64 * PI;
                        let h = [sh * phi.cos(), sh * phi.sin(), ch];
                        let ih = dot(i, h);
                        let o = [
                            2.0 * ih * h[0] - i[0],
                            2.0 * ih * h[1] - i[1],
                            2.0 * ih * h[2] - i[2],
                        ];
                        if ih <= 0.0 || o[2] <= 0.0 {
                            continue;
                        }
                        sum += lobe.eval(i, o)[0] * o[2] * 4.0 * ih * dw;
                    }
                }
                sum
            })
            .collect();
        // Ē by the trapezoid rule over the table.
        let step = PI / 2.0 / ALBEDO_STEPS as f64;
        let mean = 2.0
            * (0..ALBEDO_STEPS)
                .map(|k| {
                    let f = |k: usize| {
                        let t = k as f64 * step;
                        table[k] * t.cos() * t.sin()
                    };
                    0.5 * (f(k) + f(k + 1)) * step
                })
                .sum::<f64>();
        DirectionalAlbedo { table, mean }
    }

    /// E at cos θ.
    pub fn at(&self, cos_t: f64) -> f64 {
        let x = cos_t.clamp(0.0, 1.0).acos() / (PI / 2.0) * ALBEDO_STEPS as f64;
        let k = (x.floor() as usize).min(ALBEDO_STEPS - 1);
        let f = x - k as f64;
        self.table[k] * (1.0 - f) + self.table[k + 1] * f
    }
}

fn coat_lobe(alpha: f64, f0: f64) -> Lobe {
    Lobe { ndf: Ndf::Ggx(alpha), f0: [f0; 3], weight: [1.0; 3] }
}

/// Albedo, roughness and F0 of the red plastic.
const PLASTIC: ([f64; 3], f64, f64) = ([0.6, 0.12, 0.08], 0.12, 0.04);

/// Lambert + GGX dielectric coat, energy-coupled (a red plastic): the
/// issue's case (b).
pub fn coated_plastic() -> Analytic {
    let (albedo, alpha, coat_f0) = PLASTIC;
    let e = DirectionalAlbedo::of(&coat_lobe(alpha, coat_f0));
    Analytic::CoatedDiffuse { albedo, alpha, coat_f0, transmission: Transmission::Coupled(e) }
}

/// The same plastic seen through the smooth-interface Fresnel transmission
/// (a harder case: the base vanishes at grazing angles).
pub fn coated_plastic_fresnel() -> Analytic {
    let (albedo, alpha, coat_f0) = PLASTIC;
    Analytic::CoatedDiffuse { albedo, alpha, coat_f0, transmission: Transmission::Fresnel }
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

    /// The coat's directional albedo: F0 at normal incidence (less the tiny
    /// shadowing and lobe spread), rising towards grazing but held well below
    /// 1 by masking; the reflected energy matches a direct integration over
    /// outgoing directions.
    #[test]
    fn coat_albedo() {
        let lobe = coat_lobe(0.12, 0.04);
        let e = DirectionalAlbedo::of(&lobe);
        assert!((e.at(1.0) - 0.04).abs() < 0.002, "E(0) = {}", e.at(1.0));
        assert!(e.at(0.0) > 0.2 && e.at(0.0) < 0.5, "E(90°) = {}", e.at(0.0));
        assert!(e.mean > 0.04 && e.mean < 0.1, "Ē = {}", e.mean);
        for theta in [0.3f64, 1.0, 1.3] {
            let i = [theta.sin(), 0.0, theta.cos()];
            // Uniform in cos θo and φ (a different quadrature).
            let (nt, np) = (1200, 600);
            let mut sum = 0.0;
            for a in 0..nt {
                let u = (a as f64 + 0.5) / nt as f64;
                let s = (1.0 - u * u).sqrt();
                for b in 0..np {
                    let p = (b as f64 + 0.5) / np as f64 * PI;
                    sum += lobe.eval(i, [s * p.cos(), s * p.sin(), u])[0] * u;
                }
            }
            let direct = sum / nt as f64 * (PI / np as f64) * 2.0;
            let rel = (e.at(theta.cos()) - direct).abs() / direct;
            assert!(rel < 0.01, "θ = {theta}: {} vs {direct}", e.at(theta.cos()));
        }
    }
}
