//! **Material PSNR** (docs/benchmarks.md, "Material fidelity"), defined
//! once: for each (light, view) pair a 32 × 32 grid of uv cells over the
//! sample, each the mean of 3 × 3 sub-points; the MSE over cells, channels
//! and pairs; the peak is the 99th percentile of the truth's cell values
//! over the set. The gain-free PSNR scores the estimate after the single
//! scale factor that fits it best to the truth (least squares).

use scanner_formats::queries::Query;

/// Cells per side.
pub const CELLS: usize = 32;
/// Sub-points per cell side.
pub const SUB: usize = 3;

/// The sub-point uv of cell (i, k), sub-point (a, b).
pub fn sub_point(i: usize, k: usize, a: usize, b: usize) -> [f64; 2] {
    let n = (CELLS * SUB) as f64;
    [((i * SUB + a) as f64 + 0.5) / n, ((k * SUB + b) as f64 + 0.5) / n]
}

/// Every sub-point of every cell for one pair (`CELLS² · SUB²` queries,
/// cell-major: cell (i, k) = index k·CELLS + i holds SUB² queries).
pub fn pair_queries(light: [f64; 3], view: [f64; 3]) -> Vec<Query> {
    let mut out = Vec::with_capacity(CELLS * CELLS * SUB * SUB);
    for k in 0..CELLS {
        for i in 0..CELLS {
            for b in 0..SUB {
                for a in 0..SUB {
                    out.push(Query { uv: sub_point(i, k, a, b), wi: light, wo: view });
                }
            }
        }
    }
    out
}

/// Means of each cell's SUB² consecutive values.
pub fn cell_means(values: &[[f32; 3]]) -> Vec<[f64; 3]> {
    values
        .chunks_exact(SUB * SUB)
        .map(|c| {
            let mut m = [0.0; 3];
            for v in c {
                for k in 0..3 {
                    m[k] += v[k] as f64 / (SUB * SUB) as f64;
                }
            }
            m
        })
        .collect()
}

/// The material PSNR's peak: the 99th percentile of the truth's cell
/// values ([`cell_means`]) over all cells and channels.
pub fn peak(truth_cells: &[[f64; 3]]) -> f64 {
    let mut tv: Vec<f64> = truth_cells.iter().flatten().copied().collect();
    tv.sort_by(f64::total_cmp);
    tv[((tv.len() as f64 * 0.99) as usize).min(tv.len() - 1)]
}

/// Material PSNR of an estimate against the truth, both as answers to the
/// same [`pair_queries`] concatenated over the pairs: (PSNR, gain-free
/// PSNR, the best gain), dB.
pub fn material_psnr(estimate: &[[f32; 3]], truth: &[[f32; 3]]) -> (f64, f64, f64) {
    assert_eq!(estimate.len(), truth.len(), "answers to the same queries");
    let e = cell_means(estimate);
    let t = cell_means(truth);
    let peak = peak(&t);
    let n = (e.len() * 3) as f64;
    let mse = |s: f64| {
        e.iter()
            .zip(&t)
            .map(|(a, b)| (0..3).map(|k| (s * a[k] - b[k]).powi(2)).sum::<f64>())
            .sum::<f64>()
            / n
    };
    let num: f64 = e.iter().zip(&t).map(|(a, b)| (0..3).map(|k| a[k] * b[k]).sum::<f64>()).sum();
    let den: f64 = e.iter().map(|a| (0..3).map(|k| a[k] * a[k]).sum::<f64>()).sum();
    let gain = if den > 0.0 { num / den } else { 1.0 };
    let psnr = |m: f64| 10.0 * (peak * peak / m).log10();
    (psnr(mse(1.0)), psnr(mse(gain)), gain)
}

/// The material's answers to [`pair_queries`] at every captured pair (its
/// own calibrated directions), beside the values of the images it was
/// built from at the same points — the region images, each carried to its
/// pair's central directions by the texel model `texels` when the material
/// has one (`texel_fit::centred_image`; empty `texels`: none): the
/// palettisation error alone, as (material, images) concatenated over the
/// pairs for [`material_psnr`].
pub fn captured_pair_answers(
    material: &scanner_shading::Material,
    regions: &super::RegionSet,
    texels: &[scanner_shading::texel::TexelParams],
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    use rayon::prelude::*;
    let pairs: Vec<(usize, usize)> = (0..regions.lights.len())
        .flat_map(|l| (0..regions.views.len()).map(move |v| (l, v)))
        .collect();
    type Answers = Vec<[f32; 3]>;
    let per_pair: Vec<(Answers, Answers)> = pairs
        .par_iter()
        .map(|&(li, vi)| {
            let q = pair_queries(regions.light_dirs[li], regions.view_dirs[vi]);
            let mat = super::material::shade(material, &q);
            let img = super::texel_fit::held_image(regions, texels, li, vi);
            let reg = q
                .iter()
                .map(|q| {
                    let (v, d) = (
                        super::regions::bilinear(regions.size, &img, q.uv),
                        regions.detail_at(li, q.uv),
                    );
                    std::array::from_fn(|k| (v[k] * d[k]) as f32)
                })
                .collect();
            (mat, reg)
        })
        .collect();
    let (mut m, mut r) = (Vec::new(), Vec::new());
    for (a, b) in per_pair {
        m.extend(a);
        r.extend(b);
    }
    (m, r)
}
