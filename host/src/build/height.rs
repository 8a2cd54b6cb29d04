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
//! views agree. Per view the frames of up to [`LIGHTS`] lights are read
//! (white-balanced by the colour calibration's view response, each light
//! in units of its irradiance at the sample's centre times cos θi) and per
//! pixel the median over the lights taken. What is compared is the
//! **chroma** (red − green, blue − green): a dielectric's highlight has the
//! light's colour and leaves it alone, while the luminance carries the
//! highlights on the sample's bumps, which lean towards each view as a
//! height would (leather, 2048², six near-normal lights: luminance put the
//! flush sample at −0.056 mm, 20 σ off; chroma at +0.006 ± 0.002 mm). Each
//! view's chroma is read on a grid over the sample's inner 80 % through
//! its homography at height h
//! ([`super::calibrate::ViewCalibration::homography_at_height`]), a
//! quadratic trend subtracted (beam, vignetting, the view's shading) and
//! scaled to unit variance; the cost is the mean squared difference of the
//! views' images from their mean (≈ 1 − their mean correlation). It is
//! scanned over ±[`MAX_HEIGHT_MM`] in steps of ⅓ px of the outermost
//! view's parallax, the best step refined by golden section. Its
//! uncertainty is the delete-a-group jackknife over eight groups of views.
//!
//! A sample without colour texture (a grey or uniform one) leaves the cost
//! flat: its [`HeightFit::agreement`] is low and its chroma measures
//! nothing (nor does a height at the end of the range). Every sample's
//! face is also measured on its outline against the holder
//! ([`super::outline`]), and the two joined ([`FaceCue`]): each parameter
//! from the cue that measured it, their inverse-variance mean where both
//! did and agree within 4 σ, neither where they disagree — unless a thin
//! sample's sides explain the disagreement ([`thin_sides`]: the chroma's
//! then). Without either the images are read in the holder's plane
//! ([`HeightFit::applied_mm`]).

use rayon::prelude::*;

use super::calibrate::{Calibration, ViewCalibration};
use super::error::BuildError;
use super::linalg::Homography;
use super::outline::OutlineFit;
use super::scanread::ScanFrames;
use crate::camera::Frame;
use crate::exrio::PixelRect;
use crate::stats::median;
use scanner_geometry::{SampleFace, ScannerGeometry};

/// The heights searched, ± mm (also the range of a given
/// `--sample-height`): a board several mm thick standing on the holder
/// whose targets were thin cards (session 82: a leather 5 mm proud and
/// 5 mm thick, its sides showing so its outline not read, was read in
/// the holder's plane at ±3 mm, 14.8 dB).
pub const MAX_HEIGHT_MM: f64 = 10.0;

/// At most this many lights' frames are read (evenly spread over the
/// scan's).
pub const LIGHTS: usize = 8;

/// A height whose largest parallax between views is below this is left at
/// 0, frame px: the views already agree to within it (a registration
/// error of a fifth of a pixel costs little), and a measurement this small
/// is within reach of a bias (a metal's coloured highlights lean its
/// chroma too: crumpled gold foil, flush, measured −0.011 ± 0.004 mm at
/// 4096², 0.05 px).
pub const NEGLIGIBLE_PX: f64 = 0.2;

/// The least [`HeightFit::agreement`] of a measurement: below it the views
/// agree at no height much better than at any other.
pub const MIN_AGREEMENT: f64 = 0.25;

/// Views per jackknife group count: views `i` with `i % GROUPS == g`.
const GROUPS: usize = 8;

/// The face's tilt is measured on this many patches a side over the
/// sample's inner 80 % (each patch's height, then a plane through them).
pub const PATCHES: usize = 3;

/// The largest tilt measured, degrees: each patch's height is searched
/// within the height its centre has at this tilt about the sample's.
pub const MAX_TILT_DEG: f64 = 5.0;

/// A tilt is applied when it moves the outline's corners in some view by
/// more than [`NEGLIGIBLE_PX`] or turns the face by more than this,
/// degrees (the views' calibrated directions hold to 0.05°).
pub const NEGLIGIBLE_TILT_DEG: f64 = 0.1;

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
    /// How much better the views agree at the height than over the range
    /// searched: 1 − cost there / median cost (the cost being 1 − the views'
    /// mean correlation with their consensus, about).
    pub agreement: f64,
    /// The lights whose frames were read.
    pub lights: usize,
    /// The face's rise along u and along v, mm per mm (a plane through the
    /// patches' heights; 0 when fewer than four were measured).
    pub slope: [f64; 2],
    /// Their standard uncertainties (infinite: no tilt measured).
    pub slope_sigma: [f64; 2],
    /// The patches whose heights were measured (of [`PATCHES`]²).
    pub patches: usize,
    /// The patches' root-mean-square distance from the plane, mm: a face
    /// curved, or one whose texture misleads a patch (0 below four
    /// patches).
    pub flatness_mm: f64,
    /// The largest shift the tilt makes at the outline's corners in any
    /// view, px.
    pub tilt_px: f64,
    /// What the face was measured on.
    pub cue: FaceCue,
    /// The outline's fit, when the face was measured on it (not where the
    /// sample's sides were seen beyond its edges), or when its
    /// disagreement with the chroma told thin sides ([`HeightFit::thin_sides`]).
    pub outline: Option<OutlineFit>,
    /// What lies beyond the edges facing the views against beyond the
    /// others, at the applied face ([`super::outline::beyond_edges`]).
    pub beyond: Option<super::outline::Beyond>,
    /// The chroma and the outline disagreed as a thin sample's sides make
    /// them disagree ([`thin_sides`]): the face is the chroma's, and the
    /// sides are read as shown.
    pub thin_sides: bool,
}

