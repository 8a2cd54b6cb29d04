//! The sample's face above the holder's plane, measured on the sample's own
//! frames.
//!
//! The calibration's homographies map the holder's plane, where the
//! targets lay. A sample thicker than the targets, or one that does not lie
//! flat against the holder, has its face `h` mm off that plane, and each
//! view then sees it shifted by the parallax of its virtual camera: by
//! h · tan θ along the view's azimuth, 2.1 h at the outer ring's 65°. The
//! views no longer agree on where a texel is (leather at h = 0.3 mm, 1024²:
//! 31.4 dB at novel pairs against 36.8 dB in the plane; docs/benchmarks.md,
//! session 78).
//!
//! Every view sees the same texture, so the height is the one at which the
//! views agree. Per view the frames of up to [`LIGHTS`] lights are summed
//! (the texture under an average light), read on a grid of the sample's
//! inner 80 % through the view's homography at height h
//! ([`super::calibrate::ViewCalibration::homography_at_height`]), a
//! quadratic trend divided out (beam, vignetting, the view's shading); the
//! cost is the squared difference of the views' images from their mean.
//! It is scanned over ±[`MAX_HEIGHT_MM`] in steps of ⅓ px of the outermost
//! view's parallax, the best step refined by golden section. Its
//! uncertainty is the delete-a-group jackknife over eight groups of views.
//!
//! A textureless sample leaves the cost flat: its height comes out with a
//! large uncertainty and is not applied ([`HeightFit::applied_mm`]).

use rayon::prelude::*;

use super::calibrate::{Calibration, ViewCalibration};
use super::error::BuildError;
use super::linalg::Homography;
use super::scanread::ScanFrames;
use crate::camera::Frame;
use crate::exrio::PixelRect;
use scanner_geometry::ScannerGeometry;

/// The heights searched, ± mm.
pub const MAX_HEIGHT_MM: f64 = 3.0;

/// At most this many lights' frames are read (evenly spread over the
/// scan's).
pub const LIGHTS: usize = 8;

/// A height whose largest parallax between views is below this is left at
/// 0, frame px: the views already agree to within it.
pub const NEGLIGIBLE_PX: f64 = 0.05;

/// Views per jackknife group count: views `i` with `i % GROUPS == g`.
const GROUPS: usize = 8;

/// The measured height of the sample's face.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeightFit {
    /// Above the holder's plane, towards the mirrors, mm.
    pub height_mm: f64,
    /// Its standard uncertainty (jackknife over groups of views), mm.
    pub sigma_mm: f64,
    /// The largest shift in the frame between the outline's corners at
    /// height 0 and at 1 mm, over the views, px per mm.
    pub parallax_px_per_mm: f64,
    /// The lights whose frames were summed.
    pub lights: usize,
}

impl HeightFit {
    /// The height the region images use: the measured one where it is
    /// both significant (beyond 4 σ) and large enough to matter (the
    /// views' parallax above [`NEGLIGIBLE_PX`]); else 0, the holder's plane.
    pub fn applied_mm(&self) -> f64 {
        let h = self.height_mm;
        if h.abs() > 4.0 * self.sigma_mm && h.abs() * self.parallax_px_per_mm > NEGLIGIBLE_PX {
            h
        } else {
            0.0
        }
    }
}

/// A view's summed frames over the window its sample can fall in.
struct ViewCrop {
    rect: PixelRect,
    /// Luminance (sum of the channels), row-major over `rect`.
    lum: Vec<f64>,
}

impl ViewCrop {
    fn bilinear(&self, p: [f64; 2]) -> f64 {
        let w = self.rect[2] - self.rect[0];
        let h = self.rect[3] - self.rect[1];
        let fx = p[0] - 0.5 - self.rect[0] as f64;
        let fy = p[1] - 0.5 - self.rect[1] as f64;
        let (x0, y0) = (fx.floor(), fy.floor());
        let (tx, ty) = (fx - x0, fy - y0);
        let at = |x: f64, y: f64| {
            let x = (x.max(0.0) as usize).min(w - 1);
            let y = (y.max(0.0) as usize).min(h - 1);
            self.lum[y * w + x]
        };
        let top = at(x0, y0) * (1.0 - tx) + at(x0 + 1.0, y0) * tx;
        let bottom = at(x0, y0 + 1.0) * (1.0 - tx) + at(x0 + 1.0, y0 + 1.0) * tx;
        top * (1.0 - ty) + bottom * ty
    }
}

/// The views' images at one height, detrended, and the cost over the views
/// in `keep`.
struct Views<'a> {
    g: &'a ScannerGeometry,
    views: &'a [ViewCalibration],
    crops: Vec<ViewCrop>,
    grid: Vec<[f64; 2]>,
}

