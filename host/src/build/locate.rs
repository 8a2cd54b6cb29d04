//! Finding each mirror's view of the sample in the checkerboard scan
//! (Fig. 8 steps 2–3): a coarse translation from the sample's silhouette,
//! the patent's low-frequency Fourier phase alignment, and a homography
//! fitted to the checker's inner corners.
//!
//! All three work on the **sum over lights** of the checkerboard frames'
//! luminance: every frame shows every view, so summing gives the best
//! signal without knowing which light lit what.

use scanner_geometry::ScannerGeometry;

use super::linalg::Homography;
use super::plane::Plane;

/// The calibration target: a checkerboard of `squares` × `squares` over
/// the sample, aligned with uv, the square at uv (0, 0) light.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Checkerboard {
    /// Squares along each side.
    pub squares: u32,
}

impl Default for Checkerboard {
    fn default() -> Checkerboard {
        Checkerboard { squares: 8 }
    }
}

impl Checkerboard {
    /// +1 on light squares, −1 on dark ones.
    pub fn pattern(&self, uv: [f64; 2]) -> f64 {
        let n = self.squares as f64;
        let i = (uv[0] * n).floor() as i64;
        let j = (uv[1] * n).floor() as i64;
        if (i + j).rem_euclid(2) == 0 { 1.0 } else { -1.0 }
    }

    /// The inner corners, uv.
    pub fn inner_corners(&self) -> Vec<[f64; 2]> {
        let n = self.squares;
        (1..n)
            .flat_map(|j| (1..n).map(move |i| [i as f64 / n as f64, j as f64 / n as f64]))
            .collect()
    }
}

/// One view's location by each method.
#[derive(Debug, Clone, PartialEq)]
pub struct RegionFit {
    /// The view (mirror) index.
    pub view: usize,
    /// From the nominal geometry alone.
    pub nominal: Homography,
    /// After silhouette alignment and Fourier phase refinement.
    pub phase: Homography,
    /// RMS distance of the phase alignment's window centres from the
    /// homography fitted to them, px (NaN if the alignment did not run):
    /// how far the view departs from one homography locally, which ranks
    /// the views' edge errors ([`PhaseStep::rms_px`]).
    pub phase_rms_px: f64,
    /// The squares (along u, v) the phase alignment had settled off before
    /// the outline put it back ([`square_lock`]), if it had.
    pub relocked_squares: Option<[i32; 2]>,
    /// Fitted to the inner corners (None if too few were found).
    pub corners: Option<Homography>,
    /// Inner corners used by the fit.
    pub corners_used: usize,
    /// RMS residual of that fit, px.
    pub corner_rms_px: f64,
    /// Whether the corner fit is the better estimate: it explains the
    /// checker's pixels at least as well as the phase alignment does.
    pub by_corners: bool,
}

impl RegionFit {
    /// The better estimate: the corner fit or the phase alignment.
    pub fn best(&self) -> Homography {
        match self.corners {
            Some(c) if self.by_corners => c,
            _ => self.phase,
        }
    }
}

/// Why a view could not be located.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LocateError {
    /// The view is not in the frame, or too dark to find.
    #[error("the sample cannot be found through mirror {view}: {reason}")]
    NotFound {
        /// The view.
        view: usize,
        /// Why.
        reason: String,
    },
}

/// The nominal homography of view `l`: sample uv → frame pixel.
pub fn nominal_homography(g: &ScannerGeometry, l: usize) -> Option<Homography> {
    let mut src = Vec::new();
    let mut dst = Vec::new();
    for j in 0..=4 {
        for i in 0..=4 {
            let uv = [i as f64 / 4.0, j as f64 / 4.0];
            src.push(uv);
            dst.push(g.view_point(l, uv)?);
        }
    }
    Homography::fit(&src, &dst)
}

/// How far from its nominal place a view is searched: as far as
/// manufacturing errors can move it, 60 px of the default 4096² sensor
/// (scaled to this one; the room `scanner geometry` asks of a design,
/// [`ScannerGeometry::view_margin_px`]), at least 6 px.
fn search_margin(g: &ScannerGeometry) -> isize {
    g.view_margin_px().max(6.0).round() as isize
}

/// The frame pixels [`locate`] may look at for `view`: the nominal view
/// with twice the search margin around it (the refinements look a little
/// beyond the shifted view).
pub fn search_window(g: &ScannerGeometry, view: usize) -> Option<crate::exrio::PixelRect> {
    Some(nominal_homography(g, view)?.window(2.0 * search_margin(g) as f64 + 8.0))
}

