//! A texture set as a glTF 2.0 asset (docs/texture-set.md, "Exported
//! glTF assets"): one square of the material's extent, with a
//! metallic-roughness material that any glTF viewer shows.
//!
//! glTF describes a texel by a base colour and a metallic factor, where the
//! texel model has a diffuse albedo and F0; [`metallic_form`] picks, per
//! texel, the pair whose diffuse = base · (1 − m) and
//! F0 = 0.04 · (1 − m) + base · m (the same relation by which the
//! simulator reads a texture set in the glTF form) come closest to the
//! model's; `KHR_materials_specular`'s specular colour
//! ([`specular_colour`]) then gives viewers that read it the model's F0,
//! which glTF's core fixes at 0.04 for a dielectric. The normal map is
//! re-expressed in glTF's tangent space, whose +Y points up the image
//! (towards row 0), where a texture set's y points along +v (down the
//! image).

use serde_json::json;

use super::export::{TextureSet, srgb};

/// The files of an exported asset, in the order written.
pub const FILES: [&str; 6] = [
    "material.gltf",
    "material.bin",
    "baseColor.png",
    "metallicRoughness.png",
    "normal.png",
    "specularColor.png",
];

/// The maps, in [`FILES`]' order from its third: base colour,
/// metallic-roughness, normal, specular colour.
const MAPS: usize = 4;

/// Whether `name` is a file a glTF export writes.
pub fn is_gltf_file(name: &str) -> bool {
    FILES.contains(&name)
}

/// Dielectric F0 of glTF's metallic-roughness model (index of refraction 1.5).
pub const DIELECTRIC_F0: f32 = 0.04;

/// Steps of the metallic factor searched by [`metallic_form`].
const METALLIC_STEPS: u32 = 256;

/// glTF's (base colour, metallic) for a texel of diffuse albedo `diffuse`
/// and F0 `f0`: the pair, base in [0, 1]³ and m in [0, 1] on a grid of
/// 1/256, that minimises the squared differences of base · (1 − m) from
/// the albedo and of 0.04 · (1 − m) + base · m from F0, over the three
/// channels. A dielectric texel (F0 = 0.04) comes out exact with m = 0, a
/// bare metal (albedo 0) with m = 1 and base = F0.
pub fn metallic_form(diffuse: [f32; 3], f0: [f32; 3]) -> ([f32; 3], f32) {
    let mut best = ([0.0; 3], 0.0, f32::INFINITY);
    for k in 0..=METALLIC_STEPS {
        let m = k as f32 / METALLIC_STEPS as f32;
        let d = 1.0 - m;
        // Per channel a quadratic in the base: its least-squares value,
        // clamped (exact for one variable).
        let base: [f32; 3] = std::array::from_fn(|c| {
            let b = (d * diffuse[c] + m * (f0[c] - DIELECTRIC_F0 * d)) / (d * d + m * m);
            b.clamp(0.0, 1.0)
        });
        let err: f32 = (0..3)
            .map(|c| {
                let ed = base[c] * d - diffuse[c];
                let es = DIELECTRIC_F0 * d + base[c] * m - f0[c];
                ed * ed + es * es
            })
            .sum();
        if err < best.2 {
            best = (base, m, err);
        }
    }
    (best.0, best.1)
}

/// The model a glTF-form texture set gives for `base` and `metallic`
/// (docs/texture-set.md): (diffuse albedo, F0).
pub fn model_of(base: [f32; 3], metallic: f32) -> ([f32; 3], [f32; 3]) {
    let d = 1.0 - metallic;
    (base.map(|b| b * d), base.map(|b| DIELECTRIC_F0 * d + b * metallic))
}

