//! Alternating weighted least squares (AWLS) fitting of the NPF model
//! (spec/npf-brdf.md §3–4), per colour channel.
//!
//! One factor is updated at a time, everything else fixed:
//! - a **bin** of D (or F): every sample in the bin obeys ρ̂ − ρd ≈ x·y, so
//!   x = Σ w z y / Σ w y², accumulated for all bins in one parallel pass;
//! - **G, Smith variant**: re-derived from D after each D update; if the
//!   objective rose, a golden-section search over the blend between the old
//!   and new D (G re-derived at every point) keeps the best, never worse than
//!   before;
//! - **G, independent variant**: Gi with Go fixed and Go with Gi fixed by the
//!   bin update (a sample contributes to the two bins it interpolates between,
//!   by its interpolation weights), averaged, Gaussian-smoothed; the same
//!   golden-section guard;
//! - **ρs, ρd**: weighted linear regression ρ̂ ≈ a·x + b by Cramer's rule; if
//!   b < 0, b = 0 and a = Σ w x ρ̂ / Σ w x².
//!
//! After each update a table is normalised to max 1 (its scale moves into ρs)
//! and clamped to [1e-6, 1]. Iterations stop when the objective falls by at
//! most `tolerance` (relative) or after `max_iterations`.

use std::f64::consts::LN_2;
use std::time::Instant;

use rayon::prelude::*;

use super::coords::{
    MERL_CELLS, N_PHI_D, N_THETA_D, N_THETA_H, cell_centre, from_directions, g_interp, merl_index,
    phi_d_bin, theta_d_bin, theta_h_bin, to_directions,
};
use super::merl::MerlTable;
use super::npf::{Channel, EPSILON, NaiveModel, NpfModel};
use super::smith::smith_g;
use super::{BINS, MAX_VALUE, Vec3};

/// How G is obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum GVariant {
    /// Derived from D (Smith).
    Smith,
    /// Its own table.
    Independent,
}

/// How samples are weighted.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub enum Weighting {
    /// wV · wI · wE with the compressive exponent p (spec §3).
    Compressive {
        /// Exponent p ∈ [1, 2].
        p: f64,
    },
    /// Every valid sample weighs 1 (plain least squares, for comparison).
    Unweighted,
}

/// Fit settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// G variant.
    pub g: GVariant,
    /// Weighting.
    pub weighting: Weighting,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Stop when the objective falls by this fraction or less.
    pub tolerance: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            g: GVariant::Smith,
            weighting: Weighting::Compressive { p: 1.4 },
            max_iterations: 60,
            tolerance: 1e-5,
        }
    }
}

/// One scattered measurement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Towards the light (local frame, z = normal).
    pub wi: Vec3,
    /// Towards the viewer.
    pub wo: Vec3,
    /// BRDF value per channel, sr⁻¹ (negative: missing in that channel).
    pub rgb: [f64; 3],
}

/// Why samples could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// No usable sample.
    #[error("no valid sample (all missing or below the horizon)")]
    Empty,
    /// A measurement is not finite or not unit length.
    #[error("measurement {index} is invalid: {why}")]
    Invalid {
        /// Its index.
        index: usize,
        /// What is wrong.
        why: &'static str,
    },
    /// A colour channel has no measured value (every value is missing).
    #[error("channel {channel} has no measurement: every value is missing (negative)")]
    ChannelMissing {
        /// R, G or B.
        channel: char,
    },
    /// Values too large to fit (the fit works in single precision and its
    /// weights underflow long before): not BRDF values in sr⁻¹.
    #[error(
        "channel {channel} has values up to {max:.3e}, beyond any BRDF (at most {MAX_VALUE:.0e} sr⁻¹): are the units right?"
    )]
    TooLarge {
        /// R, G or B.
        channel: char,
        /// Its largest value.
        max: f64,
    },
}

/// Fitting samples in structure-of-arrays form.
#[derive(Debug, Clone)]
pub struct Samples {
    th: Vec<u8>,
    td: Vec<u8>,
    ph: Vec<u8>,
    gi: Vec<u8>,
    gwi: Vec<f32>,
    go: Vec<u8>,
    gwo: Vec<f32>,
    inv_cc: Vec<f32>,
    cc: Vec<f32>,
    base_w: Vec<f32>,
    values: [Vec<f32>; 3],
}