impl Views<'_> {
    /// View `vi`'s image over the grid at height `h`, its quadratic trend
    /// divided out; `None` where the view holds no light.
    fn image(&self, vi: usize, h: f64) -> Option<Vec<f64>> {
        let hom: Homography = self.views[vi].homography_at_height(self.g, h);
        let values: Vec<f64> =
            self.grid.iter().map(|&uv| self.crops[vi].bilinear(hom.apply(uv))).collect();
        let trend = quadratic_trend(&self.grid, &values)?;
        Some(values.iter().zip(&trend).map(|(v, t)| v / t - 1.0).collect())
    }

    /// Σ over the views in `keep` and the grid of the squared difference
    /// from their mean, per value.
    fn cost(&self, h: f64, keep: &(dyn Fn(usize) -> bool + Sync)) -> f64 {
        let images: Vec<Vec<f64>> = (0..self.views.len())
            .into_par_iter()
            .filter(|&vi| keep(vi))
            .filter_map(|vi| self.image(vi, h))
            .collect();
        if images.len() < 2 {
            return f64::INFINITY;
        }
        let n = images.len() as f64;
        let mut sum = 0.0;
        for i in 0..self.grid.len() {
            let mean = images.iter().map(|im| im[i]).sum::<f64>() / n;
            sum += images.iter().map(|im| (im[i] - mean).powi(2)).sum::<f64>();
        }
        sum / (n * self.grid.len() as f64)
    }

    /// The height of least cost in [lo, hi] by golden section to `tol`.
    fn golden(&self, lo: f64, hi: f64, tol: f64, keep: &(dyn Fn(usize) -> bool + Sync)) -> f64 {
        let r = (5f64.sqrt() - 1.0) / 2.0;
        let (mut a, mut b) = (lo, hi);
        let mut c = b - r * (b - a);
        let mut d = a + r * (b - a);
        let (mut fc, mut fd) = (self.cost(c, keep), self.cost(d, keep));
        while b - a > tol {
            if fc < fd {
                b = d;
                (d, fd) = (c, fc);
                c = b - r * (b - a);
                fc = self.cost(c, keep);
            } else {
                a = c;
                (c, fc) = (d, fd);
                d = a + r * (b - a);
                fd = self.cost(d, keep);
            }
        }
        (a + b) / 2.0
    }
}

/// The least-squares quadratic in uv through `values` at `points`,
/// evaluated there; `None` if the values hold no light.
fn quadratic_trend(points: &[[f64; 2]], values: &[f64]) -> Option<Vec<f64>> {
    let basis = |p: [f64; 2]| {
        let (u, v) = (p[0] - 0.5, p[1] - 0.5);
        [1.0, u, v, u * u, u * v, v * v]
    };
    let mut a = [0.0; 36];
    let mut b = [0.0; 6];
    for (&p, &y) in points.iter().zip(values) {
        let f = basis(p);
        for i in 0..6 {
            b[i] += f[i] * y;
            for j in 0..6 {
                a[i * 6 + j] += f[i] * f[j];
            }
        }
    }
    let c = super::linalg::solve_spd(6, &a, &b)?;
    let trend: Vec<f64> =
        points.iter().map(|&p| basis(p).iter().zip(&c).map(|(f, c)| f * c).sum()).collect();
    let floor = 1e-3 * trend.iter().fold(0.0f64, |m, &t| m.max(t));
    (floor > 0.0 && trend.iter().all(|&t| t > floor)).then_some(trend)
}

/// The window of the frame view `v`'s sample can fall in at any height
/// within ±[`MAX_HEIGHT_MM`].
fn search_window(g: &ScannerGeometry, v: &ViewCalibration) -> PixelRect {
    let a = v.homography_at_height(g, -MAX_HEIGHT_MM).window(3.0);
    let b = v.homography_at_height(g, MAX_HEIGHT_MM).window(3.0);
    [a[0].min(b[0]), a[1].min(b[1]), a[2].max(b[2]), a[3].max(b[3])]
}

/// The largest shift of an outline corner per mm of height over the views,
/// px per mm.
fn parallax(g: &ScannerGeometry, views: &[ViewCalibration]) -> f64 {
    views.iter().map(|v| view_parallax(g, v)).fold(0.0, f64::max)
}

/// The largest shift of view `v`'s outline corners per mm of height, px
/// per mm.
pub fn view_parallax(g: &ScannerGeometry, v: &ViewCalibration) -> f64 {
    let (a, b) = (v.homography.corners(), v.homography_at_height(g, 1.0).corners());
    (0..4).map(|k| (a[k][0] - b[k][0]).hypot(a[k][1] - b[k][1])).fold(0.0, f64::max)
}