/// Locate view `view` in `sum` (the luminance summed over the checkerboard
/// frames) starting from the nominal geometry.
pub fn locate(
    g: &ScannerGeometry,
    view: usize,
    sum: &Plane,
    target: &Checkerboard,
) -> Result<RegionFit, LocateError> {
    let fail = |reason: String| LocateError::NotFound { view, reason };
    let nominal = nominal_homography(g, view).ok_or_else(|| fail("behind the camera".into()))?;
    let margin = search_margin(g);
    let shifted = coarse_shift(sum, &nominal, margin).map_err(fail)?;
    let (mut phase, mut phase_rms_px) = phase_align(sum, shifted, target);
    let mut relocked_squares = None;
    // How well the lock explains the checker, and the lens' blur that
    // explains it best (fitted once: the corners are judged at it too).
    let mut fitted = pattern_residuals(sum, &phase, [&phase], target, &BLURS);
    if let Some((relocked, squares)) =
        fitted.and_then(|([own], sigma)| square_lock(sum, &phase, target, own, sigma))
    {
        tracing::info!(
            "mirror {view}: the checker's phase had settled {squares:?} squares off; put back \
             by the sample's outline"
        );
        (phase, phase_rms_px) = phase_align(sum, relocked, target);
        relocked_squares = Some(squares);
        fitted = None; // another lock: its blur fitted again below
    }
    // The phase alignment moves the outline by at most a square or so; a
    // pattern that is not the checkerboard (a sample scanned as one) can
    // send it anywhere — beyond the frame region read for the view, or to
    // a scale at which the corner search would take minutes.
    let drift = outline_distance(&shifted, &phase);
    if drift.is_nan() || drift > margin as f64 {
        return Err(fail(format!(
            "the checker pattern would move the view's outline by {drift:.0} px (at most {margin} \
             px): is it a checkerboard scan?"
        )));
    }
    let (corners, corners_used, corner_rms_px) = match corner_fit(sum, &phase, target) {
        Some((h, n, rms)) => (Some(h), n, rms),
        None => (None, 0, f64::NAN),
    };
    // The corner fit only if it explains the checker's pixels at least as
    // well as the phase alignment: on squares of a few pixels the corners
    // lose their precision first.
    let by_corners = corners.is_some_and(|c| {
        let blurs = fitted.as_ref().map_or(&BLURS[..], |(_, sigma)| std::slice::from_ref(sigma));
        pattern_residuals(sum, &phase, [&phase, &c], target, blurs).is_none_or(|([p, c], _)| c <= p)
    });
    Ok(RegionFit {
        view,
        nominal,
        phase,
        phase_rms_px,
        relocked_squares,
        corners,
        corners_used,
        corner_rms_px,
        by_corners,
    })
}

/// The Fourier phase alignment from `start` ([`phase_refine`] until it
/// moves the outline by under 0.01 px, at most 6 steps): the homography
/// and the windows' RMS residual, px (NaN if no step ran).
fn phase_align(sum: &Plane, start: Homography, target: &Checkerboard) -> (Homography, f64) {
    let (mut phase, mut rms_px) = (start, f64::NAN);
    for _ in 0..6 {
        let Some(step) = phase_refine(sum, &phase, target) else { break };
        let moved = outline_distance(&phase, &step.homography);
        (phase, rms_px) = (step.homography, step.rms_px);
        if moved < 0.01 {
            break;
        }
    }
    (phase, rms_px)
}

/// The whole-square shifts (in squares along u and v) the phase alignment
/// cannot see: the checker's fundamental repeats under a shift by one
/// square along both u and v, or by two along one (an odd total inverts
/// the pattern, which the alignment does not settle on).
const SQUARE_LOCKS: [[i32; 2]; 8] =
    [[1, 1], [1, -1], [-1, 1], [-1, -1], [2, 0], [-2, 0], [0, 2], [0, -2]];

