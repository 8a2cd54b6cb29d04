//! Multi-view super-resolution of a light's region images
//! (docs/calibration-format.md, "Region images: detail from every view").
//!
//! A region image is the sample seen through one view's pixels (≥ 0.2 mm on
//! the default scanner, coarser across a grazing view) and resampled: it
//! holds no detail finer than its view's pixels. But the views see the
//! sample on different pixel lattices — shifted, rotated and foreshortened
//! by their mirrors — and under one light a sample's f · cos θi changes
//! with the view far more slowly over uv than it does with the texture.
//! Together the frames hold detail that no single view resolves.
//!
//! For each light the builder solves for one S × S image X that, seen
//! through every view's pixels, best explains them all:
//!
//!   min Σ_views ω_v Σ_pixels (mean of X over the pixel's square − pixel / G_v)²
//!       + λ ‖∇X‖²,
//!
//! G_v the view's level against the views' mean image ([`view_gain`]: X is
//! one image up to each view's level), each pixel's square mapped onto the
//! sample by its view's homography
//! (4 × 4 points, X looked up bilinearly like the material does), only
//! pixels whose squares lie wholly on the sample, each normalised by the
//! colour calibration like the region images are. ω_v makes every view
//! count alike however many pixels it has (as in the views' mean image M
//! below), and λ is relative to the data term's mean diagonal, so neither
//! depends on the number of views or the pixels per texel. Conjugate
//! gradients on the normal equations, from M, for a fixed number of
//! iterations. The views are solved in two interleaved halves, and X is
//! the mean of the two solutions (as fast as one solve over all views).
//!
//! X is view-independent; each view's image keeps its own level and takes
//! only the detail its own pixels lose: `R'_v = R_v + s_v · (X − B_v(X))`
//! per channel, B_v(X) what view v would make of a sample that is X (X
//! seen through v's pixels by the forward model, then resampled by the
//! region images' own filter), s_v = ⟨R_v⟩ / ⟨B_v(X)⟩ (⟨·⟩ a local mean,
//! binomial, σ ≈ 2.8 texels; clamped to [1/4, 4]) so the detail keeps in
//! proportion to the view's level (a sheen, a highlight), values floored at
//! 0 and what the floor adds taken from the texels around
//! ([`keep_local_level`]). A frontal view, whose pixels are finest, takes little; a grazing one
//! most. The detail is added, not multiplied: at the thin dark lines of a
//! print, X / B_v(X) divides by small values and cost 2.2 dB (at novel
//! pairs, `printed-paper`) where the sum gains 0.6. An earlier version
//! gave every view the same factor X / M against the views' mean image M:
//! it sharpened the frontal views twice (−1.7 dB on the print at views
//! within 10° of the normal).
//!
//! That holds where the views agree on one image. Where they do not — a
//! glossy sample's highlights and sheen move with the view — X is a
//! compromise whose "detail" would print one view's highlight into the
//! others. So each texel and channel takes the detail in a share t ∈ [0, 1]
//! by how well X explains the pixels that cover it: their relative RMS
//! residual e (√(Σ w r²/Σ w b²), w their coverage of the texel), t = 1 for
//! e ≤ 0.3, 0 for e ≥ 0.6, linear between. On the simulator's rough metal e
//! (of the luminance) is 0.8–0.94 everywhere and its images stay as they
//! were; the woven fabric's median is 0.15–0.23.
//!
//! Nor is all of X's detail the sample's where the views agree: the solve
//! sharpens the pixels' noise as readily as the texture. The halves' noises
//! are independent, their textures the same, so the product of their log
//! detail (against M: (X / M) · (⟨M⟩ / ⟨X⟩)), locally averaged, estimates
//! the power of the detail that is the sample's; over the power of X's own
//! log detail it is Wiener's gain (signal over signal plus noise, clamped
//! to [0, 1]), which scales the share t above per texel and channel. A
//! smooth glossy sample (`red-plastic`, outside the library) lost 0.8 dB at
//! its captured pairs without it, all of it on the pairs without
//! highlights.
//!
//! A view's own pixels are noisy too. Its residual D_v = R_v − s_v · B_v(X)
//! is what it alone sees and its noise; where X explains the views (t), the
//! view keeps the share of D_v that is not the sensor's noise, Wiener's gain
//! 1 − ⟦N_v⟧ / ⟦D_v²⟧ with N_v the texel's variance from the sensor's model
//! (the region builder's [`TexelNoise`]) and ⟦·⟧ local means.
//!
//! Where X does not explain the views (a highlight one view alone sees),
//! that takes none of the noise out: then each image loses the noise its
//! texture does not hide, a local Wiener filter ([`denoise`]) against the
//! share of the sensor's variance the residual's gain left.

use crate::build::calibrate::ViewSampler;
use crate::build::linalg::Homography;
use crate::build::plane::cell_uv;
use crate::build::scanread::BicubicFilter;
use crate::camera::Frame;

/// Settings of [`sharpen_light`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SharpenOptions {
    /// Gradient penalty relative to the data term's mean diagonal.
    pub smoothness: f32,
    /// Conjugate-gradient iterations.
    pub iterations: usize,
    /// Points per side of a pixel's square in the forward model.
    pub points: usize,
    /// Shrink each view's own residual (its image less its level times X
    /// as it would see it) where the sensor's noise makes most of it.
    pub view_noise: bool,
}

impl Default for SharpenOptions {
    fn default() -> Self {
        SharpenOptions { smoothness: 0.08, iterations: 20, points: 4, view_noise: true }
    }
}

/// Largest ratio of levels (a view's to X's, and X's detail to the mean
/// image's) taken (and 1 / it the least).
const MAX_RATIO: f32 = 4.0;
/// Binomial passes of the local means that levels are taken over (σ ≈ 2.8
/// texels).
const LOCAL_PASSES: usize = 8;
/// The texels whose pixels X explains to this relative RMS residual
/// ([`misfit`]) take all of its detail, those beyond [`MISFIT_NONE`] none,
/// those between a share of it in proportion.
const MISFIT_FULL: f32 = 0.3;
const MISFIT_NONE: f32 = 0.6;
/// Binomial passes of the local means behind the detail's gain (σ ≈ 1.4
/// texels): the power of the detail and the part of it both halves hold.
const GAIN_PASSES: usize = 2;

/// One view's pixels on the sample: rows of the forward model (sparse:
/// texel, weight) and the pixels' values.
#[derive(Default)]
struct Rows {
    /// The view's index among the region images.
    view: usize,
    /// The frame window the rows' pixels lie in: its corner and size.
    origin: [usize; 2],
    extent: [usize; 2],
    /// Each row's pixel within the window (`y · width + x`).
    pixel: Vec<u32>,
    /// Weight of every row of the view: views count alike, however many
    /// pixels they see the sample with (as in the views' mean image).
    scale: f32,
    start: Vec<u32>,
    texel: Vec<u32>,
    weight: Vec<f32>,
    value: Vec<[f32; 3]>,
}

impl Rows {
    /// No rows yet, of view `view` in the frame window at `origin` of
    /// `extent` px.
    fn empty(view: usize, origin: [usize; 2], extent: [usize; 2]) -> Rows {
        Rows { view, origin, extent, scale: 1.0, start: vec![0], ..Rows::default() }
    }

    fn len(&self) -> usize {
        self.value.len()
    }

    /// Appends the row of window pixel `pixel` whose square the forward
    /// model samples at `uvs` (each point weighing `share`) on a `size`²
    /// grid: the points' bilinear taps summed per texel (`acc` the scratch).
    fn push_row(
        &mut self,
        pixel: u32,
        size: usize,
        uvs: &[[f64; 2]],
        share: f64,
        acc: &mut Vec<(u32, f32)>,
    ) {
        acc.clear();
        for &uv in uvs {
            bilinear_taps(size, uv, |t, w| {
                let w = (w * share) as f32;
                match acc.iter_mut().find(|a| a.0 == t) {
                    Some(a) => a.1 += w,
                    None => acc.push((t, w)),
                }
            });
        }
        for &(t, w) in acc.iter() {
            self.texel.push(t);
            self.weight.push(w);
        }
        self.start.push(self.texel.len() as u32);
        self.pixel.push(pixel);
    }

    fn row(&self, i: usize) -> (&[u32], &[f32]) {
        let (a, b) = (self.start[i] as usize, self.start[i + 1] as usize);
        (&self.texel[a..b], &self.weight[a..b])
    }

    /// Row `i` of the forward model applied to `x`: what the pixel would
    /// read if the sample were `x`.
    #[inline]
    fn forward(&self, i: usize, x: &[[f32; 3]]) -> [f32; 3] {
        let (t, w) = self.row(i);
        let mut y = [0.0f32; 3];
        for (&t, &w) in t.iter().zip(w) {
            let v = x[t as usize];
            for k in 0..3 {
                y[k] += w * v[k];
            }
        }
        y
    }

    /// `f(i, forward(i, x))` for every row `i` in order. Two rows' forward
    /// sums are taken at a time: each is a chain of dependent additions,
    /// and two chains keep the core busy.
    #[inline(always)]
    fn for_each_forward(&self, x: &[[f32; 3]], f: &mut impl FnMut(usize, [f32; 3])) {
        for i in (0..self.len() / 2).map(|p| 2 * p) {
            let [a, b] = self.forward_pair(i, x);
            f(i, a);
            f(i + 1, b);
        }
        if self.len() % 2 == 1 {
            f(self.len() - 1, self.forward(self.len() - 1, x));
        }
    }

    /// [`Rows::forward`] of rows `i` and `i + 1`, their sums interleaved
    /// (each in its own taps' order, as `forward` adds them).
    #[inline(always)]
    fn forward_pair(&self, i: usize, x: &[[f32; 3]]) -> [[f32; 3]; 2] {
        let ((ta, wa), (tb, wb)) = (self.row(i), self.row(i + 1));
        let (mut a, mut b) = ([0.0f32; 3], [0.0f32; 3]);
        let both = ta.len().min(tb.len());
        for j in 0..both {
            let (va, vb) = (x[ta[j] as usize], x[tb[j] as usize]);
            for k in 0..3 {
                a[k] += wa[j] * va[k];
                b[k] += wb[j] * vb[k];
            }
        }
        for (&t, &w) in ta[both..].iter().zip(&wa[both..]) {
            for k in 0..3 {
                a[k] += w * x[t as usize][k];
            }
        }
        for (&t, &w) in tb[both..].iter().zip(&wb[both..]) {
            for k in 0..3 {
                b[k] += w * x[t as usize][k];
            }
        }
        [a, b]
    }
}

/// What view `r` would make of a sample that is `x`: its pixels as the
/// forward model reads them from `x`, resampled at the S × S texel centres
/// the way the region images are ([`ViewSampler::region_sample`], its
/// `filters` in the rows' window): `x` blurred by this view's own pixels
/// and filter.
fn own_view_image(r: &Rows, fp: &ViewFootprint, x: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let (filters, edge) = (&fp.own, &fp.edge);
    let [w, h] = r.extent;
    let mut rgb = vec![0.0f32; w * h * 3];
    edge.for_each_forward(x, &mut |i, y| {
        rgb[edge.pixel[i] as usize * 3..][..3].copy_from_slice(&y);
    });
    r.for_each_forward(x, &mut |i, y| {
        rgb[r.pixel[i] as usize * 3..][..3].copy_from_slice(&y);
    });
    let window = Frame { width: w as u32, height: h as u32, rgb };
    filters.iter().map(|b| b.apply(&window).map(|v| v as f32)).collect()
}

/// An S × S (or 2S × 2S) RGB image, row-major.
pub type Image = Vec<[f32; 3]>;

/// What turns view `vi`'s frame value at uv into f · cos θi (`None`: not
/// usable there, e.g. unlit): the region images' own normalisation.
pub type PixelValue<'a> = dyn Fn(usize, [f64; 2], [f64; 3]) -> Option<[f32; 3]> + Sync + 'a;

/// The variance of view `vi`'s region image at texel `t` (row-major over
/// the S × S grid) where it holds the value given, per channel, from the
/// sensor's noise alone.
pub type TexelNoise<'a> = dyn Fn(usize, usize, [f32; 3]) -> [f32; 3] + Sync + 'a;

