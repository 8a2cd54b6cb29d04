//! Importance sampling on material files (docs/benchmarks.md, "Importance
//! sampling"): at 64 seeded (uv, wo) — wo uniform over the hemisphere up
//! to θ 75° — 4 000 draws of `Material::sample` and 4 000 cosine-weighted
//! directions each; prints the variance of the sampled estimate of
//! ∫ f cos θi dωi over cosine sampling's (geometric mean, median, 90th
//! percentile, worst) and the largest deviation from quadrature in
//! standard errors (|z| ≤ 4 expected of an unbiased estimate).
//!
//! `cargo run --release -p tests --example sampling_variance -- A.material B.material …`

use rand::{Rng, SeedableRng};
use scanner_shading::Material;

fn main() {
    let paths: Vec<String> = std::env::args().skip(1).collect();
    if paths.is_empty() {
        eprintln!("usage: sampling_variance MATERIAL…");
        std::process::exit(2);
    }
    println!(
        "| material | prepare_importance | geometric mean | median | 90 % | worst (wo) | largest |z| |"
    );
    println!("|---|---|---|---|---|---|---|");
    for path in paths {
        let m = match Material::open(path.as_ref()) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("{e}");
                std::process::exit(3);
            }
        };
        let t = std::time::Instant::now();
        m.prepare_importance();
        let prepare = t.elapsed().as_secs_f64();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut ratios = Vec::new();
        let (mut worst, mut worst_wo, mut largest_z) = (0.0f64, [0.0f32; 3], 0.0f64);
        for k in 0..64 {
            let z = rng.random_range(75f32.to_radians().cos()..1.0);
            let phi = rng.random::<f32>() * std::f32::consts::TAU;
            let r = (1.0 - z * z).sqrt();
            let wo = [r * phi.cos(), r * phi.sin(), z];
            let uv = [rng.random(), rng.random()];
            let c = tests::sampling_check(&m, uv, wo, 4_000, 100 + k);
            ratios.push(c.variance_ratio);
            largest_z = largest_z.max(c.deviation.abs());
            if c.variance_ratio > worst {
                (worst, worst_wo) = (c.variance_ratio, wo);
            }
        }
        ratios.sort_by(f64::total_cmp);
        let geo = (ratios.iter().map(|r| r.ln()).sum::<f64>() / ratios.len() as f64).exp();
        let theta = worst_wo[2].acos().to_degrees();
        let phi = worst_wo[1].atan2(worst_wo[0]).to_degrees();
        println!(
            "| {path} | {prepare:.2} s | {geo:.3} | {:.3} | {:.3} | {worst:.2} (θ {theta:.0}°, φ {phi:.0}°) | {largest_z:.2} |",
            ratios[32], ratios[57]
        );
    }
}
