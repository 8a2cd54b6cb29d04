//! A material's fitted texel model as a texture set (docs/texture-set.md):
//! diffuse albedo, F0, roughness and normal maps that any physically based
//! renderer reads, and that the simulator scans like its own samples.
//!
//! The maps hold the texel model (docs/material-format.md, "Texel model")
//! and, when the file has a detail layer, its shared factor: what is
//! common to every light and view. The captured images' residuals — what
//! the model does not explain (shadowing between threads, interreflection,
//! anything not Lambert plus GGX) — stay in the material file.

use std::path::Path;

use scanner_shading::format::MaterialData;
use scanner_shading::texel::{STORED, TexelParams};

use super::BuildError;

/// How the maps are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapFormat {
    /// OpenEXR, 32-bit float, linear: every map exactly as the file holds it.
    Exr,
    /// 16-bit PNG: diffuse and specular sRGB-encoded, roughness and normal
    /// linear (the texture-set convention).
    Png,
}

impl std::str::FromStr for MapFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<MapFormat, String> {
        match s {
            "exr" => Ok(MapFormat::Exr),
            "png" => Ok(MapFormat::Png),
            _ => Err(format!("{s}: the maps are `exr` or `png`")),
        }
    }
}

impl MapFormat {
    /// The maps' file extension.
    pub fn extension(self) -> &'static str {
        match self {
            MapFormat::Exr => "exr",
            MapFormat::Png => "png",
        }
    }
}

/// The map names of a texture set, in the order they are written.
pub const MAPS: [&str; 4] = ["diffuse", "specular", "roughness", "normal"];
/// The texture set's description file.
pub const DESCRIPTION: &str = "material.toml";

/// A texture set in memory: `side` × `side` texels over a square of
/// `size_mm`, row-major with row 0 at v = 0.
#[derive(Debug, Clone)]
pub struct TextureSet {
    /// The material's name.
    pub name: String,
    /// Side of the square the maps cover, mm (the material's extent).
    pub size_mm: f64,
    /// Texels per side.
    pub side: usize,
    /// Diffuse albedo ρd per texel, linear RGB in [0, 1].
    pub diffuse: Vec<[f32; 3]>,
    /// F0 per texel, linear RGB in [0, 1].
    pub specular: Vec<[f32; 3]>,
    /// Roughness √α per texel, in [0, 1].
    pub roughness: Vec<f32>,
    /// Unit normal per texel, sample-local (x along +u, y along +v), z > 0.
    pub normal: Vec<[f32; 3]>,
}

/// The texel model of `data` as a texture set. With a detail layer the maps
/// have its resolution (2S), the model's parameters interpolated
/// bilinearly as the shading does, and the layer's shared factor
/// multiplies the diffuse albedo and F0 (each clamped to [0, 1]); a layer's
/// light components depend on the light and are left out. An enlarged
/// material's maps cover its whole piece, one texel per texel of its map
/// (two with a detail layer), each the model at the place on the sample
/// the shading looks it up.
///
/// Refused (an input error) when the file holds no texel model or does not
/// span a square.
pub fn texture_set(data: &MaterialData) -> Result<TextureSet, BuildError> {
    let m = &data.meta;
    if !m.texel_model || data.texels.is_empty() {
        return Err(BuildError::Input(
            "the material holds no texel model to export (it was built with `--texel-model off`, \
             or `auto` found that the model did not explain the scan better than a diffuse fit; \
             `scanner build --texel-model on` keeps one)"
                .into(),
        ));
    }
    let [w, h] = m.extent_mm;
    if w != h {
        return Err(BuildError::Input(format!(
            "the material spans {w} × {h} mm: a texture set covers a square"
        )));
    }
    let s = m.resolution as usize;
    let stored: Vec<[f32; STORED]> = data.texels.iter().map(TexelParams::to_stored).collect();
    let scale_by = |mut p: TexelParams, d: [f32; 3]| {
        let scale = |x: [f32; 3]| std::array::from_fn(|c| (x[c] * d[c]).clamp(0.0, 1.0));
        p.diffuse = scale(p.diffuse);
        p.specular = scale(p.specular);
        p
    };
    let (side, params): (usize, Vec<TexelParams>) = if let Some(e) = &m.enlargement {
        // An enlarged material: the piece's map texels (twice as fine with
        // a detail layer), each the model where the shading looks it up.
        let material = scanner_shading::Material::from_data(data.clone())
            .map_err(|e| BuildError::Input(e.to_string()))?;
        let f = if data.detail.is_empty() { 1 } else { 2 };
        if e.columns != e.rows {
            return Err(BuildError::Input(format!(
                "the material's map is {} × {} texels over a square: a texture set's maps are \
                 square",
                e.columns, e.rows
            )));
        }
        let side = f * e.columns as usize;
        if side > MAX_SIDE {
            return Err(BuildError::Input(format!(
                "maps of {side}² texels (the map's {} a side{}): a texture set has at most \
                 {MAX_SIDE} a side",
                e.columns,
                if f == 2 { ", twice for the detail layer" } else { "" }
            )));
        }
        let detail: Vec<[f32; 3]> = data.detail.clone();
        let params = (0..side * side)
            .map(|i| {
                let (x, y) = (i % side, i / side);
                let uv = [(x as f32 + 0.5) / side as f32, (y as f32 + 0.5) / side as f32];
                let at = material.scanned_uv(uv);
                let p = TexelParams::from_stored(&bilinear(&stored, s, at));
                if detail.is_empty() {
                    p
                } else {
                    let (t, w) = scanner_shading::bilinear_footprint(2 * s, at);
                    let d = std::array::from_fn(|c| {
                        (0..4).map(|k| w[k] * detail[t[k] as usize][c]).sum::<f32>()
                    });
                    scale_by(p, d)
                }
            })
            .collect();
        (side, params)
    } else if data.detail.is_empty() {
        (s, data.texels.clone())
    } else {
        let f = 2 * s;
        let params = (0..f * f)
            .map(|i| {
                let (x, y) = (i % f, i / f);
                let uv = [(x as f32 + 0.5) / f as f32, (y as f32 + 0.5) / f as f32];
                let v = bilinear(&stored, s, uv);
                scale_by(TexelParams::from_stored(&v), data.detail[i])
            })
            .collect();
        (f, params)
    };
    Ok(TextureSet {
        name: m.name.clone(),
        size_mm: w,
        side,
        diffuse: params.iter().map(|p| p.diffuse).collect(),
        specular: params.iter().map(|p| keep_lobe(p.specular)).collect(),
        roughness: params.iter().map(|p| p.alpha.sqrt().clamp(0.0, 1.0)).collect(),
        // The stored x, y give z (`TexelParams::from_stored`): unit but for
        // rounding, which this takes out.
        normal: params
            .iter()
            .map(|p| {
                let n = p.normal;
                let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                n.map(|c| c / l)
            })
            .collect(),
    })
}