/// Every view's pixels on the sample and their rows of the forward model on
/// the S × S and the 2S × 2S grids. They depend on the views' homographies
/// alone, not on the light: made once per scan, each light's rows
/// ([`light_rows`]) are these less the pixels it leaves unusable, with its
/// frame's values.
pub struct Footprints {
    /// The frames' width and height, px.
    frame: [usize; 2],
    size: usize,
    views: Vec<ViewFootprint>,
}

impl std::fmt::Debug for Footprints {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let pixels: usize = self.views.iter().map(|v| v.centre.len()).sum();
        f.debug_struct("Footprints")
            .field("views", &self.views.len())
            .field("pixels", &pixels)
            .field("size", &self.size)
            .finish()
    }
}

/// One view's part of [`Footprints`].
struct ViewFootprint {
    /// Each pixel's index in the frame (`y · width + x`) and its centre's uv.
    frame_pixel: Vec<usize>,
    centre: Vec<[f64; 2]>,
    /// Its rows on the S × S and on the 2S × 2S grid (no values).
    grids: [Rows; 2],
    /// The region images' filter at each S × S texel, in the rows' frame
    /// window ([`own_view_image`]).
    own: Vec<BicubicFilter>,
    /// For a view whose region images read the pixels straddling the
    /// sample's edge, those pixels (and the ones within the clean margin)
    /// as the S × S forward model sees them: each reads the sample's part
    /// of its square, share × the mean of X there. Not rows of the solve.
    edge: Rows,
}

impl Footprints {
    /// The footprints of `samplers`' views in frames of `frame` (width,
    /// height) px on an S × S grid (`size`) and its 2S one, each pixel's
    /// square taken at `points` × `points` points.
    /// `straddles`: per view, whether its region images read the pixels
    /// straddling the sample's edge (empty: none does).
    pub fn new(
        samplers: &[ViewSampler],
        straddles: &[bool],
        frame: [usize; 2],
        size: usize,
        points: usize,
    ) -> Footprints {
        use rayon::prelude::*;
        let views = samplers
            .par_iter()
            .enumerate()
            .map(|(vi, s)| {
                let straddling = straddles.get(vi).copied().unwrap_or(false);
                ViewFootprint::new(vi, s, straddling, frame, &[size, 2 * size], points)
            })
            .collect();
        Footprints { frame, size, views }
    }
}

impl ViewFootprint {
    /// The rows of view `vi` on each grid of `sizes` (S × S texels each):
    /// every frame pixel whose square lies on the sample.
    fn new(
        vi: usize,
        sampler: &ViewSampler,
        straddling: bool,
        [width, height]: [usize; 2],
        sizes: &[usize],
        points: usize,
    ) -> ViewFootprint {
        let (mut frame_pixel, mut centre) = (Vec::new(), Vec::new());
        let h: &Homography = sampler.homography();
        let Some(inv) = h.inverse() else {
            let grids = std::array::from_fn(|_| Rows::empty(vi, [0, 0], [0, 0]));
            let edge = Rows::empty(vi, [0, 0], [0, 0]);
            return ViewFootprint { frame_pixel, centre, grids, own: Vec::new(), edge };
        };
        let [x0, y0, x1, y1] = h.window(1.0);
        let (x1, y1) = (x1.min(width), y1.min(height));
        let extent = [x1.saturating_sub(x0), y1.saturating_sub(y0)];
        let mut grids: [Rows; 2] = std::array::from_fn(|_| Rows::empty(vi, [x0, y0], extent));
        let mut acc: Vec<(u32, f32)> = Vec::with_capacity(32);
        let mut uvs: Vec<[f64; 2]> = Vec::with_capacity(points * points);
        let share = 1.0 / (points * points) as f64;
        let mut edge = Rows::empty(vi, [x0, y0], extent);
        // The frame points a pixel's square is sampled at, row by row.
        let square = |px: usize, py: usize| {
            (0..points * points).map(move |k| {
                [
                    px as f64 + ((k % points) as f64 + 0.5) / points as f64,
                    py as f64 + ((k / points) as f64 + 0.5) / points as f64,
                ]
            })
        };
        for py in y0..y1 {
            for px in x0..x1 {
                let pixel = ((py - y0) * extent[0] + (px - x0)) as u32;
                let p = [px as f64 + 0.5, py as f64 + 0.5];
                if sampler.pixel_on_sample(p) {
                    frame_pixel.push(py * width + px);
                    centre.push(inv.apply(p));
                    uvs.clear();
                    uvs.extend(square(px, py).map(|q| inv.apply(q)));
                    for (rows, &size) in grids.iter_mut().zip(sizes) {
                        rows.push_row(pixel, size, &uvs, share, &mut acc);
                    }
                } else if straddling && sampler.share(p) > 0.0 {
                    uvs.clear();
                    uvs.extend(
                        square(px, py)
                            .filter(|&q| sampler.point_on_sample(q))
                            .map(|q| inv.apply(q)),
                    );
                    edge.push_row(pixel, sizes[0], &uvs, share, &mut acc);
                    edge.value.push([0.0; 3]);
                }
            }
        }
        // The view's sampler in the window's pixels.
        let shifted = sampler.translated([-(x0 as f64), -(y0 as f64)]);
        let size = sizes[0];
        let own = (0..size * size)
            .map(|t| {
                let uv = cell_uv(t, size);
                if straddling {
                    shifted.region_filter_straddling(extent, uv)
                } else {
                    shifted.region_filter(extent, uv)
                }
            })
            .collect();
        ViewFootprint { frame_pixel, centre, grids, own, edge }
    }

    /// This view's rows on both grids under one light: the pixels whose
    /// `value` (frame value → f · cos θi) is usable and finite, with it.
    fn rows(&self, value: &PixelValue<'_>, frame: &Frame) -> [Rows; 2] {
        let mut all: [Rows; 2] = std::array::from_fn(|g| {
            Rows::empty(self.grids[g].view, self.grids[g].origin, self.grids[g].extent)
        });
        for (i, (&p, &centre)) in self.frame_pixel.iter().zip(&self.centre).enumerate() {
            let raw = std::array::from_fn(|k| frame.rgb[p * 3 + k] as f64);
            let Some(value) = value(self.grids[0].view, centre, raw) else {
                continue;
            };
            if !value.iter().all(|v| v.is_finite()) {
                continue;
            }
            for (rows, grid) in all.iter_mut().zip(&self.grids) {
                let (t, w) = grid.row(i);
                rows.texel.extend_from_slice(t);
                rows.weight.extend_from_slice(w);
                rows.start.push(rows.texel.len() as u32);
                rows.pixel.push(grid.pixel[i]);
                rows.value.push(value);
            }
        }
        all
    }
}

/// The four bilinear taps of uv on an S × S grid of texel centres (clamped
/// at the borders, like the region images' and the material's lookups).
#[inline]
fn bilinear_taps(size: usize, uv: [f64; 2], mut tap: impl FnMut(u32, f64)) {
    let (x0, x1, tx) = super::plane::cell_taps(size, uv[0]);
    let (y0, y1, ty) = super::plane::cell_taps(size, uv[1]);
    tap((y0 * size + x0) as u32, (1.0 - tx) * (1.0 - ty));
    tap((y0 * size + x1) as u32, tx * (1.0 - ty));
    tap((y1 * size + x0) as u32, (1.0 - tx) * ty);
    tap((y1 * size + x1) as u32, tx * ty);
}

/// The normal equations' operator: (AᵀA + λ L) x, L the 4-neighbour graph
/// Laplacian of the S × S grid.
fn normal_apply(rows: &[&Rows], size: usize, lambda: f32, x: &[[f32; 3]], out: &mut [[f32; 3]]) {
    out.fill([0.0; 3]);
    for r in rows {
        let mut scatter = |i: usize, y: [f32; 3]| {
            let (t, w) = r.row(i);
            let y = y.map(|v| v * r.scale);
            for (&t, &w) in t.iter().zip(w) {
                let o = &mut out[t as usize];
                for k in 0..3 {
                    o[k] += w * y[k];
                }
            }
        };
        r.for_each_forward(x, &mut scatter);
    }
    for yy in 0..size {
        for xx in 0..size {
            let t = yy * size + xx;
            let mut n = 0.0f32;
            let mut s = [0.0f32; 3];
            let mut add = |u: usize| {
                n += 1.0;
                for k in 0..3 {
                    s[k] += x[u][k];
                }
            };
            if xx > 0 {
                add(t - 1);
            }
            if xx + 1 < size {
                add(t + 1);
            }
            if yy > 0 {
                add(t - size);
            }
            if yy + 1 < size {
                add(t + size);
            }
            for k in 0..3 {
                out[t][k] += lambda * (n * x[t][k] - s[k]);
            }
        }
    }
}

fn dot3(a: &[[f32; 3]], b: &[[f32; 3]]) -> [f64; 3] {
    let mut s = [0.0f64; 3];
    for (x, y) in a.iter().zip(b) {
        for k in 0..3 {
            s[k] += x[k] as f64 * y[k] as f64;
        }
    }
    s
}

/// Solve for the image that explains every view's pixels (see the module
/// documentation), starting from `start`; `None` if no pixel is usable.
fn solve(
    rows: &[&Rows],
    size: usize,
    opts: &SharpenOptions,
    start: &[[f32; 3]],
) -> Option<Vec<[f32; 3]>> {
    let n = size * size;
    let mut rhs = vec![[0.0f32; 3]; n];
    let mut diag = vec![0.0f64; n];
    for r in rows {
        for i in 0..r.len() {
            let (t, w) = r.row(i);
            for (&t, &w) in t.iter().zip(w) {
                for (o, v) in rhs[t as usize].iter_mut().zip(r.value[i]) {
                    *o += r.scale * w * v;
                }
                diag[t as usize] += (r.scale * w * w) as f64;
            }
        }
    }
    let mean_diag = diag.iter().sum::<f64>() / n as f64;
    if mean_diag <= 0.0 {
        return None;
    }
    let lambda = (opts.smoothness as f64 * mean_diag) as f32;
    let mut x = start.to_vec();
    let mut ap = vec![[0.0f32; 3]; n];
    normal_apply(rows, size, lambda, &x, &mut ap);
    let mut res: Vec<[f32; 3]> =
        rhs.iter().zip(&ap).map(|(b, a)| std::array::from_fn(|k| b[k] - a[k])).collect();
    let mut p = res.clone();
    let mut rr = dot3(&res, &res);
    for _ in 0..opts.iterations {
        normal_apply(rows, size, lambda, &p, &mut ap);
        let pap = dot3(&p, &ap);
        let alpha: [f32; 3] =
            std::array::from_fn(|k| if pap[k] > 0.0 { (rr[k] / pap[k]) as f32 } else { 0.0 });
        for t in 0..n {
            for k in 0..3 {
                x[t][k] += alpha[k] * p[t][k];
                res[t][k] -= alpha[k] * ap[t][k];
            }
        }
        let rn = dot3(&res, &res);
        let beta: [f32; 3] =
            std::array::from_fn(|k| if rr[k] > 0.0 { (rn[k] / rr[k]) as f32 } else { 0.0 });
        for t in 0..n {
            for k in 0..3 {
                p[t][k] = res[t][k] + beta[k] * p[t][k];
            }
        }
        rr = rn;
    }
    Some(x)
}

/// Per texel and channel, the relative RMS residual of the pixels whose
/// squares cover it (weighted by their coverage): √(Σ w (A x − b)² / Σ w b²).
/// Per channel: a white highlight on a red body stands out in green and
/// blue however bright the red is.
fn misfit(rows: &[&Rows], size: usize, x: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let n = size * size;
    let (mut num, mut den) = (vec![[0.0f64; 3]; n], vec![[0.0f64; 3]; n]);
    for r in rows {
        let mut scatter = |i: usize, y: [f32; 3]| {
            let (t, w) = r.row(i);
            let b = r.value[i];
            for (&t, &w) in t.iter().zip(w) {
                let w = (r.scale * w) as f64;
                for k in 0..3 {
                    num[t as usize][k] += w * ((y[k] - b[k]) as f64).powi(2);
                    den[t as usize][k] += w * (b[k] as f64).powi(2);
                }
            }
        };
        r.for_each_forward(x, &mut scatter);
    }
    num.iter()
        .zip(&den)
        .map(|(a, b)| {
            std::array::from_fn(|k| {
                if b[k] > 0.0 { (a[k] / b[k]).sqrt() as f32 } else { f32::INFINITY }
            })
        })
        .collect()
}

