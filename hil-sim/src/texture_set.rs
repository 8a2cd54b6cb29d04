//! Texture-set samples: a material a user defines with image maps
//! (docs/texture-set.md), scanned by the simulator like the built-in ones.
//!
//! A directory holds `material.toml` and either the maps `diffuse`,
//! `specular` (F0), `roughness` and `normal`, or the glTF metallic-roughness
//! maps `baseColor`, `metallicRoughness` and `normal`; each `.png` (8 or
//! 16 bit; colour maps sRGB-encoded, roughness, metallic-roughness and
//! normal linear) or `.exr` (linear). The maps tile periodically over
//! `size_mm`; lookups are bilinear.

use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::Deserialize;

use crate::materials::{Material, Texel};

/// Version of `material.toml`.
pub const TEXTURE_SET_FORMAT: u32 = 1;
/// GGX α floor: α = roughness² is singular at 0 (a perfect mirror).
pub const MIN_ALPHA: f64 = 1e-3;

/// Why a texture set was refused: the file and what is wrong with it.
#[derive(Debug, thiserror::Error)]
#[error("{}: {reason}", path.display())]
pub struct TextureSetError {
    /// The file (or the directory, for a missing map).
    pub path: PathBuf,
    /// What is wrong.
    pub reason: String,
}

fn err(path: &Path, reason: impl Into<String>) -> TextureSetError {
    TextureSetError { path: path.to_path_buf(), reason: reason.into() }
}

/// `material.toml`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    format: u32,
    name: String,
    size_mm: f64,
    #[serde(default)]
    sample_offset_mm: [f64; 2],
}

/// One map, row-major, `channels` per pixel: linear values once loaded
/// ([`load_map`]), as stored when read ([`read_image`], [`read_exr`]).
#[derive(Debug, Clone)]
struct Map {
    width: usize,
    height: usize,
    channels: usize,
    data: Vec<f32>,
}