/// The specular colour `KHR_materials_specular` needs so that a texel of
/// `base` and `metallic` has the F0 `f0` after all: the dielectric F0 of
/// that extension, min(0.04 · colour, 1), mixed with the base colour by
/// the metallic factor as glTF mixes them, per channel; at least 0, so
/// where the metal's share m · base alone exceeds F0 that share stays. (A
/// metal, m = 1, takes its F0 from its base colour alone: 1.)
pub fn specular_colour(base: [f32; 3], metallic: f32, f0: [f32; 3]) -> [f32; 3] {
    let d = 1.0 - metallic;
    if d <= 0.0 {
        return [1.0; 3];
    }
    std::array::from_fn(|c| ((f0[c] - metallic * base[c]) / (DIELECTRIC_F0 * d)).max(0.0))
}

/// The model a viewer with `KHR_materials_specular` gives for `base`,
/// `metallic` and the specular colour `colour` (factor × texture):
/// (diffuse albedo, F0), with glTF's mix of the dielectric and metal F0.
pub fn model_with_specular(
    base: [f32; 3],
    metallic: f32,
    colour: [f32; 3],
) -> ([f32; 3], [f32; 3]) {
    let d = 1.0 - metallic;
    let f0 = std::array::from_fn(|c| d * (DIELECTRIC_F0 * colour[c]).min(1.0) + metallic * base[c]);
    (base.map(|b| b * d), f0)
}

/// A unit normal of the sample's frame (x along +u, y along +v) in glTF's
/// tangent space (x along +u, y up the image: −v).
pub fn gltf_normal(n: [f32; 3]) -> [f32; 3] {
    [n[0], -n[1], n[2]]
}

/// The asset's files, (name, bytes), in [`FILES`] order.
pub fn gltf_files(set: &TextureSet) -> Result<Vec<(String, Vec<u8>)>, String> {
    let (maps, factor) = maps(set)?;
    let (json, bin) = document(set, factor, None);
    let mut files = vec![(FILES[0].into(), json.into_bytes()), (FILES[1].into(), bin)];
    files.extend(FILES[2..].iter().map(|f| f.to_string()).zip(maps));
    Ok(files)
}

/// The asset as one binary glTF file (`.glb`): the document, the mesh and
/// the four maps in one buffer.
pub fn glb(set: &TextureSet) -> Result<Vec<u8>, String> {
    let (maps, factor) = maps(set)?;
    let (json, bin) = document(set, factor, Some(&maps));
    // Chunks padded to 4 bytes: the JSON with spaces, the buffer with 0s.
    let mut json = json.into_bytes();
    json.resize(json.len().next_multiple_of(4), b' ');
    let mut bin = bin;
    bin.resize(bin.len().next_multiple_of(4), 0);
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let total = u32::try_from(total).map_err(|_| format!("{total} bytes: too large for a .glb"))?;
    let mut out = Vec::with_capacity(total as usize);
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend(total.to_le_bytes());
    for (kind, chunk) in [(b"JSON", &json), (b"BIN\0", &bin)] {
        out.extend((chunk.len() as u32).to_le_bytes());
        out.extend(kind);
        out.extend(chunk.iter());
    }
    Ok(out)
}

/// The maps as PNGs (base colour, metallic-roughness, normal, specular
/// colour) and the specular colour's factor: the texture holds the colour
/// over it, sRGB-encoded as the extension asks.
fn maps(set: &TextureSet) -> Result<([Vec<u8>; MAPS], f32), String> {
    let texels = set.side * set.side;
    let mut base = Vec::with_capacity(texels);
    let mut metal_rough = Vec::with_capacity(texels);
    let mut specular = Vec::with_capacity(texels);
    for i in 0..texels {
        let (b, m) = metallic_form(set.diffuse[i], set.specular[i]);
        base.push(b.map(srgb));
        // R unused (occlusion elsewhere), G roughness, B metallic: linear.
        metal_rough.push([0.0, set.roughness[i], m]);
        specular.push(specular_colour(b, m, set.specular[i]));
    }
    let factor = specular.iter().flatten().fold(0.0f32, |a, &c| a.max(c));
    let factor = if factor > 0.0 { factor } else { 1.0 };
    let specular: Vec<[f32; 3]> = specular.iter().map(|c| c.map(|v| srgb(v / factor))).collect();
    let normal: Vec<[f32; 3]> =
        set.normal.iter().map(|&n| gltf_normal(n).map(|c| (c + 1.0) * 0.5)).collect();
    let png =
        |px: &[[f32; 3]], name: &str| png8(set.side as u32, px).map_err(|e| format!("{name}: {e}"));
    let maps = [
        png(&base, FILES[2])?,
        png(&metal_rough, FILES[3])?,
        png(&normal, FILES[4])?,
        png(&specular, FILES[5])?,
    ];
    Ok((maps, factor))
}