/// A binomial blur (1 4 6 4 1)/16 along both axes of an S × S image,
/// edges clamped.
fn blur(img: &[[f32; 3]], size: usize) -> Vec<[f32; 3]> {
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    // Tap j of position i (0 ≤ i < size), clamped at the edges.
    let tap = |i: usize, j: usize| (i + j).saturating_sub(2).min(size - 1);
    // The five taps' weighted sum, in the taps' order (value by value: the
    // images are flat, a texel's three channels in turn).
    let sum = |v: [f32; 5]| {
        let mut acc = 0.0f32;
        for (w, v) in K.iter().zip(v) {
            acc += w * v;
        }
        acc
    };
    let line = 3 * size;
    let mut along_x = vec![[0.0f32; 3]; size * size];
    for (src, dst) in
        img.as_flattened().chunks_exact(line).zip(along_x.as_flattened_mut().chunks_exact_mut(line))
    {
        let clamped = |i: usize| {
            let (x, k) = (i / 3, i % 3);
            sum(std::array::from_fn(|j| src[3 * tap(x, j) + k]))
        };
        // Within the row (x from 2 to size − 3) no tap is clamped: a loop
        // the compiler vectorises.
        let inner = if size >= 5 { 6..line - 6 } else { 0..0 };
        for i in (0..inner.start).chain(inner.end.max(inner.start)..line) {
            dst[i] = clamped(i);
        }
        for i in inner {
            dst[i] = sum(std::array::from_fn(|j| src[i + 3 * j - 6]));
        }
    }
    // Along y row by row: the five source rows are contiguous.
    let mut out = vec![[0.0f32; 3]; size * size];
    let flat = along_x.as_flattened();
    for (y, dst) in out.as_flattened_mut().chunks_exact_mut(line).enumerate() {
        let rows: [&[f32]; 5] = std::array::from_fn(|j| &flat[tap(y, j) * line..][..line]);
        for (i, d) in dst.iter_mut().enumerate() {
            *d = sum(std::array::from_fn(|j| rows[j][i]));
        }
    }
    out
}

/// Per texel and channel of an `size`² all-views image `x` solved as the
/// mean of two `halves`, the share of its detail (against the views' mean
/// image `mean`) that both halves hold: Wiener's gain, signal over signal
/// plus noise, the signal's power estimated by the product of the halves'
/// log detail, whose noises are independent. `on_2s`: `x` is on the 2S
/// grid of an S × S one, and the local means cover the same area of the
/// sample as on the S grid ([`local_mean`]).
fn agreed_share(
    x: &[[f32; 3]],
    halves: &[Vec<[f32; 3]>; 2],
    mean: &[[f32; 3]],
    size: usize,
    on_2s: bool,
    level: [f32; 3],
) -> Vec<[f32; 3]> {
    let n = size * size;
    let local = |img: &[[f32; 3]], passes: usize| local_mean(img, size, on_2s, passes);
    let ml = local(mean, LOCAL_PASSES);
    // The detail factor of an all-views image: (x / m) · (⟨m⟩ / ⟨x⟩).
    let ratio_of = |x: &[[f32; 3]]| -> Vec<[f32; 3]> {
        let xl = local(x, LOCAL_PASSES);
        (0..n)
            .map(|t| {
                std::array::from_fn(|k| {
                    let (x, m, xl, ml) = (x[t][k], mean[t][k], xl[t][k], ml[t][k]);
                    let r = (x * ml) / (m * xl);
                    if m > level[k] && m > 0.0 && xl > 0.0 && r.is_finite() {
                        r.clamp(1.0 / MAX_RATIO, MAX_RATIO)
                    } else {
                        1.0
                    }
                })
            })
            .collect()
    };
    let ratio = ratio_of(x);
    let (ra, rb) = (ratio_of(&halves[0]), ratio_of(&halves[1]));
    let agreed = local(
        &(0..n).map(|t| std::array::from_fn(|k| ra[t][k].ln() * rb[t][k].ln())).collect::<Vec<_>>(),
        GAIN_PASSES,
    );
    let power =
        local(&ratio.iter().map(|r| r.map(|r| r.ln().powi(2))).collect::<Vec<_>>(), GAIN_PASSES);
    agreed
        .iter()
        .zip(&power)
        .map(|(a, p)| {
            std::array::from_fn(|k| if p[k] > 0.0 { (a[k] / p[k]).clamp(0.0, 1.0) } else { 0.0 })
        })
        .collect()
}

/// `passes` binomial passes of a `size`² image ([`blur`]); with `on_2s`
/// (`size` = 2S) the same area of the sample as on the S grid, and as
/// cheaply: the passes on the image's 2 × 2 means, looked up back on the
/// 2S grid (a local mean is smooth on the S grid's scale).
fn local_mean(img: &[[f32; 3]], size: usize, on_2s: bool, passes: usize) -> Image {
    if on_2s {
        let s = size / 2;
        double(&(0..passes).fold(halve(img, s), |a, _| blur(&a, s)), s)
    } else {
        (0..passes).fold(img.to_vec(), |a, _| blur(&a, size))
    }
}

/// Box mean of every 2 × 2 block of a 2S × 2S image: its value at the
/// S × S grid's texel centres when looked up bilinearly.
fn halve(fine: &[[f32; 3]], size: usize) -> Image {
    let f = 2 * size;
    (0..size * size)
        .map(|t| {
            let (x, y) = (2 * (t % size), 2 * (t / size));
            let a = [
                fine[y * f + x],
                fine[y * f + x + 1],
                fine[(y + 1) * f + x],
                fine[(y + 1) * f + x + 1],
            ];
            std::array::from_fn(|k| 0.25 * (a[0][k] + a[1][k] + a[2][k] + a[3][k]))
        })
        .collect()
}

/// An S × S image looked up bilinearly at the 2S × 2S grid's texel centres
/// (what the material's S × S lookups give there).
fn double(img: &[[f32; 3]], size: usize) -> Vec<[f32; 3]> {
    let f = 2 * size;
    (0..f * f)
        .map(|t| {
            let uv = [((t % f) as f64 + 0.5) / f as f64, ((t / f) as f64 + 0.5) / f as f64];
            super::regions::bilinear(size, img, uv).map(|v| v as f32)
        })
        .collect()
}

/// The views' rows on an S × S grid and on its 2S × 2S one under one light
/// (its frame's values through `value`), each view counting alike (`None`:
/// fewer than two views with usable pixels, nothing to check the detail
/// by).
fn light_rows(views: &Footprints, value: &PixelValue<'_>, frame: &Frame) -> Option<[Vec<Rows>; 2]> {
    let (mut coarse, mut fine) = (Vec::new(), Vec::new());
    for v in &views.views {
        let [c, f] = v.rows(value, frame);
        if c.len() > 0 {
            coarse.push(c);
            fine.push(f);
        }
    }
    if coarse.len() < 2 {
        return None;
    }
    for rows in [&mut coarse, &mut fine] {
        let typical = rows.iter().map(Rows::len).sum::<usize>() as f32 / rows.len() as f32;
        for r in rows.iter_mut() {
            r.scale = typical / r.len() as f32;
        }
    }
    Some([coarse, fine])
}

/// What [`solve_halves`] finds.
struct Solved {
    /// The all-views image.
    x: Image,
    /// How well it explains the views' pixels, in [0, 1].
    explained: Image,
    /// The share of its detail both halves agree on, in [0, 1].
    agreed: Image,
    /// How fully the views' pixels cover each texel ([`coverage`]).
    coverage: Vec<f32>,
}

impl Solved {
    /// The share of X's detail taken at texel `t`, channel `k`.
    fn trust(&self, t: usize, k: usize) -> f32 {
        self.explained[t][k] * self.agreed[t][k]
    }
}

/// Per texel of a `size`² grid, how fully the views' pixels cover it: the
/// sum over views of ω_v times the weights of the view's pixels on it,
/// over the median texel's, at most 1.
///
/// Only pixels wholly on the sample are rows, so within a pixel or two of
/// the sample's edge fewer of them cover a texel (on the default scanner
/// at 2S, 2 %, 24 %, 59 %, 84 % and 93 % of the median in the outermost
/// five texels). There X is mostly the smoothness term's extrapolation,
/// which both halves share: their agreement does not tell it from the
/// sample ([`fine_detail`]).
fn coverage(rows: &[&Rows], size: usize) -> Vec<f32> {
    let mut cov = vec![0.0f32; size * size];
    for r in rows {
        for i in 0..r.len() {
            let (t, w) = r.row(i);
            for (&t, &w) in t.iter().zip(w) {
                cov[t as usize] += w * r.scale;
            }
        }
    }
    let mut order = cov.clone();
    let mid = order.len() / 2;
    let typical = *order.select_nth_unstable_by(mid, f32::total_cmp).1;
    cov.iter().map(|&c| if typical > 0.0 { (c / typical).min(1.0) } else { 0.0 }).collect()
}

/// X solved from two interleaved halves of the views (`rows`) on a
/// `size`² grid (X the mean of the halves' solutions X_A and X_B),
/// starting from `start`: X and, per texel and channel, how well X
/// explains the pixels that cover it ([`misfit`]: 1 within
/// [`MISFIT_FULL`], 0 beyond [`MISFIT_NONE`]) and the share of X's detail
/// both halves agree on ([`agreed_share`] against `mean`, the views' mean
/// image on that grid). The share of X's detail taken, its trust, is their
/// product.
fn solve_halves(
    rows: &[Rows],
    size: usize,
    opts: &SharpenOptions,
    start: &[[f32; 3]],
    mean: &[[f32; 3]],
    on_2s: bool,
    level: [f32; 3],
) -> Option<Solved> {
    let half = |odd: usize| -> Option<Vec<[f32; 3]>> {
        let h: Vec<&Rows> = rows.iter().skip(odd).step_by(2).collect();
        solve(&h, size, opts, start)
    };
    let halves = [half(0)?, half(1)?];
    let x: Vec<[f32; 3]> = halves[0]
        .iter()
        .zip(&halves[1])
        .map(|(a, b)| std::array::from_fn(|k| 0.5 * (a[k] + b[k])))
        .collect();
    // Where the views do not agree on one image (a highlight or a sheen
    // that moves with the view: X explains little of their pixels), X's
    // detail is not the sample's; it is taken only where X explains them.
    // Nor is all of it the sample's where they do: the halves' agreement.
    let all: Vec<&Rows> = rows.iter().collect();
    let gain = agreed_share(&x, &halves, mean, size, on_2s, level);
    let explained = misfit(&all, size, &x)
        .iter()
        .map(|e| e.map(|e| ((MISFIT_NONE - e) / (MISFIT_NONE - MISFIT_FULL)).clamp(0.0, 1.0)))
        .collect();
    Some(Solved { x, explained, agreed: gain, coverage: coverage(&all, size) })
}

