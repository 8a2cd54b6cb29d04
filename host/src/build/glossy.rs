//! The source's home offsets from a glossy target (docs/calibration-format.md,
//! "Light directions").
//!
//! The checkerboard fixes every view and mirror plane, but not where the
//! beam leaves the fold mirror: the disk's and the tilt's home positions
//! (switch tolerances) rotate every light by the same small angle, and
//! neither a matte image nor the white target's flat light field shows it.
//! A glossy black target does: through the view near a light's mirror
//! reflection it shows the flank of that light's specular lobe, and where
//! the flank lies across the sample — the camera sees the sample over
//! ≈ 1.2° through a mirror — moves with the beam.
//!
//! The fit: every frame value y over a view's uv grid, divided by the
//! view's white response, is modelled as `s · f_s(ωi, ωo) cos θi + b`,
//! with f_s a dielectric microfacet lobe (GGX of unknown α, Smith G,
//! Schlick F with F0 = 0.04), ωi the light's direction and ωo the direction
//! from that sample point to the view's (calibrated) virtual camera; s and
//! b per (light, view) pair absorb the beam's strength, the target's
//! actual F0 and any diffuse part. The unknowns shared by all pairs — the disk
//! and tilt home offsets and α — are fitted by Levenberg–Marquardt, s and b
//! solved in closed form inside (variable projection).

use rayon::prelude::*;
use scanner_geometry::{DVec3, ScannerGeometry, world_to_sample};
use serde::{Deserialize, Serialize};

use crate::brdf::analytic::{Ndf, schlick};

use super::calibrate::{BuildProgress, ColourCalibration, ViewCalibration, light_direction};
use super::error::BuildError;
use super::linalg::solve_spd;
use super::scanread::{ScanFrames, frame_bilinear};

/// Views whose direction lies within this angle of a light's mirror
/// reflection are searched for its highlight.
pub const SEARCH_DEG: f64 = 6.0;
/// uv samples per side of a view's grid.
const GRID: usize = 40;

/// The fitted source offsets, recorded in the calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceOffsets {
    /// Added to the nominal disk home position, degrees.
    pub disk_deg: f64,
    /// Added to the nominal tilt home position, degrees.
    pub tilt_deg: f64,
    /// The glossy target's fitted GGX α.
    pub alpha: f64,
    /// (light, view) pairs whose highlight flank was fitted.
    pub pairs: usize,
    /// Lights among them.
    pub lights: usize,
    /// RMS residual of the fit, relative to each pair's peak.
    pub rms_rel: f64,
}

/// One (light, view) pair's highlight observations.
#[derive(Debug, Clone)]
pub struct Highlight {
    /// Lit mirror.
    pub light: usize,
    /// Seen mirror.
    pub view: usize,
    /// Commanded axes of the frame.
    pub axes: [f64; 3],
    /// Calibrated unit normal of the lit mirror, world.
    pub light_normal: DVec3,
    /// The camera mirrored in the view's calibrated plane, world, mm.
    pub viewer: DVec3,
    /// Sample points, world, mm.
    pub points: Vec<DVec3>,
    /// Frame value over the view's white response at each point.
    pub values: Vec<f64>,
}

/// F0 of the glossy target (a dielectric: glass, lacquer).
pub const TARGET_F0: f64 = 0.04;

/// The target's specular f · cos θi (up to scale) for unit sample-local
/// directions: GGX D, Smith G1 G1, Schlick F with [`TARGET_F0`].
fn specular(wi: DVec3, wo: DVec3, alpha: f64) -> f64 {
    let ndf = Ndf::Ggx(alpha);
    let h = (wi + wo).normalize();
    ndf.d(h.z) * ndf.g1(wi.z) * ndf.g1(wo.z) * schlick(TARGET_F0, wi.dot(h)) / (4.0 * wo.z)
}

/// `g` with the source's home positions moved by (disk, tilt) degrees.
pub fn with_offsets(g: &ScannerGeometry, disk_deg: f64, tilt_deg: f64) -> ScannerGeometry {
    let mut g = g.clone();
    g.source.disk_zero_deg += disk_deg;
    g.source.tilt_zero_deg += tilt_deg;
    g
}

/// One pair's residuals (relative to its peak) for light direction `wi`
/// (sample-local), the view's virtual camera `viewer` (world, mm) and the
/// target's α, the pair's scale and offset solved in closed form.
pub fn pair_residuals(h: &Highlight, wi: DVec3, viewer: DVec3, alpha: f64) -> Vec<f64> {
    let d: Vec<f64> = h
        .points
        .iter()
        .map(|&q| specular(wi, world_to_sample((viewer - q).normalize()), alpha))
        .collect();
    // y ≈ s·d + b by least squares.
    let n = d.len() as f64;
    let (sd, sy) = (d.iter().sum::<f64>(), h.values.iter().sum::<f64>());
    let sdd = d.iter().map(|x| x * x).sum::<f64>();
    let sdy = d.iter().zip(&h.values).map(|(x, y)| x * y).sum::<f64>();
    let det = n * sdd - sd * sd;
    let (s, b) = if det.abs() > 1e-300 {
        ((n * sdy - sd * sy) / det, (sdd * sy - sd * sdy) / det)
    } else {
        (0.0, sy / n)
    };
    let peak = h.values.iter().copied().fold(f64::MIN, f64::max).max(1e-300);
    d.iter().zip(&h.values).map(|(x, y)| (y - s * x - b) / peak).collect()
}