impl Samples {
    fn with_capacity(n: usize) -> Samples {
        Samples {
            th: Vec::with_capacity(n),
            td: Vec::with_capacity(n),
            ph: Vec::with_capacity(n),
            gi: Vec::with_capacity(n),
            gwi: Vec::with_capacity(n),
            go: Vec::with_capacity(n),
            gwo: Vec::with_capacity(n),
            inv_cc: Vec::with_capacity(n),
            cc: Vec::with_capacity(n),
            base_w: Vec::with_capacity(n),
            values: [Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n)],
        }
    }

    fn push(
        &mut self,
        wi: Vec3,
        wo: Vec3,
        bins: (usize, usize, usize),
        w_volume: f64,
        rgb: [f64; 3],
    ) {
        let (ci, co) = (wi[2], wo[2]);
        let (a, w) = g_interp(ci.acos());
        let (b, v) = g_interp(co.acos());
        self.th.push(bins.0 as u8);
        self.td.push(bins.1 as u8);
        self.ph.push(h_bin_of(bins.2) as u8);
        self.gi.push(a as u8);
        self.gwi.push(w as f32);
        self.go.push(b as u8);
        self.gwo.push(v as f32);
        self.inv_cc.push((1.0 / (ci * co)) as f32);
        self.cc.push((ci * co) as f32);
        self.base_w.push((w_volume * ci * co) as f32);
        for (values, v) in self.values.iter_mut().zip(rgb) {
            values.push(v as f32);
        }
    }

    /// Every valid cell of a MERL table, at its cell centre, with the
    /// volume-form weight wV = θh′ sin θd √(1 − sin²θd sin²φd).
    pub fn from_merl(table: &MerlTable) -> Result<Samples, SampleError> {
        let mut s = Samples::with_capacity(MERL_CELLS / 2);
        for th in 0..N_THETA_H {
            for td in 0..N_THETA_D {
                for pd in 0..N_PHI_D {
                    let hd = cell_centre(th, td, pd);
                    let (wi, wo) = to_directions(hd);
                    if wi[2] <= 1e-6 || wo[2] <= 1e-6 {
                        continue;
                    }
                    let i = merl_index(th, td, pd);
                    let rgb = [0, 1, 2].map(|c| table.get(c, i));
                    if rgb.iter().all(|v| *v < 0.0) {
                        continue;
                    }
                    let u = (th as f64 + 0.5) / N_THETA_H as f64;
                    let (sd, sp) = (hd.theta_d.sin(), hd.phi_d.sin());
                    let wv = u * sd * (1.0 - sd * sd * sp * sp).max(0.0).sqrt();
                    s.push(wi, wo, (th, td, pd), wv, rgb);
                }
            }
        }
        s.checked()
    }

    /// Every channel has measured values, none beyond [`MAX_VALUE`].
    fn checked(self) -> Result<Samples, SampleError> {
        if self.is_empty() {
            return Err(SampleError::Empty);
        }
        for (values, channel) in self.values.iter().zip(['R', 'G', 'B']) {
            let max = values.iter().fold(f32::NEG_INFINITY, |m, v| m.max(*v)) as f64;
            if max < 0.0 {
                return Err(SampleError::ChannelMissing { channel });
            }
            if max > MAX_VALUE {
                return Err(SampleError::TooLarge { channel, max });
            }
        }
        Ok(self)
    }

    /// Channels that are zero (or missing) wherever measured: their model
    /// is black.
    pub fn black_channels(&self) -> Vec<char> {
        self.values
            .iter()
            .zip(['R', 'G', 'B'])
            .filter(|(v, _)| v.iter().all(|x| *x <= 0.0))
            .map(|(_, c)| c)
            .collect()
    }

    /// Scattered measurements (each its own weight: wV = 1).
    pub fn from_measurements(measurements: &[Measurement]) -> Result<Samples, SampleError> {
        let mut s = Samples::with_capacity(measurements.len());
        for (index, m) in measurements.iter().enumerate() {
            let finite = m.wi.iter().chain(&m.wo).chain(&m.rgb).all(|x| x.is_finite());
            if !finite {
                return Err(SampleError::Invalid { index, why: "not finite" });
            }
            let unit =
                |v: Vec3| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() - 1.0).abs() < 1e-6;
            if !unit(m.wi) || !unit(m.wo) {
                return Err(SampleError::Invalid { index, why: "directions must be unit vectors" });
            }
            if m.wi[2] <= 1e-6 || m.wo[2] <= 1e-6 || m.rgb.iter().all(|v| *v < 0.0) {
                continue;
            }
            let hd = from_directions(m.wi, m.wo);
            let bins = (theta_h_bin(hd.theta_h), theta_d_bin(hd.theta_d), phi_d_bin(hd.phi_d));
            let finite_f32 = m.rgb.iter().all(|v| v.abs() <= f32::MAX as f64);
            if !finite_f32 {
                let channel = ['R', 'G', 'B']
                    [m.rgb.iter().position(|v| v.abs() > f32::MAX as f64).unwrap_or(0)];
                let max = m.rgb.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                return Err(SampleError::TooLarge { channel, max });
            }
            s.push(m.wi, m.wo, bins, 1.0, m.rgb);
        }
        s.checked()
    }

    /// How many of the 90 θh′ bins (D's) and of the 90 θd bins (F's) hold
    /// no sample: the fit interpolates them from their neighbours.
    pub fn bins_without_samples(&self) -> [usize; 2] {
        [&self.th, &self.td].map(|bins| {
            let mut seen = [false; BINS];
            for &b in bins {
                seen[b as usize] = true;
            }
            seen.iter().filter(|s| !**s).count()
        })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.th.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.th.is_empty()
    }
}