/// What a [`HeightFit`] was measured on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaceCue {
    /// The views' chroma, where they agree (colour texture).
    Chroma,
    /// The sample's outline against the holder ([`super::outline`]): a
    /// sample whose colour texture does not say.
    Outline,
    /// Both, joined.
    Both,
    /// Both measured the height, and they disagree: not measured.
    Conflict,
    /// Neither.
    None,
}

impl FaceCue {
    /// Its name in `regions.json`.
    pub fn name(self) -> &'static str {
        match self {
            FaceCue::Chroma => "chroma",
            FaceCue::Outline => "outline",
            FaceCue::Both => "chroma and outline",
            FaceCue::Conflict => "disagreeing",
            FaceCue::None => "none",
        }
    }
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

    /// Whether the sample's sides were seen beyond the edges facing the
    /// views ([`super::outline::Beyond::seen`]), or told by the outline's
    /// disagreement with the chroma ([`HeightFit::thin_sides`]).
    pub fn sides_seen(&self) -> bool {
        self.thin_sides || self.beyond.is_some_and(|b| b.seen())
    }

    /// The face the region images use: tilted where the tilt is both
    /// significant (beyond 4 σ) and large enough to matter (its parallax
    /// above [`NEGLIGIBLE_PX`] or its angle above [`NEGLIGIBLE_TILT_DEG`]),
    /// else level at [`Self::applied_mm`].
    pub fn applied_face(&self) -> SampleFace {
        let [a, b] = self.slope;
        let [sa, sb] = self.slope_sigma;
        let chi2 = (a / sa).powi(2) + (b / sb).powi(2);
        let tilted = SampleFace { height_mm: self.height_mm, slope: self.slope };
        let matters = self.tilt_px > NEGLIGIBLE_PX || tilted.tilt_deg() > NEGLIGIBLE_TILT_DEG;
        if chi2 > 16.0 && matters && self.sigma_mm.is_finite() {
            tilted
        } else {
            SampleFace::at_height(self.applied_mm())
        }
    }

    /// The uncertainty of the applied face's height at the outline's
    /// corners, mm (where its error moves the edges most): the height's
    /// and the slopes' in quadrature.
    pub fn corner_sigma_mm(&self, size_mm: f64) -> f64 {
        let face = self.applied_face();
        if face.is_flush() {
            return 0.0;
        }
        if face.is_level() {
            return self.sigma_mm;
        }
        // h + a x + b y at a corner (|x| = |y| = size/2), the fits'
        // height at the centre and slopes independent.
        let half = size_mm / 2.0;
        (self.sigma_mm.powi(2)
            + (self.slope_sigma[0] * half).powi(2)
            + (self.slope_sigma[1] * half).powi(2))
        .sqrt()
    }
}

/// A view's frames over the window its sample can fall in, per pixel the
/// median over the lights.
struct ViewCrop {
    rect: PixelRect,
    /// [`PLANES`] planes, each row-major over `rect`.
    planes: [Vec<f32>; PLANES],
    /// Whether any light reached the view.
    lit: bool,
}

/// A crop's planes: luminance (the white-balanced channels' sum), then the
/// chroma red − green and blue − green, which a dielectric's white
/// highlight leaves alone.
const PLANES: usize = 3;

impl ViewCrop {
    fn bilinear(&self, plane: usize, p: [f64; 2]) -> f64 {
        let w = self.rect[2] - self.rect[0];
        let p = [p[0] - self.rect[0] as f64, p[1] - self.rect[1] as f64];
        super::plane::bilinear(&self.planes[plane], w, p)
    }
}

/// The views' images at one height, detrended, and the cost over the views
/// in `keep`.
struct Views<'a> {
    g: &'a ScannerGeometry,
    views: &'a [ViewCalibration],
    crops: &'a [ViewCrop],
    grid: Vec<[f64; 2]>,
}

