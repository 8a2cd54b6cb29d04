//! Writes eight texture sets (docs/texture-set.md) unlike the library
//! materials and unlike each other, for checking that the builder
//! generalises (docs/benchmarks.md, "Five more samples outside the
//! library" and what follows it). Nothing in the builder was tuned to them.
//!
//! - `red-plastic`: a glossy dielectric (F0 0.04, roughness 0.25–0.32)
//!   with an orange-peel bump (slopes ±0.03, 2 mm);
//! - `gold-foil`: a bare metal (F0 (1.0, 0.77, 0.33), no diffuse,
//!   roughness 0.22–0.34), crumpled (slopes up to ±0.2, 3–7 mm);
//! - `dark-rubber`: near-black (albedo 0.03), rough (0.85), fine bumps
//!   (0.8 mm) — the noise floor;
//! - `printed-paper`: matte white paper with 0.3 mm dark lines every 2 mm
//!   and a 5 mm dot screen — high contrast below the camera's resolution;
//! - `green-tile`: the glTF metallic-roughness form (`baseColor`,
//!   `metallicRoughness`), a glazed tile with metallic flecks;
//! - `chrome`: a near-mirror (F0 0.9, roughness 0.12: GGX α 0.0144) with a
//!   gentle waviness (slopes ±0.04, 8 and 4 mm), on 64² maps: highlights
//!   ≈ 2 500× a white target, beyond the device's shortest exposure;
//! - `brushed`: a brushed metal (F0 0.6, roughness 0.25–0.35) with grooves
//!   of 0.25 mm across y (slopes ±0.3), on 256² maps over 4 mm;
//! - `glint-stripes`: a matte colour gradient under a faint (F0 0.003)
//!   specular layer whose roughness runs in stripes from 0.1 to 0.5 (GGX
//!   α 0.01–0.25) over bumps of 5 mm (slopes ±0.1), on 1024² maps over
//!   100 mm: where the stripes are smooth, glints sharper than the
//!   captured directions' spacing.
//!
//! `cargo run --release -p tests --example unseen_samples -- DIR`, then
//! `cargo run --release -p tests --example material_fidelity -- --materials DIR/red-plastic,…`.
//!
//! With `--other-kinds` it writes instead nine sets that try the main job's
//! limits (docs/benchmarks.md, "Texture sets of other kinds"): `one` (1 × 1
//! maps, a 10 m tile), `big4k` (4096² maps over 200 mm), `white-hot`
//! (albedo 1 and F0 1), `tiny-tile` (random colours over a 0.5 mm tile),
//! `blotchy` (2048² maps: blotches, glossy bumps), `steep` (normals
//! tilted up to 80°), `mirror` (F0 1, roughness 0), `polished` (a uniform
//! metal, roughness 0.15) and `satin` (uniform, roughness 0.3).
//!
//! With `--relief` it writes two sets of fine relief (docs/benchmarks.md,
//! "Relief finer than a texel"): `stone` (2048² maps over 100 mm: a
//! fractal relief and speckle, periodic value noise) and `tiles` (1024²
//! over 60 mm: glazed tiles of 25 colours with a gentle waviness, in
//! bevelled grout grooves).

use std::f64::consts::PI;
use std::path::Path;

fn srgb(c: f64) -> f64 {
    if c <= 0.0031308 { 12.92 * c } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 }
}

fn byte(x: f64) -> u8 {
    (x * 255.0).round().clamp(0.0, 255.0) as u8
}

/// One texel of a set: (diffuse or base colour, F0 or [_, roughness,
/// metallic], roughness, height-field slopes (∂h/∂x, ∂h/∂y)).
struct Texel {
    colour: [f64; 3],
    specular: [f64; 3],
    roughness: f64,
    slope: (f64, f64),
}

/// Writes a set of `size_mm` in W × W maps whose texel at material point
/// (x, y) mm is `f(x, y)`; `gltf` writes the metallic-roughness form
/// (`specular` then holds [0, roughness, metallic]).
fn write_set<const W: u32>(
    dir: &Path,
    name: &str,
    size_mm: f64,
    gltf: bool,
    f: impl Fn(f64, f64) -> Texel,
) {
    write_set_at::<W>(dir, name, size_mm, None, gltf, f)
}