/// The phase alignment settles on the checker's fundamental wherever the
/// coarse shift left it within half a period; a start off by more than
/// half a square along both u and v (the silhouette misread: a holder
/// lighter than the dark squares, a view under 3 px a square) settles a
/// whole square off along both — the pattern looks the same — and the
/// corner fit follows (a grey 0.2 holder put one view of 40 there,
/// 1.1 × 1.1 squares off, docs/benchmarks.md session 95). The sample's
/// outline tells these apart: `h` shifted by each of [`SQUARE_LOCKS`],
/// then one alignment step (a wrong lock's windows reach the holder,
/// which warps it by up to half a square; shifted, the warp stays), is
/// scored by how well the checker it predicts explains the pixels inside
/// it ([`pattern_residuals`], each candidate over its own sample, at the
/// blur `sigma` that fits `h` best: the lens' whatever the lock), and a
/// shift whose mean squared residual is under half `h`'s (`own`)
/// replaces it (returned with the squares `h` was off by). A wrong lock
/// lays a strip of the holder, flat, over a row of squares on two sides,
/// which the checker's levels cannot explain whatever the holder's
/// level. In nine scans (bins 2 and 4, holders 0–0.8) the right lock's
/// residual came out 0.08–0.19 of a wrong one's (10 views, all put
/// back), every other shift's at least 0.73 × the lock's it was tried
/// from (7.7 × on a black holder, where no view moved).
fn square_lock(
    sum: &Plane,
    h: &Homography,
    target: &Checkerboard,
    own: f64,
    sigma: f64,
) -> Option<(Homography, [i32; 2])> {
    let score = |c: &Homography| pattern_residuals(sum, c, [c], target, &[sigma]).map(|r| r.0[0]);
    let n = target.squares as f64;
    SQUARE_LOCKS
        .iter()
        .filter_map(|s| {
            let c = h.after_shift([s[0] as f64 / n, s[1] as f64 / n]);
            let c = phase_refine(sum, &c, target)?.homography;
            Some((score(&c)?, c, [-s[0], -s[1]]))
        })
        .filter(|(r, _, _)| *r < 0.5 * own)
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, c, off)| (c, off))
}

/// How far apart two homographies put the sample's corners: the largest
/// of the four distances, px (NaN if either is not finite there).
fn outline_distance(a: &Homography, b: &Homography) -> f64 {
    (0..4)
        .map(|k| {
            let uv = [(k & 1) as f64, (k >> 1) as f64];
            let (p, q) = (a.apply(uv), b.apply(uv));
            (p[0] - q[0]).hypot(p[1] - q[1])
        })
        .fold(0.0, |m: f64, d| if d.is_nan() || m.is_nan() { f64::NAN } else { m.max(d) })
}

/// Translate `h` so the sample's silhouette matches the lit pixels: row
/// and column profiles of the thresholded image against those of the
/// predicted quadrilateral, searched over ±`margin` px.
fn coarse_shift(sum: &Plane, h: &Homography, margin: isize) -> Result<Homography, String> {
    let inv = h.inverse().ok_or("degenerate view")?;
    let b = h.bounds();
    if b[2] < 0.0 || b[3] < 0.0 || b[0] > sum.width as f64 || b[1] > sum.height as f64 {
        return Err("outside the frame".into());
    }
    // Threshold: a third of the dark squares' level inside the prediction.
    let mut inner = Vec::new();
    for y in b[1].floor() as isize..=b[3].ceil() as isize {
        for x in b[0].floor() as isize..=b[2].ceil() as isize {
            let uv = inv.apply([x as f64 + 0.5, y as f64 + 0.5]);
            if (0.2..0.8).contains(&uv[0]) && (0.2..0.8).contains(&uv[1]) {
                inner.push(sum.at(x, y));
            }
        }
    }
    if inner.len() < 16 {
        return Err("the view is smaller than 4 × 4 px".into());
    }
    inner.sort_by(f32::total_cmp);
    let mut dark = inner[inner.len() / 4] as f64;
    let mut bright = inner[inner.len() * 9 / 10] as f64;
    if bright <= 0.0 {
        // The view is far enough from its prediction (a small view, or a
        // lens the geometry file does not know) that the prediction's
        // middle is dark: the levels from the whole search window, where
        // the lit view is a small part.
        let mut window = Vec::new();
        for y in b[1].floor() as isize - margin..=b[3].ceil() as isize + margin {
            for x in b[0].floor() as isize - margin..=b[2].ceil() as isize + margin {
                window.push(sum.at(x, y));
            }
        }
        window.sort_by(f32::total_cmp);
        dark = 0.0;
        bright = window[window.len() * 99 / 100] as f64;
    }
    if !(bright > 0.0 && dark >= 0.0) {
        return Err("no light in the predicted view".into());
    }
    let thr = (dark / 3.0).max(bright * 0.005);
    let x0 = b[0].floor() as isize - margin;
    let y0 = b[1].floor() as isize - margin;
    let w = (b[2].ceil() as isize - x0 + margin + 1) as usize;
    let hgt = (b[3].ceil() as isize - y0 + margin + 1) as usize;
    let (mut obs_x, mut obs_y) = (vec![0.0; w], vec![0.0; hgt]);
    let (mut mod_x, mut mod_y) = (vec![0.0; w], vec![0.0; hgt]);
    for yy in 0..hgt {
        for xx in 0..w {
            let (x, y) = (x0 + xx as isize, y0 + yy as isize);
            if sum.at(x, y) as f64 > thr {
                obs_x[xx] += 1.0;
                obs_y[yy] += 1.0;
            }
            let uv = inv.apply([x as f64 + 0.5, y as f64 + 0.5]);
            if (0.0..1.0).contains(&uv[0]) && (0.0..1.0).contains(&uv[1]) {
                mod_x[xx] += 1.0;
                mod_y[yy] += 1.0;
            }
        }
    }
    let best = |obs: &[f64], model: &[f64]| -> f64 {
        let n = obs.len() as isize;
        let ssd = |d: isize| -> f64 {
            (0..n)
                .map(|i| {
                    let m = if (0..n).contains(&(i - d)) { model[(i - d) as usize] } else { 0.0 };
                    (obs[i as usize] - m).powi(2)
                })
                .sum()
        };
        let (mut bd, mut bv) = (0, f64::INFINITY);
        for d in -margin..=margin {
            let v = ssd(d);
            if v < bv {
                (bd, bv) = (d, v);
            }
        }
        // Sub-pixel: the parabola through the minimum and its neighbours.
        let (a, c) = (ssd(bd - 1), ssd(bd + 1));
        let den = a - 2.0 * bv + c;
        bd as f64 + if den > 0.0 { 0.5 * (a - c) / den } else { 0.0 }
    };
    let (dx, dy) = (best(&obs_x, &mod_x), best(&obs_y, &mod_y));
    if dx.abs() >= margin as f64 || dy.abs() >= margin as f64 {
        return Err(format!("no silhouette within ±{margin} px of the nominal view"));
    }
    let mut m = h.0;
    for k in 0..3 {
        m[k] += dx * m[6 + k];
        m[3 + k] += dy * m[6 + k];
    }
    Ok(Homography(m))
}