impl Views<'_> {
    /// View `vi`'s image over the grid at height `h`, its quadratic trend
    /// divided out; `None` where the view holds no light.
    fn image(&self, vi: usize, h: f64) -> Option<Vec<f64>> {
        let hom: Homography = self.views[vi].homography_at_height(self.g, h);
        let points: Vec<[f64; 2]> = self.grid.iter().map(|&uv| hom.apply(uv)).collect();
        let read = |plane: usize| -> Vec<f64> {
            points.iter().map(|&p| self.crops[vi].bilinear(plane, p)).collect()
        };
        // A view the beams leave dark holds nothing to compare.
        if !self.crops[vi].lit {
            return None;
        }
        let mut out = Vec::with_capacity(2 * self.grid.len());
        for plane in 1..PLANES {
            let values = read(plane);
            let trend = quadratic_trend(&self.grid, &values)?;
            out.extend(values.iter().zip(&trend).map(|(v, t)| v - t));
        }
        // Unit variance: a view agrees by its pattern, not by its contrast
        // (reading the dark holder beside a sample must not look better).
        let n = out.len() as f64;
        let mean = out.iter().sum::<f64>() / n;
        let sd = (out.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        if !(sd > 0.0 && sd.is_finite()) {
            return None;
        }
        out.iter_mut().for_each(|v| *v = (*v - mean) / sd);
        Some(out)
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
        let len = images[0].len();
        let mut sum = 0.0;
        for i in 0..len {
            let mean = images.iter().map(|im| im[i]).sum::<f64>() / n;
            sum += images.iter().map(|im| (im[i] - mean).powi(2)).sum::<f64>();
        }
        sum / (n * len as f64)
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

/// A height found by [`search`].
#[derive(Debug, Clone, Copy)]
struct Found {
    height: f64,
    /// Jackknife standard uncertainty; infinite: no measurement (a minimum
    /// at the end of the range, or views that agree no better there than
    /// anywhere).
    sigma: f64,
    agreement: f64,
}

/// The height of least cost within `centre` ± `half` mm: scanned on
/// `coarse`'s grid at `step` mm, refined by golden section on `views`'
/// grid to `tol` mm, its uncertainty by the delete-a-group jackknife.
fn search(
    views: &Views<'_>,
    coarse: &Views<'_>,
    centre: f64,
    [half, step, tol]: [f64; 3],
) -> Found {
    let steps = (half / step).ceil() as i64;
    let all_views = |_: usize| true;
    let costs: Vec<(f64, f64)> = (-steps..=steps)
        .map(|k| {
            let h = centre + k as f64 * step;
            (h, coarse.cost(h, &all_views))
        })
        .collect();
    let (best, best_cost) =
        costs.iter().copied().min_by(|a, b| a.1.total_cmp(&b.1)).unwrap_or((0.0, f64::INFINITY));
    let typical = median(costs.iter().map(|c| c.1).collect()).unwrap_or(0.0);
    let agreement = if typical > 0.0 { 1.0 - best_cost / typical } else { 0.0 };
    let inside = (best - centre).abs() < half - step;
    let height = views.golden(best - step, best + step, tol, &all_views);
    let groups: Vec<f64> = (0..GROUPS)
        .map(|grp| views.golden(height - step, height + step, tol, &move |vi| vi % GROUPS != grp))
        .collect();
    let mean = groups.iter().sum::<f64>() / GROUPS as f64;
    let var = (GROUPS - 1) as f64 / GROUPS as f64
        * groups.iter().map(|h| (h - mean).powi(2)).sum::<f64>();
    let measured = inside && agreement >= MIN_AGREEMENT;
    Found { height, sigma: if measured { var.sqrt() } else { f64::INFINITY }, agreement }
}

/// A plane through heights: its height at the sample's centre, slopes and
/// their uncertainties, and the points' rms distance from it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PlaneFit {
    height: f64,
    slope: [f64; 2],
    sigma: [f64; 3],
    rms: f64,
}

/// The weighted least-squares plane h + a x + b y through `points` (x, y
/// mm, height mm, its σ). Its uncertainties are the fit's, inflated by the
/// scatter when the points disagree beyond their σ; `None` below four
/// points or when they do not span a plane.
fn fit_plane(points: &[([f64; 2], f64, f64)]) -> Option<PlaneFit> {
    if points.len() < 4 {
        return None;
    }
    let mut a = [0.0; 9];
    let mut b = [0.0; 3];
    for &(p, h, s) in points {
        let f = [1.0, p[0], p[1]];
        let w = 1.0 / (s * s).max(1e-12);
        for i in 0..3 {
            b[i] += w * f[i] * h;
            for j in 0..3 {
                a[i * 3 + j] += w * f[i] * f[j];
            }
        }
    }
    let c = super::linalg::solve_spd(3, &a, &b)?;
    let residual = |&(p, h, _): &([f64; 2], f64, f64)| h - c[0] - c[1] * p[0] - c[2] * p[1];
    let chi2: f64 = points.iter().map(|q| (residual(q) / q.2.max(1e-6)).powi(2)).sum();
    let scale = (chi2 / (points.len() - 3) as f64).max(1.0);
    let mut sigma = [0.0; 3];
    for (k, s) in sigma.iter_mut().enumerate() {
        let mut e = [0.0; 3];
        e[k] = 1.0;
        *s = (super::linalg::solve_spd(3, &a, &e)?[k] * scale).sqrt();
    }
    let rms =
        (points.iter().map(|q| residual(q).powi(2)).sum::<f64>() / points.len() as f64).sqrt();
    Some(PlaneFit { height: c[0], slope: [c[1], c[2]], sigma, rms })
}

/// The least-squares quadratic in uv through `values` at `points`,
/// evaluated there.
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
    Some(points.iter().map(|&p| basis(p).iter().zip(&c).map(|(f, c)| f * c).sum()).collect())
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
    /// where [`HeightFit::applied_face`] says.
    #[default]
    Measure,
    /// There ([`SampleFace::FLUSH`]: in the holder's plane, as the
    /// targets).
    Given(SampleFace),
}