fn h_bin_of(phi_bin: usize) -> usize {
    phi_bin / 2
}

/// What a fit did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FitReport {
    /// Final objective per channel.
    pub objective: [f64; 3],
    /// Iterations per channel.
    pub iterations: [usize; 3],
    /// Objective after every iteration, per channel (index 0: initial).
    pub history: [Vec<f64>; 3],
    /// Golden-section searches that were needed, per channel.
    pub line_searches: [usize; 3],
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// Samples and weights of one channel.
struct Data<'a> {
    s: &'a Samples,
    c: usize,
    w: Vec<f32>,
}

/// Initial D, F, ρ sweeps with G = 1 (cheap: they only use the moments).
const INIT_SWEEPS: usize = 8;

/// Chunk size of parallel passes.
const CHUNK: usize = 1 << 14;

impl Data<'_> {
    fn new<'a>(s: &'a Samples, c: usize, weighting: Weighting) -> Data<'a> {
        let values = &s.values[c];
        let w = match weighting {
            Weighting::Unweighted => {
                values.iter().map(|v| if *v >= 0.0 { 1.0 } else { 0.0 }).collect()
            }
            Weighting::Compressive { p } => {
                let median = weighted_median(values, &s.base_w).max(1e-12);
                values
                    .iter()
                    .zip(&s.base_w)
                    .map(|(v, bw)| {
                        if *v >= 0.0 { bw * compressive(*v as f64 / median, p) as f32 } else { 0.0 }
                    })
                    .collect()
            }
        };
        Data { s, c, w }
    }

    #[inline]
    fn g(table: &[f64; BINS], a: u8, w: f32) -> f64 {
        let a = a as usize;
        table[a] * (1.0 - w as f64) + table[a + 1] * w as f64
    }

    /// Σ over samples of `f(j)` into per-bin sums, chunks in parallel. The
    /// chunks' sums are added in order, so the rounding is the same on
    /// every run (a parallel reduction's grouping follows rayon's work
    /// stealing).
    fn accumulate<const K: usize>(
        &self,
        f: impl Fn(usize, &mut [[f64; BINS]; K]) + Sync,
    ) -> [[f64; BINS]; K] {
        let n = self.s.len();
        let chunks: Vec<[[f64; BINS]; K]> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|chunk| {
                let mut acc = [[0.0; BINS]; K];
                for j in chunk * CHUNK..((chunk + 1) * CHUNK).min(n) {
                    if self.w[j] > 0.0 {
                        f(j, &mut acc);
                    }
                }
                acc
            })
            .collect();
        let mut sum = [[0.0; BINS]; K];
        for acc in &chunks {
            for (s, a) in sum.iter_mut().zip(acc) {
                for (s, a) in s.iter_mut().zip(a) {
                    *s += a;
                }
            }
        }
        sum
    }

    /// Gi with Go fixed and Go with Gi fixed, averaged, smoothed.
    fn update_g(&self, m: &Channel) -> [f64; BINS] {
        let s = self.s;
        let v = &s.values[self.c];
        let sums = self.accumulate::<4>(|j, acc| {
            let w = self.w[j] as f64;
            let base = m.rho_s * m.d[s.th[j] as usize] * m.f[s.td[j] as usize] * s.inv_cc[j] as f64;
            let z = v[j] as f64 - m.rho_d;
            let (gi, go) = (Self::g(&m.g, s.gi[j], s.gwi[j]), Self::g(&m.g, s.go[j], s.gwo[j]));
            // x = G(θi): y = base · G(θo), spread over the two bins of θi.
            for (a, frac, other, k) in [(s.gi[j], s.gwi[j], go, 0), (s.go[j], s.gwo[j], gi, 2)] {
                let y = base * other;
                let a = a as usize;
                let frac = frac as f64;
                for (bin, share) in [(a, 1.0 - frac), (a + 1, frac)] {
                    if share > 0.0 {
                        acc[k][bin] += share * w * z * y;
                        acc[k + 1][bin] += share * w * y * y;
                    }
                }
            }
        });
        let gi = solve_bins(&m.g, &sums[0], &sums[1]);
        let go = solve_bins(&m.g, &sums[2], &sums[3]);
        let avg: [f64; BINS] = std::array::from_fn(|k| 0.5 * (gi[k] + go[k]));
        gaussian_smooth(&avg, 0.75)
    }
}