/// Windows of the phase alignment along each side of the sample.
const PHASE_WINDOWS: usize = 5;

/// One step of the Fourier phase alignment: in each of
/// [`PHASE_WINDOWS`]² overlapping windows of the rectified view, the phase
/// of the checker's fundamental (frequency (±n/2, ±n/2) per sample side)
/// against the ideal pattern's gives the local shift; the homography is
/// refitted to the shifted window centres.
///
/// Each window is two squares wide (a whole period of the fundamental)
/// and stays half a square inside the sample's edge: a window reaching
/// the edge reads the pattern darkened by the holder beside it, on one
/// side only, which moves its phase and put the outline ≈ 0.05 px outside
/// the sample on every side (docs/benchmarks.md, session 74). The
/// windows' centres spread over 0.19–0.81 of the sample, which the
/// homography needs to follow a lens' distortion. Each sample is divided
/// by the window's level, a plane in uv fitted to it (the checker is
/// orthogonal to a plane over whole periods): a pattern under a sloped
/// level has its phase moved by the slope, opposite ways on opposite
/// sides of a view.
fn phase_refine(sum: &Plane, h: &Homography, target: &Checkerboard) -> Option<PhaseStep> {
    let n = target.squares as f64;
    let f = n / 2.0; // cycles per unit uv
    let grid = 24 * target.squares as usize; // rectification samples per side
    let inset = 0.5 / n; // half a square
    let width = 2.0 / n; // two squares: one period along u and along v
    let half = (width * grid as f64 / 2.0).round() as usize; // samples a half-window
    let first = inset + width / 2.0;
    let step = (1.0 - 2.0 * first) / (PHASE_WINDOWS - 1) as f64;
    let mut src = Vec::new();
    let mut dst = Vec::new();
    for wj in 0..PHASE_WINDOWS {
        for wi in 0..PHASE_WINDOWS {
            let c = [first + step * wi as f64, first + step * wj as f64];
            let mut obs = [[0.0f64; 2]; 2]; // (re, im) for (+f, +f), (+f, −f)
            let mut model = [[0.0f64; 2]; 2];
            let mut mean = 0.0;
            let mut count = 0.0;
            let samples: Vec<([f64; 2], f64)> = (0..2 * half)
                .flat_map(|b| (0..2 * half).map(move |a| (a, b)))
                .map(|(a, b)| {
                    let uv = [
                        c[0] - width / 2.0 + (a as f64 + 0.5) / grid as f64,
                        c[1] - width / 2.0 + (b as f64 + 0.5) / grid as f64,
                    ];
                    let p = h.apply(uv);
                    (uv, sum.bilinear(p[0], p[1]))
                })
                .collect();
            // The level: mean + slope · (uv − c), by least squares (the
            // samples lie on a grid symmetric about c).
            let (mut slope, mut second) = ([0.0f64; 2], [0.0f64; 2]);
            for (uv, v) in &samples {
                mean += v;
                count += 1.0;
                for a in 0..2 {
                    slope[a] += v * (uv[a] - c[a]);
                    second[a] += (uv[a] - c[a]).powi(2);
                }
            }
            mean /= count;
            let slope = [slope[0] / second[0], slope[1] / second[1]];
            for (uv, v) in &samples {
                let p = target.pattern(*uv);
                let level = mean + slope[0] * (uv[0] - c[0]) + slope[1] * (uv[1] - c[1]);
                let r = if level > 0.0 { v / level - 1.0 } else { 0.0 };
                for (k, sign) in [1.0, -1.0].into_iter().enumerate() {
                    let ph = -std::f64::consts::TAU * f * (uv[0] + sign * uv[1]);
                    let (s, co) = ph.sin_cos();
                    obs[k][0] += r * co;
                    obs[k][1] += r * s;
                    model[k][0] += p * co;
                    model[k][1] += p * s;
                }
            }
            let arg = |k: usize| {
                // arg(obs / model)
                let (a, b) = (obs[k][0], obs[k][1]);
                let (cr, ci) = (model[k][0], model[k][1]);
                (b * cr - a * ci).atan2(a * cr + b * ci)
            };
            let mag = (obs[0][0].hypot(obs[0][1]), obs[1][0].hypot(obs[1][1]));
            if !(mag.0 > 0.0 && mag.1 > 0.0) {
                return None;
            }
            // obs ≈ model · e^{−2πi f (δu ± δv)}.
            let s_plus = -arg(0) / (std::f64::consts::TAU * f);
            let s_minus = -arg(1) / (std::f64::consts::TAU * f);
            let du = 0.5 * (s_plus + s_minus);
            let dv = 0.5 * (s_plus - s_minus);
            src.push([c[0] - du, c[1] - dv]);
            dst.push(h.apply(c));
        }
    }
    let homography = Homography::fit(&src, &dst)?;
    let squares: f64 = src
        .iter()
        .zip(&dst)
        .map(|(s, d)| {
            let p = homography.apply(*s);
            (p[0] - d[0]).powi(2) + (p[1] - d[1]).powi(2)
        })
        .sum();
    // 2 coordinates a window, 8 parameters fitted.
    let rms_px = (squares / (2 * src.len() - 8) as f64).sqrt();
    Some(PhaseStep { homography, rms_px })
}

