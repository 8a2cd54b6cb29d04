//! The metric's point-sampling limit at material_fidelity's novel pairs
//! (same seed, same pairs): a perfect area-integrating estimate (each
//! cell's mean over 12 × 12 points) scored against the metric's 3 × 3
//! points. Then the default material built from the scan, scored at the
//! same pairs, and its six worst pairs dissected: each pair's share of the
//! error, its half vector's and directions' angles, the limit's share of
//! its error, and its three worst cells (material, truth, the 12 × 12 mean
//! and the texel model under the cell's centre). And where on the sample
//! the error lies: by ring of metric cells from the sample's edge (novel
//! and captured pairs), by side, and texel by texel from the edge at every
//! 8th captured pair (region images and material against the truth at the
//! texels' centres; the outermost texels also as their inward neighbours
//! and extrapolated). First, where the calibration put the sample's edges
//! in every view against the as-built truth (views located by their
//! corners and by the phase alignment apart).
//!
//! `cargo run --release -p tests --example novel_limit -- [--materials a,b] [--out DIR] [--seed 1] [--bin 1] [--novel 300]`
//! (scans kept in `--out` as material_fidelity keeps them: that example's
//! `--out` reuses them).
use std::path::PathBuf;

use hil_sim::materials::{Sample, lookup};
use host::build::calibrate::Silent;
use host::build::material::{MaterialOptions, build_material, shade};
use scanner_shading::Material;