/// Residuals of all pairs for parameters (disk°, tilt°, ln α) with the
/// pairs' own mirror normals and virtual cameras.
fn residuals(g: &ScannerGeometry, pairs: &[Highlight], p: [f64; 3]) -> Vec<f64> {
    let gp = with_offsets(g, p[0], p[1]);
    pairs
        .iter()
        .flat_map(|h| {
            pair_residuals(h, light_direction(&gp, h.axes, h.light_normal), h.viewer, p[2].exp())
        })
        .collect()
}

fn cost(r: &[f64]) -> f64 {
    r.iter().map(|x| x * x).sum()
}

/// Fit the disk and tilt home offsets and the target's α to `pairs`.
pub fn fit_offsets(g: &ScannerGeometry, pairs: &[Highlight]) -> Result<SourceOffsets, BuildError> {
    let lights = {
        let mut l: Vec<usize> = pairs.iter().map(|h| h.light).collect();
        l.sort_unstable();
        l.dedup();
        l.len()
    };
    if pairs.len() < 3 || lights < 2 {
        return Err(BuildError::Input(format!(
            "the glossy target shows a highlight flank for {} pairs of {lights} lights; \
             need ≥ 3 pairs of ≥ 2 lights (a shorter exposure if they clip, a glossier target if they are flat)",
            pairs.len()
        )));
    }
    // α by a coarse search at the nominal offsets, then all three by LM.
    let mut p = [0.0, 0.0, 0.0];
    let mut best = f64::INFINITY;
    for k in 0..25 {
        let la = (0.002f64).ln() + k as f64 * ((0.5f64).ln() - (0.002f64).ln()) / 24.0;
        let c = cost(&residuals(g, pairs, [0.0, 0.0, la]));
        if c < best {
            best = c;
            p[2] = la;
        }
    }
    let steps = [1e-3, 1e-3, 1e-3];
    let mut lambda = 1e-3;
    let mut r = residuals(g, pairs, p);
    let mut c = cost(&r);
    for _ in 0..60 {
        let cols: Vec<Vec<f64>> = (0..3)
            .into_par_iter()
            .map(|k| {
                let (mut a, mut b) = (p, p);
                a[k] += steps[k];
                b[k] -= steps[k];
                let (ra, rb) = (residuals(g, pairs, a), residuals(g, pairs, b));
                ra.iter().zip(&rb).map(|(x, y)| (x - y) / (2.0 * steps[k])).collect()
            })
            .collect();
        let mut jtj = [0.0; 9];
        let mut jtr = [0.0; 3];
        for i in 0..r.len() {
            for a in 0..3 {
                jtr[a] += cols[a][i] * r[i];
                for b in 0..3 {
                    jtj[a * 3 + b] += cols[a][i] * cols[b][i];
                }
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut m = jtj;
            for a in 0..3 {
                m[a * 3 + a] += lambda * (jtj[a * 3 + a] + 1e-12);
            }
            let Some(d) = solve_spd(3, &m, &jtr.map(|v| -v)) else {
                lambda *= 10.0;
                continue;
            };
            let q = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
            let rq = residuals(g, pairs, q);
            let cq = cost(&rq);
            if cq < c {
                let small = d[0].abs() < 1e-6 && d[1].abs() < 1e-6;
                (p, r, c) = (q, rq, cq);
                lambda = (lambda * 0.3).max(1e-9);
                improved = !small;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    if !p.iter().all(|x| x.is_finite()) || p[0].abs() > 2.0 || p[1].abs() > 2.0 {
        return Err(BuildError::Input(format!(
            "the glossy target's highlights fit no plausible source offset (disk {:.3}°, tilt {:.3}°)",
            p[0], p[1]
        )));
    }
    Ok(SourceOffsets {
        disk_deg: p[0],
        tilt_deg: p[1],
        alpha: p[2].exp(),
        pairs: pairs.len(),
        lights,
        rms_rel: (c / r.len() as f64).sqrt(),
    })
}

/// The highlight flanks in a glossy scan: for each lit mirror, the views
/// near its mirror reflection whose uv grid shows enough contrast.
pub fn highlights(
    g: &ScannerGeometry,
    glossy: &ScanFrames,
    camera: DVec3,
    views: &[ViewCalibration],
    colour: &ColourCalibration,
    progress: &dyn BuildProgress,
) -> Result<Vec<Highlight>, BuildError> {
    let lights = glossy.lights();
    progress.stage("glossy frames", lights.len());
    let exposure_s = glossy.manifest.settings.exposure_us as f64 * 1e-6;
    // A single exposure clips at 1/t; a merged HDR frame (several
    // exposures) does not clip below the shortest one's 1/t.
    let clip = 0.95 / exposure_s.max(1e-9);
    let noise = g.sensor.read_noise_e / g.sensor.full_well_e / exposure_s.max(1e-9);
    let per_light: Vec<Vec<Highlight>> = lights
        .par_iter()
        .map(|&l| {
            let axes = glossy.axes(l)?;
            let Some(lv) = views.iter().find(|v| v.view == l) else {
                progress.step();
                return Ok(Vec::new());
            };
            let n = DVec3::from(lv.mirror_normal);
            let wi = light_direction(g, axes, n);
            let mirror = DVec3::new(-wi.x, -wi.y, wi.z);
            let near: Vec<(usize, &ViewCalibration)> = views
                .iter()
                .enumerate()
                .filter(|(_, v)| {
                    DVec3::from(v.direction).angle_between(mirror).to_degrees() < SEARCH_DEG
                })
                .collect();
            if near.is_empty() {
                progress.step();
                return Ok(Vec::new());
            }
            let windows: Vec<_> = near.iter().map(|(_, v)| v.homography.window(2.0)).collect();
            let f = glossy.read_within(l, &windows)?;
            let mut out = Vec::new();
            for (vi, v) in near {
                let viewer = v.virtual_camera(camera);
                let sampler = v.sampler();
                let (mut points, mut values) = (Vec::new(), Vec::new());
                for k in 0..GRID * GRID {
                    let uv = [
                        ((k % GRID) as f64 + 0.5) / GRID as f64,
                        ((k / GRID) as f64 + 0.5) / GRID as f64,
                    ];
                    let fp = sampler.frame_point(uv);
                    let rgb = frame_bilinear(&f, fp[0], fp[1]);
                    if rgb.iter().any(|&x| !x.is_finite() || x >= clip) {
                        continue;
                    }
                    let a = colour.view(vi, uv);
                    let a = (a[0] + a[1] + a[2]) / 3.0;
                    if a <= 0.0 {
                        continue;
                    }
                    points.push(g.sample_point(uv));
                    values.push((rgb[0] + rgb[1] + rgb[2]) / 3.0 / a);
                }
                if points.len() < GRID * GRID / 2 {
                    continue;
                }
                let (lo, hi) =
                    values.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &y| (lo.min(y), hi.max(y)));
                let mean_a = {
                    let a = colour.view(vi, [0.5, 0.5]);
                    (a[0] + a[1] + a[2]) / 3.0
                };
                // Enough signal: a flank, well above the read noise.
                if hi - lo >= 0.2 * hi && (hi - lo) * mean_a >= 50.0 * noise {
                    out.push(Highlight {
                        light: l,
                        view: v.view,
                        axes,
                        light_normal: n,
                        viewer,
                        points,
                        values,
                    });
                }
            }
            progress.step();
            Ok(out)
        })
        .collect::<Result<_, BuildError>>()?;
    Ok(per_light.into_iter().flatten().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Noise-free flanks of a known source: the fit recovers its offsets and α.
    #[test]
    fn offsets_are_recovered_from_exact_flanks() {
        let g = ScannerGeometry::default_scanner();
        let (disk, tilt, alpha) = (0.04, -0.03, 0.02);
        let truth = with_offsets(&g, disk, tilt);
        let camera = DVec3::from(g.camera.position_mm);
        let mut pairs = Vec::new();
        for l in 0..g.mirrors.len() {
            let axes = g.mirror_axes(l).unwrap().to_array();
            let n = DVec3::from(g.mirrors[l].normal);
            let wi = light_direction(&truth, axes, n);
            let mirror = DVec3::new(-wi.x, -wi.y, wi.z);
            for m in 0..g.mirrors.len() {
                if g.mirror_direction(m).unwrap().angle_between(mirror).to_degrees() > SEARCH_DEG {
                    continue;
                }
                let viewer = g.mirrors[m].reflect_point(camera);
                let points: Vec<DVec3> = (0..GRID * GRID)
                    .map(|k| {
                        g.sample_point([
                            ((k % GRID) as f64 + 0.5) / GRID as f64,
                            ((k / GRID) as f64 + 0.5) / GRID as f64,
                        ])
                    })
                    .collect();
                let values = points
                    .iter()
                    .map(|&q| {
                        let wo = world_to_sample((viewer - q).normalize());
                        3.0 * specular(wi, wo, alpha) + 0.1
                    })
                    .collect();
                pairs.push(Highlight {
                    light: l,
                    view: m,
                    axes,
                    light_normal: n,
                    viewer,
                    points,
                    values,
                });
            }
        }
        assert_eq!(pairs.len(), 16, "the first and third rings face a mirror");
        let fit = fit_offsets(&g, &pairs).unwrap();
        assert!((fit.disk_deg - disk).abs() < 1e-3, "{fit:?}");
        assert!((fit.tilt_deg - tilt).abs() < 1e-3, "{fit:?}");
        assert!((fit.alpha / alpha - 1.0).abs() < 1e-3, "{fit:?}");
        assert!(fit.rms_rel < 1e-4, "{fit:?}");
        // Too few flanks: a clear error.
        assert!(fit_offsets(&g, &pairs[..1]).is_err());
    }
}