/// An 8-bit RGB PNG of values already encoded in [0, 1].
fn png8(side: u32, px: &[[f32; 3]]) -> Result<Vec<u8>, String> {
    let code = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let img =
        image::RgbImage::from_raw(side, side, px.iter().flatten().map(|&v| code(v)).collect())
            .ok_or("map of the wrong size")?;
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| e.to_string())?;
    Ok(bytes)
}

/// glTF's component type and buffer-view targets.
const FLOAT: u32 = 5126;
const UNSIGNED_SHORT: u32 = 5123;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

/// Where sample uv (u, v) lies in the asset, m: the square centred on the
/// origin in the XZ plane, facing +Y (glTF's up). The sample's frame (x
/// along +u, y along +v, z out of the surface) is turned, not mirrored:
/// x → +X, y → −Z, z → +Y.
pub fn position(uv: [f32; 2], side_m: f32) -> [f32; 3] {
    [(uv[0] - 0.5) * side_m, 0.0, (0.5 - uv[1]) * side_m]
}

/// The tangent frame every vertex carries: T = +X (+u); glTF's bitangent,
/// cross(N, T) · w with N = +Y, must point up the image (−v, +Z), so w = −1.
pub const TANGENT: [f32; 4] = [1.0, 0.0, 0.0, -1.0];

