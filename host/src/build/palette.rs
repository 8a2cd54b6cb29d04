//! Palettes (Fig. 6 steps 4–5): each region image reduced to K colours
//! with per-pixel indices.
//!
//! **Shared indices.** At S = 128 one 8-bit index image per (light, view)
//! is 26 MB for a 40 × 40 scan, over the 16 MB a material may take. So the
//! g lights of a *light group* (the nearest lights, [`group_lights`]) share
//! each view's index image, while every (light, view) keeps its own palette
//! of K colours: a texel's index is chosen by k-means over the group's
//! texel *vectors* (g RGB values side by side), and each image's palette
//! entry is the linear mean of its texels with that index. g = 1 is the
//! patent's per-image palette.
//!
//! **Space.** Clustering runs on ln(x + ε) per channel, ε = 2 % of the
//! group's mean value: relative precision for the bright (HDR highlights
//! span decades), absolute for texels near black whose relative noise would
//! waste colours. Each texel weighs its mean value + ε, so that errors
//! count as against shot noise (Σ Δx² / (x + ε)): a glossy sample's few
//! highlight texels, hundreds of times the body, get colours of their own.
//! Palette entries are means in linear radiance, so the palettised image is
//! unbiased.
//!
//! **Why no k-means crate.** `kmeans_colors`' k-means++ seeding recomputes
//! every point's distance to every chosen centre for each new one
//! (O(n·K²): 5 × 10⁸ distances per image at K = 256, n = 16 384) and its
//! points are fixed colour types; `linfa-clustering` has no acceleration and
//! per-distance `ndarray` overhead; `quantette`, `color_quant` and
//! `imagequant` quantise 8-bit sRGB, not HDR vectors. The few dozen lines
//! below are weighted Lloyd's algorithm with incremental k-means++ seeding
//! on 16·K texels (the heaviest 4·K and a random rest), then one assignment
//! of every texel.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Groups of up to `g` lights, each light with its nearest ungrouped
/// neighbours, in light order: `groups[light] = group`.
pub fn group_lights(dirs: &[[f64; 3]], g: usize) -> Vec<u8> {
    grouped(dirs, |_| g.max(1))
}

/// Exactly `count` groups (1…L) of ⌈L / count⌉ or ⌊L / count⌋ lights,
/// the larger first, each light with its nearest ungrouped neighbours, in
/// light order: `groups[light] = group`.
pub fn group_lights_into(dirs: &[[f64; 3]], count: usize) -> Vec<u8> {
    let n = dirs.len();
    let count = count.clamp(1, n.max(1));
    let (base, extra) = (n / count, n % count);
    grouped(dirs, |group| base + usize::from(group < extra))
}

/// Lights in order, each ungrouped one starting a group of up to
/// `quota(group)` with its nearest ungrouped neighbours.
fn grouped(dirs: &[[f64; 3]], quota: impl Fn(usize) -> usize) -> Vec<u8> {
    let mut group = vec![usize::MAX; dirs.len()];
    let mut next = 0;
    for l in 0..dirs.len() {
        if group[l] != usize::MAX {
            continue;
        }
        group[l] = next;
        for _ in 1..quota(next) {
            let dot = |a: usize| (0..3).map(|k| dirs[a][k] * dirs[l][k]).sum::<f64>();
            let best = (0..dirs.len())
                .filter(|&o| group[o] == usize::MAX)
                .max_by(|&a, &b| dot(a).total_cmp(&dot(b)));
            match best {
                Some(o) => group[o] = next,
                None => break,
            }
        }
        next += 1;
    }
    group.into_iter().map(|x| x as u8).collect()
}

/// One group's palettes: `indices[texel]`, `palettes[image][colour]`.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupPalettes {
    /// Per texel, the colour index.
    pub indices: Vec<u8>,
    /// Per image of the group, K linear RGB colours.
    pub palettes: Vec<Vec<[f32; 3]>>,
}