/// Per (θh bin, θd bin) cell: Σw, Σw·v, Σw·v², Σw·γ, Σw·v·γ, Σw·γ² with
/// γ = G(θi) G(θo) / (cos θi cos θo). With G fixed, the objective and the
/// D, F, ρs, ρd updates are exact functions of these, so the samples are
/// visited once per change of G instead of once per update.
struct Moments(Vec<[f64; 6]>);

impl Moments {
    fn cell(th: usize, td: usize) -> usize {
        th * BINS + td
    }

    fn objective(&self, m: &Channel) -> f64 {
        let mut e = 0.0;
        for th in 0..BINS {
            for td in 0..BINS {
                let [sw, sv, svv, sg, svg, sgg] = self.0[Self::cell(th, td)];
                if sw == 0.0 {
                    continue;
                }
                let a = m.rho_s * m.d[th] * m.f[td];
                e += svv - 2.0 * m.rho_d * sv - 2.0 * a * svg
                    + m.rho_d * m.rho_d * sw
                    + 2.0 * m.rho_d * a * sg
                    + a * a * sgg;
            }
        }
        e.max(0.0)
    }

    /// Bin update of D (`along_th`) or F.
    fn update(&self, m: &Channel, along_th: bool) -> [f64; BINS] {
        let (mut num, mut den) = ([0.0; BINS], [0.0; BINS]);
        for th in 0..BINS {
            for td in 0..BINS {
                let [_, sv, _, sg, svg, sgg] = self.0[Self::cell(th, td)];
                let (k, other) = if along_th { (th, m.f[td]) } else { (td, m.d[th]) };
                let y = m.rho_s * other;
                num[k] += y * (svg - m.rho_d * sg);
                den[k] += y * y * sgg;
                let _ = sv;
            }
        }
        solve_bins(if along_th { &m.d } else { &m.f }, &num, &den)
    }