/// [`write_set`] with the small sample cut at `offset_mm` (the default
/// `[0, 0]` when `None`).
fn write_set_at<const W: u32>(
    dir: &Path,
    name: &str,
    size_mm: f64,
    offset_mm: Option<[f64; 2]>,
    gltf: bool,
    f: impl Fn(f64, f64) -> Texel,
) {
    let dir = dir.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    let offset =
        offset_mm.map_or(String::new(), |[x, y]| format!("sample_offset_mm = [{x:?}, {y:?}]\n"));
    std::fs::write(
        dir.join("material.toml"),
        format!("format = 1\nname = \"{name}\"\nsize_mm = {size_mm:?}\n{offset}"),
    )
    .unwrap();
    let mut colour = image::RgbImage::new(W, W);
    let mut specular = image::RgbImage::new(W, W);
    let mut roughness = image::GrayImage::new(W, W);
    let mut normal = image::RgbImage::new(W, W);
    for r in 0..W {
        for c in 0..W {
            let (x, y) =
                ((c as f64 + 0.5) / W as f64 * size_mm, (r as f64 + 0.5) / W as f64 * size_mm);
            let t = f(x, y);
            let (hx, hy) = t.slope;
            let l = (hx * hx + hy * hy + 1.0).sqrt();
            let n = [-hx / l, -hy / l, 1.0 / l];
            colour.put_pixel(c, r, image::Rgb(t.colour.map(|v| byte(srgb(v)))));
            if gltf {
                specular.put_pixel(c, r, image::Rgb(t.specular.map(byte)));
            } else {
                specular.put_pixel(c, r, image::Rgb(t.specular.map(|v| byte(srgb(v)))));
                roughness.put_pixel(c, r, image::Luma([byte(t.roughness)]));
            }
            normal.put_pixel(c, r, image::Rgb(n.map(|v| byte((v + 1.0) / 2.0))));
        }
    }
    if gltf {
        colour.save(dir.join("baseColor.png")).unwrap();
        specular.save(dir.join("metallicRoughness.png")).unwrap();
    } else {
        colour.save(dir.join("diffuse.png")).unwrap();
        specular.save(dir.join("specular.png")).unwrap();
        roughness.save(dir.join("roughness.png")).unwrap();
    }
    normal.save(dir.join("normal.png")).unwrap();
    println!("{}: {name}, {W}² maps over {size_mm} mm", dir.display());
}

/// A sum of sines of periods `periods` mm (the slopes of a smooth bump).
fn bumps(x: f64, y: f64, periods: &[f64], amplitude: f64) -> (f64, f64) {
    let (mut sx, mut sy) = (0.0, 0.0);
    for (i, &p) in periods.iter().enumerate() {
        let k = 2.0 * PI / p;
        let phase = 1.7 * i as f64;
        sx += amplitude * (k * x + phase).cos() * (k * y * 0.9 + 0.5 * phase).sin();
        sy += amplitude * (k * x + phase).sin() * (k * y * 0.9 + 0.5 * phase).cos();
    }
    (sx / periods.len() as f64, sy / periods.len() as f64)
}

/// A blotchy pattern in [0, 1] and its material (colour, F0, roughness
/// from the blotch; bumps of slopes `slope` at angular frequencies `k`
/// rad/mm along x and y).
fn blotchy(b: f64, slope: f64, k: [f64; 2], x: f64, y: f64, roughness: [f64; 2]) -> Texel {
    Texel {
        colour: [0.1 + 0.6 * b, 0.15 + 0.3 * b * b, 0.05 + 0.2 * (1.0 - b)],
        specular: [0.02 + 0.1 * b; 3],
        roughness: roughness[0] + roughness[1] * b,
        slope: (slope * (k[0] * x).cos(), slope * (k[1] * y).sin()),
    }
}