/// Palettise the images of one light group (same view; every image the
/// same texel count) to `k` ≤ 256 colours. Deterministic for a seed.
pub fn palettise(images: &[&[[f32; 3]]], k: usize, seed: u64) -> GroupPalettes {
    assert!((1..=256).contains(&k), "1…256 colours");
    assert!(!images.is_empty() && (1..=4).contains(&images.len()), "1…4 images per group");
    match images.len() {
        1 => run::<3>(images, k, seed),
        2 => run::<6>(images, k, seed),
        3 => run::<9>(images, k, seed),
        _ => run::<12>(images, k, seed),
    }
}

fn dist2<const D: usize>(a: &[f32; D], b: &[f32; D]) -> f32 {
    let mut s = 0.0;
    for i in 0..D {
        let d = a[i] - b[i];
        s += d * d;
    }
    s
}

/// Centres laid out by dimension (`dims[i · K + c]` = centre c's i-th
/// coordinate), so that the distances from a point to all of them are
/// computed several centres at a time. Each distance is the same sum, in
/// the same order, as [`dist2`]'s, and the nearest is the first at the
/// least distance: the answers are those of a loop over the centres.
struct Centres<const D: usize> {
    k: usize,
    dims: Vec<f32>,
}

impl<const D: usize> Centres<D> {
    fn new(centres: &[[f32; D]]) -> Self {
        let k = centres.len();
        assert!(k <= 256, "at most 256 centres");
        let dims = (0..D).flat_map(|i| centres.iter().map(move |c| c[i])).collect();
        Centres { k, dims }
    }

    /// The nearest centre to `p` and its squared distance ((0, ∞) if none
    /// is at a finite one).
    fn nearest(&self, p: &[f32; D]) -> (usize, f32) {
        let mut all = [0.0f32; 256];
        let d = &mut all[..self.k];
        for (i, row) in self.dims.chunks_exact(self.k.max(1)).enumerate() {
            let x = p[i];
            for (s, &c) in d.iter_mut().zip(row) {
                let e = x - c;
                *s += e * e;
            }
        }
        first_least(d)
    }
}

/// The index of the first least value of `d` (finite values; `(0, ∞)` if
/// none is below ∞), and the value.
#[inline]
fn first_least(d: &[f32]) -> (usize, f32) {
    #[cfg(target_arch = "x86_64")]
    {
        first_least_sse2(d)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        first_least_lanes(d)
    }
}

/// [`first_least`] in 8 lanes: each lane (values i ≡ lane mod 8) keeps the
/// first at its least value, then the lanes' least, the first index on
/// ties, then the values past the last 8.
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
fn first_least_lanes(d: &[f32]) -> (usize, f32) {
    let (mut best, mut at) = ([f32::INFINITY; 8], [0u32; 8]);
    let chunks = d.chunks_exact(8);
    let tail = chunks.remainder();
    for (ci, c) in chunks.enumerate() {
        for l in 0..8 {
            if c[l] < best[l] {
                best[l] = c[l];
                at[l] = (ci * 8 + l) as u32;
            }
        }
    }
    lanes_then_tail(&best, &at, d.len(), tail)
}

fn lanes_then_tail(best: &[f32; 8], at: &[u32; 8], len: usize, tail: &[f32]) -> (usize, f32) {
    let mut found = (0usize, f32::INFINITY);
    for (&v, &i) in best.iter().zip(at) {
        if v < found.1 || (v == found.1 && v < f32::INFINITY && (i as usize) < found.0) {
            found = (i as usize, v);
        }
    }
    let start = len - tail.len();
    for (j, &v) in tail.iter().enumerate() {
        if v < found.1 {
            found = (start + j, v);
        }
    }
    found
}

