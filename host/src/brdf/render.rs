//! The rendered-sphere comparison — the one definition of "rendered-sphere
//! PSNR" used everywhere (docs/npf-format.md):
//!
//! - a sphere seen orthographically along −z, [`SPHERE_SIZE`]² pixels, one
//!   sample at each pixel centre, pixels outside the disc masked out;
//! - lit by the built-in environment: a sky dome (a gradient from a blue zenith
//!   to a brown ground, world up = +y) quadratured on 2048 Fibonacci directions,
//!   plus two sun-like directional lights;
//! - outgoing radiance L = Σ f(wi, wo) cos θi Le dω over lights above the
//!   local horizon;
//! - tone mapping per channel d = (L / (1 + L))^(1/2.2) (Reinhard, then
//!   display gamma), so d ∈ [0, 1);
//! - PSNR = 10 log10(1 / MSE), MSE over the masked pixels and the 3 channels.

use std::f64::consts::PI;
use std::path::Path;

use rayon::prelude::*;

use super::{Brdf, Vec3};

/// Side of the rendered sphere image, pixels.
pub const SPHERE_SIZE: usize = 128;
/// Sky-dome quadrature directions.
pub const SKY_DIRECTIONS: usize = 2048;

fn normalize(v: Vec3) -> Vec3 {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Radiance arriving from a set of directions, with solid angles.
#[derive(Debug, Clone)]
pub struct Environment {
    /// (direction towards the light, radiance × solid angle) — for the suns,
    /// irradiance.
    lights: Vec<(Vec3, [f64; 3])>,
}

impl Environment {
    /// The built-in environment.
    pub fn builtin() -> Environment {
        let golden = PI * (3.0 - 5f64.sqrt());
        let d_omega = 4.0 * PI / SKY_DIRECTIONS as f64;
        let mut lights: Vec<(Vec3, [f64; 3])> = (0..SKY_DIRECTIONS)
            .map(|k| {
                let y = 1.0 - 2.0 * (k as f64 + 0.5) / SKY_DIRECTIONS as f64;
                let r = (1.0 - y * y).sqrt();
                let phi = golden * k as f64;
                let d = [r * phi.cos(), y, r * phi.sin()];
                let le = if y >= 0.0 {
                    let t = y;
                    [0.35 + 0.15 * t, 0.45 + 0.2 * t, 0.6 + 0.35 * t]
                } else {
                    [0.18, 0.12, 0.08]
                };
                (d, le.map(|l| l * d_omega))
            })
            .collect();
        lights.push((normalize([-0.4, 0.6, 0.7]), [3.0, 2.8, 2.5]));
        lights.push((normalize([0.6, 0.1, 0.8]), [0.8, 0.9, 1.2]));
        Environment { lights }
    }
}

/// A rendered image: linear radiance and the sphere mask.
#[derive(Debug, Clone, PartialEq)]
pub struct SphereImage {
    /// Side, pixels.
    pub size: usize,
    /// Row-major linear RGB radiance.
    pub radiance: Vec<[f32; 3]>,
    /// Whether the pixel is on the sphere.
    pub mask: Vec<bool>,
}

/// An orthonormal basis around n (Duff et al. 2017).
fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1f64.copysign(n[2]);
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    ([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]], [b, sign + n[1] * n[1] * a, -n[1]])
}

/// Render `brdf` on the sphere under `env`.
pub fn render_sphere(brdf: &dyn Brdf, env: &Environment, size: usize) -> SphereImage {
    let rows: Vec<Vec<([f32; 3], bool)>> = (0..size)
        .into_par_iter()
        .map(|y| {
            (0..size)
                .map(|x| {
                    let nx = 2.0 * (x as f64 + 0.5) / size as f64 - 1.0;
                    let ny = 1.0 - 2.0 * (y as f64 + 0.5) / size as f64;
                    let r2 = nx * nx + ny * ny;
                    if r2 >= 1.0 {
                        return ([0.0; 3], false);
                    }
                    let n = [nx, ny, (1.0 - r2).sqrt()];
                    let (t, b) = basis(n);
                    let local = |v: Vec3| [dot(v, t), dot(v, b), dot(v, n)];
                    let wo = local([0.0, 0.0, 1.0]);
                    let mut l = [0.0f64; 3];
                    for (d, e) in &env.lights {
                        let wi = local(*d);
                        if wi[2] <= 0.0 {
                            continue;
                        }
                        let f = brdf.eval(wi, wo);
                        for c in 0..3 {
                            l[c] += f[c] * wi[2] * e[c];
                        }
                    }
                    (l.map(|v| v as f32), true)
                })
                .collect()
        })
        .collect();
    let (radiance, mask) = rows.into_iter().flatten().unzip();
    SphereImage { size, radiance, mask }
}

/// The display value of a radiance: (L / (1 + L))^(1/2.2).
pub fn tone_map(l: f32) -> f32 {
    let l = l.max(0.0);
    (l / (1.0 + l)).powf(1.0 / 2.2)
}

/// Rendered-sphere PSNR of `test` against `reference`, dB.
pub fn psnr(reference: &SphereImage, test: &SphereImage) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for i in 0..reference.radiance.len() {
        if !reference.mask[i] {
            continue;
        }
        for c in 0..3 {
            let d = (tone_map(reference.radiance[i][c]) - tone_map(test.radiance[i][c])) as f64;
            sum += d * d;
            n += 1;
        }
    }
    let mse = sum / n.max(1) as f64;
    if mse == 0.0 { f64::INFINITY } else { 10.0 * (1.0 / mse).log10() }
}

/// The one-call comparison: render both under the built-in environment.
pub fn sphere_psnr(reference: &dyn Brdf, test: &dyn Brdf) -> f64 {
    let env = Environment::builtin();
    psnr(&render_sphere(reference, &env, SPHERE_SIZE), &render_sphere(test, &env, SPHERE_SIZE))
}

/// Write an image: `.png` (tone-mapped, 8-bit sRGB-like) or `.exr` (linear
/// radiance, 32-bit float), atomically.
pub fn save(image: &SphereImage, path: &Path) -> Result<(), image::ImageError> {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    let mut bytes = Vec::new();
    match ext.as_deref() {
        Some("exr") => {
            let data: Vec<f32> = image.radiance.iter().flat_map(|p| *p).collect();
            let buf = image::Rgb32FImage::from_raw(image.size as u32, image.size as u32, data)
                .expect("size matches");
            image::DynamicImage::ImageRgb32F(buf)
                .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::OpenExr)?;
        }
        Some("png") => {
            let data: Vec<u8> = image
                .radiance
                .iter()
                .flat_map(|p| p.map(|v| (tone_map(v) * 255.0).round() as u8))
                .collect();
            let buf = image::RgbImage::from_raw(image.size as u32, image.size as u32, data)
                .expect("size matches");
            buf.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)?;
        }
        _ => {
            return Err(image::ImageError::Unsupported(
                image::error::UnsupportedError::from_format_and_kind(
                    image::error::ImageFormatHint::PathExtension(path.to_path_buf()),
                    image::error::UnsupportedErrorKind::Format(
                        image::error::ImageFormatHint::Name("use .png or .exr".into()),
                    ),
                ),
            ));
        }
    }
    crate::fsutil::write_atomic(path, &bytes).map_err(image::ImageError::IoError)
}
