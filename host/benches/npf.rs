//! NPF fitting (docs/benchmarks.md): fit time per RGB material for each G
//! variant (criterion), and — printed first — iterations, line searches and
//! the error figures of the cases (a)–(c).

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use host::brdf::Brdf;
use host::brdf::analytic::{
    Analytic, beckmann_conductor, coated_plastic, coated_plastic_fresnel, exactly_representable,
    ggx_conductor, two_lobe_ggx,
};
use host::brdf::fit::{FitOptions, GVariant, Samples, Weighting, fit, fit_naive};
use host::brdf::merl::{MerlTable, cosine_weighted_relative_rmse};
use host::brdf::render::sphere_psnr;

fn cases() -> Vec<(&'static str, Analytic)> {
    vec![
        ("(a) GGX conductor α=0.2", exactly_representable(ggx_conductor(0.2))),
        ("(a) Beckmann conductor α=0.3", exactly_representable(beckmann_conductor(0.3))),
        ("GGX conductor α=0.2, exact G1", ggx_conductor(0.2)),
        ("(b) Lambert + GGX coat", coated_plastic()),
        ("Lambert + GGX coat, Fresnel transmission", coated_plastic_fresnel()),
        ("(c) two-lobe GGX", two_lobe_ggx()),
    ]
}

fn npf(c: &mut Criterion) {
    let mut tables = Vec::new();
    println!(
        "| material | G | iterations (R/G/B) | line searches | fit s | cos-weighted rel. RMSE | sphere PSNR dB |"
    );
    for (name, b) in cases() {
        let table = MerlTable::from_fn(|wi, wo| b.eval(wi, wo));
        let samples = Samples::from_merl(&table).unwrap();
        for g in [GVariant::Smith, GVariant::Independent] {
            let (model, r) =
                fit(&samples, &FitOptions { g, ..FitOptions::default() }, &|_, _, _| {});
            println!(
                "| {name} | {g:?} | {:?} | {:?} | {:.2} | {:.4} | {:.1} |",
                r.iterations,
                r.line_searches,
                r.seconds,
                cosine_weighted_relative_rmse(&table, &model),
                sphere_psnr(&table, &model)
            );
        }
        let plain = FitOptions { weighting: Weighting::Unweighted, ..FitOptions::default() };
        let (model, _) = fit(&samples, &plain, &|_, _, _| {});
        println!(
            "| {name} | Smith, unweighted | | | | {:.4} | {:.1} |",
            cosine_weighted_relative_rmse(&table, &model),
            sphere_psnr(&table, &model)
        );
        let naive = fit_naive(&samples, &FitOptions::default());
        println!("| {name} | naive D·F·H | | | | | {:.1} |", sphere_psnr(&table, &naive));
        tables.push((name, samples));
    }

    let mut group = c.benchmark_group("npf_fit");
    group.sample_size(10).measurement_time(Duration::from_secs(20));
    let timed = |n: &str| !n.contains("exact G1") && !n.contains("Fresnel transmission");
    for (name, samples) in tables.iter().filter(|(n, _)| timed(n)) {
        for g in [GVariant::Smith, GVariant::Independent] {
            let opts = FitOptions { g, ..FitOptions::default() };
            group.bench_function(format!("{name} / {g:?}"), |b| {
                b.iter(|| black_box(fit(samples, &opts, &|_, _, _| {})))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, npf);
criterion_main!(benches);