/// [`first_least_lanes`] with SSE2 (every x86-64 has it): the compiler
/// does not vectorise the lanes' index selection by itself.
#[cfg(target_arch = "x86_64")]
fn first_least_sse2(d: &[f32]) -> (usize, f32) {
    use std::arch::x86_64::*;
    let chunks = d.chunks_exact(8);
    let tail = chunks.remainder();
    let (mut best, mut at) = ([f32::INFINITY; 8], [0u32; 8]);
    // SAFETY: SSE2 is part of x86-64; every load and store is unaligned
    // and within `c`, `best` and `at`.
    unsafe {
        let mut b = [_mm_set1_ps(f32::INFINITY); 2];
        let mut i = [_mm_setzero_si128(); 2];
        let mut index = [_mm_setr_epi32(0, 1, 2, 3), _mm_setr_epi32(4, 5, 6, 7)];
        let eight = _mm_set1_epi32(8);
        for c in chunks {
            for h in 0..2 {
                let v = _mm_loadu_ps(c.as_ptr().add(4 * h));
                let m = _mm_cmplt_ps(v, b[h]);
                b[h] = _mm_or_ps(_mm_and_ps(m, v), _mm_andnot_ps(m, b[h]));
                let mi = _mm_castps_si128(m);
                i[h] = _mm_or_si128(_mm_and_si128(mi, index[h]), _mm_andnot_si128(mi, i[h]));
                index[h] = _mm_add_epi32(index[h], eight);
            }
        }
        for h in 0..2 {
            _mm_storeu_ps(best.as_mut_ptr().add(4 * h), b[h]);
            _mm_storeu_si128(at.as_mut_ptr().add(4 * h).cast(), i[h]);
        }
    }
    lanes_then_tail(&best, &at, d.len(), tail)
}

