//! Bundle adjustment of the scanner's geometry to the located views: the
//! camera's pose and intrinsics and every mirror's plane, so that each
//! view's mirror image of the sample projects where its homography says.
//!
//! Unknowns, as deviations from the nominal geometry: camera rotation
//! (3, small-angle), position (3), focal length (relative, 1), principal
//! point (2); per mirror its tilt about its two edges (2) and its shift
//! along its normal (1). Each is held to its nominal value by a Gaussian
//! prior of the scanner's assembly tolerances ([`AssemblyTolerances`]),
//! which fixes the directions the views alone leave weak (the focal
//! length against the camera's distance). Solved by Levenberg–Marquardt
//! with central-difference derivatives.

use scanner_geometry::{DVec3, ScannerGeometry};

use super::linalg::{Homography, Normal};

/// Assembly tolerances (1 σ) the calibration assumes: a hand-assembled
/// mirror array and stock optics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AssemblyTolerances {
    /// Camera orientation, each axis, degrees.
    pub camera_rotation_deg: f64,
    /// Camera position, each axis, mm.
    pub camera_shift_mm: f64,
    /// Focal length, relative.
    pub focal_rel: f64,
    /// Principal point, px of a 4096² sensor.
    pub principal_px: f64,
    /// Mirror tilt, each edge, degrees.
    pub mirror_tilt_deg: f64,
    /// Mirror position along its normal, mm.
    pub mirror_shift_mm: f64,
}

impl Default for AssemblyTolerances {
    fn default() -> AssemblyTolerances {
        AssemblyTolerances {
            camera_rotation_deg: 0.1,
            camera_shift_mm: 0.5,
            focal_rel: 0.003,
            principal_px: 3.0,
            mirror_tilt_deg: 0.15,
            mirror_shift_mm: 0.3,
        }
    }
}

const CAMERA: usize = 9;

/// The adjusted geometry: per mirror (plane point, unit normal), the camera centre.
#[derive(Debug, Clone)]
pub struct Adjusted {
    /// Camera pinhole, mm.
    pub camera: DVec3,
    /// Per view in the order given: (point, normal) of its mirror plane.
    pub planes: Vec<(DVec3, DVec3)>,
    /// RMS reprojection residual, px.
    pub rms_px: f64,
}

struct Model<'a> {
    g: &'a ScannerGeometry,
    views: &'a [usize],
    sigma: Vec<f64>,
}

impl Model<'_> {
    fn n(&self) -> usize {
        CAMERA + 3 * self.views.len()
    }

    fn plane(&self, p: &[f64], k: usize) -> (DVec3, DVec3) {
        let m = &self.g.mirrors[self.views[k]];
        let (n0, u, v) = m.frame();
        let q = &p[CAMERA + 3 * k..CAMERA + 3 * k + 3];
        let n = (n0 + u * q[0] + v * q[1]).normalize();
        (m.center() + n0 * q[2], n)
    }

    fn camera(&self, p: &[f64]) -> (DVec3, [DVec3; 3], f64, [f64; 2]) {
        let cam = &self.g.camera;
        let (r, d, f) = cam.basis();
        let w = DVec3::new(p[0], p[1], p[2]);
        let rot = |v: DVec3| {
            let a = w.length();
            if a < 1e-15 {
                return v;
            }
            let k = w / a;
            v * a.cos() + k.cross(v) * a.sin() + k * k.dot(v) * (1.0 - a.cos())
        };
        let c = DVec3::from(cam.position_mm) + DVec3::new(p[3], p[4], p[5]);
        (
            c,
            [rot(r), rot(d), rot(f)],
            cam.focal_px * (1.0 + p[6]),
            [cam.principal_px[0] + p[7], cam.principal_px[1] + p[8]],
        )
    }

    fn project(&self, p: &[f64], k: usize, uv: [f64; 2]) -> [f64; 2] {
        let (point, n) = self.plane(p, k);
        let s = self.g.sample_point(uv);
        let s2 = s - 2.0 * (s - point).dot(n) * n;
        let (c, [r, d, f], fl, pp) = self.camera(p);
        let v = s2 - c;
        let z = v.dot(f);
        [pp[0] + fl * v.dot(r) / z, pp[1] + fl * v.dot(d) / z]
    }
}

