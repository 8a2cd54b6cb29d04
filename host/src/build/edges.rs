//! The sample's edges in each view, measured on the diffuse-white
//! target's frames.
//!
//! The region images' straddling reading ([`super::regions::EdgePixels`])
//! takes a pixel the sample's edge crosses as s · S + (1 − s) · H — its
//! share s of the square on the sample, the holder's radiance H beside it
//! — and divides by s, so an edge δ px off misreads the outermost texels by
//! δ / s of the contrast with the holder: the edges must be known to about
//! 0.01 px. The checkerboard places them through each view's homography to
//! 0.01–0.05 px RMS a side (docs/benchmarks.md, sessions 73–76).
//!
//! The white target is uniform, so its frames show the edges themselves.
//! A pixel the edge crosses holds s · W + (1 − s) · H, with W the target's
//! level there (read 2.5 and 4.5 px in along the edge's normal and
//! extrapolated to the pixel; where the two differ by more than 5 %, a
//! beam's edge, the pixel is left out) and H the holder's
//! ([`super::calibrate::holder_radiance`]). Its share is the same under
//! every light, so each pixel's is the least-squares one over all of them:
//! Σ (W − H)(value − H) / Σ (W − H)². Per side, the straight edge — two
//! offsets along its normal, at its first and its last corner — whose
//! exact shares ([`ViewSampler::share`]) fit those best, weighted by
//! Σ (W − H)², by Gauss–Newton; pixels within 1.5 px of another side are
//! left out (their level and share involve two edges), as are outliers
//! beyond 5 × the residuals' RMS (a speck, a defect).
//!
//! The sample must lie where the white target lay, as the checkerboard's
//! homographies already assume.

use super::calibrate::{ViewSampler, holder_radiance};
use super::scanread::frame_bilinear;
use crate::camera::Frame;

/// The pixels each view's edges cross, found once for all frames.
#[derive(Debug)]
pub struct EdgeBands {
    views: Vec<ViewBand>,
}

#[derive(Debug)]
struct ViewBand {
    sampler: ViewSampler,
    /// The frame pixels beside the sample whose median is the holder's
    /// radiance ([`ViewSampler::holder_band`]).
    holder: Vec<u32>,
    pixels: Vec<BandPixel>,
}

#[derive(Debug, Clone, Copy)]
struct BandPixel {
    /// y · width + x.
    index: u32,
    /// The pixel's centre, frame px.
    centre: [f64; 2],
    /// Which side (v 0, u 1, v 1, u 0) crosses it.
    side: u8,
    /// The two points inside the sample the target's level is read at.
    inner: [[f64; 2]; 2],
}

/// Per view and band pixel, the sums over the frames of a (value − H) and
/// a², a = W − H (luminance: the sum of the three channels).
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeSums(Vec<Vec<[f64; 2]>>);

impl EdgeSums {
    /// Add another frame's (or set of frames') sums.
    pub fn plus(mut self, other: &EdgeSums) -> EdgeSums {
        for (a, b) in self.0.iter_mut().zip(&other.0) {
            for (x, y) in a.iter_mut().zip(b) {
                x[0] += y[0];
                x[1] += y[1];
            }
        }
        self
    }
}

/// A fitted view's edges: per side the offsets at its two corners, px
/// inside the homography's outline
/// ([`super::calibrate::ViewCalibration::edge_offsets_px`]).
pub type EdgeFit = [[f64; 2]; 4];

/// Pixels nearer than this to another side than their own, or whose
/// level is read nearer, are left out: their squares and the level's
/// bilinear taps then lie wholly within the other sides.
const CORNER_CLEAR_PX: f64 = 1.5;
/// Where inside the edge the target's level is read, px.
const INNER_PX: [f64; 2] = [2.5, 4.5];
/// The largest relative difference of the level at the two inner points.
const FLAT_LEVEL: f64 = 0.05;
/// The fewest pixels a side is fitted from.
const MIN_SIDE_PIXELS: usize = 8;