/// The nine sets of `--other-kinds` (module docs).
fn other_kinds(dir: &Path) {
    let flat = |colour: f64, specular: f64, roughness: f64| Texel {
        colour: [colour; 3],
        specular: [specular; 3],
        roughness,
        slope: (0.0, 0.0),
    };
    write_set::<1>(dir, "one", 10_000.0, false, |_, _| flat(0.3, 0.5, 1.0));
    write_set::<32>(dir, "white-hot", 10.0, false, |_, _| flat(1.0, 1.0, 0.4));
    write_set::<4>(dir, "mirror", 10.0, false, |_, _| flat(0.0, 1.0, 0.0));
    // Uniform and flat: a polished metal (GGX α 0.0225) and a satin.
    let uniform = |colour: [f64; 3], specular: [f64; 3], roughness: f64| {
        move |_: f64, _: f64| Texel { colour, specular, roughness, slope: (0.0, 0.0) }
    };
    write_set::<4>(dir, "polished", 50.0, false, uniform([0.03; 3], [0.9, 0.85, 0.8], 0.15));
    write_set::<4>(dir, "satin", 50.0, false, uniform([0.2, 0.1, 0.05], [0.05; 3], 0.3));
    // Each of the 8 × 8 texels its own colour (a splitmix64 hash).
    write_set::<8>(dir, "tiny-tile", 0.5, false, |x, y| {
        let (c, r) = ((x / 0.5 * 8.0) as u64, (y / 0.5 * 8.0) as u64);
        Texel {
            colour: [0, 1, 2].map(|k| 0.05 + 0.85 * unit_hash((r * 8 + c) * 3 + k)),
            specular: [0.04; 3],
            roughness: 0.6,
            slope: (0.0, 0.0),
        }
    });
    write_set::<64>(dir, "steep", 4.0, false, |x, _| Texel {
        slope: (6.0 * (2.0 * PI * x / 4.0).sin(), 0.0),
        ..flat(0.5, 0.04, 0.5)
    });
    write_set_at::<2048>(dir, "blotchy", 50.0, Some([3.3, 7.1]), false, |x, y| {
        let b = 0.5 + 0.5 * (1.3 * x + 2.0 * (0.7 * y).sin()).sin() * (0.9 * y).cos();
        blotchy(b, 0.15, [2.1, 1.7], x, y, [0.2, 0.5])
    });
    write_set_at::<4096>(dir, "big4k", 200.0, Some([60.0, 90.0]), false, |x, y| {
        let b = 0.5 + 0.5 * (0.9 * x + 2.0 * (0.5 * y).sin()).sin() * (0.6 * y).cos();
        blotchy(b, 0.1, [1.5, 1.1], x, y, [0.3, 0.4])
    });
}

/// splitmix64's finaliser of `z`, as a number in [0, 1]: the same on every
/// machine.
fn unit_hash(z: u64) -> f64 {
    let mut z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (z ^ (z >> 31)) as f64 / u64::MAX as f64
}

/// The row-major index in a periodic `w`² grid `pitch` mm apart of the
/// cell holding material point (x, y) mm.
fn grid_index(x: f64, y: f64, pitch: f64, w: usize) -> usize {
    ((y / pitch) as usize % w) * w + (x / pitch) as usize % w
}

/// Periodic fractal value noise on a `w`² grid: octaves of a random
/// lattice `base · 2^o` cells across, smoothly (quintic) interpolated, each
/// `2^(−o·hurst)` the amplitude of the one before; mean 0, rms 1. Seeded
/// by `seed` (splitmix64), so the same on every machine.
fn fractal(w: usize, base: usize, octaves: u32, hurst: f64, seed: u64) -> Vec<f64> {
    let hash = |o: u64, i: usize, j: usize| {
        unit_hash(seed ^ (o << 48) ^ ((i as u64) << 24) ^ j as u64) * 2.0 - 1.0
    };
    let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let mut h = vec![0.0f64; w * w];
    for o in 0..octaves {
        let n = base << o;
        let amp = 2f64.powf(-(o as f64) * hurst);
        for (p, v) in h.iter_mut().enumerate() {
            let (x, y) = [p % w, p / w].map(|k| (k as f64 + 0.5) / w as f64 * n as f64).into();
            let (i, j) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = (fade(x - i as f64), fade(y - j as f64));
            let at = |a: usize, b: usize| hash(o as u64, a % n, b % n);
            let top = at(i, j) * (1.0 - fx) + at(i + 1, j) * fx;
            let bottom = at(i, j + 1) * (1.0 - fx) + at(i + 1, j + 1) * fx;
            *v += amp * (top * (1.0 - fy) + bottom * fy);
        }
    }
    let mean = h.iter().sum::<f64>() / h.len() as f64;
    let rms = (h.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / h.len() as f64).sqrt();
    h.iter().map(|v| (v - mean) / rms).collect()
}