/// Measure the sample's height above the holder's plane on `scan`'s frames
/// (module docs); on its outline too unless its `sides` show. `progress`
/// steps once per frame read.
pub fn measure_height(
    g: &ScannerGeometry,
    cal: &Calibration,
    scan: &ScanFrames,
    sides: super::regions::SampleSides,
    progress: &dyn super::calibrate::BuildProgress,
) -> Result<HeightFit, BuildError> {
    let rects: Vec<PixelRect> = cal.views.iter().map(|v| search_window(g, v)).collect();
    let (crops, lights) = read_crops(g, cal, scan, &rects, true, ("sample height", progress))?;
    // A grid at about the frontal views' pixel pitch over the inner 80 %,
    // and one of half as many points a side for the scan over the range.
    let side = (super::regions::default_size(cal) as f64 * 0.8).round().clamp(16.0, 104.0) as usize;
    let grid = |side: usize| -> Vec<[f64; 2]> {
        (0..side * side)
            .map(|i| {
                let (x, y) = ((i % side) as f64 + 0.5, (i / side) as f64 + 0.5);
                [0.1 + 0.8 * x / side as f64, 0.1 + 0.8 * y / side as f64]
            })
            .collect()
    };
    let views = Views { g, views: &cal.views, crops: &crops, grid: grid(side) };
    let coarse = Views { grid: grid(side / 2), ..views };
    let gain = parallax(g, &cal.views);
    let step = (1.0 / 3.0) / gain.max(1e-9);
    let whole = search(&views, &coarse, 0.0, [MAX_HEIGHT_MM, step, step * 1e-3]);
    let mut fit = HeightFit {
        height_mm: whole.height,
        sigma_mm: whole.sigma,
        agreement: whole.agreement,
        parallax_px_per_mm: gain,
        lights: lights.len(),
        slope: [0.0; 2],
        slope_sigma: [f64::INFINITY; 2],
        patches: 0,
        flatness_mm: 0.0,
        tilt_px: 0.0,
        cue: if whole.sigma.is_finite() { FaceCue::Chroma } else { FaceCue::None },
        outline: None,
        beyond: None,
        thin_sides: false,
    };
    // The outline: every sample's edges against the holder, unless its
    // sides show beyond them.
    let lum = CropLuminance(&crops);
    let size = g.sample.size_mm;
    let reach = MAX_TILT_DEG.to_radians().tan() * size;
    let outline = (sides != super::regions::SampleSides::Shown)
        .then(|| super::outline::coarse_height(g, &cal.views, &lum, MAX_HEIGHT_MM))
        .flatten()
        .and_then(|h| super::outline::measure_outline(g, &cal.views, &lum, h, reach));
    // Joined with the outline, unless the band beyond the edges facing
    // the views shows the sample's sides there (asked to look): then the
    // chroma's alone.
    let finish = |fit: HeightFit| {
        let mut joined = with_outline(fit, outline, size);
        // Read at the joined face, or the chroma's where the outline
        // disagrees with it (sides move the outline; the holder's plane,
        // where a disagreement leaves the face, may lie pixels off).
        let at = match joined.cue {
            FaceCue::Conflict => fit.applied_face(),
            _ => joined.applied_face(),
        };
        let beyond = super::outline::beyond_edges(g, &cal.views, &lum, at);
        joined.beyond = beyond;
        if sides == super::regions::SampleSides::Auto {
            if joined.sides_seen() {
                return HeightFit { beyond, ..fit };
            }
            // Thin sides pull the outline part-way to the plane: told by
            // the heights' disagreement, however few pixels it spans.
            let apart = outline.is_some_and(|o| {
                disagree(fit.height_mm, fit.sigma_mm, o.face.height_mm, o.sigma[0])
            });
            if apart && outline.is_some_and(|o| thin_sides(&fit, &o, beyond)) {
                return HeightFit { beyond, thin_sides: true, outline, ..fit };
            }
        }
        joined
    };
    if !whole.sigma.is_finite() {
        return Ok(finish(fit));
    }
    // The tilt: each patch's height where its views agree, searched
    // within the height a tilt of MAX_TILT_DEG gives its centre, and the
    // plane through them.
    let patch_of = |uv: [f64; 2]| -> usize {
        let k = |t: f64| (((t - 0.1) / 0.8 * PATCHES as f64) as usize).min(PATCHES - 1);
        k(uv[1]) * PATCHES + k(uv[0])
    };
    let within = |grid: &[[f64; 2]], k: usize| -> Vec<[f64; 2]> {
        grid.iter().copied().filter(|&uv| patch_of(uv) == k).collect()
    };
    let measured: Vec<([f64; 2], f64, f64)> = (0..PATCHES * PATCHES)
        .filter_map(|k| {
            let centre_uv =
                [k % PATCHES, k / PATCHES].map(|i| 0.1 + 0.8 * (i as f64 + 0.5) / PATCHES as f64);
            let at = [(centre_uv[0] - 0.5) * size, (centre_uv[1] - 0.5) * size];
            let reach = MAX_TILT_DEG.to_radians().tan() * (at[0].abs() + at[1].abs());
            let half = (reach + 3.0 * step).min(MAX_HEIGHT_MM);
            let patch = Views { grid: within(&views.grid, k), ..views };
            let patch_coarse = Views { grid: within(&coarse.grid, k), ..views };
            // A patch's height to 1 % of a step (its σ is tens of %).
            let found = search(&patch, &patch_coarse, whole.height, [half, step, step * 1e-2]);
            found.sigma.is_finite().then_some((at, found.height, found.sigma.max(1e-4)))
        })
        .collect();
    fit.patches = measured.len();
    if let Some(plane) = fit_plane(&measured) {
        fit.slope = plane.slope;
        fit.slope_sigma = [plane.sigma[1], plane.sigma[2]];
        fit.flatness_mm = plane.rms;
        fit.tilt_px = (plane.slope[0].abs() + plane.slope[1].abs()) * size / 2.0 * gain;
        // Tilted, the face's height at the centre is the plane's (the
        // whole sample's views agree best about a blend of heights).
        let tilted = HeightFit { height_mm: plane.height, sigma_mm: plane.sigma[0], ..fit };
        if !tilted.applied_face().is_level() {
            fit = tilted;
        }
    }
    Ok(finish(fit))
}

/// The band beyond the sample's edges facing each view against beyond
/// those facing away ([`super::outline::beyond_edges`]) read on `scan`'s
/// frames with the sample's face at `face` — a face given rather than
/// measured, whose sides [`super::regions::SampleSides::Auto`] still looks
/// for. `None`: too few views with edges to compare. `progress` steps once
/// per frame read.
pub fn sides_beyond(
    g: &ScannerGeometry,
    cal: &Calibration,
    scan: &ScanFrames,
    face: SampleFace,
    progress: &dyn super::calibrate::BuildProgress,
) -> Result<Option<super::outline::Beyond>, BuildError> {
    // The band reaches BAND_FROM_PX + 2 px beyond the edges; a few pixels
    // more for the bilinear taps.
    let rects: Vec<PixelRect> =
        cal.views.iter().map(|v| v.homography_at_face(g, face).window(6.0)).collect();
    let (crops, _) = read_crops(g, cal, scan, &rects, false, ("sample's sides", progress))?;
    Ok(super::outline::beyond_edges(g, &cal.views, &CropLuminance(&crops), face))
}