/// One step of the phase alignment ([`phase_refine`]).
struct PhaseStep {
    /// The homography fitted to the shifted window centres.
    homography: Homography,
    /// The centres' RMS distance from it, px: what one homography cannot
    /// follow (noise, a lens' or the pattern's local departures). Not the
    /// homography's standard error (that formula, r·√(8/2n), comes out 3–5
    /// × below the edges' true errors: the departures are systematic);
    /// the residual itself ranks the views' edge errors (Pearson 0.81 at
    /// 4096², 0.66 at 1024²) and is of their size (docs/benchmarks.md,
    /// session 76).
    rms_px: f64,
}

/// How well each of `candidates` explains the view's pixels: the mean of
/// the squared residuals of the checkerboard it predicts, over the pixels
/// `mask` puts well inside the sample (uv within [0.04, 0.96]²); `None`
/// for a view of under 64 such pixels.
///
/// A pixel's prediction is the pattern blurred by a Gaussian of σ px (the
/// lens) and the pixel's own square (σ² + 1/12 along each line), each
/// square's edges at the distance the candidate puts them from the pixel
/// centre; scaled and offset by levels linear in uv (the light and the
/// vignetting vary across a view), fitted by least squares. σ is the one
/// of `blurs` that explains the first candidate best (returned with the
/// residuals). A candidate off by a fraction of a pixel mispredicts the
/// pixels along every edge.
fn pattern_residuals<const N: usize>(
    sum: &Plane,
    mask: &Homography,
    candidates: [&Homography; N],
    target: &Checkerboard,
    blurs: &[f64],
) -> Option<([f64; N], f64)> {
    let inv_mask = mask.inverse()?;
    let b = mask.bounds();
    let mut pixels = Vec::new();
    for y in b[1].floor() as isize..=b[3].ceil() as isize {
        for x in b[0].floor() as isize..=b[2].ceil() as isize {
            let uv = inv_mask.apply([x as f64 + 0.5, y as f64 + 0.5]);
            if uv.iter().all(|c| (0.04..=0.96).contains(c)) {
                pixels.push(([x as f64 + 0.5, y as f64 + 0.5], uv, sum.at(x, y) as f64));
            }
        }
    }
    if pixels.len() < 64 {
        return None;
    }
    let n = target.squares as f64;
    // Per candidate and pixel, once: the pattern's sign there and the
    // distances (px) to the nearest lines of constant u and of constant v.
    let edges = |h: &Homography| -> Option<Vec<[f64; 3]>> {
        let inv = h.inverse()?;
        Some(
            pixels
                .iter()
                .map(|(q, _, _)| {
                    let w = inv.apply(*q);
                    let j = inv.jacobian(*q); // d(u, v) / d(x, y)
                    let dist = |c: f64, grad: [f64; 2]| {
                        let t = c * n;
                        (t - t.round()).abs() / n / grad[0].hypot(grad[1]).max(1e-12)
                    };
                    [target.pattern(w), dist(w[0], j[0]), dist(w[1], j[1])]
                })
                .collect(),
        )
    };
    let edges: Vec<Vec<[f64; 3]>> = candidates.iter().map(|h| edges(h)).collect::<Option<_>>()?;
    // The least-squares residual of candidate `k` at blur σ, the design row
    // of a pixel [1, u, v, p, p·u, p·v].
    let residual = |k: usize, sigma: f64| -> Option<f64> {
        // erf(x / (√2 s)) as tanh: the edge's profile, s² = σ² + 1/12.
        let a = (2.0 / std::f64::consts::PI).sqrt() * 1.1 / (sigma * sigma + 1.0 / 12.0).sqrt();
        let rows: Vec<[f64; 6]> = pixels
            .iter()
            .zip(&edges[k])
            .map(|((_, uv, _), e)| {
                let p = e[0] * (a * e[1]).tanh() * (a * e[2]).tanh();
                let (du, dv) = (uv[0] - 0.5, uv[1] - 0.5);
                [1.0, du, dv, p, p * du, p * dv]
            })
            .collect();
        let mut normal = super::linalg::Normal::new(6);
        for (j, (_, _, v)) in rows.iter().zip(&pixels) {
            normal.add(j, -v);
        }
        let c = normal.step(0.0)?;
        Some(
            rows.iter()
                .zip(&pixels)
                .map(|(j, (_, _, v))| {
                    (j.iter().zip(&c).map(|(a, b)| a * b).sum::<f64>() - v).powi(2)
                })
                .sum::<f64>()
                / pixels.len() as f64,
        )
    };
    let mut blur = (f64::INFINITY, 0.0);
    for &sigma in blurs {
        let r = residual(0, sigma)?;
        if r < blur.0 {
            blur = (r, sigma);
        }
    }
    let mut out = [0.0; N];
    for (k, slot) in out.iter_mut().enumerate() {
        *slot = residual(k, blur.1)?;
    }
    Some((out, blur.1))
}