/// The slopes (∂h/∂x, ∂h/∂y) of a periodic `w`² height grid `pitch` mm
/// apart (central differences), scaled to an rms slope of `rms` (unscaled
/// when `None`).
fn slopes(h: &[f64], w: usize, pitch: f64, rms: Option<f64>) -> Vec<(f64, f64)> {
    let at = |x: usize, y: usize| h[(y % w) * w + x % w];
    let g: Vec<(f64, f64)> = (0..w * w)
        .map(|p| {
            let (x, y) = (p % w, p / w);
            (
                (at(x + 1, y) - at(x + w - 1, y)) / (2.0 * pitch),
                (at(x, y + 1) - at(x, y + w - 1)) / (2.0 * pitch),
            )
        })
        .collect();
    let scale = rms.map_or(1.0, |rms| {
        let now = (g.iter().map(|(a, b)| a * a + b * b).sum::<f64>() / g.len() as f64).sqrt();
        rms / now
    });
    g.into_iter().map(|(a, b)| (a * scale, b * scale)).collect()
}

/// The two sets of `--relief` (module docs).
fn relief(dir: &Path) {
    // Stone: a fractal relief (rms slope 0.35, features from 33 mm down to
    // the 0.05 mm texels), a speckled grey albedo following it, rough.
    const S: usize = 2048;
    let (size, pitch) = (100.0, 100.0 / S as f64);
    let relief = fractal(S, 3, 10, 0.6, 1);
    let speckle = fractal(S, 40, 5, 0.2, 2);
    let slope = slopes(&relief, S, pitch, Some(0.35));
    write_set_at::<{ S as u32 }>(dir, "stone", size, Some([40.0, 20.0]), false, |x, y| {
        let t = grid_index(x, y, pitch, S);
        let base = 0.35 + 0.08 * relief[t] + 0.06 * speckle[t];
        Texel {
            colour: [1.05 * base, 0.98 * base, 0.9 * base],
            specular: [0.04; 3],
            roughness: (0.55 + 0.1 * speckle[t]).clamp(0.0, 1.0),
            slope: slope[t],
        }
    });
    // Tiles: 12 mm glazed tiles of 25 colours (roughness 0.18, F0 0.05)
    // with a gentle waviness (0.01 mm), bevelled into 1 mm matte grout
    // grooves 0.3 mm deep.
    const T: usize = 1024;
    let (size, pitch) = (60.0, 60.0 / T as f64);
    let wave = fractal(T, 4, 8, 0.6, 3);
    let depth = |x: f64, y: f64| {
        let (fx, fy) = (x.rem_euclid(12.0), y.rem_euclid(12.0));
        let d = fx.min(12.0 - fx).min(fy).min(12.0 - fy);
        -0.3 * (1.0 - d / 0.8).clamp(0.0, 1.0).powi(2)
    };
    let height: Vec<f64> = (0..T * T)
        .map(|p| {
            let (x, y) = [p % T, p / T].map(|k| (k as f64 + 0.5) * pitch).into();
            depth(x, y) + 0.01 * wave[p]
        })
        .collect();
    let slope = slopes(&height, T, pitch, None);
    let colour = |i: f64, j: f64| {
        let k = (i.rem_euclid(5.0) * 5.0 + j.rem_euclid(5.0)) as u64;
        [0u64, 1, 2].map(|c| 0.1 + 0.7 * unit_hash(k * 3 + c))
    };
    write_set_at::<{ T as u32 }>(dir, "tiles", size, Some([5.0, 5.0]), false, |x, y| {
        let t = grid_index(x, y, pitch, T);
        let grout = x.rem_euclid(12.0) < 1.0 || y.rem_euclid(12.0) < 1.0;
        Texel {
            colour: if grout {
                [0.45, 0.44, 0.42]
            } else {
                colour((x / 12.0).floor(), (y / 12.0).floor())
            },
            specular: [if grout { 0.02 } else { 0.05 }; 3],
            roughness: if grout { 0.8 } else { 0.18 },
            slope: slope[t],
        }
    });
}