impl EdgeBands {
    /// The band pixels of every view (frames of `dims` px).
    pub fn new(samplers: &[ViewSampler], dims: [usize; 2]) -> EdgeBands {
        let views = samplers
            .iter()
            .map(|s| {
                let [x0, y0, x1, y1] = s.homography().window(2.0);
                let (x1, y1) = (x1.min(dims[0]), y1.min(dims[1]));
                let mut pixels = Vec::new();
                for y in y0..y1 {
                    for x in x0..x1 {
                        let p = [x as f64 + 0.5, y as f64 + 0.5];
                        let depth: [f64; 4] = std::array::from_fn(|k| s.edge_depth(k, p));
                        let Some(side) = (0..4).find(|&k| depth[k].abs() <= 1.0) else {
                            continue;
                        };
                        let n = s.edge_normal(side);
                        let inner = INNER_PX.map(|d| [p[0] + d * n[0], p[1] + d * n[1]]);
                        // The pixel and its level's bilinear taps clear of
                        // the other sides.
                        let clear = |q: [f64; 2]| {
                            (0..4).all(|k| k == side || s.edge_depth(k, q) >= CORNER_CLEAR_PX)
                        };
                        if !(clear(p) && inner.iter().all(|&q| clear(q))) {
                            continue;
                        }
                        pixels.push(BandPixel {
                            index: (y * dims[0] + x) as u32,
                            centre: p,
                            side: side as u8,
                            inner,
                        });
                    }
                }
                ViewBand { sampler: *s, holder: s.holder_band(dims), pixels }
            })
            .collect();
        EdgeBands { views }
    }

    /// Sums of nothing.
    pub fn zero(&self) -> EdgeSums {
        EdgeSums(self.views.iter().map(|v| vec![[0.0; 2]; v.pixels.len()]).collect())
    }

    /// One white frame's sums.
    pub fn sums(&self, f: &Frame) -> EdgeSums {
        let lum = |c: [f64; 3]| c[0] + c[1] + c[2];
        EdgeSums(
            self.views
                .iter()
                .map(|v| {
                    let h = lum(holder_radiance(f, &v.holder));
                    v.pixels
                        .iter()
                        .map(|p| {
                            let i = 3 * p.index as usize;
                            let Some(px) = f.rgb.get(i..i + 3) else { return [0.0; 2] };
                            let value = px.iter().map(|&x| x as f64).sum::<f64>();
                            let w = p.inner.map(|q| lum(frame_bilinear(f, q[0], q[1])));
                            // The level at the pixel's centre, extrapolated
                            // along the normal (a beam's profile slopes).
                            let slope = (w[1] - w[0]) / (INNER_PX[1] - INNER_PX[0]);
                            let a = w[0] - INNER_PX[0] * slope - h;
                            let flat = (w[0] - w[1]).abs() <= FLAT_LEVEL * a;
                            if !(a > 0.0 && flat && value.is_finite() && h.is_finite()) {
                                return [0.0; 2];
                            }
                            [a * (value - h), a * a]
                        })
                        .collect()
                })
                .collect(),
        )
    }

    /// Every view's edges fitted to the sums (`None`: a side with too few
    /// pixels, or a fit that does not settle within a pixel).
    pub fn fit(&self, sums: &EdgeSums) -> Vec<Option<EdgeFit>> {
        self.views.iter().zip(&sums.0).map(|(v, s)| v.fit(s)).collect()
    }
}