/// Where the region images take the sample's face to lie
/// ([`super::regions::RegionOptions::height`]).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum SampleHeight {
    /// Measured on the sample's own frames ([`measure_height`]) and used
    /// where [`HeightFit::applied_mm`] says.
    #[default]
    Measure,
    /// This far above the holder's plane, mm (0: in it, as the targets).
    Given(f64),
}

/// Measure the sample's height above the holder's plane on `scan`'s frames
/// (module docs). `progress` steps once per frame read.
pub fn measure_height(
    g: &ScannerGeometry,
    cal: &Calibration,
    scan: &ScanFrames,
    progress: &dyn super::calibrate::BuildProgress,
) -> Result<HeightFit, BuildError> {
    let all = scan.lights();
    let n = all.len().min(LIGHTS);
    let lights: Vec<usize> = (0..n).map(|i| all[i * all.len() / n.max(1)]).collect();
    let rects: Vec<PixelRect> = cal.views.iter().map(|v| search_window(g, v)).collect();
    let dims = [g.camera.width as usize, g.camera.height as usize];
    let rects: Vec<PixelRect> = rects
        .into_iter()
        .map(|r| [r[0], r[1], r[2].min(dims[0]).max(r[0] + 2), r[3].min(dims[1]).max(r[1] + 2)])
        .collect();
    progress.stage("sample height", lights.len());
    let sums = lights
        .par_iter()
        .map(|&l| -> Result<Vec<Vec<f64>>, BuildError> {
            let f = scan.read_within(l, &rects)?;
            progress.step();
            Ok(rects.iter().map(|r| crop(&f, *r)).collect())
        })
        .try_reduce_with(|mut a, b| {
            for (x, y) in a.iter_mut().zip(&b) {
                for (p, q) in x.iter_mut().zip(y) {
                    *p += q;
                }
            }
            Ok(a)
        })
        .transpose()?
        .ok_or_else(|| BuildError::Input(format!("{}: no frames", scan.dir.display())))?;
    let crops: Vec<ViewCrop> =
        rects.iter().zip(sums).map(|(&rect, lum)| ViewCrop { rect, lum }).collect();
    // A grid at about the frontal views' pixel pitch over the inner 80 %.
    let side = (super::regions::default_size(cal) as f64 * 0.8).round().clamp(16.0, 104.0) as usize;
    let grid: Vec<[f64; 2]> = (0..side * side)
        .map(|i| {
            let (x, y) = ((i % side) as f64 + 0.5, (i / side) as f64 + 0.5);
            [0.1 + 0.8 * x / side as f64, 0.1 + 0.8 * y / side as f64]
        })
        .collect();
    let views = Views { g, views: &cal.views, crops, grid };
    let gain = parallax(g, &cal.views);
    let step = (1.0 / 3.0) / gain.max(1e-9);
    let steps = (MAX_HEIGHT_MM / step).ceil() as i64;
    let all_views = |_: usize| true;
    let (mut best, mut best_cost) = (0.0, f64::INFINITY);
    for k in -steps..=steps {
        let h = k as f64 * step;
        let c = views.cost(h, &all_views);
        if c < best_cost {
            (best, best_cost) = (h, c);
        }
    }
    let tol = step * 1e-3;
    let height = views.golden(best - step, best + step, tol, &all_views);
    let groups: Vec<f64> = (0..GROUPS)
        .map(|grp| views.golden(height - step, height + step, tol, &move |vi| vi % GROUPS != grp))
        .collect();
    let mean = groups.iter().sum::<f64>() / GROUPS as f64;
    let var = (GROUPS - 1) as f64 / GROUPS as f64
        * groups.iter().map(|h| (h - mean).powi(2)).sum::<f64>();
    Ok(HeightFit {
        height_mm: height,
        sigma_mm: var.sqrt(),
        parallax_px_per_mm: gain,
        lights: lights.len(),
    })
}

/// The luminance of frame `f` over `rect` (row-major).
fn crop(f: &Frame, rect: PixelRect) -> Vec<f64> {
    let w = f.width as usize;
    let mut out = Vec::with_capacity((rect[2] - rect[0]) * (rect[3] - rect[1]));
    for y in rect[1]..rect[3] {
        for x in rect[0]..rect[2] {
            let (x, y) = (x.min(w - 1), y.min(f.height as usize - 1));
            let i = 3 * (y * w + x);
            out.push(f.rgb[i] as f64 + f.rgb[i + 1] as f64 + f.rgb[i + 2] as f64);
        }
    }
    out
}