fn main() {
    tests::check_region_args(&["--bin", "--materials", "--novel", "--out", "--seed"], &[]);
    let seed: u64 = tests::arg("--seed", 1);
    let bin: u32 = tests::arg("--bin", 1);
    let novel: usize = tests::arg("--novel", 300);
    let list: String = tests::arg("--materials", "leather".to_string());
    let pairs = tests::random_pairs(novel, 60.0, seed);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/builder-fidelity"));
    let materials: Vec<&str> = list.split(',').collect();
    let (g, cal, truth) = tests::scanned_and_calibrated(&out, seed, bin, 40, &materials);
    edge_errors(&truth, &cal);
    for &m in &materials {
        let sample = Sample::small(lookup(m).unwrap());
        let three = tests::truth_answers(&pairs, &sample);
        let dense: Vec<[f32; 3]> = pairs
            .iter()
            .flat_map(|&(wi, wo)| tests::dense_cell_answers(&sample, wi, wo, 12))
            .collect();
        let e = tests::PairErrors::new(&dense, &three);
        let (share, rest) = e.concentration(0.05);
        println!(
            "{m}: novel point-sampling limit {:.2} dB (worst 5 % share {:.0} %, other 95 % {rest:.2} dB)",
            e.db(e.mse.iter().sum::<f64>() / e.mse.len() as f64),
            share * 100.0
        );
        let regions = tests::scanned_regions(&out, &g, &cal, m);
        let provenance = tests::example_provenance(&g, &cal, "novel_limit");
        let data =
            build_material(&regions, m, 25.4, provenance, &MaterialOptions::default(), &Silent)
                .unwrap();
        let texels = data.texels.clone();
        let mat = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
        let answers = tests::pairs_answers(&pairs, &|_, q| shade(&mat, q));
        let em = tests::PairErrors::new(&answers, &three);
        let total: f64 = em.mse.iter().sum();
        println!("{m}: material {:.2} dB, peak {:.4}", em.db(total / em.mse.len() as f64), em.peak);
        let per = three.len() / pairs.len();
        let (rm, rd) = (rings(&answers, &three, per), rings(&dense, &three, per));
        println!(
            "  novel pairs' error by ring of cells from the edge (material / limit): {}",
            ring_shares(&rm, &rd)
        );
        let inner = |sum: &[f64; 16]| {
            // Without the outermost ring: 30 × 30 cells a pair are left.
            em.db((sum.iter().sum::<f64>() - sum[0]) / (em.mse.len() * 3 * 900) as f64)
        };
        println!(
            "  without the outermost ring: material {:.2} dB, limit {:.2} dB",
            inner(&rm),
            inner(&rd)
        );
        // The same at the captured pairs: region images and material.
        let captured = tests::as_built_pairs(&truth, &cal, &regions);
        let t_cap = tests::truth_answers(&captured, &sample);
        let a_reg = tests::region_answers(&captured, &regions);
        let a_mat = tests::pairs_answers(&captured, &|_, q| shade(&mat, q));
        let (rr, rc) = (rings(&a_reg, &t_cap, per), rings(&a_mat, &t_cap, per));
        println!(
            "  captured pairs' error by ring (region images / material): {}",
            ring_shares(&rr, &rc)
        );
        // Texel by texel at every 8th captured pair: the squared error of
        // texels d texels from the edge over that of the inner texels.
        let size = regions.size;
        let mut by_d = vec![[0f64; 8]; size / 2];
        for (p, &(wi, wo)) in captured.iter().enumerate().step_by(8) {
            let q: Vec<scanner_formats::queries::Query> = (0..size * size)
                .map(|t| scanner_formats::queries::Query {
                    uv: [
                        ((t % size) as f64 + 0.5) / size as f64,
                        ((t / size) as f64 + 0.5) / size as f64,
                    ],
                    wi,
                    wo,
                })
                .collect();
            let tr = hil_sim::truth::answer(&sample, &q);
            let re = tests::region_pair_answers(&regions, p, &q);
            let ma = shade(&mat, &q);
            for t in 0..size * size {
                let (x, y) = (t % size, t / size);
                let d = x.min(y).min(size - 1 - x).min(size - 1 - y);
                let e =
                    |a: &[f32; 3]| (0..3).map(|j| (a[j] - tr[t][j]).powi(2) as f64).sum::<f64>();
                by_d[d][0] += e(&re[t]);
                by_d[d][1] += e(&ma[t]);
                by_d[d][2] += 1.0;
                let sum = |a: &[f32; 3]| (a[0] + a[1] + a[2]) as f64;
                by_d[d][3] += sum(&re[t]);
                by_d[d][4] += sum(&ma[t]);
                by_d[d][5] += sum(&tr[t]);
                // The outermost texels as their inward neighbours (copy) and
                // as the line through the next two (extrapolated).
                let step = |c: usize| (c == 0) as isize - (c == size - 1) as isize;
                let (dx, dy) = (step(x), step(y));
                let at = |k: isize| {
                    let (u, v) = ((x as isize + k * dx) as usize, (y as isize + k * dy) as usize);
                    re[v * size + u]
                };
                let (a1, a2) = (at(1), at(2));
                let ex: [f32; 3] = std::array::from_fn(|j| (2.0 * a1[j] - a2[j]).max(0.0));
                by_d[d][6] += e(&a1);
                by_d[d][7] += e(&ex);
            }
        }
        let inner = |k: usize| {
            let (e, n) = by_d[8..].iter().fold((0.0, 0.0), |a, b| (a.0 + b[k], a.1 + b[2]));
            e / n
        };
        println!(
            "  captured pairs, texels d from the edge, squared error over the inner texels' (d ≥ 8), region images / material: {}",
            (0..8)
                .map(|d| format!(
                    "{d}: {:.1} / {:.1}",
                    by_d[d][0] / by_d[d][2] / inner(0),
                    by_d[d][1] / by_d[d][2] / inner(1)
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
        println!(
            "  region images' outermost texels as their inward neighbours' {:.1}, extrapolated {:.1} (same unit)",
            by_d[0][6] / by_d[0][2] / inner(0),
            by_d[0][7] / by_d[0][2] / inner(0)
        );
        println!(
            "  their mean over the truth's, region images / material: {}",
            (0..8)
                .map(|d| format!(
                    "{d}: {:.3} / {:.3}",
                    by_d[d][3] / by_d[d][5],
                    by_d[d][4] / by_d[d][5]
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
        for (name, est, t) in [
            ("novel, material", &answers, &three),
            ("captured, region images", &a_reg, &t_cap),
            ("captured, material", &a_mat, &t_cap),
        ] {
            let e = sides(est, t, per);
            let total: f64 = e.iter().sum();
            println!(
                "  {name}: outermost column at u 0 / u 1, row at v 0 / v 1: {:.0} / {:.0} / {:.0} / {:.0} % of the error",
                100.0 * e[0] / total,
                100.0 * e[1] / total,
                100.0 * e[2] / total,
                100.0 * e[3] / total
            );
        }
        for &p in em.worst_first().iter().take(6) {
            let (wi, wo) = pairs[p];
            let h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
            let hl = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
            println!(
                "  pair {p}: {:.1} % of the error; θh {:.2}°, θi {:.1}°, θo {:.1}°; dense-limit mse share {:.1} %",
                100.0 * em.mse[p] / total,
                (h[2] / hl).acos().to_degrees(),
                wi[2].acos().to_degrees(),
                wo[2].acos().to_degrees(),
                100.0 * e.mse[p] / em.mse[p]
            );
            // Its worst cells.
            let cm = host::build::fidelity::cell_means(&answers[p * per..(p + 1) * per]);
            let ct = host::build::fidelity::cell_means(&three[p * per..(p + 1) * per]);
            let cd = host::build::fidelity::cell_means(&dense[p * per..(p + 1) * per]);
            let mut cells: Vec<usize> = (0..cm.len()).collect();
            let err = |c: usize| (0..3).map(|k| (cm[c][k] - ct[c][k]).powi(2)).sum::<f64>();
            cells.sort_by(|&x, &y| err(y).total_cmp(&err(x)));
            let pe: f64 = (0..cm.len()).map(err).sum();
            for &c in cells.iter().take(3) {
                let (i, k) = (c % 32, c / 32);
                // The texel under the cell's centre.
                let side = (texels.len() as f64).sqrt() as usize;
                let (ti, tk) = ((2 * i + 1) * side / 64, (2 * k + 1) * side / 64);
                let t = tk * side + ti;
                let tp = texels.get(t);
                println!(
                    "    cell ({i}, {k}) {:.0} %: material {:.3}, truth {:.3}, dense {:.3}; texel α {:?} F0 {:?} n {:?}",
                    100.0 * err(c) / pe,
                    cm[c][1],
                    ct[c][1],
                    cd[c][1],
                    tp.map(|x| x.alpha),
                    tp.map(|x| x.specular[1]),
                    tp.map(|x| x.normal),
                );
            }
        }
    }
}

/// Each metric cell's squared error of `est` against `truth` (answers to
/// [`tests::pair_queries`], `per` a pair), over all pairs: `visit(i, k,
/// error)` for the cell in column i, row k of 32 × 32.
fn cell_errors(
    est: &[[f32; 3]],
    truth: &[[f32; 3]],
    per: usize,
    mut visit: impl FnMut(usize, usize, f64),
) {
    for (e, t) in est.chunks(per).zip(truth.chunks(per)) {
        let (ce, ct) = (host::build::fidelity::cell_means(e), host::build::fidelity::cell_means(t));
        for (c, (a, b)) in ce.iter().zip(&ct).enumerate() {
            visit(c % 32, c / 32, (0..3).map(|j| (a[j] - b[j]).powi(2)).sum::<f64>());
        }
    }
}

/// [`cell_errors`] summed by ring of cells: ring r holds the cells r cells
/// from the sample's edge (of 32 × 32: 124, 116, 108 … cells).
fn rings(est: &[[f32; 3]], truth: &[[f32; 3]], per: usize) -> [f64; 16] {
    let mut sum = [0f64; 16];
    cell_errors(est, truth, per, |i, k, e| sum[i.min(k).min(31 - i).min(31 - k)] += e);
    sum
}

/// The outermost four rings' shares of two errors, "a / b %" each (the
/// rings hold 12, 11, 11 and 10 % of the cells).
fn ring_shares(a: &[f64; 16], b: &[f64; 16]) -> String {
    let (ta, tb): (f64, f64) = (a.iter().sum(), b.iter().sum());
    (0..4)
        .map(|r| format!("{:.0} / {:.0} %", 100.0 * a[r] / ta, 100.0 * b[r] / tb))
        .collect::<Vec<_>>()
        .join(", ")
}

/// [`cell_errors`] summed over the outermost column at u 0, at u 1, the
/// outermost row at v 0, at v 1, and the rest (corners count twice).
fn sides(est: &[[f32; 3]], truth: &[[f32; 3]], per: usize) -> [f64; 5] {
    let mut sum = [0f64; 5];
    cell_errors(est, truth, per, |i, k, e| {
        let on = [i == 0, i == 31, k == 0, k == 31];
        for (s, &o) in sum.iter_mut().zip(&on) {
            if o {
                *s += e;
            }
        }
        if !on.iter().any(|&o| o) {
            sum[4] += e;
        }
    });
    sum
}

/// Where the calibrated edges lie against the as-built truth: per side of
/// the sample (v 0, u 1, v 1, u 0), the true edge's distance inside the
/// calibrated one (frame px, at 9 points along each side of every view),
/// as the mean over the views and their RMS; for the views located by
/// their corners and by the phase alignment apart.
fn edge_errors(truth: &scanner_geometry::ScannerGeometry, cal: &host::build::Calibration) {
    use host::build::calibrate::LocatedBy;
    let ends = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    for by in [LocatedBy::Corners, LocatedBy::Phase] {
        let mut per_side = [(); 4].map(|_| Vec::new());
        for v in cal.views.iter().filter(|v| v.located_by == Some(by)) {
            let sampler = v.sampler();
            for (k, side) in per_side.iter_mut().enumerate() {
                let (a, b) = (ends[k], ends[(k + 1) % 4]);
                let inside: Vec<f64> = (1..10)
                    .filter_map(|i| {
                        let t = i as f64 / 10.0;
                        let uv = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                        Some(sampler.edge_depth(k, truth.view_point(v.view, uv)?))
                    })
                    .collect();
                side.push(inside.iter().sum::<f64>() / inside.len().max(1) as f64);
            }
        }
        if per_side[0].is_empty() {
            continue;
        }
        let stats = |e: &[f64]| {
            let mean = e.iter().sum::<f64>() / e.len() as f64;
            let rms = (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt();
            format!("{mean:+.3} / {rms:.3}")
        };
        println!(
            "the true edges inside the calibrated ones, {} views located by {by:?}, px (mean / RMS), \
             sides v 0, u 1, v 1, u 0: {}",
            per_side[0].len(),
            per_side.iter().map(|e| stats(e)).collect::<Vec<_>>().join(", ")
        );
    }
}