/// Up to [`LIGHTS`] of `scan`'s lights' frames (evenly spread), each
/// view's over its window in `rects`: per pixel the mean over them of the
/// luminance (over the white target's response there) and, with `chroma`,
/// the median of the chroma (white-balanced; empty planes otherwise); and
/// the lights read. `progress` is told the stage's name and steps once per
/// frame read.
fn read_crops(
    g: &ScannerGeometry,
    cal: &Calibration,
    scan: &ScanFrames,
    rects: &[PixelRect],
    chroma: bool,
    (stage, progress): (&str, &dyn super::calibrate::BuildProgress),
) -> Result<(Vec<ViewCrop>, Vec<usize>), BuildError> {
    let all = scan.lights();
    let n = all.len().min(LIGHTS);
    let lights: Vec<usize> = (0..n).map(|i| all[i * all.len() / n.max(1)]).collect();
    progress.stage(stage, lights.len());
    let dims = [g.camera.width as usize, g.camera.height as usize];
    let rects: Vec<PixelRect> = rects
        .iter()
        .map(|r| [r[0], r[1], r[2].min(dims[0]).max(r[0] + 2), r[3].min(dims[1]).max(r[1] + 2)])
        .collect();
    let inverses: Vec<Option<Homography>> =
        cal.views.iter().map(|v| v.homography.inverse()).collect();
    // Per light, each view's crop, in units of the light's irradiance at
    // the sample's centre times cos θi (lights differ by their beams).
    let per_light = lights
        .par_iter()
        .map(|&l| -> Result<Vec<[Vec<f32>; PLANES]>, BuildError> {
            let f = scan.read_within(l, &rects)?;
            let ci = cal.lights.iter().position(|c| c.light == l).ok_or_else(|| {
                BuildError::Input(format!("mirror {l} is lit in the scan but not calibrated"))
            })?;
            let unit = cal.colour.light(ci, [0.5, 0.5]) * cal.lights[ci].direction[2].max(0.05);
            let k = if unit > 0.0 { 1.0 / unit } else { 0.0 };
            progress.step();
            Ok(rects
                .iter()
                .enumerate()
                .map(|(vi, r)| {
                    let a = cal.colour.view(vi, [0.5, 0.5]);
                    let white = a.map(|a| if a > 0.0 { k / a } else { 0.0 });
                    // The luminance per pixel over the white target's
                    // response there (the beam's profile, the view's
                    // vignetting), for the outline: its edges' levels then
                    // change only with the sample's reflectance.
                    let to_uv = inverses[vi];
                    let response = |x: usize, y: usize| -> [f64; 3] {
                        let uv = to_uv.map_or([0.5, 0.5], |h| {
                            let q = h.apply([x as f64 + 0.5, y as f64 + 0.5]);
                            q.map(|t| t.clamp(0.0, 1.0))
                        });
                        let r = cal.colour.response(ci, vi, uv);
                        let w = cal.lights[ci].direction[2].max(0.05);
                        r.map(|r| if r > 0.0 { 1.0 / (r * w) } else { 0.0 })
                    };
                    crop(&f, *r, white, &response)
                })
                .collect())
        })
        .collect::<Result<Vec<_>, _>>()?;
    if per_light.is_empty() {
        return Err(BuildError::Input(format!("{}: no frames", scan.dir.display())));
    }
    // Per view and pixel, the median over the lights of the chroma: each light's
    // diffuse shading is the same in every view, a specular lobe only in
    // the views near its mirror direction, whose pattern then leans
    // towards the view (as a height would); the median leaves those out.
    let medians: Vec<[Vec<f32>; PLANES]> = (0..rects.len())
        .into_par_iter()
        .map(|vi| {
            let n = per_light[0][vi][0].len();
            let mut values = Vec::with_capacity(per_light.len());
            std::array::from_fn(|plane| {
                if plane == 0 {
                    // The luminance: the mean, for the outline (every
                    // light's share of the sample's brightness counts).
                    let k = 1.0 / per_light.len() as f32;
                    return (0..n)
                        .map(|i| k * per_light.iter().map(|c| c[vi][0][i]).sum::<f32>())
                        .collect();
                }
                if !chroma {
                    return Vec::new();
                }
                (0..n)
                    .map(|i| {
                        values.clear();
                        values.extend(per_light.iter().map(|c| c[vi][plane][i]));
                        values.sort_unstable_by(f32::total_cmp);
                        let m = values.len();
                        0.5 * (values[(m - 1) / 2] + values[m / 2])
                    })
                    .collect()
            })
        })
        .collect();
    let crops: Vec<ViewCrop> = rects
        .iter()
        .zip(medians)
        .map(|(&rect, planes)| ViewCrop { rect, lit: planes[0].iter().any(|&v| v > 0.0), planes })
        .collect();
    Ok((crops, lights))
}

/// The most of the way from the face to the holder's plane a sample's
/// sides pull its outline. Standing on the holder, a sample's sides reach
/// down to the holder's plane: beyond the edges facing a view the outline
/// ends at their foot, which the view sees where a face in the holder's
/// plane would be, while the edges facing away show the face's own — half
/// the edges at most read as if the face lay in the plane.
pub const SIDES_PULL: f64 = 0.5;

/// Whether the chroma's face (`chroma`) and the outline's (`outline`)
/// disagree as a thin sample's sides make them: sides too thin for the
/// band beyond the facing edges to reach [`super::outline::MIN_SIDES_EXCESS`]
/// of the face's contrast still light it beyond 4 σ (`beyond`, read at
/// the chroma's face), and they pull the outline from the face towards
/// the holder's plane, by no more than [`SIDES_PULL`] of the way. A lean
/// of the chroma (a metal's coloured highlights) leaves the outline near
/// the plane and the band dark: the face is then not measured.
/// (Leather and painted wood 0.5 mm thick standing on the holder, 2048²:
/// chroma 0.500 mm, outline 0.392 ± 0.003 mm, the band 0.0099 ± 0.0012
/// of the face's contrast; docs/benchmarks.md, session 96.)
fn thin_sides(
    chroma: &HeightFit,
    outline: &OutlineFit,
    beyond: Option<super::outline::Beyond>,
) -> bool {
    let (c, o) = (chroma.height_mm, outline.face.height_mm);
    beyond.is_some_and(|b| b.lit())
        && chroma.sigma_mm.is_finite()
        && c * o > 0.0
        && o.abs() < c.abs()
        && o.abs() >= (1.0 - SIDES_PULL) * c.abs()
}