/// Give the region images of one light (`images[view]`, S × S) the detail
/// that all `views`' pixels of `frame` hold together (see the module
/// documentation), and return the light's log detail beyond S × S
/// ([`fine_detail`]). Each view's image then loses the sensor's noise its
/// texture does not hide and the detail did not take out ([`denoise`]).
/// `None`, images untouched: fewer than two views with usable pixels.
/// `unlit` (S × S, or empty: every texel lit) marks the
/// texels this light's beam left unlit: the images hold nothing there, and
/// within [`UNLIT_MARGIN`] texels of them the images keep their own
/// resampling and the log detail is 0 — the solve's and the local means'
/// reach across the boundary mixed the missing texels in (a white target
/// read 2× along it).
pub fn sharpen_light(
    views: &Footprints,
    value: &PixelValue<'_>,
    noise: &TexelNoise<'_>,
    frame: &Frame,
    opts: &SharpenOptions,
    images: &mut [Vec<[f32; 3]>],
    unlit: &[bool],
) -> Option<Vec<[f32; 3]>> {
    assert_eq!(views.views.len(), images.len(), "one region image per view");
    let dims = [frame.width as usize, frame.height as usize];
    assert_eq!(views.frame, dims, "footprints made for frames of this size");
    if images.is_empty() {
        return None;
    }
    let size = views.size;
    let n = size * size;
    let near_unlit = near_unlit(unlit, size);
    let mut mean = vec![[0.0f32; 3]; n];
    for img in images.iter() {
        for (m, v) in mean.iter_mut().zip(img) {
            for k in 0..3 {
                m[k] += v[k] / images.len() as f32;
            }
        }
    }
    let mean_total = channel_totals(&mean);
    // X is one image up to each view's level: the views' pixels are taken
    // over their view's gain against the mean image.
    let gains: Vec<[f32; 3]> = images.iter().map(|img| view_gain(img, mean_total)).collect();
    let levelled = |vi: usize, uv: [f64; 2], raw: [f64; 3]| -> Option<[f32; 3]> {
        let v = value(vi, uv, raw)?;
        Some(std::array::from_fn(|k| v[k] / gains[vi][k]))
    };
    let [rows, fine_rows] = light_rows(views, &levelled, frame)?;
    let level: [f32; 3] = mean_total.map(|t| (t / n as f64) as f32 * 1e-3);
    let solved = solve_halves(&rows, size, opts, &mean, &mean, false, level)?;
    // Before the images change: `None` leaves them untouched.
    let mut detail = fine_detail(&fine_rows, size, opts, &solved, &mean, level)?;
    drop(fine_rows);
    let x = &solved.x;
    let local = |img: &[[f32; 3]]| (0..LOCAL_PASSES).fold(img.to_vec(), |a, _| blur(&a, size));
    let denoiser = opts.view_noise.then(|| Denoiser::new(size));
    // Each view takes the detail its own pixels and resampling lose: X less
    // X as this view would see it, in proportion to the view's level. Where
    // X explains the views, what the view holds beyond its level times X as
    // it sees it (its residual: what it alone sees, and its noise) it keeps
    // in the share that is not the sensor's noise.
    for r in &rows {
        let own = own_view_image(r, &views.views[r.view], x);
        let image = &mut images[r.view];
        let (il, ol) = (local(image), local(&own));
        let scale: Image = (0..n)
            .map(|t| {
                std::array::from_fn(|k| {
                    if ol[t][k] > 0.0 {
                        (il[t][k] / ol[t][k]).clamp(1.0 / MAX_RATIO, MAX_RATIO)
                    } else {
                        1.0
                    }
                })
            })
            .collect();
        let residual: Image = (0..n)
            .map(|t| std::array::from_fn(|k| image[t][k] - scale[t][k] * own[t][k]))
            .collect();
        let keep = if opts.view_noise {
            residual_share(image, &residual, |t, v| noise(r.view, t, v), size)
        } else {
            vec![[1.0; 3]; n]
        };
        // The share of the sensor's noise the image keeps: all of it but
        // the residual's noise taken out here.
        let mut left = vec![[1.0f32; 3]; n];
        // What the floor at 0 adds, per texel and channel.
        let mut floored = vec![[0.0f32; 3]; n];
        for t in (0..n).filter(|&t| !near_unlit.get(t).copied().unwrap_or(false)) {
            for k in 0..3 {
                let s = scale[t][k];
                let out = solved.explained[t][k] * (1.0 - keep[t][k]);
                let v = &mut image[t][k];
                *v -= out * residual[t][k] - solved.trust(t, k) * s * (x[t][k] - own[t][k]);
                floored[t][k] = (-*v).max(0.0);
                *v = v.max(0.0);
                left[t][k] = 1.0 - out;
            }
        }
        keep_local_level(image, &floored, &near_unlit, size);
        if let Some(d) = &denoiser {
            d.denoise(image, &near_unlit, |t, v| {
                let q = noise(r.view, t, v);
                std::array::from_fn(|k| q[k] * left[t][k] * left[t][k])
            });
        }
    }
    if !near_unlit.is_empty() {
        let fine = 2 * size;
        for (t, d) in detail.iter_mut().enumerate() {
            if near_unlit[(t / fine / 2) * size + (t % fine) / 2] {
                *d = [0.0; 3];
            }
        }
    }
    Some(detail)
}

/// Binomial passes of the local sums over which [`keep_local_level`]
/// takes back what the floor at 0 added (σ ≈ 1.4 texels).
const FLOOR_PASSES: usize = 2;

/// Takes back from `image`'s texels near those floored at 0 what the floor
/// added (`floored`, per texel and channel): the detail a view takes is X
/// less X as the view sees it, whose local mean is 0, so where it would
/// take a dark texel below 0 the floor alone would raise the view's local
/// level above what its pixels measured. Each floored texel's amount is
/// taken from the texels around it in proportion to the local weights
/// ([`FLOOR_PASSES`]) times their values: texel t loses the share
/// ⟦floored / ⟦image⟧⟧ₜ of itself (⟦·⟧ the local mean; at most all of it),
/// which sums to the amount away from the image's edge. The texels of
/// `near_unlit` are kept.
fn keep_local_level(
    image: &mut [[f32; 3]],
    floored: &[[f32; 3]],
    near_unlit: &[bool],
    size: usize,
) {
    if floored.iter().all(|f| *f == [0.0; 3]) {
        return;
    }
    let level = local_mean(image, size, false, FLOOR_PASSES);
    let per_level: Image = floored
        .iter()
        .zip(&level)
        .map(|(f, l)| std::array::from_fn(|k| if l[k] > 0.0 { f[k] / l[k] } else { 0.0 }))
        .collect();
    let share = local_mean(&per_level, size, false, FLOOR_PASSES);
    for (t, v) in image.iter_mut().enumerate() {
        if near_unlit.get(t).copied().unwrap_or(false) {
            continue;
        }
        for k in 0..3 {
            v[k] *= (1.0 - share[t][k]).max(0.0);
        }
    }
}

/// Binomial passes of [`Denoiser`]'s local statistics (σ = 2.4 texels).
const DENOISE_PASSES: usize = 6;

/// Takes from region images (`size`², row-major) the sensor's noise that
/// their texture does not hide: per texel and channel the local linear
/// fit (the plane that a least-squares fit weighted by [`DENOISE_PASSES`]
/// binomial passes puts at the texel) plus Wiener's share of the texel's
/// departure from it, (σ² − σn²) / σ², σ² the local variance the plane
/// leaves, σn² the sensor's (`sensor(texel, local mean)`). A uniform
/// glossy sample's highlight, seen by one view alone and taken at a fifth
/// of the sensor's full scale at worst, varied by ≈ 1 % from texel to
/// texel, and the lobe's slope across the sample (±30 %) is no texture: a
/// local mean's variance took it for some (docs/benchmarks.md). The
/// texels of `near_unlit` ([`near_unlit`]: within [`UNLIT_MARGIN`] of one
/// the beam left unlit; empty: none) are kept.
#[derive(Debug)]
pub struct Denoiser {
    size: usize,
    /// Per texel, the local weights' means of (u, v, u v) and (u², v², 0),
    /// u and v in texels from the grid's centre.
    moments: [Image; 2],
}

impl Denoiser {
    pub fn new(size: usize) -> Denoiser {
        let at = |f: fn([f32; 2]) -> [f32; 3]| -> Image {
            let img: Image = (0..size * size).map(|t| f(texel_offset(t, size))).collect();
            local_mean(&img, size, false, DENOISE_PASSES)
        };
        Denoiser { size, moments: [at(|[u, v]| [u, v, u * v]), at(|[u, v]| [u * u, v * v, 0.0])] }
    }

    /// Denoises `image` (the docs of [`Denoiser`]).
    pub fn denoise(
        &self,
        image: &mut [[f32; 3]],
        near_unlit: &[bool],
        sensor: impl Fn(usize, [f32; 3]) -> [f32; 3],
    ) {
        let (size, n) = (self.size, self.size * self.size);
        assert_eq!(image.len(), n, "an S × S image");
        let local = |img: &[[f32; 3]]| local_mean(img, size, false, DENOISE_PASSES);
        // The image less its mean: single precision keeps the local
        // variance's digits.
        let total = channel_totals(image);
        let offset: [f32; 3] = total.map(|t| (t / n as f64) as f32);
        let centred: Image =
            image.iter().map(|v| std::array::from_fn(|k| v[k] - offset[k])).collect();
        let times = |f: &dyn Fn(usize) -> [f32; 3]| -> Image {
            let img: Image = centred
                .iter()
                .enumerate()
                .map(|(t, v)| {
                    let w = f(t);
                    std::array::from_fn(|k| v[k] * w[k])
                })
                .collect();
            local(&img)
        };
        let mean = local(&centred);
        let square = times(&|t| centred[t]);
        let along_u = times(&|t| [texel_offset(t, size)[0]; 3]);
        let along_v = times(&|t| [texel_offset(t, size)[1]; 3]);
        let noise = local(
            &(0..n)
                .map(|t| sensor(t, std::array::from_fn(|k| mean[t][k] + offset[k])))
                .collect::<Vec<_>>(),
        );
        let [first, second] = &self.moments;
        for t in (0..n).filter(|&t| !near_unlit.get(t).copied().unwrap_or(false)) {
            // The weights' covariance of u and v.
            let [mu, mv, muv] = first[t];
            let (suu, svv, suv) = (second[t][0] - mu * mu, second[t][1] - mv * mv, muv - mu * mv);
            let det = suu * svv - suv * suv;
            let [u, v] = texel_offset(t, size);
            for k in 0..3 {
                let (m, q) = (mean[t][k], noise[t][k]);
                let (cu, cv) = (along_u[t][k] - m * mu, along_v[t][k] - m * mv);
                let (a, b) = if det > 1e-6 * suu * svv {
                    ((svv * cu - suv * cv) / det, (suu * cv - suv * cu) / det)
                } else {
                    (0.0, 0.0)
                };
                let plane = m + a * (u - mu) + b * (v - mv);
                let var = (square[t][k] - m * m - (a * cu + b * cv)).max(0.0);
                let keep = if var > 0.0 { ((var - q) / var).clamp(0.0, 1.0) } else { 1.0 };
                if keep < 1.0 {
                    image[t][k] = offset[k] + plane + keep * (centred[t][k] - plane);
                }
            }
        }
    }
}

/// Texel `t` of an S × S grid, in texels from the grid's centre along u and v.
fn texel_offset(t: usize, size: usize) -> [f32; 2] {
    let centre = (size as f32 - 1.0) / 2.0;
    [(t % size) as f32 - centre, (t / size) as f32 - centre]
}

/// Texels within this many (Chebyshev distance) of one a beam left unlit
/// take no multi-view detail ([`sharpen_light`]).
pub const UNLIT_MARGIN: usize = 3;

/// The texels of an S × S `unlit` mask within [`UNLIT_MARGIN`] of an unlit
/// one (empty: none is unlit).
pub fn near_unlit(unlit: &[bool], size: usize) -> Vec<bool> {
    near(unlit, size, UNLIT_MARGIN)
}

/// The texels of an S × S `mask` (row-major; empty: none) within `reach`
/// texels of a marked one (Chebyshev distance); empty if none is marked.
fn near(mask: &[bool], size: usize, reach: usize) -> Vec<bool> {
    if !mask.contains(&true) || mask.len() != size * size {
        return Vec::new();
    }
    let mut out = vec![false; size * size];
    for (t, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let (x, y) = (t % size, t / size);
        for j in y.saturating_sub(reach)..=(y + reach).min(size - 1) {
            for i in x.saturating_sub(reach)..=(x + reach).min(size - 1) {
                out[j * size + i] = true;
            }
        }
    }
    out
}

/// Each channel's sum over an image's texels.
fn channel_totals(img: &[[f32; 3]]) -> [f64; 3] {
    std::array::from_fn(|k| img.iter().map(|v| v[k] as f64).sum())
}