impl Map {
    /// Bilinear, periodic lookup at material point `p` (mm) over a tile of
    /// side `size`: pixel (c, r) is centred on ((c + 0.5)/W, (r + 0.5)/H)·size.
    fn sample<const C: usize>(&self, p: [f64; 2], size: f64) -> [f64; C] {
        debug_assert_eq!(self.channels, C);
        let x = p[0] / size * self.width as f64 - 0.5;
        let y = p[1] / size * self.height as f64 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let wrap = |i: f64, n: usize| (i as i64).rem_euclid(n as i64) as usize;
        let (xa, xb) = (wrap(x0, self.width), wrap(x0 + 1.0, self.width));
        let (ya, yb) = (wrap(y0, self.height), wrap(y0 + 1.0, self.height));
        let at = |c: usize, r: usize, k: usize| self.data[(r * self.width + c) * C + k] as f64;
        std::array::from_fn(|k| {
            let top = at(xa, ya, k) * (1.0 - fx) + at(xb, ya, k) * fx;
            let bottom = at(xa, yb, k) * (1.0 - fx) + at(xb, yb, k) * fx;
            top * (1.0 - fy) + bottom * fy
        })
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Encoding {
    /// Colour: sRGB-encoded in a PNG.
    Srgb,
    /// Data: linear in a PNG.
    Linear,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Channels {
    /// RGB (a PNG's alpha is ignored); a grey PNG counts as R = G = B.
    Rgb,
    /// RGB without the grey convenience (normals).
    StrictRgb,
    /// One channel: a grey image (alpha ignored), or an RGB one whose R, G
    /// and B are equal.
    Grey,
}

/// The sRGB decoding of a texture set's colour maps (an encoded value in
/// [0, 1] to linear).
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.040_45 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// Decode a PNG (or any format the `image` crate guesses) as stored: 1 or 3
/// channels, alpha dropped, values in [0, 1] still encoded.
fn read_image(path: &Path) -> Result<Map, TextureSetError> {
    use image::DynamicImage as D;
    let img = image::ImageReader::open(path)
        .map_err(|e| err(path, format!("cannot open: {e}")))?
        .with_guessed_format()
        .map_err(|e| err(path, format!("cannot read: {e}")))?
        .decode()
        .map_err(|e| err(path, format!("cannot decode: {e}")))?;
    let (width, height) = (img.width() as usize, img.height() as usize);
    let (channels, data): (usize, Vec<f32>) = match &img {
        D::ImageLuma8(_) | D::ImageLuma16(_) | D::ImageLumaA8(_) | D::ImageLumaA16(_) => {
            (1, img.to_luma32f().into_raw())
        }
        D::ImageRgb8(_)
        | D::ImageRgba8(_)
        | D::ImageRgb16(_)
        | D::ImageRgba16(_)
        | D::ImageRgb32F(_)
        | D::ImageRgba32F(_) => (3, img.to_rgb32f().into_raw()),
        other => return Err(err(path, format!("unsupported pixel type {:?}", other.color()))),
    };
    Ok(Map { width, height, channels, data })
}

/// Decode an OpenEXR file's first layer as stored: its `R`, `G` and `B`
/// channels, else its `Y` (luminance) channel, else its one channel other
/// than `A`. Any sample type; subsampled channels are refused.
fn read_exr(path: &Path) -> Result<Map, TextureSetError> {
    use exr::prelude::{AnyChannel, FlatSamples};
    let image = exr::prelude::read_first_flat_layer_from_file(path)
        .map_err(|e| err(path, format!("cannot decode: {e}")))?;
    let layer = &image.layer_data;
    let (width, height) = (layer.size.width(), layer.size.height());
    let list = &layer.channel_data.list;
    let find = |name: &str| list.iter().find(|c| c.name.eq(name));
    let names = || list.iter().map(|c| c.name.to_string()).collect::<Vec<_>>().join(", ");
    let chosen: Vec<&AnyChannel<FlatSamples>> = match (find("R"), find("G"), find("B"), find("Y")) {
        (Some(r), Some(g), Some(b), _) => vec![r, g, b],
        (_, _, _, Some(_)) if find("RY").is_some() || find("BY").is_some() => {
            return Err(err(path, "luminance/chroma (Y, RY, BY) image: store R, G, B or Y alone"));
        }
        (_, _, _, Some(y)) => vec![y],
        _ => {
            let colour: Vec<_> = list.iter().filter(|c| !c.name.eq("A")).collect();
            if colour.len() != 1 {
                return Err(err(
                    path,
                    format!("channels [{}]: expected R, G and B, or one channel", names()),
                ));
            }
            colour
        }
    };
    for c in &chosen {
        if c.sample_data.len() != width * height {
            return Err(err(path, format!("channel {} is subsampled", c.name)));
        }
    }
    let channels = chosen.len();
    let mut data = vec![0.0f32; width * height * channels];
    for (k, c) in chosen.iter().enumerate() {
        for (i, v) in c.sample_data.values_as_f32().enumerate() {
            data[i * channels + k] = v;
        }
    }
    Ok(Map { width, height, channels, data })
}

/// Load `path` as linear values with the channel layout asked for.
fn load_map(path: &Path, enc: Encoding, want: Channels) -> Result<Map, TextureSetError> {
    let is_exr = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    let Map { width, height, channels: src_channels, data: raw } =
        if is_exr { read_exr(path)? } else { read_image(path)? };
    if width == 0 || height == 0 {
        return Err(err(path, "empty image"));
    }
    let decode = |v: f32| if !is_exr && enc == Encoding::Srgb { srgb_to_linear(v) } else { v };
    if let Some(i) = raw.iter().position(|v| !v.is_finite()) {
        let px = i / src_channels;
        return Err(err(path, format!("pixel ({}, {}) is {}", px % width, px / width, raw[i])));
    }
    let data: Vec<f32> = match (want, src_channels) {
        (Channels::Rgb, 1) => raw.into_iter().flat_map(|v| [decode(v); 3]).collect(),
        (Channels::Rgb | Channels::StrictRgb, 3) => raw.into_iter().map(decode).collect(),
        (Channels::Rgb | Channels::StrictRgb, n) => {
            return Err(err(path, format!("{n} channel(s), expected RGB")));
        }
        (Channels::Grey, 1) => raw.into_iter().map(decode).collect(),
        (Channels::Grey, _) => {
            // Grey stored as RGB (R = G = B) is grey.
            if let Some(i) = raw.chunks_exact(3).position(|c| c[0] != c[1] || c[1] != c[2]) {
                return Err(err(
                    path,
                    format!(
                        "3 different channels at pixel ({}, {}), expected one (grey, or R = G = B)",
                        i % width,
                        i / width
                    ),
                ));
            }
            raw.chunks_exact(3).map(|c| decode(c[0])).collect()
        }
    };
    let channels = if want == Channels::Grey { 1 } else { 3 };
    Ok(Map { width, height, channels, data })
}

/// A material defined by image maps (see the module documentation).
#[derive(Debug, Clone)]
pub struct TextureSet {
    name: String,
    size_mm: f64,
    sample_offset_mm: [f64; 2],
    /// Linear diffuse albedo, RGB.
    diffuse: Map,
    /// Linear F0, RGB.
    specular: Map,
    /// Roughness (GGX α = roughness²), grey.
    roughness: Map,
    /// Encoded normal c (n = normalize(2c − 1)), RGB.
    normal: Map,
}

/// The map file `stem.png` or `stem.exr` in `dir`, if there is one.
fn find(dir: &Path, stem: &str) -> Result<Option<PathBuf>, TextureSetError> {
    let png = dir.join(format!("{stem}.png"));
    let exr = dir.join(format!("{stem}.exr"));
    match (png.is_file(), exr.is_file()) {
        (true, true) => Err(err(dir, format!("both {stem}.png and {stem}.exr: keep one"))),
        (true, false) => Ok(Some(png)),
        (false, true) => Ok(Some(exr)),
        (false, false) => Ok(None),
    }
}

fn require(dir: &Path, stem: &str) -> Result<PathBuf, TextureSetError> {
    find(dir, stem)?.ok_or_else(|| err(&dir.join(format!("{stem}.png")), "missing (.png or .exr)"))
}

impl TextureSet {
    /// Load and check a texture-set directory.
    pub fn load(dir: &Path) -> Result<TextureSet, TextureSetError> {
        let manifest_path = dir.join("material.toml");
        let text = scanner_formats::input::read_to_string(&manifest_path)
            .map_err(|e| err(&manifest_path, format!("cannot read: {e}")))?;
        let m: Manifest =
            toml::from_str(&text).map_err(|e| err(&manifest_path, e.message().to_string()))?;
        if m.format != TEXTURE_SET_FORMAT {
            return Err(err(
                &manifest_path,
                format!("format {} (this build reads {TEXTURE_SET_FORMAT})", m.format),
            ));
        }
        if !(m.size_mm.is_finite() && m.size_mm > 0.0 && m.size_mm <= 10_000.0) {
            return Err(err(&manifest_path, format!("size_mm {} outside (0, 10000]", m.size_mm)));
        }
        // Within ±1e9 mm, as every number of the scanner's files: beyond
        // about 1e12 mm the sample's 25.4 mm would lose its precision.
        if !m.sample_offset_mm.iter().all(|v| v.abs() <= 1e9) {
            let [x, y] = m.sample_offset_mm;
            return Err(err(
                &manifest_path,
                format!("sample_offset_mm [{x:e}, {y:e}] must be finite and within ±1e9 mm"),
            ));
        }
        if m.name.trim().is_empty() {
            return Err(err(&manifest_path, "name is empty"));
        }
        let gltf = find(dir, "baseColor")?.is_some() || find(dir, "metallicRoughness")?.is_some();
        let classic = find(dir, "diffuse")?.is_some() || find(dir, "specular")?.is_some();
        if gltf && classic {
            return Err(err(
                dir,
                "both diffuse/specular and glTF baseColor/metallicRoughness maps: keep one form",
            ));
        }
        let normal_path = require(dir, "normal")?;
        let normal = load_map(&normal_path, Encoding::Linear, Channels::StrictRgb)?;
        let (diffuse, specular, roughness, files) = if gltf {
            let base_path = require(dir, "baseColor")?;
            let mr_path = require(dir, "metallicRoughness")?;
            let base = load_map(&base_path, Encoding::Srgb, Channels::Rgb)?;
            let mr = load_map(&mr_path, Encoding::Linear, Channels::StrictRgb)?;
            same_size(&base, &base_path, &mr, &mr_path)?;
            let mut diffuse = base.clone();
            let mut specular = base.clone();
            let mut rough = Map { channels: 1, data: Vec::with_capacity(mr.data.len() / 3), ..mr };
            for (i, px) in mr.data.chunks_exact(3).enumerate() {
                let (r, m) = (px[1], px[2]);
                check_unit(&mr_path, "metallic", m, i, mr.width)?;
                rough.data.push(r);
                for k in 0..3 {
                    let b = base.data[3 * i + k];
                    diffuse.data[3 * i + k] = b * (1.0 - m);
                    specular.data[3 * i + k] = 0.04 * (1.0 - m) + b * m;
                }
            }
            (diffuse, specular, rough, [base_path, mr_path.clone(), mr_path])
        } else {
            let d_path = require(dir, "diffuse")?;
            let s_path = require(dir, "specular")?;
            let r_path = require(dir, "roughness")?;
            let d = load_map(&d_path, Encoding::Srgb, Channels::Rgb)?;
            let s = load_map(&s_path, Encoding::Srgb, Channels::Rgb)?;
            let r = load_map(&r_path, Encoding::Linear, Channels::Grey)?;
            (d, s, r, [d_path, s_path, r_path])
        };
        let [d_path, s_path, r_path] = &files;
        same_size(&diffuse, d_path, &specular, s_path)?;
        same_size(&diffuse, d_path, &roughness, r_path)?;
        same_size(&diffuse, d_path, &normal, &normal_path)?;
        for (i, &v) in diffuse.data.iter().enumerate() {
            check_unit(d_path, "diffuse albedo", v, i / 3, diffuse.width)?;
        }
        for (i, &v) in specular.data.iter().enumerate() {
            check_unit(s_path, "specular F0", v, i / 3, specular.width)?;
        }
        for (i, &v) in roughness.data.iter().enumerate() {
            check_unit(r_path, "roughness", v, i, roughness.width)?;
        }
        for (i, c) in normal.data.chunks_exact(3).enumerate() {
            let n = DVec3::new(
                2.0 * c[0] as f64 - 1.0,
                2.0 * c[1] as f64 - 1.0,
                2.0 * c[2] as f64 - 1.0,
            );
            if !(n.length() > 1e-3 && n.z > 0.0) {
                let why = if n.length() > 1e-3 {
                    "a normal must point out of the surface (z > 0)"
                } else {
                    "no direction (2c − 1 is a zero vector)"
                };
                return Err(err(
                    &normal_path,
                    format!(
                        "pixel ({}, {}) decodes to ({:.4}, {:.4}, {:.4}): {why}",
                        i % normal.width,
                        i / normal.width,
                        n.x,
                        n.y,
                        n.z
                    ),
                ));
            }
        }
        Ok(TextureSet {
            name: m.name,
            size_mm: m.size_mm,
            sample_offset_mm: m.sample_offset_mm,
            diffuse,
            specular,
            roughness,
            normal,
        })
    }

    /// Maps' size, px.
    pub fn resolution(&self) -> [usize; 2] {
        [self.diffuse.width, self.diffuse.height]
    }
}

fn same_size(a: &Map, a_path: &Path, b: &Map, b_path: &Path) -> Result<(), TextureSetError> {
    if (a.width, a.height) == (b.width, b.height) {
        Ok(())
    } else {
        Err(err(
            b_path,
            format!(
                "{}×{} px, but {} is {}×{}: every map must have the same size",
                b.width,
                b.height,
                a_path.file_name().map(|f| f.to_string_lossy()).unwrap_or_default(),
                a.width,
                a.height
            ),
        ))
    }
}

fn check_unit(
    path: &Path,
    what: &str,
    v: f32,
    px: usize,
    width: usize,
) -> Result<(), TextureSetError> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err(err(path, format!("pixel ({}, {}): {what} {v} outside [0, 1]", px % width, px / width)))
    }
}

impl Material for TextureSet {
    fn name(&self) -> &str {
        &self.name
    }

    fn texel(&self, p: [f64; 2]) -> Texel {
        let s = self.size_mm;
        let r: [f64; 1] = self.roughness.sample(p, s);
        let c: [f64; 3] = self.normal.sample(p, s);
        let n = DVec3::new(2.0 * c[0] - 1.0, 2.0 * c[1] - 1.0, 2.0 * c[2] - 1.0);
        // Interpolating between valid normals can only cancel out between
        // opposite ones; fall back to the geometric normal there.
        let normal = if n.length() > 1e-6 && n.z > 0.0 { n.normalize() } else { DVec3::Z };
        Texel {
            diffuse: self.diffuse.sample(p, s),
            specular: self.specular.sample(p, s),
            roughness: (r[0] * r[0]).max(MIN_ALPHA),
            normal,
        }
    }

    fn tile_mm(&self) -> f64 {
        self.size_mm
    }

    fn sample_offset_mm(&self) -> [f64; 2] {
        self.sample_offset_mm
    }
}