/// Whether two measurements `a` ± `sa` and `b` ± `sb` of one parameter
/// disagree: beyond 4 σ of their difference.
fn disagree(a: f64, sa: f64, b: f64, sb: f64) -> bool {
    (a - b).abs() > 4.0 * sa.hypot(sb)
}

/// The chroma's measurement `chroma` joined with the outline's (module
/// docs): where only one measured a parameter (the face's height, each
/// slope), its value; where both did and agree within 4 σ, their
/// inverse-variance mean; where they disagree by more than that but by
/// less than moves any view [`NEGLIGIBLE_PX`] (each reading's bias is
/// below its σ's reach, yet the views would be read alike at either:
/// a proud stone's fine relief leans its chroma 0.024 mm below its
/// outline's 0.300 ± 0.001 mm at 4096², 0.11 px), that mean too, its σ
/// scaled by how far beyond 4 σ they lie; where they disagree more,
/// neither — a metal's coloured highlights lean its chroma, an outline may
/// be a mask's or show the sample's sides, and which one erred cannot be
/// told ([`FaceCue::Conflict`] when the heights disagree: the face is then
/// not measured).
fn with_outline(chroma: HeightFit, outline: Option<OutlineFit>, size_mm: f64) -> HeightFit {
    let Some(o) = outline else {
        return chroma;
    };
    let mut fit = HeightFit { outline: Some(o), ..chroma };
    // A parameter's value, σ, and whether the outline took part, from the
    // two readings and the frame px a unit of the parameter moves a view
    // by at most; `None` when the two disagree.
    let join = |c: f64, sc: f64, o: f64, so: f64, px: f64| -> Option<(f64, f64, bool)> {
        if !sc.is_finite() {
            return Some((o, so, true));
        }
        if !so.is_finite() {
            return Some((c, sc, false));
        }
        let gap = (c - o).abs();
        let apart = disagree(c, sc, o, so);
        let negligible = gap * px <= NEGLIGIBLE_PX;
        if apart && !negligible {
            return None;
        }
        let (wc, wo) = (1.0 / (sc * sc).max(1e-18), 1.0 / (so * so).max(1e-18));
        let scale = if apart { gap / (4.0 * sc.hypot(so)) } else { 1.0 };
        Some(((wc * c + wo * o) / (wc + wo), (wc + wo).sqrt().recip() * scale, true))
    };
    let px = chroma.parallax_px_per_mm;
    let Some((h, sh, used_h)) =
        join(chroma.height_mm, chroma.sigma_mm, o.face.height_mm, o.sigma[0], px)
    else {
        fit.sigma_mm = f64::INFINITY;
        fit.slope = [0.0; 2];
        fit.slope_sigma = [f64::INFINITY; 2];
        fit.tilt_px = 0.0;
        fit.cue = FaceCue::Conflict;
        return fit;
    };
    let slopes: [(f64, f64, bool); 2] = std::array::from_fn(|k| {
        join(
            chroma.slope[k],
            chroma.slope_sigma[k],
            o.face.slope[k],
            o.sigma[1 + k],
            px * size_mm / 2.0,
        )
        .unwrap_or((0.0, f64::INFINITY, true))
    });
    fit.height_mm = h;
    fit.sigma_mm = sh;
    fit.slope = slopes.map(|s| s.0);
    fit.slope_sigma = slopes.map(|s| s.1);
    let [a, b] = fit.slope;
    fit.tilt_px = (a.abs() + b.abs()) * size_mm / 2.0 * fit.parallax_px_per_mm;
    let outline_used = used_h || slopes.iter().any(|s| s.2);
    fit.cue = match (chroma.cue, outline_used) {
        (FaceCue::Chroma, true) => FaceCue::Both,
        (FaceCue::Chroma, false) => FaceCue::Chroma,
        (_, true) => FaceCue::Outline,
        (cue, false) => cue,
    };
    fit
}

/// The crops' luminance for the outline.
struct CropLuminance<'a>(&'a [ViewCrop]);

impl super::outline::Luminance for CropLuminance<'_> {
    fn at(&self, view: usize, p: [f64; 2]) -> f64 {
        self.0[view].bilinear(0, p)
    }

    fn lit(&self, view: usize) -> bool {
        self.0[view].lit
    }
}