/// A view's overall level against the views' mean image (whose
/// [`channel_totals`] are `mean_total`), per channel: Σ image / Σ mean over
/// the texels, clamped to [1 / [`MAX_RATIO`], [`MAX_RATIO`]] (1 where
/// either sum is not positive).
///
/// The views see a sample at different levels — a dark glossy one's
/// sheen, the colour calibration's residual per view — and near the
/// sample's edge fewer of them cover a texel (grazing views' coarser
/// pixels do not fit within its margin), so an X solved from their
/// pixels as they are takes the level of the views that cover each texel:
/// on a dark rubber 6 % below the mean image in the outermost texels,
/// 14 % on a smooth red plastic, a ramp that the views' images then took
/// as detail (docs/benchmarks.md, "The views' levels", session 64).
fn view_gain(image: &[[f32; 3]], mean_total: [f64; 3]) -> [f32; 3] {
    let total = channel_totals(image);
    std::array::from_fn(|k| {
        let (a, b) = (total[k], mean_total[k]);
        if a > 0.0 && b > 0.0 { ((a / b) as f32).clamp(1.0 / MAX_RATIO, MAX_RATIO) } else { 1.0 }
    })
}

/// Per texel and channel, the share of a view's `residual` that is not
/// its image's noise (`noise(texel, value)`: the variance of `image`'s
/// texel from the sensor alone): Wiener's gain 1 − ⟦noise⟧ / ⟦residual²⟧,
/// clamped to [0, 1], ⟦·⟧ local means ([`GAIN_PASSES`]); 1 where the
/// residual is 0 around the texel.
fn residual_share(
    image: &[[f32; 3]],
    residual: &[[f32; 3]],
    noise: impl Fn(usize, [f32; 3]) -> [f32; 3],
    size: usize,
) -> Image {
    let local = |img: Image| (0..GAIN_PASSES).fold(img, |a, _| blur(&a, size));
    let power = local(residual.iter().map(|d| d.map(|d| d * d)).collect());
    let noise = local(image.iter().enumerate().map(|(t, &v)| noise(t, v)).collect());
    power
        .iter()
        .zip(&noise)
        .map(|(p, q)| {
            std::array::from_fn(
                |k| if p[k] > 0.0 { (1.0 - q[k] / p[k]).clamp(0.0, 1.0) } else { 1.0 },
            )
        })
        .collect()
}

/// The light's detail beyond S × S, for the detail layer: X solved again on
/// the 2S × 2S grid (from X at S), and per texel and channel
/// t · ln((X / X_S) · (⟨X_S⟩ / ⟨X⟩)), X_S the S × S solution looked up
/// bilinearly on the 2S grid, ⟨·⟩ local means (σ ≈ 5.6 texels of 2S), t the
/// trust on that grid (the rows of [`light_rows`]' 2S grid), within the
/// sample's edge no stronger than inside ([`edge_limited`]). The S × S
/// images do not take X at 2S: there each view's pixels alias its finest
/// patterns into their levels, so the views' different levels (a sheen)
/// bend it.
fn fine_detail(
    rows: &[Rows],
    size: usize,
    opts: &SharpenOptions,
    at_s: &Solved,
    mean: &[[f32; 3]],
    level: [f32; 3],
) -> Option<Vec<[f32; 3]>> {
    let (fine, x) = (2 * size, &at_s.x);
    // Both grids' coverage: where the pixels leave X_S undetermined, the
    // ratio below is not the sample's either.
    let coarse_coverage = double(&at_s.coverage.iter().map(|&c| [c; 3]).collect::<Vec<_>>(), size);
    // From X at S, half the iterations do (the woven fabric scored the same
    // within 0.01 dB with all of them).
    let fine_opts = SharpenOptions { iterations: opts.iterations.div_ceil(2), ..*opts };
    let solved =
        solve_halves(rows, fine, &fine_opts, &double(x, size), &double(mean, size), true, level)?;
    let xf = &solved.x;
    // Against X at S looked up there, each over its own local level (the
    // two solves need not agree on it).
    let coarse = double(x, size);
    let local = |img: &[[f32; 3]]| local_mean(img, fine, true, LOCAL_PASSES);
    let (fl, cl) = (local(xf), local(&coarse));
    let detail: Image = (0..fine * fine)
        .map(|t| {
            std::array::from_fn(|k| {
                let (f, c) = (xf[t][k] * cl[t][k], coarse[t][k] * fl[t][k]);
                if f > level[k] && c > level[k] {
                    solved.trust(t, k) * (f / c).clamp(1.0 / MAX_RATIO, MAX_RATIO).ln()
                } else {
                    0.0
                }
            })
        })
        .collect();
    let weight: Vec<f32> =
        (0..fine * fine).map(|t| (coarse_coverage[t][0] * solved.coverage[t]).powi(4)).collect();
    Some(edge_limited(&detail, &weight))
}

/// Log detail on the 2S grid (`fine`²) kept at the texels the pixels
/// cover (`weight` 1) and, where they do not (weight 0: the sample's edge),
/// no stronger than where they do: scaled by w + (1 − w) · min(1, √(P_w /
/// P_e)) per channel, P_w the detail's mean power weighted by w and P_e
/// weighted by 1 − w.
///
/// A sample whose detail is as strong at its edge as inside (a weave, a
/// print's lines) keeps it to the edge; one whose detail is faint (fine
/// bumps on a near-black rubber) loses the edge's extrapolation, which its
/// detail layer's light components had been fitted to (docs/benchmarks.md,
/// "The sample's edges", session 63). w is the two grids' coverage to the
/// fourth power.
fn edge_limited(detail: &[[f32; 3]], weight: &[f32]) -> Image {
    let (mut covered, mut edge) = ([0.0f64; 3], [0.0f64; 3]);
    let (mut sum_w, mut sum_e) = (0.0f64, 0.0f64);
    for (d, &w) in detail.iter().zip(weight) {
        let w = w as f64;
        for k in 0..3 {
            let p = (d[k] as f64).powi(2);
            covered[k] += w * p;
            edge[k] += (1.0 - w) * p;
        }
        sum_w += w;
        sum_e += 1.0 - w;
    }
    let limit: [f32; 3] = std::array::from_fn(|k| {
        let (c, e) =
            (covered[k] / sum_w.max(f64::MIN_POSITIVE), edge[k] / sum_e.max(f64::MIN_POSITIVE));
        if e > c { (c / e).sqrt() as f32 } else { 1.0 }
    });
    detail
        .iter()
        .zip(weight)
        .map(|(d, &w)| std::array::from_fn(|k| d[k] * (w + (1.0 - w) * limit[k])))
        .collect()
}

/// The detail layer shared by every pair, from the lights' log detail
/// ([`sharpen_light`]; a light without one counts as no detail): their
/// mean, in the share that the two halves of the lights (alternate lights)
/// agree on — Wiener's gain again, now against what differs between lights
/// (a shadow's or a sheen's direction, each light's own noise) — and
/// exponentiated. `None` if no light has one.
pub fn shared_detail(details: &[Option<Vec<[f32; 3]>>], fine: usize) -> Option<Vec<[f32; 3]>> {
    if details.iter().all(Option::is_none) {
        return None;
    }
    let mean_of = |odd: Option<usize>| -> Vec<[f32; 3]> {
        let mut sum = vec![[0.0f32; 3]; fine * fine];
        let mut n = 0usize;
        for (l, d) in details.iter().enumerate() {
            if odd.is_some_and(|o| l % 2 != o) {
                continue;
            }
            n += 1;
            for (s, v) in sum.iter_mut().zip(d.iter().flatten()) {
                for k in 0..3 {
                    s[k] += v[k];
                }
            }
        }
        sum.into_iter().map(|s| s.map(|v| v / n.max(1) as f32)).collect()
    };
    let (d, da, db) = (mean_of(None), mean_of(Some(0)), mean_of(Some(1)));
    let smooth = |img: Vec<[f32; 3]>| local_mean(&img, fine, true, GAIN_PASSES);
    let agreed =
        smooth(da.iter().zip(&db).map(|(a, b)| std::array::from_fn(|k| a[k] * b[k])).collect());
    let power = smooth(d.iter().map(|v| v.map(|v| v * v)).collect());
    Some(
        (0..fine * fine)
            .map(|t| {
                std::array::from_fn(|k| {
                    let (a, p) = (agreed[t][k], power[t][k]);
                    let g = if p > 0.0 { (a / p).clamp(0.0, 1.0) } else { 0.0 };
                    (g * d[t][k]).exp()
                })
            })
            .collect(),
    )
}

/// Most light components of the detail layer ([`light_components`]).
pub const MAX_LIGHT_COMPONENTS: usize = 2;
/// A light component fitted on one half of the lights is kept if the
/// other half holds, per light, at least this share of the energy it holds
/// in its own ([`light_components`]).
const HELD_OUT_SHARE: f64 = 0.5;

/// The detail layer: a factor shared by every pair, and what changes with
/// the light beyond it ([`detail_layer`]).
#[derive(Debug, Clone, PartialEq)]
pub struct DetailLayer {
    /// 2S × 2S RGB factors shared by every pair ([`shared_detail`]).
    pub shared: Image,
    /// The light components: 2S × 2S RGB log detail, each scaled to
    /// max |value| = 1 (none when the lights agree).
    pub bases: Vec<Image>,
    /// Per light (in region-set order), one coefficient per component.
    pub coefficients: Vec<Vec<f32>>,
}

impl DetailLayer {
    /// The factor for light `li` at one point, `at` giving each of the
    /// layer's images (the shared factor, each component) there.
    pub fn factor(&self, li: usize, at: impl Fn(&[[f32; 3]]) -> [f32; 3]) -> [f32; 3] {
        let mut log = [0.0f32; 3];
        for (b, c) in self.bases.iter().zip(&self.coefficients[li]) {
            let v = at(b);
            for k in 0..3 {
                log[k] += c * v[k];
            }
        }
        scanner_shading::detail_factor(at(&self.shared), log)
    }
}

/// The detail layer from the lights' log detail ([`sharpen_light`]; a
/// light without one counts as no detail): the shared factor
/// ([`shared_detail`]) and the light components ([`light_components`]).
/// `None` if no light has detail.
pub fn detail_layer(details: &[Option<Image>], fine: usize) -> Option<DetailLayer> {
    let shared = shared_detail(details, fine)?;
    let (bases, coefficients) = light_components(details, fine);
    Some(DetailLayer { shared, bases, coefficients })
}

