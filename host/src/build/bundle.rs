//! Bundle adjustment of the scanner's geometry to the located views: the
//! camera's pose and intrinsics and every mirror's plane, so that each
//! view's mirror image of the sample projects where its homography says.
//!
//! Unknowns, as deviations from the nominal geometry: camera rotation
//! (3, small-angle), position (3), focal length (relative, 1), principal
//! point (2), the lens' radial distortion k1 (1); per mirror its tilt about its two edges (2) and its shift
//! along its normal (1). Each is held to its nominal value by a Gaussian
//! prior of the scanner's assembly tolerances ([`AssemblyTolerances`]),
//! which fixes the directions the views alone leave weak (the focal
//! length against the camera's distance). Solved by Levenberg–Marquardt
//! with central-difference derivatives.

use rayon::prelude::*;
use scanner_geometry::{DVec3, ScannerGeometry};

use super::calibrate::light_direction;
use super::glossy::{Highlight, pair_residuals, with_offsets};
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
    /// The lens' radial distortion k1 about the geometry file's
    /// (`scanner_geometry::radial_distort`): loose, a stock lens' is
    /// rarely known; the views' shapes across the image measure it. (Its
    /// k2 is the geometry file's: over the views' narrow field, r⁴ and r²
    /// are too alike to tell apart — fitted together, a true (−0.05, 0)
    /// came out (−0.061, +0.139) with no better directions.) 0 holds it
    /// at the geometry file's: the views do not move it.
    pub lens_k1: f64,
    /// Mirror tilt, each edge, degrees.
    pub mirror_tilt_deg: f64,
    /// Mirror position along its normal, mm.
    pub mirror_shift_mm: f64,
    /// Disk and tilt home positions (switch repeatability), degrees.
    pub source_zero_deg: f64,
}

impl Default for AssemblyTolerances {
    fn default() -> AssemblyTolerances {
        AssemblyTolerances {
            camera_rotation_deg: 0.1,
            camera_shift_mm: 0.5,
            focal_rel: 0.003,
            principal_px: 3.0,
            lens_k1: 0.1,
            mirror_tilt_deg: 0.15,
            mirror_shift_mm: 0.3,
            source_zero_deg: 0.1,
        }
    }
}

const CAMERA: usize = 10;

/// The lens' k1 among the camera's parameters.
const K1: usize = 9;

/// One highlight pair's linearisation: its parameters, residuals and the
/// residuals' derivative along each parameter.
type GlossyBlock = (Vec<usize>, Vec<f64>, Vec<Vec<f64>>);

/// The adjusted geometry: per mirror (plane point, unit normal), the camera centre.
#[derive(Debug, Clone)]
pub struct Adjusted {
    /// Camera pinhole, mm.
    pub camera: DVec3,
    /// The lens' radial distortion (k1 fitted, k2 the geometry file's).
    pub lens_distortion: [f64; 2],
    /// Per view in the order given: (point, normal) of its mirror plane.
    pub planes: Vec<(DVec3, DVec3)>,
    /// RMS reprojection residual, px.
    pub rms_px: f64,
    /// With highlights: the source's home offsets (disk, tilt, degrees),
    /// the glossy target's α and the highlights' RMS residual (relative).
    pub source: Option<([f64; 2], f64, f64)>,
}

/// A glossy target's highlight flanks to adjust the source's home offsets
/// (and the mirror planes and camera they involve) with.
#[derive(Debug, Clone, Copy)]
pub struct Highlights<'a> {
    /// The pairs (their own normals and viewers are not used).
    pub pairs: &'a [Highlight],
    /// Their noise, relative to each pair's peak.
    pub sigma: f64,
    /// Starting point: disk and tilt offsets (degrees), α.
    pub start: ([f64; 2], f64),
}

struct Model<'a> {
    g: &'a ScannerGeometry,
    views: &'a [usize],
    sigma: Vec<f64>,
}

impl Model<'_> {
    fn n(&self) -> usize {
        self.sigma.len()
    }

    /// Index of the first source parameter (disk, tilt, ln α).
    fn source(&self) -> usize {
        CAMERA + 3 * self.views.len()
    }

    /// A highlight pair's residuals (divided by `sigma`); None if its
    /// mirrors are not among the views.
    fn glossy(&self, p: &[f64], h: &Highlight, sigma: f64) -> Option<Vec<f64>> {
        let kl = self.views.iter().position(|&v| v == h.light)?;
        let km = self.views.iter().position(|&v| v == h.view)?;
        let s = self.source();
        let gp = with_offsets(self.g, p[s], p[s + 1]);
        let wi = light_direction(&gp, h.axes, self.plane(p, kl).1);
        let (c, ..) = self.camera(p);
        let (point, n) = self.plane(p, km);
        let viewer = c - 2.0 * (c - point).dot(n) * n;
        let mut r = pair_residuals(h, wi, viewer, p[s + 2].exp());
        r.iter_mut().for_each(|x| *x /= sigma);
        Some(r)
    }

    /// The parameters a highlight pair depends on.
    fn glossy_params(&self, h: &Highlight) -> Option<Vec<usize>> {
        let kl = self.views.iter().position(|&v| v == h.light)?;
        let km = self.views.iter().position(|&v| v == h.view)?;
        let s = self.source();
        Some(
            (3..6)
                .chain([CAMERA + 3 * kl, CAMERA + 3 * kl + 1])
                .chain(CAMERA + 3 * km..CAMERA + 3 * km + 3)
                .chain(s..s + 3)
                .collect(),
        )
    }

    fn plane(&self, p: &[f64], k: usize) -> (DVec3, DVec3) {
        let m = &self.g.mirrors[self.views[k]];
        let (n0, u, v) = m.frame();
        let q = &p[CAMERA + 3 * k..CAMERA + 3 * k + 3];
        let n = (n0 + u * q[0] + v * q[1]).normalize();
        (m.center() + n0 * q[2], n)
    }

    fn camera(&self, p: &[f64]) -> (DVec3, [DVec3; 3], f64, [f64; 2], [f64; 2]) {
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
            [cam.distortion[0] + p[K1], cam.distortion[1]],
        )
    }

    fn project(&self, p: &[f64], k: usize, uv: [f64; 2]) -> [f64; 2] {
        let (point, n) = self.plane(p, k);
        let s = self.g.sample_point(uv);
        let s2 = s - 2.0 * (s - point).dot(n) * n;
        let (c, [r, d, f], fl, pp, k) = self.camera(p);
        let v = s2 - c;
        let z = v.dot(f);
        let n = scanner_geometry::radial_distort(k, [v.dot(r) / z, v.dot(d) / z]);
        [pp[0] + fl * n[0], pp[1] + fl * n[1]]
    }
}

