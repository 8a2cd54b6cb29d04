//! The metric's point-sampling limit at material_fidelity's novel pairs
//! (same seed, same pairs): a perfect area-integrating estimate (each
//! cell's mean over 12 × 12 points) scored against the metric's 3 × 3
//! points. Then the default material built from the scan, scored at the
//! same pairs, and its six worst pairs dissected: each pair's share of the
//! error, its half vector's and directions' angles, the limit's share of
//! its error, and its three worst cells (material, truth, the 12 × 12 mean
//! and the texel model under the cell's centre).
//!
//! `cargo run --release -p tests --example novel_limit -- [--materials a,b] [--out DIR] [--seed 1] [--novel 300]`
//! (scans kept in `--out` as material_fidelity keeps them: that example's
//! `--out` reuses them).
use std::path::PathBuf;

use hil_sim::materials::{Sample, lookup};
use host::build::calibrate::Silent;
use host::build::material::{MaterialOptions, build_material, shade};
use scanner_shading::Material;

fn main() {
    tests::check_region_args(&["--materials", "--novel", "--out", "--seed"], &[]);
    let seed: u64 = tests::arg("--seed", 1);
    let novel: usize = tests::arg("--novel", 300);
    let list: String = tests::arg("--materials", "leather".to_string());
    let pairs = tests::random_pairs(novel, 60.0, seed);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/builder-fidelity"));
    let materials: Vec<&str> = list.split(',').collect();
    let (g, cal, _truth) = tests::scanned_and_calibrated(&out, seed, 1, 40, &materials);
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