/// The JSON document and its binary buffer: four vertices (position,
/// normal, tangent, uv) and two triangles, then, with `embedded`, the
/// maps (for a `.glb`; else the images are the files beside it);
/// `specular_factor` is the specular colour's.
fn document(
    set: &TextureSet,
    specular_factor: f32,
    embedded: Option<&[Vec<u8>; MAPS]>,
) -> (String, Vec<u8>) {
    let side_m = (set.size_mm / 1000.0) as f32;
    let corners = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let mut bin: Vec<u8> = Vec::new();
    let mut put = |values: &[f32]| values.iter().for_each(|v| bin.extend(v.to_le_bytes()));
    let positions: Vec<[f32; 3]> = corners.iter().map(|&uv| position(uv, side_m)).collect();
    positions.iter().for_each(|p| put(p));
    corners.iter().for_each(|_| put(&[0.0, 1.0, 0.0]));
    corners.iter().for_each(|_| put(&TANGENT));
    corners.iter().for_each(|uv| put(uv));
    // Counter-clockwise seen from +Y.
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend(i.to_le_bytes());
    }
    let mut views: Vec<serde_json::Value> = [
        (0, 48, ARRAY_BUFFER),
        (48, 48, ARRAY_BUFFER),
        (96, 64, ARRAY_BUFFER),
        (160, 32, ARRAY_BUFFER),
        (192, 12, ELEMENT_ARRAY_BUFFER),
    ]
    .iter()
    .map(|&(offset, len, target): &(usize, usize, u32)| {
        json!({ "buffer": 0, "byteOffset": offset, "byteLength": len, "target": target })
    })
    .collect();
    assert_eq!(bin.len(), 204, "the layout above");
    let images: Vec<serde_json::Value> = match embedded {
        None => FILES[2..].iter().map(|f| json!({ "uri": f })).collect(),
        Some(maps) => maps
            .iter()
            .map(|png| {
                // Each image 4-byte aligned after the one before.
                bin.resize(bin.len().next_multiple_of(4), 0);
                views
                    .push(json!({ "buffer": 0, "byteOffset": bin.len(), "byteLength": png.len() }));
                bin.extend(png);
                json!({ "bufferView": views.len() - 1, "mimeType": "image/png" })
            })
            .collect(),
    };
    let buffer = match embedded {
        None => json!({ "uri": FILES[1], "byteLength": bin.len() }),
        Some(_) => json!({ "byteLength": bin.len() }),
    };
    let lo = |k: usize| positions.iter().map(|p| p[k]).fold(f32::INFINITY, f32::min);
    let hi = |k: usize| positions.iter().map(|p| p[k]).fold(f32::NEG_INFINITY, f32::max);
    let name = if set.name.trim().is_empty() { "scanned" } else { &set.name };
    let texture = |i: usize| json!({ "source": i, "sampler": 0 });
    let doc = json!({
        "asset": {
            "version": "2.0",
            "generator": format!("scanner {} (material scanner)", env!("CARGO_PKG_VERSION")),
            "extras": {
                "size_mm": set.size_mm,
                "note": "The texel model of a scanned material: the sample's extent, uv as in \
                         docs/texture-set.md; it does not tile seamlessly."
            }
        },
        "scene": 0,
        "scenes": [{ "name": name, "nodes": [0] }],
        "nodes": [{ "name": name, "mesh": 0 }],
        "meshes": [{
            "name": name,
            "primitives": [{
                "attributes": { "POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3 },
                "indices": 4,
                "material": 0
            }]
        }],
        "materials": [{
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorTexture": { "index": 0 },
                "metallicRoughnessTexture": { "index": 1 },
                "metallicFactor": 1.0,
                "roughnessFactor": 1.0
            },
            "normalTexture": { "index": 2 },
            // F0 where glTF's core fixes a dielectric's at 0.04; viewers
            // without the extension show the core material.
            "extensions": {
                "KHR_materials_specular": {
                    "specularColorFactor": [specular_factor, specular_factor, specular_factor],
                    "specularColorTexture": { "index": 3 }
                }
            }
        }],
        "extensionsUsed": ["KHR_materials_specular"],
        "textures": [texture(0), texture(1), texture(2), texture(3)],
        // Linear filtering with mipmaps; clamped: the tile is the sample.
        "samplers": [{ "magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071 }],
        "images": images,
        "buffers": [buffer],
        "bufferViews": views,
        "accessors": [
            { "bufferView": 0, "componentType": FLOAT, "count": 4, "type": "VEC3",
              "min": [lo(0), lo(1), lo(2)], "max": [hi(0), hi(1), hi(2)] },
            { "bufferView": 1, "componentType": FLOAT, "count": 4, "type": "VEC3" },
            { "bufferView": 2, "componentType": FLOAT, "count": 4, "type": "VEC4" },
            { "bufferView": 3, "componentType": FLOAT, "count": 4, "type": "VEC2" },
            { "bufferView": 4, "componentType": UNSIGNED_SHORT, "count": 6, "type": "SCALAR" }
        ]
    });
    (serde_json::to_string_pretty(&doc).expect("JSON of plain values"), bin)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    }

    #[test]
    fn dielectrics_and_metals_convert_exactly() {
        let (b, m) = metallic_form([0.5, 0.3, 0.1], [0.04; 3]);
        assert_eq!(m, 0.0);
        assert!(b.iter().zip([0.5, 0.3, 0.1]).all(|(x, y)| (x - y).abs() < 1e-6), "{b:?}");
        let (b, m) = metallic_form([0.0; 3], [0.9, 0.6, 0.3]);
        assert_eq!(m, 1.0);
        assert!(b.iter().zip([0.9, 0.6, 0.3]).all(|(x, y)| (x - y).abs() < 1e-6), "{b:?}");
        // Between: the model it gives back is the nearest on the grid — no
        // other (base, m) of the grid comes closer.
        for (d, f) in [([0.3, 0.2, 0.1], [0.2; 3]), ([0.05; 3], [0.5, 0.4, 0.2])] {
            let (b, m) = metallic_form(d, f);
            let err = |b: [f32; 3], m: f32| {
                let (dd, ff) = model_of(b, m);
                (0..3).map(|c| (dd[c] - d[c]).powi(2) + (ff[c] - f[c]).powi(2)).sum::<f32>()
            };
            let e = err(b, m);
            for k in 0..=20 {
                for g in 0..=20 {
                    let other = err([g as f32 / 20.0; 3], k as f32 / 20.0);
                    assert!(e <= other + 1e-7, "{d:?} {f:?}: {e} vs {other}");
                }
            }
            assert!(m > 0.0 && m < 1.0, "{m}");
        }
    }

    #[test]
    fn the_specular_colour_restores_f0() {
        for (d, f) in [
            ([0.5, 0.3, 0.1], [0.05, 0.05, 0.05]),
            ([0.3, 0.2, 0.1], [0.2; 3]),
            ([0.05; 3], [0.5, 0.4, 0.2]),
            ([0.6, 0.1, 0.1], [0.02, 0.03, 0.04]),
        ] {
            let (b, m) = metallic_form(d, f);
            let colour = specular_colour(b, m, f);
            let (dd, ff) = model_with_specular(b, m, colour);
            assert_eq!(dd, model_of(b, m).0, "the diffuse is the core's");
            // Exact but where the metal's share alone, m · base, exceeds F0
            // (no specular colour takes light away): there, that share.
            for c in 0..3 {
                let want = f[c].max(m * b[c]);
                assert!(
                    (ff[c] - want).abs() < 1e-6,
                    "{d:?} {f:?}: {ff:?} (m {m}, colour {colour:?})"
                );
            }
        }
        // F0 = 0.04 at m = 0: white, the extension's default.
        assert_eq!(specular_colour([0.5; 3], 0.0, [0.04; 3]), [1.0; 3]);
        // A bare metal takes its F0 from its base colour.
        assert_eq!(specular_colour([0.9, 0.6, 0.3], 1.0, [0.9, 0.6, 0.3]), [1.0; 3]);
    }

    /// The normal a renderer reads from the glTF map, through the vertex
    /// tangent frame, is the sample's normal turned as the square is.
    #[test]
    fn the_normal_map_holds_the_samples_normals_in_gltf_tangent_space() {
        let n_vertex = [0.0, 1.0, 0.0];
        let t = [TANGENT[0], TANGENT[1], TANGENT[2]];
        let b = cross(n_vertex, t).map(|c| c * TANGENT[3]);
        // The sample's frame as the square places it.
        let turn = |v: [f32; 3]| {
            let (o, x, y) =
                (position([0.0, 0.0], 1.0), position([1.0, 0.0], 1.0), position([0.0, 1.0], 1.0));
            let ex: [f32; 3] = std::array::from_fn(|k| x[k] - o[k]);
            let ey: [f32; 3] = std::array::from_fn(|k| y[k] - o[k]);
            let ez = cross(ex, ey);
            std::array::from_fn(|k| v[0] * ex[k] + v[1] * ey[k] + v[2] * ez[k])
        };
        // Not mirrored: the surface's outward normal is the vertex normal.
        assert_eq!(turn([0.0, 0.0, 1.0]), n_vertex);
        // The triangles (0, 1, 2) and (0, 2, 3) of the corners uv (0, 0),
        // (1, 0), (1, 1), (0, 1) turn counter-clockwise seen from the
        // normal's side: their front faces face it.
        let p = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]].map(|uv| position(uv, 1.0));
        for [a, b, c] in [[0, 1, 2], [0, 2, 3]] {
            let e1: [f32; 3] = std::array::from_fn(|k| p[b][k] - p[a][k]);
            let e2: [f32; 3] = std::array::from_fn(|k| p[c][k] - p[a][k]);
            assert!(cross(e1, e2)[1] > 0.0, "triangle {a} {b} {c}");
        }
        // Up the image is −v.
        assert_eq!(b, turn([0.0, -1.0, 0.0]));
        for n in [[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.3, 0.4, 0.866_025_4]] {
            let g = gltf_normal(n);
            let world: [f32; 3] =
                std::array::from_fn(|k| g[0] * t[k] + g[1] * b[k] + g[2] * n_vertex[k]);
            let want = turn(n);
            assert!(
                (0..3).all(|k| (world[k] - want[k]).abs() < 1e-6),
                "{n:?}: {world:?} vs {want:?}"
            );
        }
    }

    #[test]
    fn the_document_describes_its_buffer_and_maps() {
        let set = TextureSet {
            name: "tile \"one\"".into(),
            size_mm: 25.4,
            side: 2,
            diffuse: vec![[0.5; 3]; 4],
            specular: vec![[0.04; 3]; 4],
            roughness: vec![0.5; 4],
            normal: vec![[0.0, 0.0, 1.0]; 4],
        };
        let files = gltf_files(&set).unwrap();
        let names: Vec<&str> = files.iter().map(|f| f.0.as_str()).collect();
        assert_eq!(names, FILES);
        let doc: serde_json::Value = serde_json::from_slice(&files[0].1).unwrap();
        assert_eq!(doc["asset"]["version"], "2.0");
        assert_eq!(doc["materials"][0]["name"], "tile \"one\"");
        assert_eq!(doc["buffers"][0]["byteLength"], files[1].1.len());
        let max = &doc["accessors"][0]["max"];
        assert!((max[0].as_f64().unwrap() - 0.0127).abs() < 1e-6, "{max}");
        for (i, image) in doc["images"].as_array().unwrap().iter().enumerate() {
            assert_eq!(image["uri"], FILES[2 + i]);
            let png = image::load_from_memory(&files[2 + i].1).unwrap().to_rgb8();
            assert_eq!(png.dimensions(), (2, 2));
        }
        // Every buffer view lies within the buffer; indices within 4 vertices.
        for v in doc["bufferViews"].as_array().unwrap() {
            let end = v["byteOffset"].as_u64().unwrap() + v["byteLength"].as_u64().unwrap();
            assert!(end as usize <= files[1].1.len());
        }
        let idx: Vec<u16> =
            files[1].1[192..].chunks(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
        assert_eq!(idx, [0, 1, 2, 0, 2, 3]);
        assert!(is_gltf_file("material.gltf") && !is_gltf_file("material.toml"));

        // The one-file form: header, JSON chunk, BIN chunk holding the mesh
        // and the same four PNGs.
        let bytes = glb(&set).unwrap();
        assert_eq!(&bytes[..4], b"glTF");
        let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        assert_eq!((word(4), word(8)), (2, bytes.len()));
        let json_len = word(12);
        assert_eq!(&bytes[16..20], b"JSON");
        assert_eq!(json_len % 4, 0);
        let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        let bin_at = 20 + json_len;
        assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
        let bin = &bytes[bin_at + 8..bin_at + 8 + word(bin_at)];
        assert!(doc["buffers"][0].get("uri").is_none());
        assert!(doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize <= bin.len());
        assert_eq!(&bin[..204], &files[1].1[..], "the same mesh");
        for (i, image) in doc["images"].as_array().unwrap().iter().enumerate() {
            let view = &doc["bufferViews"][image["bufferView"].as_u64().unwrap() as usize];
            let at = view["byteOffset"].as_u64().unwrap() as usize;
            assert_eq!(at % 4, 0);
            let len = view["byteLength"].as_u64().unwrap() as usize;
            assert_eq!(&bin[at..at + len], &files[2 + i].1[..], "{}", FILES[2 + i]);
            assert_eq!(image["mimeType"], "image/png");
        }
    }
}