/// Frame `f` over `rect` (row-major), its channels times `white`, as
/// [`PLANES`] planes; the luminance's channels times `lum_white` at each
/// pixel (x, y) instead.
fn crop(
    f: &Frame,
    rect: PixelRect,
    white: [f64; 3],
    lum_white: &dyn Fn(usize, usize) -> [f64; 3],
) -> [Vec<f32>; PLANES] {
    let w = f.width as usize;
    let n = (rect[2] - rect[0]) * (rect[3] - rect[1]);
    let mut out: [Vec<f32>; PLANES] = std::array::from_fn(|_| Vec::with_capacity(n));
    for y in rect[1]..rect[3] {
        for x in rect[0]..rect[2] {
            let (x, y) = (x.min(w - 1), y.min(f.height as usize - 1));
            let i = 3 * (y * w + x);
            let c: [f64; 3] = std::array::from_fn(|k| f.rgb[i + k] as f64 * white[k]);
            let l = lum_white(x, y);
            out[0].push((0..3).map(|k| f.rgb[i + k] as f64 * l[k]).sum::<f64>() as f32);
            out[1].push((c[0] - c[1]) as f32);
            out[2].push((c[2] - c[1]) as f32);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A face measured on the chroma at `h` ± `sigma` mm, level (its
    /// slopes not measured), 4 px of parallax per mm.
    fn measured(h: f64, sigma: f64) -> HeightFit {
        HeightFit {
            height_mm: h,
            sigma_mm: sigma,
            parallax_px_per_mm: 4.0,
            agreement: 0.8,
            lights: 8,
            slope: [0.0; 2],
            slope_sigma: [f64::INFINITY; 2],
            patches: 0,
            flatness_mm: 0.0,
            tilt_px: 0.0,
            cue: FaceCue::Chroma,
            outline: None,
            beyond: None,
            thin_sides: false,
        }
    }

    /// An outline's face `face` ± `sigma` (height mm, slopes), centred,
    /// of the calibrated size.
    fn outlined(face: SampleFace, sigma: [f64; 3]) -> OutlineFit {
        OutlineFit {
            face,
            sigma,
            shift_mm: [0.0; 2],
            size_error_mm: 0.0,
            points: 1000,
            views: 40,
            rms_px: 0.1,
        }
    }

    /// A height is applied only when it is both significant and large
    /// enough to move the views by a fifth of a pixel.
    #[test]
    fn a_height_is_applied_when_significant_and_not_negligible() {
        let fit = measured;
        assert_eq!(fit(0.3, 0.002).applied_mm(), 0.3);
        assert_eq!(fit(-0.3, 0.002).applied_mm(), -0.3);
        // 3 σ: not significant.
        assert_eq!(fit(0.3, 0.1).applied_mm(), 0.0);
        // 0.16 px of parallax: negligible, however precise.
        assert_eq!(fit(0.04, 0.0001).applied_mm(), 0.0);
        // No measurement.
        assert_eq!(fit(0.3, f64::INFINITY).applied_mm(), 0.0);
    }

    /// The plane through patches' heights: exact through points on one,
    /// its uncertainties inflated when they scatter beyond their σ, none
    /// below four points.
    #[test]
    fn the_plane_through_the_patches_is_weighted_least_squares() {
        let at = |x: f64, y: f64| 0.2 + 0.03 * x - 0.01 * y;
        let grid: Vec<[f64; 2]> =
            (0..9).map(|k| [(k % 3) as f64 * 8.0 - 8.0, (k / 3) as f64 * 8.0 - 8.0]).collect();
        let exact: Vec<_> = grid.iter().map(|&p| (p, at(p[0], p[1]), 0.01)).collect();
        let fit = fit_plane(&exact).unwrap();
        assert!((fit.height - 0.2).abs() < 1e-12 && fit.rms < 1e-12, "{fit:?}");
        assert!((fit.slope[0] - 0.03).abs() < 1e-12 && (fit.slope[1] + 0.01).abs() < 1e-12);
        // σ of the centre's height: 0.01 / √9 from nine equal points.
        assert!((fit.sigma[0] - 0.01 / 3.0).abs() < 1e-9, "{fit:?}");
        // Scatter of ±0.05 against σ 0.01: the uncertainties grow with it.
        let bumpy: Vec<_> = exact
            .iter()
            .enumerate()
            .map(|(k, &(p, h, s))| (p, h + if k % 2 == 0 { 0.05 } else { -0.05 }, s))
            .collect();
        let rough = fit_plane(&bumpy).unwrap();
        assert!(rough.sigma[1] > 3.0 * fit.sigma[1] && rough.rms > 0.04, "{rough:?}");
        assert!(fit_plane(&exact[..3]).is_none());
    }

    /// A tilt is applied when significant and large enough to matter; the
    /// face's height is then the plane's.
    #[test]
    fn a_tilt_is_applied_when_significant_and_not_negligible() {
        let fit = |slope: [f64; 2], sigma: f64, tilt_px: f64| HeightFit {
            slope,
            slope_sigma: [sigma; 2],
            patches: 9,
            flatness_mm: 0.01,
            tilt_px,
            ..measured(0.1, 0.003)
        };
        let f = fit([0.02, -0.01], 0.001, 1.5).applied_face();
        assert_eq!(f, SampleFace { height_mm: 0.1, slope: [0.02, -0.01] });
        // Its uncertainty at a corner: height and slopes in quadrature.
        let corner = fit([0.02, -0.01], 0.001, 1.5).corner_sigma_mm(25.4);
        assert!((corner - (0.003f64.powi(2) + 2.0 * 0.0127f64.powi(2)).sqrt()).abs() < 1e-12);
        assert_eq!(fit([0.001, 0.0], 0.0001, 0.1).corner_sigma_mm(25.4), 0.003);
        // Not significant (2.2 σ): level at the height.
        assert_eq!(fit([0.02, -0.01], 0.01, 1.5).applied_face(), SampleFace::at_height(0.1));
        // Significant but negligible: 0.06°, 0.1 px.
        assert_eq!(fit([0.001, 0.0], 0.0001, 0.1).applied_face(), SampleFace::at_height(0.1));
        // Without a patch measured.
        assert!(fit([0.0; 2], f64::INFINITY, 0.0).applied_face().is_level());
    }

    /// The chroma's and the outline's measurements joined: each parameter
    /// from the one that measured it, their inverse-variance mean where
    /// both did and agree or disagree by less than moves a view
    /// [`NEGLIGIBLE_PX`], neither where they disagree more.
    #[test]
    fn the_outline_joins_the_chroma_where_they_agree() {
        let chroma = |h: f64, sigma: f64, slope_sigma: f64| HeightFit {
            slope: [0.02, 0.0],
            slope_sigma: [slope_sigma; 2],
            patches: 9,
            flatness_mm: 0.01,
            cue: if sigma.is_finite() { FaceCue::Chroma } else { FaceCue::None },
            ..measured(h, sigma)
        };
        let outline =
            outlined(SampleFace { height_mm: 0.21, slope: [0.021, -0.001] }, [0.01, 0.001, 0.001]);
        // Without an outline: the chroma's.
        let c = chroma(0.2, 0.01, 0.001);
        assert_eq!(with_outline(c, None, 25.4), c);
        // Only the outline measured.
        let f = with_outline(chroma(0.0, f64::INFINITY, f64::INFINITY), Some(outline), 25.4);
        assert_eq!((f.height_mm, f.slope, f.cue), (0.21, [0.021, -0.001], FaceCue::Outline));
        assert_eq!([f.sigma_mm, f.slope_sigma[0]], [0.01, 0.001]);
        assert!((f.tilt_px - 0.022 * 12.7 * 4.0).abs() < 1e-12);
        // Both, agreeing: the mean, σ/√2 for equal σ.
        let f = with_outline(chroma(0.2, 0.01, 0.001), Some(outline), 25.4);
        assert!((f.height_mm - 0.205).abs() < 1e-12 && (f.slope[0] - 0.0205).abs() < 1e-12);
        assert!((f.sigma_mm - 0.01 / 2f64.sqrt()).abs() < 1e-12 && f.cue == FaceCue::Both);
        // The heights disagreeing by 7 σ: no face measured.
        let f = with_outline(chroma(0.31, 0.01, 0.001), Some(outline), 25.4);
        assert!(f.sigma_mm.is_infinite() && f.slope_sigma[0].is_infinite(), "{f:?}");
        assert_eq!((f.applied_face(), f.cue), (SampleFace::FLUSH, FaceCue::Conflict));
        // Disagreeing by 7.6 σ but 0.096 px (a proud stone's chroma leaned
        // by its relief): joined, σ scaled by 7.6 / 4.
        let lean = outlined(SampleFace::at_height(0.3), [0.001, 0.001, 0.001]);
        let f = with_outline(chroma(0.276, 0.003, f64::INFINITY), Some(lean), 25.4);
        let (w, sigma) = (1.0 / 0.003f64.powi(2) + 1e6, 0.003f64.hypot(0.001));
        let mean = (0.276 / 0.003f64.powi(2) + 0.3e6) / w;
        assert!((f.height_mm - mean).abs() < 1e-12 && f.cue == FaceCue::Both, "{f:?}");
        assert!((f.sigma_mm - w.sqrt().recip() * 0.024 / (4.0 * sigma)).abs() < 1e-12, "{f:?}");
        assert_eq!(f.applied_mm(), f.height_mm);
        // Within 4 σ: σ not scaled.
        let f = with_outline(chroma(0.297, 0.003, f64::INFINITY), Some(lean), 25.4);
        assert!((f.sigma_mm - w.sqrt().recip()).abs() < 1e-12, "{f:?}");
        // The same lean at 10 px per mm (0.24 px): no face measured.
        let steep = HeightFit { parallax_px_per_mm: 10.0, ..chroma(0.276, 0.003, f64::INFINITY) };
        assert_eq!(with_outline(steep, Some(lean), 25.4).cue, FaceCue::Conflict);
        // A slope disagreeing (0.02 against 0.03 ± 0.001): that slope not
        // measured, the other joined.
        let mut c = chroma(0.2, 0.01, 0.001);
        c.slope = [0.03, -0.001];
        let f = with_outline(c, Some(outline), 25.4);
        assert!(f.slope_sigma[0].is_infinite() && f.slope[0] == 0.0, "{f:?}");
        assert!((f.slope[1] + 0.001).abs() < 1e-12 && f.cue == FaceCue::Both, "{f:?}");
    }

    /// A disagreement is told as thin sides only when the outline lies
    /// between the holder's plane and the chroma's face, at most
    /// [`SIDES_PULL`] of the way to the plane, and the band beyond the
    /// facing edges is lit beyond 4 σ.
    #[test]
    fn thin_sides_pull_the_outline_part_way_to_the_plane() {
        let chroma = |h: f64| measured(h, 0.002);
        let outline = |h: f64| outlined(SampleFace::at_height(h), [0.003, 0.001, 0.001]);
        let band =
            |excess: f64| Some(crate::build::outline::Beyond { excess, sigma: 0.0012, views: 36 });
        // The leather 0.5 mm thick at 2048² (session 96).
        assert!(thin_sides(&chroma(0.5), &outline(0.392), band(0.0099)));
        // Standing below the holder's plane (a recess): the same, mirrored.
        assert!(thin_sides(&chroma(-0.5), &outline(-0.392), band(0.0099)));
        // The band dark (3 σ): a lean, not sides.
        assert!(!thin_sides(&chroma(0.5), &outline(0.392), band(0.0036)));
        // Pulled more than half-way: a metal's highlights leaning the
        // chroma (−0.38 mm against the outline's −0.009 mm).
        assert!(!thin_sides(&chroma(-0.38), &outline(-0.009), band(0.0099)));
        assert!(!thin_sides(&chroma(0.5), &outline(0.24), band(0.0099)));
        // Beyond the chroma's face, or across the plane: not the sides'.
        assert!(!thin_sides(&chroma(0.5), &outline(0.55), band(0.0099)));
        assert!(!thin_sides(&chroma(0.5), &outline(-0.1), band(0.0099)));
        // No band read, or no chroma measured.
        assert!(!thin_sides(&chroma(0.5), &outline(0.392), None));
        let unmeasured = HeightFit { sigma_mm: f64::INFINITY, ..chroma(0.5) };
        assert!(!thin_sides(&unmeasured, &outline(0.392), band(0.0099)));
    }

    /// The trend a view's chroma loses is the least-squares quadratic: a
    /// quadratic comes back exactly, a pattern orthogonal to it not at all.
    #[test]
    fn the_quadratic_trend_is_least_squares() {
        let points: Vec<[f64; 2]> =
            (0..100).map(|i| [(i % 10) as f64 / 9.0, (i / 10) as f64 / 9.0]).collect();
        let q = |p: [f64; 2]| 0.3 + 0.2 * p[0] - 0.7 * p[1] + 0.5 * p[0] * p[1] + 0.1 * p[1] * p[1];
        let values: Vec<f64> = points.iter().map(|&p| q(p)).collect();
        let trend = quadratic_trend(&points, &values).unwrap();
        for (t, v) in trend.iter().zip(&values) {
            assert!((t - v).abs() < 1e-9);
        }
    }
}