/// Adjust the nominal geometry `g` to the located views (`views[k]` with
/// homography `homographies[k]`, corner precision `sigma_px`).
pub fn adjust(
    g: &ScannerGeometry,
    views: &[usize],
    homographies: &[Homography],
    sigma_px: f64,
    tol: &AssemblyTolerances,
) -> Adjusted {
    let scale = g.camera.focal_px / 5600.0;
    let mut sigma = vec![
        tol.camera_rotation_deg.to_radians(),
        tol.camera_rotation_deg.to_radians(),
        tol.camera_rotation_deg.to_radians(),
        tol.camera_shift_mm,
        tol.camera_shift_mm,
        tol.camera_shift_mm,
        tol.focal_rel,
        tol.principal_px * scale,
        tol.principal_px * scale,
    ];
    for _ in views {
        sigma.extend([
            tol.mirror_tilt_deg.to_radians(),
            tol.mirror_tilt_deg.to_radians(),
            tol.mirror_shift_mm,
        ]);
    }
    let model = Model { g, views, sigma };
    let n = model.n();
    let grid: Vec<[f64; 2]> =
        (0..5).flat_map(|j| (0..5).map(move |i| [i as f64 / 4.0, j as f64 / 4.0])).collect();
    let targets: Vec<Vec<[f64; 2]>> =
        homographies.iter().map(|h| grid.iter().map(|&uv| h.apply(uv)).collect()).collect();
    let build = |p: &[f64]| -> Normal {
        let mut eq = Normal::new(n);
        for (k, t) in targets.iter().enumerate() {
            let params: Vec<usize> =
                (0..CAMERA).chain(CAMERA + 3 * k..CAMERA + 3 * k + 3).collect();
            for (uv, target) in grid.iter().zip(t) {
                let base = model.project(p, k, *uv);
                let mut jx = Vec::with_capacity(params.len());
                let mut jy = Vec::with_capacity(params.len());
                for &i in &params {
                    let h = 1e-3 * model.sigma[i];
                    let mut q = p.to_vec();
                    q[i] += h;
                    let a = model.project(&q, k, *uv);
                    q[i] -= 2.0 * h;
                    let b = model.project(&q, k, *uv);
                    jx.push((i, (a[0] - b[0]) / (2.0 * h) / sigma_px));
                    jy.push((i, (a[1] - b[1]) / (2.0 * h) / sigma_px));
                }
                eq.add_sparse(&jx, (base[0] - target[0]) / sigma_px);
                eq.add_sparse(&jy, (base[1] - target[1]) / sigma_px);
            }
        }
        for (i, (&pi, &si)) in p.iter().zip(&model.sigma).enumerate() {
            eq.add_sparse(&[(i, 1.0 / si)], pi / si);
        }
        eq
    };
    let mut p = vec![0.0; n];
    let mut lambda = 1e-3;
    let mut eq = build(&p);
    for _ in 0..30 {
        let Some(step) = eq.step(lambda) else { break };
        let q: Vec<f64> = p.iter().zip(&step).map(|(a, b)| a + b).collect();
        let next = build(&q);
        if next.cost < eq.cost {
            let gain = eq.cost - next.cost;
            p = q;
            eq = next;
            lambda = (lambda * 0.3).max(1e-9);
            if gain < 1e-9 * eq.cost.max(1.0) {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e6 {
                break;
            }
        }
    }
    let mut sq = 0.0;
    let mut count = 0;
    for (k, t) in targets.iter().enumerate() {
        for (uv, target) in grid.iter().zip(t) {
            let x = model.project(&p, k, *uv);
            sq += (x[0] - target[0]).powi(2) + (x[1] - target[1]).powi(2);
            count += 1;
        }
    }
    let (camera, _, _, _) = model.camera(&p);
    Adjusted {
        camera,
        planes: (0..views.len()).map(|k| model.plane(&p, k)).collect(),
        rms_px: (sq / count as f64).sqrt(),
    }
}
