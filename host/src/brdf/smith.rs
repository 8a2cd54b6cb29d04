//! The Smith shadowing-masking term derived from a tabulated D
//! (spec/npf-brdf.md §4, "G derived from D"):
//!
//! G1(θ) = cos θ / σ(θ),  σ(θ) = ∫ max(0, ω·m) D(m) dm,  ∫ D(m) cos θm dm = 1.
//!
//! D is read from its 90-bin table by linear interpolation in θh′ between bin
//! centres. For an isotropic D the azimuthal integral of max(0, ω·m) has a
//! closed form, so only the θm integral is numerical: 15-point Gauss–Legendre
//! on panels in θh′ (where the table is uniform), split at the kink
//! θm = π/2 − θ where the clamped cosine starts to cut.

use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::OnceLock;

use super::BINS;
use super::coords::g_bin_centre;

/// 15-point Gauss–Legendre nodes and weights on [−1, 1].
fn gauss_legendre_15() -> &'static [(f64, f64); 15] {
    static GL: OnceLock<[(f64, f64); 15]> = OnceLock::new();
    GL.get_or_init(|| {
        let n = 15;
        let mut out = [(0.0, 0.0); 15];
        for (i, slot) in out.iter_mut().enumerate() {
            // Newton on P_n from the Chebyshev guess.
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    break;
                }
            }
            *slot = (x, 2.0 / ((1.0 - x * x) * dp * dp));
        }
        out
    })
}

/// ∫_a^b f(u) du by `panels` panels of 15-point Gauss–Legendre.
fn integrate(a: f64, b: f64, panels: usize, f: impl Fn(f64) -> f64) -> f64 {
    let gl = gauss_legendre_15();
    let h = (b - a) / panels as f64;
    let mut sum = 0.0;
    for p in 0..panels {
        let (lo, hi) = (a + p as f64 * h, a + (p + 1) as f64 * h);
        let (mid, half) = ((lo + hi) / 2.0, (hi - lo) / 2.0);
        for &(x, w) in gl {
            sum += w * half * f(mid + half * x);
        }
    }
    sum
}

/// D at θh′ = u, linear between bin centres (k + 0.5)/90, clamped.
fn d_at(d: &[f64; BINS], u: f64) -> f64 {
    let x = u * BINS as f64 - 0.5;
    if x <= 0.0 {
        return d[0];
    }
    if x >= (BINS - 1) as f64 {
        return d[BINS - 1];
    }
    let a = x.floor() as usize;
    let w = x - a as f64;
    d[a] * (1.0 - w) + d[a + 1] * w
}

/// ∫_0^{2π} max(0, sin θ sin θm cos φ + cos θ cos θm) dφ.
fn azimuthal(theta: f64, theta_m: f64) -> f64 {
    let a = theta.sin() * theta_m.sin();
    let b = theta.cos() * theta_m.cos();
    if b >= a {
        2.0 * PI * b
    } else if b <= -a {
        0.0
    } else {
        let phi0 = (-b / a).acos();
        2.0 * (b * phi0 + a * phi0.sin())
    }
}

const PANELS: usize = 16;

/// The 90-bin G table (at bin centres) of the Smith term of `d`.
pub fn smith_g(d: &[f64; BINS]) -> [f64; BINS] {
    // θm = (π/2)u², dθm = π u du.
    let norm = 2.0
        * PI
        * integrate(0.0, 1.0, 2 * PANELS, |u| {
            let t = FRAC_PI_2 * u * u;
            d_at(d, u) * t.cos() * t.sin() * PI * u
        });
    let mut g = [1.0; BINS];
    if norm.is_nan() || norm <= 0.0 {
        return g;
    }
    for (k, gk) in g.iter_mut().enumerate() {
        let theta = g_bin_centre(k);
        let sigma_part = |lo: f64, hi: f64| {
            integrate(lo, hi, PANELS, |u| {
                let t = FRAC_PI_2 * u * u;
                d_at(d, u) * t.sin() * azimuthal(theta, t) * PI * u
            })
        };
        let kink = (1.0 - theta / FRAC_PI_2).max(0.0).sqrt();
        let sigma = (sigma_part(0.0, kink) + sigma_part(kink, 1.0)) / norm;
        *gk = (theta.cos() / sigma).clamp(0.0, 1.0);
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::brdf::analytic::Ndf;
    use crate::brdf::coords::cell_centre;

    #[test]
    fn gauss_legendre_integrates_polynomials_exactly() {
        let v = integrate(0.0, 2.0, 1, |x| x.powi(28) + 3.0 * x * x);
        let exact = 2f64.powi(29) / 29.0 + 8.0;
        assert!((v - exact).abs() / exact < 1e-12, "{v} vs {exact}");
    }

    #[test]
    fn smith_from_a_tabulated_ndf_matches_the_analytic_g1() {
        for ndf in [Ndf::Ggx(0.15), Ndf::Ggx(0.4), Ndf::Beckmann(0.2)] {
            let d: [f64; BINS] = std::array::from_fn(|k| ndf.d(cell_centre(k, 0, 0).theta_h.cos()));
            let g = smith_g(&d);
            for (k, gk) in g.iter().enumerate().take(80) {
                let exact = ndf.g1(g_bin_centre(k).cos());
                assert!((gk - exact).abs() < 0.01, "{ndf:?} bin {k}: {gk} vs {exact}");
            }
        }
    }
}