fn run<const D: usize>(images: &[&[[f32; 3]]], k: usize, seed: u64) -> GroupPalettes {
    let n = images[0].len();
    let g = images.len();
    let mean =
        images.iter().flat_map(|i| i.iter().flatten()).map(|&x| x.max(0.0) as f64).sum::<f64>()
            / (n * g * 3) as f64;
    let eps = (0.02 * mean).max(1e-12) as f32;
    let points: Vec<[f32; D]> = (0..n)
        .map(|t| std::array::from_fn(|i| (images[i / 3][t][i % 3].max(0.0) + eps).ln()))
        .collect();
    // Each texel's weight: its mean value + ε, so that the clustering's
    // Σ w·Δ(ln)² ≈ Σ Δx² / (x + ε), the error against a variance that grows
    // with the value as shot noise does. Unweighted, a few highlight texels
    // among thousands of the body get a colour or two between them, and
    // their relative error, times values thousands of times the body's,
    // dominates every absolute error.
    let weight: Vec<f32> = (0..n)
        .map(|t| {
            let sum: f32 = (0..D).map(|i| images[i / 3][t][i % 3].max(0.0)).sum();
            sum / D as f32 + eps
        })
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // The training subset: the heaviest quarter of its size, then texels at
    // random, each standing for its share of the rest.
    let m = n.min(16 * k);
    let mut order: Vec<usize> = (0..n).collect();
    let heavy = if m < n {
        order.select_nth_unstable_by(m / 4, |&a, &b| weight[b].total_cmp(&weight[a]));
        m / 4
    } else {
        m
    };
    for i in heavy..m {
        let j = rng.random_range(i..n);
        order.swap(i, j);
    }
    let stand_for = if m > heavy { (n - heavy) as f32 / (m - heavy) as f32 } else { 1.0 };
    let train: Vec<([f32; D], f32)> = order[..m]
        .iter()
        .enumerate()
        .map(|(i, &t)| (points[t], if i < heavy { weight[t] } else { weight[t] * stand_for }))
        .collect();
    // k-means++ seeding (weighted), distances updated incrementally.
    let k = k.min(m);
    let mut centres: Vec<[f32; D]> = vec![train[rng.random_range(0..m)].0];
    let mut d2: Vec<f32> = train.iter().map(|(p, _)| dist2(p, &centres[0])).collect();
    while centres.len() < k {
        let total: f64 = d2.iter().zip(&train).map(|(&x, (_, w))| (x * w) as f64).sum();
        if total <= 0.0 {
            break; // fewer distinct texels than colours
        }
        let mut r = rng.random::<f64>() * total;
        let mut pick = m - 1;
        for (i, (&x, (_, w))) in d2.iter().zip(&train).enumerate() {
            r -= (x * w) as f64;
            if r <= 0.0 {
                pick = i;
                break;
            }
        }
        let c = train[pick].0;
        for ((p, _), d) in train.iter().zip(d2.iter_mut()) {
            *d = d.min(dist2(p, &c));
        }
        centres.push(c);
    }
    // Lloyd on the subset, weighted means.
    let mut assign = vec![usize::MAX; m];
    for _ in 0..12 {
        let mut changed = 0;
        let layout = Centres::new(&centres);
        for ((p, _), a) in train.iter().zip(assign.iter_mut()) {
            let (c, _) = layout.nearest(p);
            if c != *a {
                *a = c;
                changed += 1;
            }
        }
        let mut sum = vec![[0f64; D]; centres.len()];
        let mut total = vec![0f64; centres.len()];
        for ((p, w), &a) in train.iter().zip(&assign) {
            total[a] += *w as f64;
            for i in 0..D {
                sum[a][i] += (w * p[i]) as f64;
            }
        }
        for (c, (s, &tw)) in centres.iter_mut().zip(sum.iter().zip(&total)) {
            if tw > 0.0 {
                *c = std::array::from_fn(|i| (s[i] / tw) as f32);
            }
        }
        if changed * 1000 < m {
            break;
        }
    }
    // Every texel to its nearest centre; palettes as linear means.
    let layout = Centres::new(&centres);
    let indices: Vec<u8> = points.iter().map(|p| layout.nearest(p).0 as u8).collect();
    let mut palettes = Vec::with_capacity(g);
    for img in images {
        let mut sum = vec![[0f64; 3]; 256];
        let mut count = vec![0usize; 256];
        for (px, &i) in img.iter().zip(&indices) {
            count[i as usize] += 1;
            for c in 0..3 {
                sum[i as usize][c] += px[c].max(0.0) as f64;
            }
        }
        palettes.push(
            (0..k.max(1))
                .map(|i| {
                    if count[i] > 0 {
                        sum[i].map(|s| (s / count[i] as f64) as f32)
                    } else {
                        [0.0; 3]
                    }
                })
                .collect(),
        );
    }
    GroupPalettes { indices, palettes }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_nearest_centre_is_the_first_at_the_least_distance() {
        // Against a loop over the centres, with duplicate centres (ties)
        // and counts that fill and do not fill the lanes.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for k in [1usize, 5, 8, 13, 64, 256] {
            let mut centres: Vec<[f32; 6]> =
                (0..k).map(|_| std::array::from_fn(|_| rng.random_range(-2.0..2.0))).collect();
            if k > 4 {
                centres[k - 1] = centres[1];
                centres[3] = centres[k / 2];
            }
            let layout = Centres::new(&centres);
            for _ in 0..500 {
                let p: [f32; 6] = match rng.random_range(0..4) {
                    0 => centres[rng.random_range(0..k)],
                    _ => std::array::from_fn(|_| rng.random_range(-3.0..3.0)),
                };
                let mut want = (0, f32::INFINITY);
                for (i, c) in centres.iter().enumerate() {
                    let d = dist2(&p, c);
                    if d < want.1 {
                        want = (i, d);
                    }
                }
                assert_eq!(layout.nearest(&p), want, "K = {k}, {p:?}");
                let mut d = [0.0f32; 256];
                for (c, x) in centres.iter().zip(d.iter_mut()) {
                    *x = dist2(&p, c);
                }
                assert_eq!(first_least_lanes(&d[..k]), want, "K = {k}, {p:?}");
            }
        }
    }

    #[test]
    fn few_colours_are_kept_exactly_and_many_approximated() {
        // 4 distinct colours per image: reproduced exactly with K = 4.
        let a: Vec<[f32; 3]> = (0..1024).map(|i| [(i % 4) as f32, 1.0, 10.0]).collect();
        let b: Vec<[f32; 3]> = (0..1024).map(|i| [0.5, ((i % 4) * 3) as f32, 0.1]).collect();
        let p = palettise(&[&a, &b], 4, 1);
        for (t, &i) in p.indices.iter().enumerate() {
            assert_eq!(p.palettes[0][i as usize], a[t]);
            assert_eq!(p.palettes[1][i as usize], b[t]);
        }
        // A smooth HDR ramp over 3 decades in 64 colours (ε = 2 % of the
        // mean: relative above, absolute below).
        let ramp: Vec<[f32; 3]> =
            (0..4096).map(|i| [10f32.powf(i as f32 / 4096.0 * 3.0 - 2.0); 3]).collect();
        let mean = ramp.iter().map(|p| p[0]).sum::<f32>() / 4096.0;
        let eps = 0.02 * mean;
        let p = palettise(&[&ramp], 64, 2);
        let mut worst = [0f32; 2];
        for (t, &i) in p.indices.iter().enumerate() {
            let (got, want) = (p.palettes[0][i as usize][0], ramp[t][0]);
            let e = (got - want).abs();
            worst[0] = worst[0].max(e / ((want + eps) * mean).sqrt());
            worst[1] = worst[1].max(e / (want + eps));
        }
        // Within 8 % of √((x + ε)·mean), the noise-like scale the
        // clustering weighs errors by, and never beyond 15 % of x + ε.
        assert!(worst[0] < 0.08 && worst[1] < 0.15, "{worst:?}");
        // Deterministic.
        assert_eq!(palettise(&[&ramp], 64, 2), p);
    }

    #[test]
    fn sparse_highlights_get_colours_of_their_own() {
        // A glossy sample's region image: 4 000 body texels near 0.05 and
        // 150 highlight texels from 1 to 300 (each its own value), as a
        // metal speck under its mirror direction gives.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut img: Vec<[f32; 3]> =
            (0..4000).map(|_| [0.05 * (0.8 + 0.4 * rng.random::<f32>()); 3]).collect();
        img.extend((0..150).map(|i| [300f32.powf(i as f32 / 149.0); 3]));
        let p = palettise(&[&img], 256, 5);
        let rel = |t: usize| {
            let got = p.palettes[0][p.indices[t] as usize][0];
            (got - img[t][0]).abs() / img[t][0]
        };
        let body = (0..4000).map(rel).fold(0f32, f32::max);
        let highlight = (4000..img.len()).map(rel).fold(0f32, f32::max);
        // Unweighted (every texel alike) the highlights were 2 % off: 6
        // on values up to 300, a hundred times the body.
        assert!(highlight < 0.005 && body < 0.01, "highlights {highlight}, body {body}");
    }

    /// Five lights: two pairs of neighbours and one apart.
    fn five_lights() -> [[f64; 3]; 5] {
        let d = |t: f64, p: f64| {
            let (t, p) = (f64::to_radians(t), f64::to_radians(p));
            [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
        };
        [d(10.0, 0.0), d(50.0, 0.0), d(12.0, 5.0), d(52.0, 3.0), d(30.0, 180.0)]
    }

    #[test]
    fn lights_are_grouped_with_their_nearest() {
        let dirs = five_lights();
        assert_eq!(group_lights(&dirs, 2), vec![0, 1, 0, 1, 2]);
        assert_eq!(group_lights(&dirs, 1), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn lights_are_grouped_into_a_given_number_of_groups() {
        let dirs = five_lights();
        // The larger groups first, each light with its nearest.
        assert_eq!(group_lights_into(&dirs, 2), vec![0, 1, 0, 1, 0]);
        assert_eq!(group_lights_into(&dirs, 3), vec![0, 1, 0, 1, 2]);
        assert_eq!(group_lights_into(&dirs, 5), vec![0, 1, 2, 3, 4]);
        // Out of range: one group, or one light each.
        assert_eq!(group_lights_into(&dirs, 0), vec![0; 5]);
        assert_eq!(group_lights_into(&dirs, 9), vec![0, 1, 2, 3, 4]);
    }
}