    fn update_rho(&self, m: &mut Channel) {
        let (mut s, mut sx, mut sxx, mut sy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for th in 0..BINS {
            for td in 0..BINS {
                let [sw, sv, _, sg, svg, sgg] = self.0[Self::cell(th, td)];
                let df = m.d[th] * m.f[td];
                s += sw;
                sx += df * sg;
                sxx += df * df * sgg;
                sy += sv;
                sxy += df * svg;
            }
        }
        regress(m, [s, sx, sxx, sy, sxy]);
    }
}

/// ρ̂ ≈ a·x + b by Cramer's rule from [Σw, Σwx, Σwx², Σwy, Σwxy].
fn regress(m: &mut Channel, sums: [f64; 5]) {
    let [s, sx, sxx, sy, sxy] = sums;
    let det = s * sxx - sx * sx;
    let (mut a, mut b) = if det.abs() > 1e-300 {
        ((s * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det)
    } else {
        (m.rho_s, m.rho_d)
    };
    // b < 0 (spec) — and a ≤ 0, which would switch the specular term off for
    // good (every later bin update would see y = 0): fit through 0.
    if b < 0.0 || a <= 0.0 {
        b = 0.0;
        a = if sxx > 0.0 { sxy / sxx } else { m.rho_s };
    }
    m.rho_s = a.max(f64::MIN_POSITIVE);
    m.rho_d = b;
}

impl Data<'_> {
    fn moments(&self, g: &[f64; BINS]) -> Moments {
        let s = self.s;
        let v = &s.values[self.c];
        let n = s.len();
        let chunk = n.div_ceil(4 * rayon::current_num_threads()).max(1);
        let parts: Vec<Vec<[f64; 6]>> = (0..n.div_ceil(chunk))
            .into_par_iter()
            .map(|p| {
                let mut acc = vec![[0.0; 6]; BINS * BINS];
                for j in p * chunk..((p + 1) * chunk).min(n) {
                    let w = self.w[j] as f64;
                    if w <= 0.0 {
                        continue;
                    }
                    let gamma = Self::g(g, s.gi[j], s.gwi[j])
                        * Self::g(g, s.go[j], s.gwo[j])
                        * s.inv_cc[j] as f64;
                    let y = v[j] as f64;
                    let a = &mut acc[Moments::cell(s.th[j] as usize, s.td[j] as usize)];
                    a[0] += w;
                    a[1] += w * y;
                    a[2] += w * y * y;
                    a[3] += w * gamma;
                    a[4] += w * y * gamma;
                    a[5] += w * gamma * gamma;
                }
                acc
            })
            .collect();
        let mut total = vec![[0.0; 6]; BINS * BINS];
        for part in parts {
            for (t, p) in total.iter_mut().zip(part) {
                for k in 0..6 {
                    t[k] += p[k];
                }
            }
        }
        Moments(total)
    }
}

/// x_k = num_k / den_k where there are samples; a bin without samples
/// takes the value interpolated linearly between the nearest bins with
/// samples on either side, or the nearest one's beyond the last. (Keeping
/// its old value instead would leave it on the scale of the tables before
/// the update: with sparse measurements the sampled bins of D and F could
/// then shrink towards ε while ρs grew to match, and the model predicted
/// ρs — 10¹⁰ sr⁻¹ and more — wherever the unsampled bins meet.) With no
/// sample at all, the old table.
fn solve_bins(old: &[f64; BINS], num: &[f64; BINS], den: &[f64; BINS]) -> [f64; BINS] {
    let sampled: Vec<usize> = (0..BINS).filter(|&k| den[k] > 0.0).collect();
    let (Some(&first), Some(&last)) = (sampled.first(), sampled.last()) else {
        return *old;
    };
    let x = |k: usize| num[k] / den[k];
    let mut out = [0.0; BINS];
    out[..first].fill(x(first));
    out[last..].fill(x(last));
    for pair in sampled.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        for (k, slot) in out.iter_mut().enumerate().take(b).skip(a) {
            let t = (k - a) as f64 / (b - a) as f64;
            *slot = x(a) * (1.0 - t) + x(b) * t;
        }
    }
    out
}

/// Normalise to max 1, clamp to [ε, 1]; returns the scale removed.
fn normalise(t: &mut [f64; BINS]) -> f64 {
    let m = t.iter().copied().fold(0.0, f64::max);
    if m <= 0.0 || !m.is_finite() {
        *t = [1.0; BINS];
        return 0.0;
    }
    for x in t.iter_mut() {
        *x = (*x / m).clamp(EPSILON, 1.0);
    }
    m
}

fn gaussian_smooth(t: &[f64; BINS], sigma: f64) -> [f64; BINS] {
    let r = (3.0 * sigma).ceil() as isize;
    std::array::from_fn(|k| {
        let (mut sum, mut wsum) = (0.0, 0.0);
        for d in -r..=r {
            let i = k as isize + d;
            if (0..BINS as isize).contains(&i) {
                let w = (-(d * d) as f64 / (2.0 * sigma * sigma)).exp();
                sum += w * t[i as usize];
                wsum += w;
            }
        }
        sum / wsum
    })
}

