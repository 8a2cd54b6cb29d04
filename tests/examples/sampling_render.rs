//! What importance sampling buys a renderer, to look at: each material file
//! given, a flat patch seen from θ 40° (orthographic, uv over its extent)
//! under a dim sky and two round lights — one of 8° radius at the mirror
//! direction, one of 5° at θ 60°, φ 100° — shaded by sampling the material
//! only (no light sampling). One row per material, three panels: a
//! reference (256 draws of `Material::sample` per pixel), 16 cosine-weighted
//! draws, 16 draws of `Material::sample`; the RMSE of each against the
//! reference is printed. Tone mapped x / (1 + x), sRGB.
//!
//! `cargo run --release -p tests --example sampling_render -- OUT.png A.material B.material …`

use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use scanner_shading::Material;

const SIDE: usize = 160;
const GAP: usize = 4;

/// Radiance arriving along wi (sample frame).
fn environment(wi: [f32; 3], wo: [f32; 3]) -> f32 {
    let disc = |centre: [f32; 3], radius_deg: f32, radiance: f32| {
        let c = wi[0] * centre[0] + wi[1] * centre[1] + wi[2] * centre[2];
        if c >= radius_deg.to_radians().cos() { radiance } else { 0.0 }
    };
    let mirror = [-wo[0], -wo[1], wo[2]];
    let (t, p) = (60f32.to_radians(), 100f32.to_radians());
    let side = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
    0.15 * (0.5 + 0.5 * wi[2]) + disc(mirror, 8.0, 12.0) + disc(side, 5.0, 20.0)
}

/// One panel: per pixel the mean of `spp` estimates, with the material's
/// draws or cosine-weighted ones.
fn render(
    m: &Material,
    wo: [f32; 3],
    spp: usize,
    material_draws: bool,
    seed: u64,
) -> Vec<[f32; 3]> {
    (0..SIDE * SIDE)
        .into_par_iter()
        .map(|i| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ (i as u64 * 0x9E37_79B9));
            let uv =
                [((i % SIDE) as f32 + 0.5) / SIDE as f32, ((i / SIDE) as f32 + 0.5) / SIDE as f32];
            let mut sum = [0.0f32; 3];
            for _ in 0..spp {
                let (uc, u): (f32, [f32; 2]) = (rng.random(), [rng.random(), rng.random()]);
                let (wi, w) = if material_draws {
                    match m.sample(uv, wo, uc, u) {
                        Some(s) => (s.wi, s.weight()),
                        None => continue,
                    }
                } else {
                    let wi = scanner_shading::importance::cosine_direction(u);
                    if wi[2] <= 0.0 {
                        continue;
                    }
                    let f = m.eval(uv, wi, wo);
                    (wi, f.map(|c| c * std::f32::consts::PI / wi[2]))
                };
                let le = environment(wi, wo);
                for k in 0..3 {
                    sum[k] += w[k] * le;
                }
            }
            sum.map(|c| c / spp as f32)
        })
        .collect()
}

fn rmse(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let s: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(x, y)| (0..3).map(move |k| ((x[k] - y[k]) as f64).powi(2)))
        .sum();
    (s / (3 * a.len()) as f64).sqrt()
}

fn srgb_byte(x: f32) -> u8 {
    let t = (x / (1.0 + x)).clamp(0.0, 1.0);
    let s = if t <= 0.0031308 { 12.92 * t } else { 1.055 * t.powf(1.0 / 2.4) - 0.055 };
    (s * 255.0).round() as u8
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        eprintln!("usage: sampling_render OUT.png MATERIAL…");
        std::process::exit(2);
    }
    let (t, p) = (40f32.to_radians(), 0f32);
    let wo = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
    let rows = args.len() - 1;
    let (w, h) = (3 * SIDE + 2 * GAP, rows * SIDE + (rows - 1) * GAP);
    let mut img = image::RgbImage::new(w as u32, h as u32);
    for (r, path) in args[1..].iter().enumerate() {
        let m = match Material::open(path.as_ref()) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("{e}");
                std::process::exit(3);
            }
        };
        m.prepare_importance();
        let reference = render(&m, wo, 256, true, 1);
        let cosine = render(&m, wo, 16, false, 2);
        let drawn = render(&m, wo, 16, true, 3);
        println!(
            "{path}: 16 draws per pixel, RMSE against the reference: cosine-weighted {:.4}, the material's {:.4}",
            rmse(&cosine, &reference),
            rmse(&drawn, &reference)
        );
        for (c, panel) in [&reference, &cosine, &drawn].into_iter().enumerate() {
            for (i, px) in panel.iter().enumerate() {
                let (x, y) =
                    (c * (SIDE + GAP) + i % SIDE, r * (SIDE + GAP) + (SIDE - 1 - i / SIDE));
                img.put_pixel(x as u32, y as u32, image::Rgb(px.map(srgb_byte)));
            }
        }
    }
    if let Err(e) = img.save(&args[0]) {
        eprintln!("{}: {e}", args[0]);
        std::process::exit(4);
    }
    println!("wrote {}: per row reference | cosine-weighted | the material's draws", args[0]);
}