/// Adjust the nominal geometry `g` to the located views (`views[k]` with
/// homography `homographies[k]`, corner precision `sigma_px`) and, if
/// given, a glossy target's highlights (which adds the source's home
/// offsets and the target's α to the unknowns).
pub fn adjust(
    g: &ScannerGeometry,
    views: &[usize],
    homographies: &[Homography],
    sigma_px: f64,
    tol: &AssemblyTolerances,
    highlights: Option<Highlights<'_>>,
) -> Adjusted {
    let scale = g.camera.focal_px / 5600.0;
    let held_k1 = tol.lens_k1 <= 0.0 || tol.lens_k1.is_nan();
    let mut sigma: Vec<f64> = vec![
        tol.camera_rotation_deg.to_radians(),
        tol.camera_rotation_deg.to_radians(),
        tol.camera_rotation_deg.to_radians(),
        tol.camera_shift_mm,
        tol.camera_shift_mm,
        tol.camera_shift_mm,
        tol.focal_rel,
        tol.principal_px * scale,
        tol.principal_px * scale,
        // Held, k1 keeps its prior's row alone and stays the file's.
        if held_k1 { 1.0 } else { tol.lens_k1 },
    ];
    for _ in views {
        sigma.extend([
            tol.mirror_tilt_deg.to_radians(),
            tol.mirror_tilt_deg.to_radians(),
            tol.mirror_shift_mm,
        ]);
    }
    if highlights.is_some() {
        // ln α is held by a prior too weak to matter.
        sigma.extend([tol.source_zero_deg, tol.source_zero_deg, 10.0]);
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
            let params: Vec<usize> = (0..CAMERA)
                .filter(|&i| !(held_k1 && i == K1))
                .chain(CAMERA + 3 * k..CAMERA + 3 * k + 3)
                .collect();
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
        if let Some(hl) = &highlights {
            // Each pair's residuals and derivatives, pairs in parallel.
            let blocks: Vec<GlossyBlock> = hl
                .pairs
                .par_iter()
                .filter_map(|h| {
                    let base = model.glossy(p, h, hl.sigma)?;
                    let params = model.glossy_params(h)?;
                    let cols = params
                        .iter()
                        .map(|&i| {
                            let step = 1e-3 * model.sigma[i];
                            let mut q = p.to_vec();
                            q[i] += step;
                            let a = model.glossy(&q, h, hl.sigma).expect("same mirrors");
                            q[i] -= 2.0 * step;
                            let b = model.glossy(&q, h, hl.sigma).expect("same mirrors");
                            a.iter().zip(&b).map(|(x, y)| (x - y) / (2.0 * step)).collect()
                        })
                        .collect();
                    Some((params, base, cols))
                })
                .collect();
            let mut j = Vec::new();
            for (params, base, cols) in blocks {
                for (r, &res) in base.iter().enumerate() {
                    j.clear();
                    j.extend(params.iter().zip(&cols).map(|(&i, c)| (i, c[r])));
                    eq.add_sparse(&j, res);
                }
            }
        }
        for (i, (&pi, &si)) in p.iter().zip(&model.sigma).enumerate() {
            eq.add_sparse(&[(i, 1.0 / si)], pi / si);
        }
        eq
    };
    let mut p = vec![0.0; n];
    if let Some(hl) = &highlights {
        let s = model.source();
        (p[s], p[s + 1], p[s + 2]) = (hl.start.0[0], hl.start.0[1], hl.start.1.ln());
    }
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
    let (camera, _, _, _, lens_distortion) = model.camera(&p);
    let source = highlights.map(|hl| {
        let r: Vec<f64> =
            hl.pairs.iter().filter_map(|h| model.glossy(&p, h, 1.0)).flatten().collect();
        let rms = (r.iter().map(|x| x * x).sum::<f64>() / r.len().max(1) as f64).sqrt();
        let s = model.source();
        ([p[s], p[s + 1]], p[s + 2].exp(), rms)
    });
    Adjusted {
        camera,
        lens_distortion,
        planes: (0..views.len()).map(|k| model.plane(&p, k)).collect(),
        rms_px: (sq / count as f64).sqrt(),
        source,
    }
}