/// wE = (f(x)/x)^p, f(x) = (1 − e^(−αx))/α, α = ln 2.
pub fn compressive(x: f64, p: f64) -> f64 {
    if x < 1e-9 {
        return 1.0;
    }
    ((1.0 - (-LN_2 * x).exp()) / (LN_2 * x)).powf(p)
}

/// The weighted median of the non-negative `values` with `weights`.
pub fn weighted_median(values: &[f32], weights: &[f32]) -> f64 {
    let mut pairs: Vec<(f32, f32)> = values
        .iter()
        .zip(weights)
        .filter(|(v, w)| **v >= 0.0 && **w > 0.0)
        .map(|(v, w)| (*v, *w))
        .collect();
    if pairs.is_empty() {
        return 0.0;
    }
    pairs.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = pairs.iter().map(|p| p.1 as f64).sum();
    let mut acc = 0.0;
    for (v, w) in &pairs {
        acc += *w as f64;
        if acc >= total / 2.0 {
            return *v as f64;
        }
    }
    pairs.last().map_or(0.0, |p| p.0 as f64)
}

/// Golden-section search of t ∈ [0, 1] for the candidate with the lowest
/// objective (7 steps: the bracket shrinks to 3.4 %); t = 0 (the state
/// before the update) is always a candidate, so the result is never worse.
fn golden_section<T>(mut candidate: impl FnMut(f64) -> (T, f64), at_zero: (T, f64)) -> (T, f64) {
    const INV_PHI: f64 = 0.618_033_988_749_894_8;
    let (mut a, mut b) = (0.0f64, 1.0f64);
    let mut x1 = b - INV_PHI * (b - a);
    let mut x2 = a + INV_PHI * (b - a);
    let mut c1 = candidate(x1);
    let mut c2 = candidate(x2);
    for _ in 0..7 {
        if c1.1 < c2.1 {
            b = x2;
            x2 = x1;
            c2 = c1;
            x1 = b - INV_PHI * (b - a);
            c1 = candidate(x1);
        } else {
            a = x1;
            x1 = x2;
            c1 = c2;
            x2 = a + INV_PHI * (b - a);
            c2 = candidate(x2);
        }
    }
    [c1, c2].into_iter().fold(at_zero, |best, c| if c.1 < best.1 { c } else { best })
}

/// Blend two factor tables at their effective scales: (1−t)·s0·T0 + t·s1·T1,
/// renormalised; returns (table, scale).
fn blend(t0: &[f64; BINS], s0: f64, t1: &[f64; BINS], s1: f64, t: f64) -> ([f64; BINS], f64) {
    let mut table: [f64; BINS] = std::array::from_fn(|k| (1.0 - t) * s0 * t0[k] + t * s1 * t1[k]);
    let scale = normalise(&mut table);
    (table, scale)
}

/// An update that changes G (and so the moments): keep the full step
/// (`candidate(1)`) if the objective did not rise, else golden-section search
/// the blend old → new (`candidate(t)`) and keep the best, never worse than
/// the state before (`old`, objective `e_old`).
fn guarded_step(
    data: &Data<'_>,
    old: (Channel, Moments),
    e_old: f64,
    searches: &mut usize,
    candidate: impl Fn(f64) -> Channel,
) -> (Channel, Moments) {
    let evaluate = |t: f64| {
        let c = candidate(t);
        let mo = data.moments(&c.g);
        let e = mo.objective(&c);
        ((c, mo), e)
    };
    let (full, e_full) = evaluate(1.0);
    if e_full <= e_old {
        return full;
    }
    *searches += 1;
    golden_section(evaluate, (old, e_old)).0
}

