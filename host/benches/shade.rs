//! Shading speed (docs/benchmarks.md, "Material files"): `Material::eval`
//! on one core for random uv and random directions over the hemisphere, on
//! a material of the size (40 × 40 directions of the default
//! scanner, S = 128, 256 colours, 2 lights per index image, random
//! palettes and indices), default and patent interpolation, beside a
//! baseline measured in the same run: `eval` at one captured pair for
//! every query (one image and one palette instead of up to nine). The
//! `lookup` group times one direction lookup alone, of which a random
//! `eval` makes four.

use std::hint::black_box;

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use host::build::material::PATENT_DEFAULT;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scanner_shading::format::DirectionTables;
use scanner_shading::locate::TriangleLocator;
use scanner_shading::{Interpolation, Material, ShadeQuery};

#[path = "support/synthetic.rs"]
mod synthetic;

const QUERIES: usize = 1 << 16;

/// The size: 40 × 40 directions, S = 128, K = 256, g = 2.
fn material(interpolation: Interpolation, half_vector_shift: f64) -> Material {
    let shape =
        synthetic::Shape { mirrors: 40, resolution: 128, colours: 256, lights_per_index: 2 };
    let data = synthetic::synthetic(&shape, interpolation, half_vector_shift, 1);
    Material::from_bytes(&data.to_bytes().unwrap()).unwrap()
}

/// The unit direction of height `z` and azimuth uniform in [0, 2π).
fn at_height(rng: &mut ChaCha8Rng, z: f32) -> [f32; 3] {
    let p = rng.random::<f32>() * std::f32::consts::TAU;
    let r = (1.0 - z * z).sqrt();
    [r * p.cos(), r * p.sin(), z]
}

fn queries() -> Vec<ShadeQuery> {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let dir = |rng: &mut ChaCha8Rng| {
        let z: f32 = rng.random::<f32>().max(1e-3);
        at_height(rng, z)
    };
    (0..QUERIES)
        .map(|_| ShadeQuery {
            uv: [rng.random(), rng.random()],
            wi: dir(&mut rng),
            wo: dir(&mut rng),
        })
        .collect()
}

fn shade(c: &mut Criterion) {
    let q = queries();
    let mut out = vec![[0f32; 3]; q.len()];
    let mut group = c.benchmark_group("eval");
    group.throughput(Throughput::Elements(q.len() as u64));
    let default = material(Interpolation::Default, 0.5);
    // Baseline: every query at one captured pair (one image, one palette).
    group.bench_function("baseline: eval at one captured pair", |b| {
        let (wi, wo) = (
            default.metadata().lights[0].direction.map(|x| x as f32),
            default.metadata().views[0].direction.map(|x| x as f32),
        );
        b.iter(|| {
            for (q, o) in q.iter().zip(out.iter_mut()) {
                *o = default.eval(q.uv, wi, wo);
            }
            black_box(&out);
        })
    });
    group.bench_function("default interpolation", |b| {
        b.iter(|| {
            default.eval_batch(&q, &mut out);
            black_box(&out);
        })
    });
    // The same material enlarged to a piece of 403² texels (80 mm, the
    // library's large piece at S = 128), each matched at random: one map
    // lookup more per query, and the sample's texels read in a scattered
    // order.
    group.bench_function("default interpolation, enlarged (403² map)", |b| {
        let shape =
            synthetic::Shape { mirrors: 40, resolution: 128, colours: 256, lights_per_index: 2 };
        let data = synthetic::with_enlargement(
            synthetic::synthetic(&shape, Interpolation::Default, 0.5, 1),
            403,
            403,
            [80.0, 80.0],
            6,
        );
        let enlarged = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
        b.iter(|| {
            enlarged.eval_batch(&q, &mut out);
            black_box(&out);
        })
    });
    // The same queries through `eval` one at a time: what the blocks buy.
    group.bench_function("default interpolation, eval per query", |b| {
        b.iter(|| {
            for (q, o) in q.iter().zip(out.iter_mut()) {
                *o = default.eval(q.uv, q.wi, q.wo);
            }
            black_box(&out);
        })
    });
    // With a texel model the builder writes β = 0 (since session 65); the
    // β = ½ row is what files of earlier builders hold.
    for (name, shift, detail) in [
        ("default interpolation with a texel model", 0.0, None),
        ("default interpolation with a texel model, β = ½", 0.5, None),
        ("default interpolation with a texel model and a detail layer", 0.0, Some(0)),
        (
            "default interpolation with a texel model and a detail layer with 2 light components",
            0.0,
            Some(2),
        ),
    ] {
        group.bench_function(name, |b| {
            let shape = synthetic::Shape {
                mirrors: 40,
                resolution: 128,
                colours: 256,
                lights_per_index: 2,
            };
            let mut data = synthetic::with_texel_model(
                synthetic::synthetic(&shape, Interpolation::Default, shift, 1),
                5,
            );
            if let Some(components) = detail {
                data = synthetic::with_detail(data, components, 6);
            }
            let modelled = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
            b.iter(|| {
                modelled.eval_batch(&q, &mut out);
                black_box(&out);
            })
        });
    }
    group.bench_function("default interpolation, no half-vector shift", |b| {
        let unshifted = material(Interpolation::Default, 0.0);
        b.iter(|| {
            unshifted.eval_batch(&q, &mut out);
            black_box(&out);
        })
    });
    // A renderer's pattern: a 256² image of the tile under one light and view.
    let image: Vec<ShadeQuery> = (0..QUERIES)
        .map(|i| ShadeQuery {
            uv: [((i % 256) as f32 + 0.5) / 256.0, ((i / 256) as f32 + 0.5) / 256.0],
            wi: [0.3, 0.2, 0.93],
            wo: [-0.4, 0.1, 0.91],
        })
        .collect();
    group.bench_function("default interpolation, one image (coherent)", |b| {
        b.iter(|| {
            default.eval_batch(&image, &mut out);
            black_box(&out);
        })
    });
    // A query file's pattern (the material PSNR's): pairs of random
    // directions, each asked at 64 random uv.
    let runs: Vec<ShadeQuery> = q
        .iter()
        .enumerate()
        .map(|(i, x)| ShadeQuery { wi: q[i / 64 * 64].wi, wo: q[i / 64 * 64].wo, ..*x })
        .collect();
    group.bench_function("default interpolation, random uv, 64 per direction pair", |b| {
        b.iter(|| {
            default.eval_batch(&runs, &mut out);
            black_box(&out);
        })
    });
    group.bench_function("patent interpolation", |b| {
        let patent = material(PATENT_DEFAULT, 0.5);
        b.iter(|| {
            patent.eval_batch(&q, &mut out);
            black_box(&out);
        })
    });
    group.finish();
}