/// The lens blurs σ, px, [`pattern_residuals`] tries.
const BLURS: [f64; 11] = [0.0, 0.15, 0.25, 0.4, 0.55, 0.7, 0.85, 1.0, 1.2, 1.5, 2.0];

/// The inner corners located to sub-pixel precision (the gradient of the
/// lightly blurred image is orthogonal to the offset from a saddle point,
/// as in OpenCV's cornerSubPix), then a homography fitted to them with
/// outliers (3 × the median residual) dropped: (homography, corners used,
/// RMS residual in px).
fn corner_fit(
    sum: &Plane,
    h: &Homography,
    target: &Checkerboard,
) -> Option<(Homography, usize, f64)> {
    let b = h.bounds();
    let pad = 4isize;
    let x0 = b[0].floor() as isize - pad;
    let y0 = b[1].floor() as isize - pad;
    let w = (b[2].ceil() as isize - x0 + pad) as usize;
    let hh = (b[3].ceil() as isize - y0 + pad) as usize;
    let img = sum.crop(x0, y0, w, hh).blurred(0.7);
    let n = target.squares as f64;
    let mut src = Vec::new();
    let mut dst = Vec::new();
    for uv in target.inner_corners() {
        let p0 = h.apply(uv);
        let j = h.jacobian(uv);
        // Edge vectors of one square at this corner, px.
        let eu = [j[0][0] / n, j[1][0] / n];
        let ev = [j[0][1] / n, j[1][1] / n];
        let det = eu[0] * ev[1] - eu[1] * ev[0];
        if det.abs() < 4.0 {
            continue; // squares under 2 × 2 px: no corner to find
        }
        let to_basis = |d: [f64; 2]| {
            [(d[0] * ev[1] - d[1] * ev[0]) / det, (eu[0] * d[1] - eu[1] * d[0]) / det]
        };
        let mut q = [p0[0] - x0 as f64, p0[1] - y0 as f64];
        let reach = (eu[0].abs() + ev[0].abs()).max(eu[1].abs() + ev[1].abs()).ceil() as isize;
        let mut ok = false;
        for _ in 0..30 {
            let (mut a11, mut a12, mut a22, mut b1, mut b2) = (0.0, 0.0, 0.0, 0.0, 0.0);
            let (cx, cy) = (q[0].floor() as isize, q[1].floor() as isize);
            for yy in cy - reach..=cy + reach {
                for xx in cx - reach..=cx + reach {
                    let px = [xx as f64 + 0.5, yy as f64 + 0.5];
                    let c = to_basis([px[0] - q[0], px[1] - q[1]]);
                    // Stay well inside the four squares around the corner.
                    if c[0].abs() > 0.6 || c[1].abs() > 0.6 {
                        continue;
                    }
                    let wgt = (-(c[0] * c[0] + c[1] * c[1]) / (2.0 * 0.3 * 0.3)).exp();
                    let gx = 0.5 * (img.at(xx + 1, yy) - img.at(xx - 1, yy)) as f64;
                    let gy = 0.5 * (img.at(xx, yy + 1) - img.at(xx, yy - 1)) as f64;
                    let (gxx, gxy, gyy) = (gx * gx * wgt, gx * gy * wgt, gy * gy * wgt);
                    a11 += gxx;
                    a12 += gxy;
                    a22 += gyy;
                    b1 += gxx * px[0] + gxy * px[1];
                    b2 += gxy * px[0] + gyy * px[1];
                }
            }
            let d = a11 * a22 - a12 * a12;
            if d.is_nan() || d <= 1e-12 * (a11 + a22).powi(2) || !d.is_finite() {
                break;
            }
            let next = [(a22 * b1 - a12 * b2) / d, (a11 * b2 - a12 * b1) / d];
            let step = (next[0] - q[0]).hypot(next[1] - q[1]);
            q = next;
            if step < 1e-3 {
                ok = true;
                break;
            }
        }
        let moved = to_basis([q[0] + x0 as f64 - p0[0], q[1] + y0 as f64 - p0[1]]);
        if ok && moved[0].abs() < 0.35 && moved[1].abs() < 0.35 {
            src.push(uv);
            dst.push([q[0] + x0 as f64, q[1] + y0 as f64]);
        }
    }
    let min_corners = ((target.squares - 1).pow(2) as usize / 2).max(4);
    let mut fit = Homography::fit(&src, &dst)?;
    for _ in 0..2 {
        let res: Vec<f64> = src
            .iter()
            .zip(&dst)
            .map(|(s, d)| {
                let p = fit.apply(*s);
                (p[0] - d[0]).hypot(p[1] - d[1])
            })
            .collect();
        let cut = (3.0 * crate::stats::median(res.clone()).unwrap_or(0.0)).max(0.05);
        let keep: Vec<usize> = (0..res.len()).filter(|&i| res[i] <= cut).collect();
        if keep.len() == src.len() {
            break;
        }
        src = keep.iter().map(|&i| src[i]).collect();
        dst = keep.iter().map(|&i| dst[i]).collect();
        if src.len() < min_corners {
            return None;
        }
        fit = Homography::fit(&src, &dst)?;
    }
    if src.len() < min_corners {
        return None;
    }
    let rms = (src
        .iter()
        .zip(&dst)
        .map(|(s, d)| {
            let p = fit.apply(*s);
            (p[0] - d[0]).powi(2) + (p[1] - d[1]).powi(2)
        })
        .sum::<f64>()
        / src.len() as f64)
        .sqrt();
    Some((fit, src.len(), rms))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A view rendered by 8 × 8 rays a pixel: the checker (light 1, dark
    /// 0.05) times `level(uv)` on the sample, 0 (the holder) around it.
    fn render(h: &Homography, size: usize, level: &dyn Fn([f64; 2]) -> f64) -> Plane {
        render_on(h, size, level, 0.0)
    }

    /// [`render`] on a holder of level `holder`.
    fn render_on(
        h: &Homography,
        size: usize,
        level: &dyn Fn([f64; 2]) -> f64,
        holder: f64,
    ) -> Plane {
        let target = Checkerboard::default();
        let inv = h.inverse().unwrap();
        let mut plane = Plane::new(size, size);
        let k = 8;
        for y in 0..size {
            for x in 0..size {
                let mut s = 0.0;
                for b in 0..k {
                    for a in 0..k {
                        let q = [
                            x as f64 + (a as f64 + 0.5) / k as f64,
                            y as f64 + (b as f64 + 0.5) / k as f64,
                        ];
                        let uv = inv.apply(q);
                        if uv.iter().all(|c| (0.0..1.0).contains(c)) {
                            let light = target.pattern(uv) > 0.0;
                            s += level(uv) * if light { 1.0 } else { 0.05 };
                        } else {
                            s += holder;
                        }
                    }
                }
                plane.data[y * size + x] = (s / (k * k) as f64) as f32;
            }
        }
        plane
    }

    /// The phase alignment puts the sample's sides where they are: no
    /// outward bias from the holder beside the edge, none from a level
    /// sloped or domed across the view. Before: the sides +0.03 to
    /// +0.07 px out on average, single sides up to 0.15 px off; now
    /// within ±0.01 px on average, 0.03 px each (what is left moves the
    /// outline, the pixel grid's sampling of the squares' edges).
    #[test]
    fn the_phase_alignment_is_unbiased() {
        let target = Checkerboard::default();
        type Level = Box<dyn Fn([f64; 2]) -> f64>;
        let levels: [(&str, Level); 3] = [
            ("flat", Box::new(|_| 1.0)),
            ("ramp", Box::new(|uv| 0.7 + 0.6 * uv[0] - 0.2 * uv[1])),
            ("dome", Box::new(|uv| 1.0 - 0.5 * ((uv[0] - 0.5).powi(2) + (uv[1] - 0.5).powi(2)))),
        ];
        for side in [32.0, 128.0] {
            let o = side * 0.25;
            // Sheared, so that the sides are not the pixel grid's lines.
            let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
            let dst = [
                [o, o],
                [o + side, o + 1.3],
                [o + side + 0.7, o + side + 1.3],
                [o + 0.7, o + side],
            ];
            let truth = Homography::fit(&src, &dst).unwrap();
            for (name, level) in &levels {
                let sum = render(&truth, (side * 1.5) as usize, level);
                let mut start = truth.0;
                start[2] += 0.3;
                start[5] -= 0.2;
                let mut phase = Homography(start);
                for _ in 0..12 {
                    phase = phase_refine(&sum, &phase, &target).unwrap().homography;
                }
                // How far out each side's midpoint lies, px.
                let c = truth.apply([0.5, 0.5]);
                let out = [[0.5, 0.0], [1.0, 0.5], [0.5, 1.0], [0.0, 0.5]].map(|m| {
                    let (a, b) = (phase.apply(m), truth.apply(m));
                    let d = [b[0] - c[0], b[1] - c[1]];
                    ((a[0] - b[0]) * d[0] + (a[1] - b[1]) * d[1]) / d[0].hypot(d[1])
                });
                let mean = out.iter().sum::<f64>() / 4.0;
                assert!(
                    mean.abs() < 0.015 && out.iter().all(|o| o.abs() < 0.035),
                    "{side} px, {name} level: sides {out:+.4?} px out, mean {mean:+.4}"
                );
            }
        }
    }

    /// A start more than half a square off along u and v settles a whole
    /// square off (the checker looks the same); the outline puts it back,
    /// on a black holder, a grey one between the squares' levels and one
    /// lighter than the light squares — and leaves a right lock alone.
    #[test]
    fn a_lock_a_whole_square_off_is_put_back_by_the_outline() {
        let target = Checkerboard::default();
        let side = 48.0; // 6 px squares
        let o = 20.0;
        let src = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        let dst =
            [[o, o], [o + side, o + 1.1], [o + side + 0.9, o + side + 1.4], [o + 0.6, o + side]];
        let truth = Homography::fit(&src, &dst).unwrap();
        let level = |uv: [f64; 2]| 0.8 + 0.3 * uv[0] - 0.1 * uv[1];
        for holder in [0.0, 0.3, 1.2] {
            let sum = render_on(&truth, 96, &level, holder);
            for (start, off) in [([0.0, 0.0], [0, 0]), ([0.8, 0.7], [1, 1]), ([-0.7, 0.8], [-1, 1])]
            {
                let start = truth.after_shift([start[0] / 8.0, start[1] / 8.0]);
                let (phase, _) = phase_align(&sum, start, &target);
                // The premise: the alignment alone settles near `off`
                // squares off (warped: its windows then reach the holder).
                let settled = truth.after_shift([off[0] as f64 / 8.0, off[1] as f64 / 8.0]);
                let (near, far) =
                    (outline_distance(&phase, &settled), outline_distance(&phase, &truth));
                assert!(
                    near < 4.0 && (off == [0, 0] || far > 3.0),
                    "holder {holder}: from {start:?} the alignment settled {near:.2} px from {off:?} \
                     squares off, {far:.2} px from the truth"
                );
                let ([own], sigma) =
                    pattern_residuals(&sum, &phase, [&phase], &target, &BLURS).unwrap();
                let fixed = match square_lock(&sum, &phase, &target, own, sigma) {
                    Some((h, squares)) => {
                        assert_eq!(squares, off, "holder {holder}");
                        phase_align(&sum, h, &target).0
                    }
                    None => phase,
                };
                let d = outline_distance(&fixed, &truth);
                assert!(
                    d < 0.1,
                    "holder {holder}, settled {off:?} squares off: {d:.3} px from the truth"
                );
                if off == [0, 0] {
                    let lock = square_lock(&sum, &phase, &target, own, sigma);
                    assert!(lock.is_none(), "holder {holder}");
                }
            }
        }
    }
}