fn fit_channel(
    data: &Data<'_>,
    opts: &FitOptions,
    progress: &(dyn Fn(usize, usize, f64) + Sync),
) -> (Channel, Vec<f64>, usize) {
    let smith = opts.g == GVariant::Smith;
    // Initialisation: a few exact D, F, ρ sweeps with G = 1 give D its shape
    // before G is coupled to it (from a flat D, the Smith G is far from its
    // final form and the first D steps would mostly be undone by the guard).
    let mut m = Channel::flat();
    let mut mo = data.moments(&m.g);
    mo.update_rho(&mut m);
    for _ in 0..INIT_SWEEPS {
        m.d = mo.update(&m, true);
        m.rho_s *= normalise(&mut m.d);
        m.f = mo.update(&m, false);
        m.rho_s *= normalise(&mut m.f);
        mo.update_rho(&mut m);
    }
    if smith {
        m.g = smith_g(&m.d);
        mo = data.moments(&m.g);
        mo.update_rho(&mut m);
    }
    let mut e = mo.objective(&m);
    let mut history = vec![e];
    let mut searches = 0;
    for it in 0..opts.max_iterations {
        let e_start = e;

        // D — and with it the Smith G, which changes the moments.
        let mut new = m.clone();
        new.d = mo.update(&m, true);
        new.rho_s *= normalise(&mut new.d);
        if smith {
            let old = m.clone();
            (m, mo) = guarded_step(data, (old.clone(), mo), e, &mut searches, |t| {
                let mut c = old.clone();
                (c.d, c.rho_s) = blend(&old.d, old.rho_s, &new.d, new.rho_s, t);
                c.g = smith_g(&c.d);
                c
            });
        } else if mo.objective(&new) <= e {
            m = new;
        }

        // F: an exact minimiser in its bins (kept only if the objective did
        // not rise, so rounding can never make it rise either).
        let e_before_f = mo.objective(&m);
        let mut new = m.clone();
        new.f = mo.update(&m, false);
        new.rho_s *= normalise(&mut new.f);
        if mo.objective(&new) <= e_before_f {
            m = new;
        }

        // Independent G: one pass for its bin sums, one for the new moments.
        if !smith {
            let e_before = mo.objective(&m);
            let mut new = m.clone();
            new.g = data.update_g(&m);
            let sg = normalise(&mut new.g);
            new.rho_s *= sg * sg;
            let old = m.clone();
            let (sq_old, sq_new) = (old.rho_s.sqrt(), new.rho_s.sqrt());
            (m, mo) = guarded_step(data, (old.clone(), mo), e_before, &mut searches, |t| {
                let mut c = old.clone();
                let (g, s) = blend(&old.g, sq_old, &new.g, sq_new, t);
                c.g = g;
                c.rho_s = s * s;
                c
            });
        }

        // ρs, ρd (the same guard).
        let e_before_rho = mo.objective(&m);
        let mut new = m.clone();
        mo.update_rho(&mut new);
        let e_new = mo.objective(&new);
        (m, e) = if e_new <= e_before_rho { (new, e_new) } else { (m, e_before_rho) };
        history.push(e);
        progress(data.c, it + 1, e);
        // Converged (an iteration that changed nothing would repeat itself:
        // a zero objective stops too), or fitted to rounding (an exactly
        // representable BRDF).
        if e_start - e <= opts.tolerance * e_start || e < 1e-7 * history[0] {
            break;
        }
    }
    (m, history, searches)
}

/// Fit an NPF model to `samples`; `progress(channel, iteration, objective)`
/// is called after every iteration.
pub fn fit(
    samples: &Samples,
    opts: &FitOptions,
    progress: &(dyn Fn(usize, usize, f64) + Sync),
) -> (NpfModel, FitReport) {
    let started = Instant::now();
    let results: Vec<(Channel, Vec<f64>, usize)> = (0..3)
        .into_par_iter()
        .map(|c| {
            let data = Data::new(samples, c, opts.weighting);
            fit_channel(&data, opts, progress)
        })
        .collect();
    let mut it = results.into_iter();
    let (r, g, b) = (it.next().unwrap(), it.next().unwrap(), it.next().unwrap());
    let report = FitReport {
        objective: [
            r.1.last().copied().unwrap_or(0.0),
            g.1.last().copied().unwrap_or(0.0),
            b.1.last().copied().unwrap_or(0.0),
        ],
        iterations: [r.1.len() - 1, g.1.len() - 1, b.1.len() - 1],
        line_searches: [r.2, g.2, b.2],
        history: [r.1, g.1, b.1],
        seconds: started.elapsed().as_secs_f64(),
    };
    let metadata = serde_json::json!({
        "fitter": "awls",
        "g": opts.g,
        "weighting": opts.weighting,
        "samples": samples.len(),
        "objective": report.objective,
        "iterations": report.iterations,
    });
    (NpfModel { channels: [r.0, g.0, b.0], metadata }, report)
}

