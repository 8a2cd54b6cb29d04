//! The half/difference parameterisation of an isotropic BRDF
//! (spec/npf-brdf.md §1) and the MERL table binning (§5).

use std::f64::consts::{FRAC_PI_2, PI};

use super::Vec3;

/// MERL resolution in θh.
pub const N_THETA_H: usize = 90;
/// MERL resolution in θd.
pub const N_THETA_D: usize = 90;
/// MERL resolution in φd.
pub const N_PHI_D: usize = 180;
/// Cells in a MERL table (per channel).
pub const MERL_CELLS: usize = N_THETA_H * N_THETA_D * N_PHI_D;

/// (θh, θd, φd), radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfDiff {
    /// Angle between the half vector and the normal.
    pub theta_h: f64,
    /// Angle between each direction and the half vector.
    pub theta_d: f64,
    /// Rotation of `wi` about the half vector, folded into [0, π).
    pub phi_d: f64,
}

fn normalize(v: Vec3) -> Vec3 {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

/// The spec's forward map, with the half vector in the zx-plane.
pub fn to_directions(hd: HalfDiff) -> (Vec3, Vec3) {
    let (sh, ch) = hd.theta_h.sin_cos();
    let (sd, cd) = hd.theta_d.sin_cos();
    let (sp, cp) = hd.phi_d.sin_cos();
    let wi = [sh * cd - ch * cp * sd, -sp * sd, ch * cd + sh * cp * sd];
    let wo = [sh * cd + ch * cp * sd, sp * sd, ch * cd - sh * cp * sd];
    (wi, wo)
}

/// (θh, θd, φd) of a pair of directions (φh is rotated away; φd folded into
/// [0, π) by reciprocity).
pub fn from_directions(wi: Vec3, wo: Vec3) -> HalfDiff {
    let h = normalize([wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]]);
    let theta_h = h[2].clamp(-1.0, 1.0).acos();
    let phi_h = h[1].atan2(h[0]);
    // Rotate wi by −φh about z, then by −θh about y: the half-vector frame.
    let (sp, cp) = (-phi_h).sin_cos();
    let x = wi[0] * cp - wi[1] * sp;
    let y = wi[0] * sp + wi[1] * cp;
    let z = wi[2];
    let (st, ct) = (-theta_h).sin_cos();
    let dx = x * ct + z * st;
    let dz = -x * st + z * ct;
    let dy = y;
    // wi = (−cos φd sin θd, −sin φd sin θd, cos θd) in that frame.
    let theta_d = dz.clamp(-1.0, 1.0).acos();
    let mut phi_d = (-dy).atan2(-dx);
    if phi_d < 0.0 {
        phi_d += PI;
    }
    if phi_d >= PI {
        phi_d -= PI;
    }
    HalfDiff { theta_h, theta_d, phi_d }
}

/// MERL bin of θh: floor(sqrt(θh/(π/2))·90), clamped.
pub fn theta_h_bin(theta_h: f64) -> usize {
    let u = (theta_h.max(0.0) / FRAC_PI_2).sqrt();
    ((u * N_THETA_H as f64) as usize).min(N_THETA_H - 1)
}

/// MERL bin of θd: floor(θd/(π/2)·90), clamped.
pub fn theta_d_bin(theta_d: f64) -> usize {
    ((theta_d.max(0.0) / FRAC_PI_2 * N_THETA_D as f64) as usize).min(N_THETA_D - 1)
}

/// MERL bin of φd (already folded into [0, π)): floor(φd/π·180), clamped.
pub fn phi_d_bin(phi_d: f64) -> usize {
    ((phi_d.max(0.0) / PI * N_PHI_D as f64) as usize).min(N_PHI_D - 1)
}

/// Index of a cell: φd_i + 180·θd_i + 180·90·θh_i.
pub fn merl_index(th: usize, td: usize, pd: usize) -> usize {
    pd + N_PHI_D * td + N_PHI_D * N_THETA_D * th
}

/// Cell centre of MERL cell (θh_i, θd_i, φd_i): the point every lookup of the
/// cell stands for (centre in θh′ = sqrt(θh/(π/2)), θd and φd).
pub fn cell_centre(th: usize, td: usize, pd: usize) -> HalfDiff {
    let u = (th as f64 + 0.5) / N_THETA_H as f64;
    HalfDiff {
        theta_h: u * u * FRAC_PI_2,
        theta_d: (td as f64 + 0.5) / N_THETA_D as f64 * FRAC_PI_2,
        phi_d: (pd as f64 + 0.5) / N_PHI_D as f64 * PI,
    }
}

/// θ of the centre of G/cosine bin `k` (of 90 over [0, π/2]).
pub fn g_bin_centre(k: usize) -> f64 {
    (k as f64 + 0.5) * FRAC_PI_2 / 90.0
}

/// Linear interpolation position of θ between G bin centres: (lower bin,
/// weight of the upper bin), clamped at both ends.
pub fn g_interp(theta: f64) -> (usize, f64) {
    let x = theta / FRAC_PI_2 * 90.0 - 0.5;
    if x <= 0.0 {
        return (0, 0.0);
    }
    if x >= 89.0 {
        return (88, 1.0);
    }
    let a = x.floor();
    (a as usize, x - a)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forward_and_inverse_maps_agree() {
        for th in [0.01, 0.3, 0.9, 1.3] {
            for td in [0.05, 0.4, 1.0, 1.4] {
                for pd in [0.1, 1.0, 2.0, 3.0] {
                    let hd = HalfDiff { theta_h: th, theta_d: td, phi_d: pd };
                    let (wi, wo) = to_directions(hd);
                    let back = from_directions(wi, wo);
                    assert!((back.theta_h - th).abs() < 1e-9, "{hd:?} {back:?}");
                    assert!((back.theta_d - td).abs() < 1e-9, "{hd:?} {back:?}");
                    assert!((back.phi_d - pd).abs() < 1e-9, "{hd:?} {back:?}");
                    // Swapping the directions is φd + π, folded back.
                    let swapped = from_directions(wo, wi);
                    assert!((swapped.phi_d - pd).abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn rotation_about_the_normal_does_not_matter() {
        let hd = HalfDiff { theta_h: 0.5, theta_d: 0.7, phi_d: 1.1 };
        let (wi, wo) = to_directions(hd);
        let rot = |v: Vec3, a: f64| {
            let (s, c) = a.sin_cos();
            [v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]]
        };
        let back = from_directions(rot(wi, 2.0), rot(wo, 2.0));
        assert!((back.theta_h - 0.5).abs() < 1e-9 && (back.phi_d - 1.1).abs() < 1e-9);
    }

    #[test]
    fn bins_follow_the_merl_convention() {
        assert_eq!(theta_h_bin(0.0), 0);
        assert_eq!(theta_h_bin(FRAC_PI_2), 89);
        assert_eq!(theta_h_bin(cell_centre(37, 0, 0).theta_h), 37);
        assert_eq!(theta_d_bin(cell_centre(0, 61, 0).theta_d), 61);
        assert_eq!(phi_d_bin(cell_centre(0, 0, 170).phi_d), 170);
        assert_eq!(merl_index(89, 89, 179), MERL_CELLS - 1);
        assert_eq!(g_interp(g_bin_centre(10)), (10, 0.0));
    }
}
