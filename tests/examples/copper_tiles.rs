//! Writes `copper-tiles`, a texture set (docs/texture-set.md) unlike the
//! library materials, for checking that the builder generalises
//! (docs/benchmarks.md, "A sample outside the library"): a 4 × 4
//! checker of polished copper (F0 (0.95, 0.64, 0.54), roughness 0.2–0.5)
//! and striped blue paint (F0 0.04, roughness 0.35–0.75), under an egg-crate
//! bump map (slopes up to ±0.25), 30 mm per tile.
//!
//! `cargo run --release -p tests --example copper_tiles -- DIR`, then
//! `cargo run --release -p tests --example material_fidelity -- --materials DIR`.

use std::f64::consts::PI;
use std::path::PathBuf;

const W: u32 = 256;

fn srgb(c: f64) -> f64 {
    if c <= 0.0031308 { 12.92 * c } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 }
}

fn byte(x: f64) -> u8 {
    (x * 255.0).round().clamp(0.0, 255.0) as u8
}

fn main() {
    let dir: PathBuf = std::env::args().nth(1).expect("usage: copper_tiles DIR").into();
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("material.toml"),
        "format = 1\nname = \"copper-tiles\"\nsize_mm = 30.0\n",
    )
    .unwrap();
    let mut diffuse = image::RgbImage::new(W, W);
    let mut specular = image::RgbImage::new(W, W);
    let mut roughness = image::GrayImage::new(W, W);
    let mut normal = image::RgbImage::new(W, W);
    for r in 0..W {
        for c in 0..W {
            let (x, y) = (c as f64 / W as f64, r as f64 / W as f64);
            let copper = ((x * 4.0).floor() + (y * 4.0).floor()) as i64 % 2 == 1;
            let (d, s, rough) = if copper {
                ([0.02; 3], [0.95, 0.64, 0.54], 0.35 + 0.15 * (30.0 * PI * x).sin())
            } else {
                (
                    [0.10 + 0.05 * (40.0 * PI * x).sin(), 0.25, 0.55 + 0.1 * (20.0 * PI * y).sin()],
                    [0.04; 3],
                    0.55 + 0.2 * (14.0 * PI * (x + y)).sin(),
                )
            };
            let (hx, hy) = (
                0.25 * (12.0 * PI * x).cos() * (12.0 * PI * y).sin(),
                0.25 * (12.0 * PI * x).sin() * (12.0 * PI * y).cos(),
            );
            let l = (hx * hx + hy * hy + 1.0).sqrt();
            let n = [-hx / l, -hy / l, 1.0 / l];
            diffuse.put_pixel(c, r, image::Rgb(d.map(|v| byte(srgb(v)))));
            specular.put_pixel(c, r, image::Rgb(s.map(|v| byte(srgb(v)))));
            roughness.put_pixel(c, r, image::Luma([byte(rough)]));
            normal.put_pixel(c, r, image::Rgb(n.map(|v| byte((v + 1.0) / 2.0))));
        }
    }
    diffuse.save(dir.join("diffuse.png")).unwrap();
    specular.save(dir.join("specular.png")).unwrap();
    roughness.save(dir.join("roughness.png")).unwrap();
    normal.save(dir.join("normal.png")).unwrap();
    println!("{}: copper-tiles, {W}² maps over 30 mm", dir.display());
}