/// One direction lookup alone (`TriangleLocator::weights`, the default
/// interpolation's), over the default scanner's view triangulation: 2²⁰
/// random directions over the hemisphere (beyond the outer ring too) and
/// within 60° of the normal. A random `eval` makes four.
fn lookup(c: &mut Criterion) {
    let shape = synthetic::Shape { mirrors: 40, resolution: 1, colours: 1, lights_per_index: 2 };
    let data = synthetic::synthetic(&shape, Interpolation::Default, 0.5, 1);
    let DirectionTables::Triangles { views, .. } = &data.tables else {
        panic!("the default interpolation has triangles")
    };
    let dirs: Vec<[f32; 3]> =
        data.meta.views.iter().map(|m| m.direction.map(|x| x as f32)).collect();
    let locator = TriangleLocator::new(&dirs, views, "views").unwrap();
    let mut group = c.benchmark_group("lookup");
    for (name, max_theta) in [("hemisphere", 90f32), ("within 60°", 60.0)] {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let zmin = max_theta.to_radians().cos().max(1e-3);
        let ds: Vec<[f32; 3]> = (0..1 << 20)
            .map(|_| {
                let z: f32 = zmin + (1.0 - zmin) * rng.random::<f32>();
                at_height(&mut rng, z)
            })
            .collect();
        group.throughput(Throughput::Elements(ds.len() as u64));
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut sum = 0f32;
                let mut w = [(0u16, 0f32); 3];
                for &d in &ds {
                    locator.weights(d, &mut w);
                    sum += w[0].1 + w[1].0 as f32;
                }
                black_box(sum)
            })
        });
    }
    group.finish();
}

/// Importance sampling (docs/benchmarks.md, "Importance sampling") on the
/// texel-model material of the `eval` group: `sample` and `pdf` per query
/// beside `eval` per query on the same (uv, wo) in the same run (a draw
/// makes one `eval` and one `pdf`), and building every view's table.
fn sampling(c: &mut Criterion) {
    let shape =
        synthetic::Shape { mirrors: 40, resolution: 128, colours: 256, lights_per_index: 2 };
    let data = synthetic::with_texel_model(
        synthetic::synthetic(&shape, Interpolation::Default, 0.5, 1),
        5,
    );
    let m = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
    m.prepare_importance();
    let q = queries();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let numbers: Vec<[f32; 3]> = (0..q.len()).map(|_| rng.random()).collect();
    let mut group = c.benchmark_group("sampling");
    group.throughput(Throughput::Elements(q.len() as u64));
    group.bench_function("baseline: eval per query", |b| {
        b.iter(|| {
            let mut sum = 0f32;
            for q in &q {
                sum += m.eval(q.uv, q.wi, q.wo)[0];
            }
            black_box(sum)
        })
    });
    group.bench_function("sample", |b| {
        b.iter(|| {
            let mut sum = 0f32;
            for (q, r) in q.iter().zip(&numbers) {
                if let Some(s) = m.sample(q.uv, q.wo, r[0], [r[1], r[2]]) {
                    sum += s.f_cos[0] / s.pdf;
                }
            }
            black_box(sum)
        })
    });
    group.bench_function("pdf", |b| {
        b.iter(|| {
            let mut sum = 0f32;
            for q in &q {
                sum += m.pdf(q.uv, q.wi, q.wo);
            }
            black_box(sum)
        })
    });
    group.finish();
    let mut group = c.benchmark_group("sampling tables");
    group.sample_size(10);
    let bytes = data.to_bytes().unwrap();
    group.bench_function("prepare_importance, 40 views", |b| {
        b.iter_batched(
            || Material::from_bytes(&bytes).unwrap(),
            |fresh| {
                fresh.prepare_importance();
                black_box(fresh.pdf([0.5; 2], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]))
            },
            BatchSize::LargeInput,
        )
    });
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = shade, lookup, sampling
}
criterion_main!(benches);