/// What changes with the light in the lights' log detail: the leading
/// principal components (up to [`MAX_LIGHT_COMPONENTS`]) of each light's
/// log detail less the lights' mean, and each light's coefficients on them
/// (zero for a light without detail). A grazing light shadows a pore or a
/// grain that a steep one lights; one shared factor gives them the mean.
///
/// The components are those of the lights' Gram matrix (one row per light,
/// [`symmetric_eigen`](super::linalg::symmetric_eigen)). A component is
/// kept only if the lights agree on it: fitted on one half of the lights
/// (alternate lights) it must hold at least [`HELD_OUT_SHARE`] of its
/// energy in the other half, both ways — noise, and detail that one light
/// alone shows, fail. The lights' own coefficients are not shrunk: each
/// is the light's projection on a component, which averages over every
/// texel.
pub fn light_components(details: &[Option<Image>], fine: usize) -> (Vec<Image>, Vec<Vec<f32>>) {
    use rayon::prelude::*;
    let n = fine * fine;
    let nl = details.len();
    let with: Vec<usize> = (0..nl).filter(|&l| details[l].is_some()).collect();
    let none = (Vec::new(), vec![Vec::new(); nl]);
    if with.len() < 4 {
        return none;
    }
    // Residuals from the mean over all lights (a light without detail
    // counting as zero, as in the shared factor).
    let mut mean = vec![[0.0f64; 3]; n];
    for d in details.iter().flatten() {
        for (m, v) in mean.iter_mut().zip(d) {
            for k in 0..3 {
                m[k] += v[k] as f64 / nl as f64;
            }
        }
    }
    let resid: Vec<Vec<f32>> = with
        .par_iter()
        .map(|&l| {
            let d = details[l].as_ref().expect("a light with detail");
            d.iter()
                .zip(&mean)
                .flat_map(|(v, m)| (0..3).map(move |k| (v[k] as f64 - m[k]) as f32))
                .collect()
        })
        .collect();
    let dot =
        |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
    let m = resid.len();
    let gram: Vec<f64> = (0..m * m)
        .into_par_iter()
        .map(|ij| {
            let (i, j) = (ij / m, ij % m);
            if j <= i { dot(&resid[i], &resid[j]) } else { 0.0 }
        })
        .collect();
    let gram_of = |rows: &[usize]| -> Vec<f64> {
        let k = rows.len();
        (0..k * k)
            .map(|ij| {
                let (a, b) = (rows[ij / k], rows[ij % k]);
                gram[a.max(b) * m + a.min(b)]
            })
            .collect()
    };
    // Unit components (as images) of a set of residual rows.
    let components = |rows: &[usize], count: usize| -> Vec<Vec<f32>> {
        let (values, vectors) = super::linalg::symmetric_eigen(rows.len(), &gram_of(rows));
        values
            .iter()
            .zip(&vectors)
            .take(count)
            .filter(|(v, _)| **v > 0.0)
            .map(|(v, vec)| {
                let mut b = vec![0.0f32; 3 * n];
                for (&r, &w) in rows.iter().zip(vec) {
                    let w = (w / v.sqrt()) as f32;
                    b.iter_mut().zip(&resid[r]).for_each(|(b, x)| *b += w * x);
                }
                b
            })
            .collect()
    };
    let all: Vec<usize> = (0..m).collect();
    let halves = [0, 1].map(|h| all.iter().copied().filter(|i| i % 2 == h).collect::<Vec<_>>());
    let half_components = halves.each_ref().map(|h| components(h, MAX_LIGHT_COMPONENTS));
    // Whether the r-th component fitted on half h holds, per light, at
    // least HELD_OUT_SHARE of its energy in the other half (the components
    // are orthonormal: each one's energy in a row is its own projection's).
    let agrees = |h: usize, r: usize| -> bool {
        let Some(c) = half_components[h].get(r - 1) else {
            return false;
        };
        let energy = |rows: &[usize]| {
            rows.iter().map(|&i| dot(c, &resid[i]).powi(2)).sum::<f64>() / rows.len() as f64
        };
        energy(&halves[1 - h]) >= HELD_OUT_SHARE * energy(&halves[h])
    };
    let keep = (1..=MAX_LIGHT_COMPONENTS).take_while(|&r| agrees(0, r) && agrees(1, r)).count();
    if keep == 0 {
        return none;
    }
    let comps = components(&all, keep);
    let mut coefficients = vec![vec![0.0f32; comps.len()]; nl];
    let mut bases = Vec::with_capacity(comps.len());
    for (r, c) in comps.iter().enumerate() {
        let top = c.iter().fold(0.0f32, |a, x| a.max(x.abs())).max(f32::MIN_POSITIVE);
        for (i, &l) in with.iter().enumerate() {
            coefficients[l][r] = (dot(c, &resid[i]) * top as f64) as f32;
        }
        bases.push(c.chunks_exact(3).map(|v| [v[0] / top, v[1] / top, v[2] / top]).collect());
    }
    (bases, coefficients)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur is (1 4 6 4 1)/16 along x, then along y, each tap clamped
    /// to the image — bit for bit, at sizes from 1 to wider than the kernel.
    #[test]
    fn the_blur_is_the_clamped_binomial_kernel_along_each_axis() {
        const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
        for size in [1usize, 2, 3, 4, 7] {
            let img: Image = (0..size * size)
                .map(|t| std::array::from_fn(|k| ((t * 7 + k * 13) % 11) as f32 * 0.37 - 1.0))
                .collect();
            let clamp = |i: isize| i.clamp(0, size as isize - 1) as usize;
            let pass = |src: &Image, along_x: bool| -> Image {
                (0..size * size)
                    .map(|t| {
                        let (x, y) = ((t % size) as isize, (t / size) as isize);
                        let mut acc = [0.0f32; 3];
                        for (j, w) in K.iter().enumerate() {
                            let o = j as isize - 2;
                            let v = if along_x {
                                src[y as usize * size + clamp(x + o)]
                            } else {
                                src[clamp(y + o) * size + x as usize]
                            };
                            for k in 0..3 {
                                acc[k] += w * v[k];
                            }
                        }
                        acc
                    })
                    .collect()
            };
            assert_eq!(blur(&img, size), pass(&pass(&img, true), false), "size {size}");
        }
    }

    /// A sample with detail at 12–13 cycles across: finer than the views'
    /// ≈ 20 px resolve, coarser than the 32² grid's Nyquist.
    fn pattern(uv: [f64; 2]) -> [f32; 3] {
        let tau = std::f64::consts::TAU;
        let a = (tau * 12.5 * uv[0]).sin() * (tau * 12.0 * uv[1]).sin();
        let b = (tau * (13.0 * uv[0] + 3.0 * uv[1])).cos();
        [0.5 + 0.3 * a, 0.4 + 0.2 * b, 0.3 + 0.15 * a - 0.1 * b].map(|x| x as f32)
    }

    /// Views of the unit square: rotated, foreshortened by up to 2×, ≈ 20 px
    /// across, at sub-pixel offsets, each in its own 48 px cell of a frame.
    fn homographies() -> Vec<Homography> {
        (0..12)
            .map(|k| {
                let kf = k as f64;
                let (s, c) = (0.7 * kf + 0.3).sin_cos();
                let (sx, sy) = (20.0 + 0.37 * kf, 20.0 / (1.0 + 0.09 * kf));
                let (cx, cy) = (
                    24.0 + 48.0 * (k % 4) as f64 + 0.13 * kf,
                    24.0 + 48.0 * (k / 4) as f64 + 0.29 * kf,
                );
                // px = centre + R · diag(sx, sy) · (uv − ½)
                let (a, b, d, e) = (c * sx, -s * sy, s * sx, c * sy);
                Homography([a, b, cx - 0.5 * (a + b), d, e, cy - 0.5 * (d + e), 0.0, 0.0, 1.0])
            })
            .collect()
    }

    /// [`homographies`] and their samplers.
    fn views() -> (Vec<Homography>, Vec<ViewSampler>) {
        let hs = homographies();
        let samplers = hs.iter().map(|h| ViewSampler::new(*h)).collect();
        (hs, samplers)
    }

    /// The frame: each pixel the mean of `sample` over its square (8 × 8
    /// points), 0 off the sample; view k's values scaled by `level(k)`.
    fn frame(
        hs: &[Homography],
        sample: impl Fn([f64; 2]) -> [f32; 3],
        level: impl Fn(usize) -> f32,
    ) -> Frame {
        let (w, h) = (192usize, 144usize);
        let mut rgb = vec![0.0f32; w * h * 3];
        for (k, hom) in hs.iter().enumerate() {
            let inv = hom.inverse().unwrap();
            let [x0, y0, x1, y1] = hom.window(1.0);
            for y in y0..y1.min(h) {
                for x in x0..x1.min(w) {
                    let mut acc = [0.0f32; 3];
                    for sy in 0..8 {
                        for sx in 0..8 {
                            let uv = inv.apply([
                                x as f64 + (sx as f64 + 0.5) / 8.0,
                                y as f64 + (sy as f64 + 0.5) / 8.0,
                            ]);
                            if uv.iter().all(|c| (0.0..1.0).contains(c)) {
                                let v = sample(uv);
                                for c in 0..3 {
                                    acc[c] += v[c] * level(k) / 64.0;
                                }
                            }
                        }
                    }
                    rgb[(y * w + x) * 3..][..3].copy_from_slice(&acc);
                }
            }
        }
        Frame { width: w as u32, height: h as u32, rgb }
    }

    const S: usize = 32;

    /// No sensor noise: every view keeps its whole residual.
    static NOISELESS: fn(usize, usize, [f32; 3]) -> [f32; 3] = |_, _, _| [0.0; 3];

    /// Each view's own resampling at the texel centres (the region images
    /// without the other views).
    fn own_view(samplers: &[ViewSampler], f: &Frame) -> Vec<Vec<[f32; 3]>> {
        samplers
            .iter()
            .map(|v| {
                (0..S * S)
                    .map(|t| {
                        let uv =
                            [((t % S) as f64 + 0.5) / S as f64, ((t / S) as f64 + 0.5) / S as f64];
                        v.region_sample(f, uv).map(|x| x as f32)
                    })
                    .collect()
            })
            .collect()
    }

    /// The views' footprints on frames like `f`, at S.
    fn footprints(samplers: &[ViewSampler], f: &Frame, opts: &SharpenOptions) -> Footprints {
        Footprints::new(samplers, &[], [f.width as usize, f.height as usize], S, opts.points)
    }

    fn sharpened(
        samplers: &[ViewSampler],
        f: &Frame,
        mut images: Vec<Vec<[f32; 3]>>,
    ) -> Vec<Vec<[f32; 3]>> {
        let identity = |_: usize, _: [f64; 2], s: [f64; 3]| Some(s.map(|v| v as f32));
        let opts = SharpenOptions::default();
        sharpen_light(
            &footprints(samplers, f, &opts),
            &identity,
            &NOISELESS,
            f,
            &opts,
            &mut images,
            &[],
        );
        images
    }

    /// RMS difference of the images from `truth` at the texel centres,
    /// over the inner texels (the outermost two rows and columns left out:
    /// the views' edges).
    fn rms(images: &[Vec<[f32; 3]>], truth: impl Fn(usize, [f64; 2]) -> [f32; 3]) -> f64 {
        let (mut sum, mut n) = (0.0, 0usize);
        for (k, img) in images.iter().enumerate() {
            for (t, v) in img.iter().enumerate() {
                let (x, y) = (t % S, t / S);
                if x < 2 || y < 2 || x + 2 >= S || y + 2 >= S {
                    continue;
                }
                let w = truth(k, [(x as f64 + 0.5) / S as f64, (y as f64 + 0.5) / S as f64]);
                for c in 0..3 {
                    sum += ((v[c] - w[c]) as f64).powi(2);
                    n += 1;
                }
            }
        }
        (sum / n as f64).sqrt()
    }

    #[test]
    fn all_views_resolve_detail_no_view_does() {
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |_| 1.0);
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        let (before, after) = (rms(&own, |_, uv| pattern(uv)), rms(&sharp, |_, uv| pattern(uv)));
        let db = 20.0 * (before / after).log10();
        println!("own views {before:.4}, all views {after:.4} RMS: {db:.2} dB");
        // 2.26 dB; 2.57 if the detail were taken whether or not two halves
        // of 6 views agree on it (the noise test below is why it is not).
        assert!(db >= 1.8, "{db:.2} dB");
    }

    #[test]
    fn the_detail_layer_holds_what_s_cannot() {
        // Looked up between the S × S texel centres (at the 2S grid's), the
        // images hold a bilinear blend; the layer restores the sample there.
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |_| 1.0);
        let mut images = own_view(&samplers, &f);
        let identity = |_: usize, _: [f64; 2], s: [f64; 3]| Some(s.map(|v| v as f32));
        let opts = SharpenOptions::default();
        let views = footprints(&samplers, &f, &opts);
        let log = sharpen_light(&views, &identity, &NOISELESS, &f, &opts, &mut images, &[])
            .expect("a layer");
        let layer = shared_detail(&[Some(log.clone()), Some(log)], 2 * S).expect("a layer");
        let fine = 2 * S;
        let (mut with, mut without, mut n) = (0.0, 0.0, 0usize);
        for img in &images {
            for (t, d) in layer.iter().enumerate() {
                let (x, y) = (t % fine, t / fine);
                if x < 4 || y < 4 || x + 4 >= fine || y + 4 >= fine {
                    continue;
                }
                let uv = [(x as f64 + 0.5) / fine as f64, (y as f64 + 0.5) / fine as f64];
                let v = super::super::regions::bilinear(S, img, uv);
                let w = pattern(uv);
                for c in 0..3 {
                    without += (v[c] - w[c] as f64).powi(2);
                    with += (v[c] * d[c] as f64 - w[c] as f64).powi(2);
                    n += 1;
                }
            }
        }
        let (with, without) = ((with / n as f64).sqrt(), (without / n as f64).sqrt());
        let db = 20.0 * (without / with).log10();
        println!("at the 2S grid: images {without:.4}, × the layer {with:.4} RMS: {db:.2} dB");
        assert!(db >= 0.5, "{db:.2} dB");
    }

    /// Only pixels wholly on the sample are rows: the texels at its edge
    /// are covered by fewer of them, the inner ones alike, on both grids.
    #[test]
    fn the_sample_s_edge_is_covered_by_fewer_pixels() {
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |_| 1.0);
        let identity = |_: usize, _: [f64; 2], s: [f64; 3]| Some(s.map(|v| v as f32));
        let views = footprints(&samplers, &f, &SharpenOptions::default());
        let [coarse, fine] = light_rows(&views, &identity, &f).expect("rows");
        for (rows, size) in [(coarse, S), (fine, 2 * S)] {
            let rows: Vec<&Rows> = rows.iter().collect();
            let c = coverage(&rows, size);
            let ring = |t: usize| {
                let (x, y) = (t % size, t / size);
                x.min(y).min(size - 1 - x).min(size - 1 - y)
            };
            let at = |r: usize| (0..size * size).filter(move |&t| ring(t) == r).map(|t| c[t]);
            let edge = at(0).fold(0.0f32, f32::max);
            let inner = (size / 8..size / 2).flat_map(at).fold(1.0f32, f32::min);
            println!("{size}²: coverage at the edge ≤ {edge:.3}, inside ≥ {inner:.3}");
            assert!(c.iter().all(|c| (0.0..=1.0).contains(c)));
            assert!(edge < 0.6 && inner > 0.8, "{edge} {inner}");
        }
    }

    /// Where the pixels cover the texels the detail is kept as it is;
    /// where they do not, it is kept as strong as the covered texels hold
    /// it, no stronger: a weave's detail to the edge, not a faint sample's
    /// extrapolated edge.
    #[test]
    fn the_edge_s_detail_is_no_stronger_than_inside() {
        let fine = 32;
        let edge = |t: usize| {
            let (x, y) = (t % fine, t / fine);
            x.min(y).min(fine - 1 - x).min(fine - 1 - y) < 3
        };
        let weight: Vec<f32> = (0..fine * fine).map(|t| if edge(t) { 0.0 } else { 1.0 }).collect();
        // A checkerboard of ±a inside, ±b at the edge.
        let detail = |a: f32, b: f32| -> Image {
            (0..fine * fine)
                .map(|t| {
                    let s = if (t % fine + t / fine) % 2 == 0 { 1.0 } else { -1.0 };
                    [s * if edge(t) { b } else { a }; 3]
                })
                .collect()
        };
        let rms = |img: &Image, at_edge: bool| {
            let v: Vec<f32> =
                (0..fine * fine).filter(|&t| edge(t) == at_edge).map(|t| img[t][0]).collect();
            (v.iter().map(|x| x * x).sum::<f32>() / v.len() as f32).sqrt()
        };
        // Faint inside, strong at the edge: the edge's brought down to the
        // inside's.
        let faint = edge_limited(&detail(0.01, 0.1), &weight);
        let (e, i) = (rms(&faint, true), rms(&faint, false));
        println!("faint sample: edge {e:.4}, inside {i:.4}");
        assert!((i - 0.01).abs() < 1e-6 && (e - 0.01).abs() < 1e-4, "{e} {i}");
        // As strong at the edge as inside: kept.
        let weave = detail(0.1, 0.1);
        let kept = edge_limited(&weave, &weight);
        assert!(kept.iter().zip(&weave).all(|(a, b)| (a[0] - b[0]).abs() < 0.1 * b[0].abs()));
        // Fully covered: nothing changes.
        let all = edge_limited(&detail(0.01, 0.1), &vec![1.0; fine * fine]);
        assert_eq!(all, detail(0.01, 0.1));
    }

    #[test]
    fn lights_that_disagree_on_the_detail_leave_the_layer_flat() {
        // Two lights whose detail is opposite (a shadow that moves with the
        // light): their halves do not agree, the layer stays near 1.
        let n = 16 * 16;
        let a: Vec<[f32; 3]> = (0..n).map(|t| [if t % 2 == 0 { 0.3 } else { -0.3 }; 3]).collect();
        let b: Vec<[f32; 3]> = a.iter().map(|v| v.map(|x| -x)).collect();
        let flat = shared_detail(&[Some(a.clone()), Some(b)], 16).unwrap();
        assert!(flat.iter().flatten().all(|&x| (x - 1.0).abs() < 1e-6), "{:?}", &flat[..2]);
        // Two that agree keep it.
        let kept = shared_detail(&[Some(a.clone()), Some(a.clone())], 16).unwrap();
        for (k, v) in kept.iter().zip(&a) {
            assert!((k[0].ln() - v[0]).abs() < 1e-5, "{} against {}", k[0].ln(), v[0]);
        }
        assert!(shared_detail(&[None, None], 16).is_none());
    }

    /// Log details of `lights` lights on a 32² grid: a shared pattern, the
    /// light's share `s(l)` of a second one, and the light's own noise.
    fn light_details(lights: usize, s: impl Fn(usize) -> f32, noise: f32) -> Vec<Option<Image>> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        (0..lights)
            .map(|l| {
                Some(
                    (0..32 * 32)
                        .map(|t| {
                            let (x, y) = ((t % 32) as f32, (t / 32) as f32);
                            let shared = 0.2 * (0.9 * x).sin() * (0.7 * y).cos();
                            let moving = 0.3 * (0.5 * x + 1.3 * y).sin();
                            std::array::from_fn(|k| {
                                shared
                                    + s(l) * moving * (1.0 - 0.2 * k as f32)
                                    + noise * rng.random_range(-1.0..1.0)
                            })
                        })
                        .collect(),
                )
            })
            .collect()
    }

    #[test]
    fn light_components_hold_what_changes_with_the_light() {
        // A pattern whose strength changes with the light (a shadow that
        // grows as the light drops): one component, and each light's
        // coefficients rebuild its detail to within its noise.
        let share = |l: usize| (l as f32 * 0.7).cos();
        let details = light_details(12, share, 0.02);
        let layer = detail_layer(&details, 32).unwrap();
        assert_eq!(layer.bases.len(), 1, "one component");
        let top = layer.bases[0].iter().flatten().fold(0.0f32, |a, x| a.max(x.abs()));
        assert!((top - 1.0).abs() < 1e-6, "scaled to max |value| = 1");
        let mean: Image = (0..32 * 32)
            .map(|t| {
                std::array::from_fn(|k| {
                    details.iter().flatten().map(|d| d[t][k]).sum::<f32>() / 12.0
                })
            })
            .collect();
        for (l, d) in details.iter().enumerate() {
            let d = d.as_ref().unwrap();
            let (mut miss, mut power) = (0.0f64, 0.0f64);
            for t in 0..32 * 32 {
                for k in 0..3 {
                    let e = (d[t][k] - mean[t][k]) as f64;
                    let r = (layer.coefficients[l][0] * layer.bases[0][t][k]) as f64;
                    miss += (e - r).powi(2);
                    power += e * e;
                }
            }
            // The noise alone is 0.02² / 3 per value (uniform), 1.3e-4; the
            // moving pattern's power 0.3² / 2 · share² ≈ 0.03 · share².
            assert!(miss / (3.0 * 1024.0) < 2.0e-4, "light {l}: {:.2e}", miss / 3072.0);
            assert!(miss < 0.1 * power || share(l).abs() < 0.3, "light {l}: {miss} of {power}");
        }
    }

    #[test]
    fn lights_that_differ_only_by_their_noise_have_no_component() {
        let details = light_details(12, |_| 0.0, 0.05);
        let layer = detail_layer(&details, 32).unwrap();
        assert!(layer.bases.is_empty(), "{} components", layer.bases.len());
        assert!(layer.coefficients.iter().all(Vec::is_empty));
        // Nor do too few lights to split in halves.
        let (bases, _) = light_components(&light_details(3, |l| l as f32 - 1.0, 0.0), 32);
        assert!(bases.is_empty());
    }

    /// A view whose region images read the pixels straddling the sample's
    /// edge has its own image modelled as read: X rendered into those
    /// pixels too (each its on-sample part) and resampled by the
    /// straddling filter. Modelled by the inside filter instead, its
    /// outermost texels came out as another reading than its image's, and
    /// the difference was given to the image as detail (session 76: the
    /// painted wood −0.25 dB at the captured pairs).
    #[test]
    fn a_straddling_view_s_own_image_is_modelled_as_it_is_read() {
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |_| 1.0);
        let dims = [f.width as usize, f.height as usize];
        let x: Image = (0..S * S).map(|t| pattern(cell_uv(t, S))).collect();
        let value = |_: usize, _: [f64; 2], raw: [f64; 3]| Some(raw.map(|v| v as f32));
        let outermost = |t: usize| {
            let (i, j) = (t % S, t / S);
            i == 0 || j == 0 || i == S - 1 || j == S - 1
        };
        let mut err = [0.0f64; 2];
        for (k, straddling) in [false, true].into_iter().enumerate() {
            let fp = Footprints::new(&samplers, &vec![straddling; hs.len()], dims, S, 4);
            let [rows, _] = light_rows(&fp, &value, &f).unwrap();
            for r in &rows {
                let own = own_view_image(r, &fp.views[r.view], &x);
                for t in (0..S * S).filter(|&t| outermost(t)) {
                    let read = samplers[r.view].region_filter_straddling(dims, cell_uv(t, S));
                    let read = read.apply(&f);
                    err[k] += (0..3).map(|c| (own[t][c] as f64 - read[c]).powi(2)).sum::<f64>();
                }
            }
        }
        println!("outermost texels, straddling reading against its model: inside {err:?}");
        assert!(err[1] < 0.5 * err[0], "{err:?}");
    }

    #[test]
    fn each_view_keeps_its_own_level() {
        // Views that see the sample at different levels (a sheen, a
        // highlight): the detail is shared, each image's level stays.
        let (hs, samplers) = views();
        let level = |k: usize| 0.5 + 0.15 * k as f32;
        let f = frame(&hs, pattern, level);
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        let total = |img: &[[f32; 3]]| img.iter().flatten().map(|&x| x as f64).sum::<f64>();
        for k in 0..hs.len() {
            // Over the whole image, edges included (within 0.1 % here; 2 %
            // on the brightest view when the pixels were taken at their
            // views' levels: X took the level of the views that reach the
            // edge there).
            let (a, b) = (total(&own[k]), total(&sharp[k]));
            assert!((b / a - 1.0).abs() < 0.003, "view {k}: level {a:.4} → {b:.4}");
        }
        let before = rms(&own, |k, uv| pattern(uv).map(|x| x * level(k)));
        let after = rms(&sharp, |k, uv| pattern(uv).map(|x| x * level(k)));
        assert!(after < 0.9 * before, "{before:.4} → {after:.4}");
    }

    #[test]
    fn views_that_disagree_keep_their_images() {
        // A dark glossy sample: every view sees its highlight somewhere
        // else. No one image explains them; no view takes the others'
        // highlights, nor loses its own.
        let (hs, samplers) = views();
        let glossy = |k: usize, uv: [f64; 2]| {
            let c = [0.2 + 0.05 * k as f64, 0.8 - 0.05 * k as f64];
            let r2 = (uv[0] - c[0]).powi(2) + (uv[1] - c[1]).powi(2);
            let v = (0.05 + 2.0 * (-r2 / (2.0 * 0.04f64.powi(2))).exp()) as f32;
            [v, 0.9 * v, 0.8 * v]
        };
        let mut f = frame(&hs, pattern, |_| 1.0);
        f.rgb.fill(0.0);
        for (k, h) in hs.iter().enumerate() {
            let one = frame(&[*h], |uv| glossy(k, uv), |_| 1.0);
            for (o, v) in f.rgb.iter_mut().zip(&one.rgb) {
                *o += v;
            }
        }
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        let before = rms(&own, glossy);
        let after = rms(&sharp, glossy);
        assert!(after <= 1.05 * before, "{before:.4} → {after:.4}");
    }

    #[test]
    fn noise_is_not_taken_for_detail() {
        // A smooth sample seen through noisy pixels (1 % of the level,
        // independent per pixel, seeded): the all-views solve resolves the
        // noise as "detail"; its halves do not agree on it, so the images
        // do not take it.
        use rand::{Rng, SeedableRng};
        let (hs, samplers) = views();
        let smooth = |uv: [f64; 2]| {
            let a = (std::f64::consts::TAU * uv[0]).sin() * 0.1;
            [0.5 + a, 0.4 - a, 0.3 + 0.5 * a].map(|x| x as f32)
        };
        let mut f = frame(&hs, smooth, |_| 1.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for v in f.rgb.iter_mut().filter(|v| **v > 0.0) {
            *v *= 1.0 + 0.01 * (rng.random::<f32>() - 0.5) * 12f32.sqrt();
        }
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        let before = rms(&own, |_, uv| smooth(uv));
        let after = rms(&sharp, |_, uv| smooth(uv));
        println!("noisy smooth sample: own views {before:.5}, all views {after:.5} RMS");
        // 1.02 × with the halves' agreement, 1.36 × without it.
        assert!(after <= 1.1 * before, "{before:.5} → {after:.5}");
    }

    #[test]
    fn what_the_floor_adds_is_taken_from_its_neighbours() {
        // A flat image of 1 whose detail would take two texels to −0.6 and
        // −0.3 (floored at 0): the image's level comes back to what it was
        // before the floor, within 1 % of the deficit, from the texels
        // around them (two texels away lose over 1 %, twenty nothing); nothing
        // floored changes nothing; texels near an unlit one are kept.
        const N: usize = 32;
        let at = |x: usize, y: usize| y * N + x;
        let mut image: Image = vec![[1.0; 3]; N * N];
        let mut floored: Image = vec![[0.0; 3]; N * N];
        for (t, d) in [(at(10, 10), 0.6f32), (at(20, 12), 0.3)] {
            image[t] = [0.0; 3];
            floored[t] = [d, d, 0.0];
        }
        let before = image.clone();
        let total = |img: &Image, k: usize| img.iter().map(|v| v[k] as f64).sum::<f64>();
        let mut kept = image.clone();
        keep_local_level(&mut kept, &floored, &[], N);
        let target = total(&before, 0) - 0.9;
        assert!((total(&kept, 0) - target).abs() < 0.009, "{} against {target}", total(&kept, 0));
        assert!(kept[at(12, 10)][0] < 0.99, "{:?}", kept[at(12, 10)]);
        assert_eq!(kept[at(30, 30)], [1.0; 3]);
        assert_eq!(kept[at(10, 10)], [0.0; 3], "a floored texel stays at 0");
        assert_eq!(total(&kept, 2), total(&before, 2), "a channel not floored is kept");
        let mut same = image.clone();
        keep_local_level(&mut same, &vec![[0.0; 3]; N * N], &[], N);
        assert_eq!(same, before);
        let mut unlit = vec![false; N * N];
        unlit[at(11, 10)] = true;
        let mut near = image.clone();
        keep_local_level(&mut near, &floored, &unlit, N);
        assert_eq!(near[at(11, 10)], [1.0; 3]);
        assert!(near[at(12, 10)][0] < 0.99);
    }

    #[test]
    fn denoise_takes_the_noise_the_texture_does_not_hide() {
        // A uniform image, a ramp and a checker of 16-texel squares
        // (contrast 30 × the noise), each with 2 % white noise (seeded),
        // told its variance: the uniform image's and the ramp's noise fall
        // below a fifth; the checker, whose edges lie within the local
        // weights' reach (12 texels) of most texels, hides most of its
        // noise and keeps it, but not all: it comes closer to its clean
        // self and keeps its contrast; told there is none, nothing
        // changes; texels near an unlit one are kept.
        use rand::{Rng, SeedableRng};
        const N: usize = 64;
        const SIGMA: f32 = 0.02;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut noisy = |clean: &[[f32; 3]]| -> Image {
            clean
                .iter()
                .map(|v| v.map(|v| v + SIGMA * (rng.random::<f32>() - 0.5) * 12f32.sqrt()))
                .collect()
        };
        let told = |_: usize, _: [f32; 3]| [SIGMA * SIGMA; 3];
        let denoiser = Denoiser::new(N);
        let rms = |a: &[[f32; 3]], b: &[[f32; 3]]| {
            let s: f32 = a
                .iter()
                .zip(b)
                .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>())
                .sum();
            (s / (3 * a.len()) as f32).sqrt()
        };
        let uniform = vec![[0.5f32, 0.4, 0.3]; N * N];
        let checker: Image = (0..N * N)
            .map(|t| if (t % N / 16 + t / N / 16).is_multiple_of(2) { [0.2; 3] } else { [0.8; 3] })
            .collect();
        // A slope of half the noise per texel, which a local mean's
        // variance would take for texture.
        let ramp: Image = (0..N * N)
            .map(|t| [0.2 + 0.01 * (t % N) as f32, 0.3 + 0.006 * (t / N) as f32, 0.4])
            .collect();
        for (name, clean, most) in
            [("uniform", &uniform, 0.2), ("ramp", &ramp, 0.2), ("checker", &checker, 0.95)]
        {
            let input = noisy(clean);
            let mut out = input.clone();
            denoiser.denoise(&mut out, &[], told);
            let (before, after) = (rms(&input, clean), rms(&out, clean));
            println!("{name}: {before:.5} → {after:.5} RMS");
            assert!(after < most * before, "{name}: {before:.5} → {after:.5}");
            let mut same = input.clone();
            denoiser.denoise(&mut same, &[], |_, _| [0.0; 3]);
            assert!(same == input, "{name}: no noise, no change");
        }
        // The checker's squares keep their levels (within a quarter of the
        // noise) away from their edges; within the local means' reach of an
        // edge the texture hides the noise and it stays.
        let mut out = noisy(&checker);
        denoiser.denoise(&mut out, &[], told);
        let inner = |t: usize| (5..11).contains(&(t % 16)) && (5..11).contains(&(t / N % 16));
        for level in [0.2f32, 0.8] {
            let sel: Vec<f32> = (0..N * N)
                .filter(|&t| inner(t) && checker[t][0] == level)
                .map(|t| out[t][0])
                .collect();
            let mean = sel.iter().sum::<f32>() / sel.len() as f32;
            assert!((mean - level).abs() < 0.25 * SIGMA, "square at {level}: {mean}");
        }
        // Unlit texel in the middle: those within UNLIT_MARGIN keep their
        // values.
        let input = noisy(&uniform);
        let mut unlit = vec![false; N * N];
        unlit[32 * N + 32] = true;
        let mut out = input.clone();
        denoiser.denoise(&mut out, &near_unlit(&unlit, N), told);
        for y in 29..=35 {
            for x in 29..=35 {
                assert_eq!(out[y * N + x], input[y * N + x], "({x}, {y})");
            }
        }
        assert_ne!(out[20 * N + 20], input[20 * N + 20]);
    }

    #[test]
    fn each_view_keeps_of_its_own_what_is_not_noise() {
        // A sample the views resolve, through pixels with 5 % noise
        // (independent, seeded): told the noise's variance, the views keep
        // of their own residual what is not noise, and come closer to the
        // sample than when they keep all of it. Told there is none, they
        // keep all.
        use rand::{Rng, SeedableRng};
        let (hs, samplers) = views();
        let gentle = |uv: [f64; 2]| {
            let tau = std::f64::consts::TAU;
            let a = (tau * 3.0 * uv[0]).sin() * (tau * 2.0 * uv[1]).cos();
            [0.5 + 0.2 * a, 0.4 - 0.1 * a, 0.3 + 0.05 * a].map(|x| x as f32)
        };
        let mut f = frame(&hs, gentle, |_| 1.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        const SIGMA: f32 = 0.05;
        for v in f.rgb.iter_mut().filter(|v| **v > 0.0) {
            *v *= 1.0 + SIGMA * (rng.random::<f32>() - 0.5) * 12f32.sqrt();
        }
        let identity = |_: usize, _: [f64; 2], s: [f64; 3]| Some(s.map(|v| v as f32));
        let noise = |vi: usize, t: usize, v: [f32; 3]| {
            let gain = samplers[vi].region_noise_gain(cell_uv(t, S)) as f32;
            v.map(|v| (SIGMA * v).powi(2) * gain)
        };
        let run = |noise: &TexelNoise<'_>, view_noise: bool| {
            let mut images = own_view(&samplers, &f);
            let opts = SharpenOptions { view_noise, ..SharpenOptions::default() };
            sharpen_light(
                &footprints(&samplers, &f, &opts),
                &identity,
                noise,
                &f,
                &opts,
                &mut images,
                &[],
            );
            images
        };
        let own = own_view(&samplers, &f);
        let (all, shrunk) = (run(&noise, false), run(&noise, true));
        assert_eq!(run(&NOISELESS, true), all, "no noise: every residual kept");
        let truth = |_: usize, uv: [f64; 2]| gentle(uv);
        let (r_own, r_all, r_shrunk) = (rms(&own, truth), rms(&all, truth), rms(&shrunk, truth));
        let db = 20.0 * (r_all / r_shrunk).log10();
        println!(
            "5 % noise: own views {r_own:.4}, all views {r_all:.4}, residual shrunk {r_shrunk:.4} RMS: {db:.2} dB"
        );
        assert!(db >= 1.0, "{db:.2} dB");
    }

    #[test]
    fn a_light_s_rows_are_its_usable_pixels_with_their_frame_values() {
        // The footprints are made once; each light keeps the pixels its
        // value function can use, each row reading its own frame pixel.
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |k| 1.0 + 0.1 * k as f32);
        let opts = SharpenOptions::default();
        let views = footprints(&samplers, &f, &opts);
        let right_half =
            |_: usize, uv: [f64; 2], s: [f64; 3]| (uv[0] >= 0.5).then(|| s.map(|v| v as f32));
        let [coarse, fine] = light_rows(&views, &right_half, &f).expect("rows");
        for (rows, v) in coarse.iter().zip(&views.views) {
            let usable = v.centre.iter().filter(|c| c[0] >= 0.5).count();
            assert!(usable > 0 && usable < v.centre.len(), "view {}: {usable}", rows.view);
            assert_eq!(rows.len(), usable, "view {}", rows.view);
        }
        for rows in coarse.iter().chain(&fine) {
            let [x0, y0] = rows.origin;
            for i in 0..rows.len() {
                let p = rows.pixel[i] as usize;
                let (x, y) = (x0 + p % rows.extent[0], y0 + p / rows.extent[0]);
                let at = (y * f.width as usize + x) * 3;
                assert_eq!(rows.value[i], [f.rgb[at], f.rgb[at + 1], f.rgb[at + 2]]);
                let (t, w) = rows.row(i);
                assert!(!t.is_empty() && t.len() == w.len());
                assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5, "a row's weights sum to 1");
            }
        }
    }

    #[test]
    fn a_uniform_sample_stays_as_it_was() {
        let (hs, samplers) = views();
        let f = frame(&hs, |_| [0.2, 0.5, 0.9], |_| 1.0);
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        for (a, b) in own.iter().flatten().zip(sharp.iter().flatten()) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() <= 2e-3 * a[c], "{a:?} → {b:?}");
            }
        }
    }

    #[test]
    fn a_uniform_sample_seen_at_different_levels_stays_as_it_was() {
        // Views that see one flat sample at levels from 0.5 to 2.15 (a dark
        // glossy sample's sheen): near the edge fewer of them cover a
        // texel, and an X that took those views' level there would print
        // a ramp into every image (up to 90 % of a corner texel here when
        // the pixels were taken at their views' levels; 6 % below the
        // mean image along a dark rubber's edge).
        let (hs, samplers) = views();
        let level = |k: usize| 0.5 + 0.15 * k as f32;
        let f = frame(&hs, |_| [0.2, 0.5, 0.9], level);
        let own = own_view(&samplers, &f);
        let sharp = sharpened(&samplers, &f, own.clone());
        let mut worst = 0.0f32;
        for (a, b) in own.iter().flatten().zip(sharp.iter().flatten()) {
            for c in 0..3 {
                worst = worst.max((a[c] - b[c]).abs() / a[c]);
            }
        }
        assert!(worst <= 1e-4, "a texel moved by {:.3} %", 100.0 * worst);
    }

    #[test]
    fn no_usable_pixel_leaves_the_images() {
        let (hs, samplers) = views();
        let f = frame(&hs, pattern, |_| 1.0);
        let own = own_view(&samplers, &f);
        let unlit = |_: usize, _: [f64; 2], _: [f64; 3]| None;
        let mut images = own.clone();
        let opts = SharpenOptions::default();
        sharpen_light(
            &footprints(&samplers, &f, &opts),
            &unlit,
            &NOISELESS,
            &f,
            &opts,
            &mut images,
            &[],
        );
        assert_eq!(images, own);
    }
}