fn main() {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(
        args.next().expect("usage: unseen_samples DIR [--other-kinds | --relief]"),
    );
    match args.next().as_deref() {
        Some("--other-kinds") => return other_kinds(&dir),
        Some("--relief") => return relief(&dir),
        _ => {}
    }
    // The sizes divide the 25.4 mm sample into whole periods where the
    // patterns are periodic; the maps tile at size_mm.
    write_set::<512>(&dir, "red-plastic", 32.0, false, |x, y| Texel {
        colour: [0.45, 0.04, 0.03],
        specular: [0.04; 3],
        roughness: 0.285 + 0.035 * (2.0 * PI * x / 16.0).sin() * (2.0 * PI * y / 8.0).cos(),
        slope: bumps(x, y, &[2.0], 0.03),
    });
    write_set::<512>(&dir, "gold-foil", 28.0, false, |x, y| Texel {
        colour: [0.0; 3],
        specular: [1.0, 0.77, 0.33],
        roughness: 0.28 + 0.06 * (2.0 * PI * (x + 0.5 * y) / 7.0).sin(),
        slope: bumps(x, y, &[7.0, 4.0, 3.0], 0.2),
    });
    write_set::<512>(&dir, "dark-rubber", 24.0, false, |x, y| Texel {
        colour: [0.03, 0.03, 0.032],
        specular: [0.04; 3],
        roughness: 0.85,
        slope: bumps(x, y, &[0.8], 0.08),
    });
    write_set::<512>(&dir, "printed-paper", 20.0, false, |x, y| {
        let line = (x % 2.0) < 0.3;
        let (dx, dy) = ((x % 5.0) - 2.5, (y % 5.0) - 2.5);
        let dot = dx * dx + dy * dy < 1.0;
        let ink = if line {
            [0.03, 0.03, 0.05]
        } else if dot {
            [0.05, 0.30, 0.60]
        } else {
            [0.80, 0.79, 0.74]
        };
        Texel { colour: ink, specular: [0.04; 3], roughness: 0.9, slope: (0.0, 0.0) }
    });
    write_set::<512>(&dir, "green-tile", 30.0, true, |x, y| {
        let fleck = ((x * 3.7).sin() * (y * 4.3).sin()).abs() > 0.97;
        let (base, metallic) =
            if fleck { ([0.9, 0.8, 0.5], 1.0) } else { ([0.08, 0.35, 0.15], 0.0) };
        Texel {
            colour: base,
            specular: [0.0, 0.35 + 0.1 * (2.0 * PI * y / 10.0).sin(), metallic],
            roughness: 0.0,
            slope: bumps(x, y, &[10.0, 6.0], 0.05),
        }
    });
    write_set::<64>(&dir, "chrome", 8.0, false, |x, y| Texel {
        colour: [0.0; 3],
        specular: [0.90, 0.91, 0.92],
        roughness: 0.12,
        slope: (0.04 * (2.0 * PI * x / 8.0).cos(), 0.04 * (2.0 * PI * y / 4.0).cos()),
    });
    // In the 256² maps' pixels (p = 64 px/mm · x − ½): roughness varies
    // along the grooves, which wander slightly.
    write_set::<256>(&dir, "brushed", 4.0, false, |x, y| {
        let (px, py) = (64.0 * x - 0.5, 64.0 * y - 0.5);
        Texel {
            colour: [0.02; 3],
            specular: [0.6; 3],
            roughness: 0.3 + 0.05 * (0.7 * px + 0.01 * py).sin(),
            slope: (0.0, 0.3 * (2.0 * PI * 4.0 * y + 0.3 * (0.05 * px).sin()).sin()),
        }
    });
    write_set::<1024>(&dir, "glint-stripes", 100.0, false, |x, y| {
        let band = 0.25 * (2.0 * PI * (3.0 * x + 2.0 * y) / 100.0).sin();
        Texel {
            colour: [0.22 + 0.6 * band * 0.9, 0.22 + 0.6 * band * 0.55, 0.22 + 0.6 * band * 0.2]
                .map(|c: f64| c.max(0.01)),
            specular: [0.003; 3],
            roughness: 0.3 + 0.2 * (2.0 * PI * 7.0 * x / 100.0).sin(),
            slope: (-0.1 * (2.0 * PI * x / 5.0).cos(), -0.1 * (2.0 * PI * y / 5.0).sin()),
        }
    });
}