/// The largest side of an exported map, texels (a material's detail layer
/// at its largest resolution, 2 × 8192).
pub const MAX_SIDE: usize = 16384;

/// Smallest F0 written where a texel's F0 is 0 in every channel.
pub const MIN_F0: f32 = 1e-5;

/// F0 with its lobe kept: in a texture set, F0 = 0 in every channel means
/// a purely Lambertian texel (docs/texture-set.md), while the material's
/// texel model still has Schlick's Fresnel reflection at grazing angles
/// there. [`MIN_F0`] (a 16-bit PNG keeps it) keeps that reflection and
/// changes nothing else visibly.
fn keep_lobe(f0: [f32; 3]) -> [f32; 3] {
    if f0.iter().all(|&f| f <= 0.0) { [MIN_F0; 3] } else { f0 }
}

/// The stored parameters of an `s` × `s` grid at `uv`, interpolated as the
/// shading interpolates them.
fn bilinear(v: &[[f32; STORED]], s: usize, uv: [f32; 2]) -> [f32; STORED] {
    let (t, w) = scanner_shading::bilinear_footprint(s, uv);
    let t = t.map(|i| &v[i as usize]);
    std::array::from_fn(|k| w[0] * t[0][k] + w[1] * t[1][k] + w[2] * t[2][k] + w[3] * t[3][k])
}

/// sRGB encoding of a linear value in [0, 1].
pub(crate) fn srgb(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.003_130_8 { 12.92 * c } else { 1.055 * c.powf(1.0 / 2.4) - 0.055 }
}

impl TextureSet {
    /// The description file's text (format 1).
    pub fn description(&self) -> String {
        // A texture set needs a name; `{:?}` writes a float as TOML's
        // (25.0, not 25, which TOML reads as an integer).
        let name = toml_string(if self.name.trim().is_empty() { "scanned" } else { &self.name });
        format!(
            "# Exported by scanner {}: the texel model of a scanned material.\n\
             format = 1\nname = {name}\nsize_mm = {:?}\nsample_offset_mm = [0.0, 0.0]\n",
            env!("CARGO_PKG_VERSION"),
            self.size_mm
        )
    }

    /// The maps' files in memory, (name, bytes), in [`MAPS`] order.
    pub fn encode(&self, format: MapFormat) -> Result<Vec<(String, Vec<u8>)>, String> {
        let grey: Vec<[f32; 3]> = self.roughness.iter().map(|&r| [r; 3]).collect();
        // Normals as stored colours: c = (n + 1) / 2.
        let normal: Vec<[f32; 3]> =
            self.normal.iter().map(|n| n.map(|c| (c + 1.0) * 0.5)).collect();
        let maps: [(&[[f32; 3]], bool); 4] =
            [(&self.diffuse, true), (&self.specular, true), (&grey, false), (&normal, false)];
        MAPS.iter()
            .zip(maps)
            .map(|(name, (px, colour))| {
                let file = format!("{name}.{}", format.extension());
                let bytes = match format {
                    MapFormat::Exr => self.encode_exr(px),
                    MapFormat::Png => self.encode_png(px, colour),
                }
                .map_err(|e| format!("{file}: {e}"))?;
                Ok((file, bytes))
            })
            .collect()
    }