impl ViewBand {
    fn fit(&self, sums: &[[f64; 2]]) -> Option<EdgeFit> {
        let h = *self.sampler.homography();
        let mut fit: EdgeFit = [[0.0; 2]; 4];
        for side in 0..4 {
            // (pixel, observed share, weight)
            let mut obs: Vec<(&BandPixel, f64, f64)> = self
                .pixels
                .iter()
                .zip(sums)
                .filter(|(p, s)| p.side as usize == side && s[1] > 0.0)
                .map(|(p, s)| (p, s[0] / s[1], s[1]))
                .filter(|o| o.1.is_finite() && (-0.5..=1.5).contains(&o.1))
                .collect();
            let shares = |o: [f64; 2]| {
                let mut all = [[0.0; 2]; 4];
                all[side] = o;
                ViewSampler::with_edge_offsets(h, Some(&all))
            };
            let mut d = [0.0f64; 2];
            for round in 0..8 {
                if obs.len() < MIN_SIDE_PIXELS {
                    return None;
                }
                let at = shares(d);
                const STEP: f64 = 0.01;
                let da = [shares([d[0] + STEP, d[1]]), shares([d[0] - STEP, d[1]])];
                let db = [shares([d[0], d[1] + STEP]), shares([d[0], d[1] - STEP])];
                let (mut m, mut g, mut rr, mut wsum) = ([[0.0; 2]; 2], [0.0; 2], 0.0, 0.0);
                let mut residual = Vec::with_capacity(obs.len());
                for &(p, s, w) in &obs {
                    let r = s - at.share(p.centre);
                    let j = [
                        (da[0].share(p.centre) - da[1].share(p.centre)) / (2.0 * STEP),
                        (db[0].share(p.centre) - db[1].share(p.centre)) / (2.0 * STEP),
                    ];
                    for a in 0..2 {
                        g[a] += w * j[a] * r;
                        for b in 0..2 {
                            m[a][b] += w * j[a] * j[b];
                        }
                    }
                    rr += w * r * r;
                    wsum += w;
                    residual.push(r);
                }
                let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
                if det.is_nan() || det <= 0.0 {
                    return None;
                }
                let inv = [[m[1][1] / det, -m[0][1] / det], [-m[1][0] / det, m[0][0] / det]];
                let step =
                    [inv[0][0] * g[0] + inv[0][1] * g[1], inv[1][0] * g[0] + inv[1][1] * g[1]];
                d = [d[0] + step[0], d[1] + step[1]];
                if !(d[0].abs() <= 1.0 && d[1].abs() <= 1.0) {
                    return None;
                }
                if round == 3 {
                    let rms = (rr / wsum).sqrt();
                    let keep: Vec<bool> = residual.iter().map(|r| r.abs() <= 5.0 * rms).collect();
                    let mut k = keep.iter();
                    obs.retain(|_| *k.next().unwrap_or(&true));
                }
            }
            fit[side] = d;
        }
        Some(fit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::linalg::Homography;
    use rand::{Rng, SeedableRng};

    /// Synthetic white frames of a view whose true edges lie off the
    /// calibrated homography's outline — each side moved by its own
    /// offsets at its two corners, 0.03–0.12 px — under lights whose levels
    /// slope across the view in different directions (12 lights), beside a
    /// holder at 5 % of the level, with shot noise: the fit places every
    /// side to 0.006 px along its length (1e-6 px without the noise), where
    /// the outline alone misses by up to 0.12 px.
    #[test]
    fn the_white_target_s_frames_place_each_edge() {
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let h = Homography([60.0 * c, -60.0 * s, 40.2, 60.0 * s, 60.0 * c, 20.7, 1e-3, -2e-3, 1.0]);
        let offsets = [[0.05, 0.12], [-0.08, -0.03], [0.10, -0.06], [-0.04, 0.07]];
        let truth = ViewSampler::with_edge_offsets(h, Some(&offsets));
        let calibrated = ViewSampler::new(h);
        let dims = [128usize, 128usize];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let bands = EdgeBands::new(&[calibrated], dims);
        let mut sums = bands.zero();
        for light in 0..12 {
            let slope = [0.002 * (light as f64 - 5.5), 0.0015 * (4.0 - light as f64)];
            let mut rgb = vec![0.0f32; dims[0] * dims[1] * 3];
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let p = [x as f64 + 0.5, y as f64 + 0.5];
                    let level =
                        3000.0 * (1.0 + slope[0] * (p[0] - 64.0) + slope[1] * (p[1] - 64.0));
                    let share = truth.share(p);
                    let v = share * level + (1.0 - share) * 150.0;
                    for k in 0..3 {
                        let noise = (rng.random::<f64>() - 0.5) * 12f64.sqrt() * (v / 3.0).sqrt();
                        rgb[3 * (y * dims[0] + x) + k] = (v / 3.0 + noise) as f32;
                    }
                }
            }
            let f = Frame { width: dims[0] as u32, height: dims[1] as u32, rgb };
            sums = sums.plus(&bands.sums(&f));
        }
        let fit = bands.fit(&sums)[0].expect("every side fitted");
        let fitted = ViewSampler::with_edge_offsets(h, Some(&fit));
        let corners = h.corners();
        let mut outline_worst = 0.0f64;
        for k in 0..4 {
            let (a, b) = (corners[k], corners[(k + 1) % 4]);
            for t in [0.1, 0.3, 0.5, 0.7, 0.9] {
                let p = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                // The true edge's point beside p.
                let n = truth.edge_normal(k);
                let d = truth.edge_depth(k, p);
                let q = [p[0] - d * n[0], p[1] - d * n[1]];
                assert!(truth.edge_depth(k, q).abs() < 1e-9);
                let miss = fitted.edge_depth(k, q);
                assert!(miss.abs() < 0.006, "side {k} at {t}: {miss} px ({fit:?})");
                outline_worst = outline_worst.max(calibrated.edge_depth(k, q).abs());
            }
        }
        assert!(outline_worst > 0.1, "{outline_worst}");
    }
}