/// The fit objective E of `model` on `samples` under `weighting`, per channel.
pub fn objective(samples: &Samples, model: &NpfModel, weighting: Weighting) -> [f64; 3] {
    [0, 1, 2].map(|c| {
        let data = Data::new(samples, c, weighting);
        data.moments(&model.channels[c].g).objective(&model.channels[c])
    })
}

/// Fit the naive D·F·H model by the same AWLS bin updates.
pub fn fit_naive(samples: &Samples, opts: &FitOptions) -> NaiveModel {
    let channels: Vec<_> = (0..3)
        .into_par_iter()
        .map(|c| {
            let data = Data::new(samples, c, opts.weighting);
            let s = samples;
            let v = &s.values[c];
            let (mut rd, mut rs) = (0.0, 1.0);
            let (mut d, mut f, mut h) = ([1.0; BINS], [1.0; BINS], [1.0; BINS]);
            for _ in 0..opts.max_iterations.min(40) {
                for which in 0..3 {
                    let [num, den] = data.accumulate::<2>(|j, acc| {
                        let w = data.w[j] as f64;
                        let (dj, fj, hj) =
                            (d[s.th[j] as usize], f[s.td[j] as usize], h[s.ph[j] as usize]);
                        let (k, y) = match which {
                            0 => (s.th[j] as usize, rs * fj * hj),
                            1 => (s.td[j] as usize, rs * dj * hj),
                            _ => (s.ph[j] as usize, rs * dj * fj),
                        };
                        let z = v[j] as f64 - rd;
                        acc[0][k] += w * z * y;
                        acc[1][k] += w * y * y;
                    });
                    let t = match which {
                        0 => &mut d,
                        1 => &mut f,
                        _ => &mut h,
                    };
                    *t = solve_bins(t, &num, &den);
                    rs *= normalise(t);
                }
                // ρs, ρd by the same regression with x = D F H.
                let mut sums = [0.0f64; 5];
                for j in 0..s.len() {
                    let w = data.w[j] as f64;
                    if w > 0.0 {
                        let x = d[s.th[j] as usize] * f[s.td[j] as usize] * h[s.ph[j] as usize];
                        let y = v[j] as f64;
                        sums[0] += w;
                        sums[1] += w * x;
                        sums[2] += w * x * x;
                        sums[3] += w * y;
                        sums[4] += w * x * y;
                    }
                }
                let [sw, sx, sxx, sy, sxy] = sums;
                let det = sw * sxx - sx * sx;
                if det.abs() > 1e-300 {
                    rs = (sw * sxy - sx * sy) / det;
                    rd = (sxx * sy - sx * sxy) / det;
                }
                if rd < 0.0 {
                    rd = 0.0;
                    rs = sxy / sxx;
                }
            }
            (rd, rs.max(0.0), d, f, h)
        })
        .collect();
    NaiveModel { channels: [channels[0], channels[1], channels[2]] }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compressive_weight_shape() {
        assert!((compressive(0.0, 1.4) - 1.0).abs() < 1e-12);
        assert!((compressive(1e-6, 1.4) - 1.0).abs() < 1e-5);
        // The median maps to f = 1/(2α): wE(1) = (1/(2 ln 2))^p.
        assert!((compressive(1.0, 1.0) - 1.0 / (2.0 * LN_2)).abs() < 1e-12);
        let mut last = 1.0;
        for k in 1..100 {
            let w = compressive(k as f64 * 0.5, 1.4);
            assert!(w < last && w > 0.0);
            last = w;
        }
    }

    #[test]
    fn weighted_median_weighs() {
        assert_eq!(weighted_median(&[1.0, 2.0, 3.0], &[1.0, 1.0, 1.0]), 2.0);
        assert_eq!(weighted_median(&[1.0, 2.0, 3.0], &[1.0, 1.0, 5.0]), 3.0);
        assert_eq!(weighted_median(&[-1.0, 2.0, 3.0], &[9.0, 1.0, 1.0]), 2.0);
    }

    #[test]
    fn golden_section_never_returns_worse_than_zero() {
        let (t, e) = golden_section(|t| (t, 5.0 + t), (0.0, 4.0));
        assert_eq!((t, e), (0.0, 4.0));
        let (t, e) = golden_section(|t| (t, (t - 0.3) * (t - 0.3)), (0.0, 0.09));
        assert!(e < 1e-3 && (t - 0.3).abs() < 0.03, "{t} {e}");
    }
}