    fn encode_exr(&self, px: &[[f32; 3]]) -> Result<Vec<u8>, String> {
        let n = self.side as u32;
        let img = image::Rgb32FImage::from_raw(n, n, px.iter().flatten().copied().collect())
            .ok_or("map of the wrong size")?;
        let mut bytes = Vec::new();
        image::DynamicImage::ImageRgb32F(img)
            .write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::OpenExr)
            .map_err(|e| e.to_string())?;
        Ok(bytes)
    }

    fn encode_png(&self, px: &[[f32; 3]], colour: bool) -> Result<Vec<u8>, String> {
        let n = self.side as u32;
        let code = |v: f32| {
            let e = if colour { srgb(v) } else { v.clamp(0.0, 1.0) };
            (e * 65535.0).round() as u16
        };
        let img = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(
            n,
            n,
            px.iter().flatten().map(|&v| code(v)).collect::<Vec<u16>>(),
        )
        .ok_or("map of the wrong size")?;
        let mut bytes = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
            .map_err(|e| e.to_string())?;
        Ok(bytes)
    }

    /// Write the set into the directory `dir` (which must exist): each file
    /// atomically.
    pub fn write(&self, dir: &Path, format: MapFormat) -> Result<(), BuildError> {
        let out = |name: &str, e: String| {
            BuildError::Output(format!("{}: {e}", dir.join(name).display()))
        };
        for (name, bytes) in self.encode(format).map_err(|e| out("", e))? {
            crate::fsutil::write_atomic(&dir.join(&name), &bytes)
                .map_err(|e| out(&name, e.to_string()))?;
        }
        crate::fsutil::write_atomic(&dir.join(DESCRIPTION), self.description().as_bytes())
            .map_err(|e| out(DESCRIPTION, e.to_string()))
    }
}

/// A TOML basic string.
fn toml_string(s: &str) -> String {
    let mut out = String::from("\"");
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if c.is_control() => out.push_str(&format!("\\u{:04X}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// Whether `name` is a file a texture-set export writes.
pub fn is_texture_set_file(name: &str) -> bool {
    let map = |(stem, ext): (&str, &str)| {
        MAPS.contains(&stem)
            && [MapFormat::Exr, MapFormat::Png].map(MapFormat::extension).contains(&ext)
    };
    name == DESCRIPTION || name.split_once('.').is_some_and(map)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_description_is_toml_for_any_name_and_size() {
        for (name, size) in [
            ("plain", 25.4),
            ("with \"quotes\"", 25.0),
            ("back\\slash", 1e-3),
            ("tab\there", 9999.5),
            ("ünïcödé", 12.0),
            ("  ", 25.4),
        ] {
            let set = TextureSet {
                name: name.into(),
                size_mm: size,
                side: 1,
                diffuse: vec![[0.5; 3]],
                specular: vec![[0.04; 3]],
                roughness: vec![0.5],
                normal: vec![[0.0, 0.0, 1.0]],
            };
            let doc: toml::Table = set.description().parse().unwrap();
            let want = if name.trim().is_empty() { "scanned" } else { name };
            assert_eq!(doc["name"].as_str(), Some(want));
            assert_eq!(doc["size_mm"].as_float(), Some(size), "{}", set.description());
        }
    }

    #[test]
    fn a_lobe_with_no_f0_is_kept_through_a_png() {
        assert_eq!(keep_lobe([0.0; 3]), [MIN_F0; 3]);
        assert_eq!(keep_lobe([0.0, 0.2, 0.0]), [0.0, 0.2, 0.0]);
        let set = TextureSet {
            name: "x".into(),
            size_mm: 1.0,
            side: 1,
            diffuse: vec![[0.5; 3]],
            specular: vec![[MIN_F0; 3]],
            roughness: vec![0.5],
            normal: vec![[0.0, 0.0, 1.0]],
        };
        let maps = set.encode(MapFormat::Png).unwrap();
        assert_eq!(maps[1].0, "specular.png");
        let png = image::load_from_memory(&maps[1].1).unwrap().to_rgb16();
        // Decoded as a texture set's sRGB map: above 0, within 10 % of MIN_F0.
        let code = png.get_pixel(0, 0).0[0] as f32 / 65535.0;
        assert!((code / 12.92 - MIN_F0).abs() < 0.1 * MIN_F0, "{code}");
    }

    #[test]
    fn only_its_own_files_are_recognised() {
        for ok in ["material.toml", "diffuse.exr", "normal.png", "roughness.exr", "specular.png"] {
            assert!(is_texture_set_file(ok), "{ok}");
        }
        for no in ["diffuse.tif", "baseColor.png", "material.json", "diffuse.exr.tmp", "x.png"] {
            assert!(!is_texture_set_file(no), "{no}");
        }
    }
}
