//! A material of random content over the default scanner's directions, for
//! the shading benchmark and the fuzz seeds (`#[path]`-included by both).

use host::build::material::{patent_table, triangulate};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scanner_geometry::ScannerGeometry;
use scanner_shading::format::{DirectionTables, FORMAT, Mirror, Provenance, VERSION};
use scanner_shading::{Interpolation, MaterialData, Metadata};

/// The size of a synthetic material.
#[derive(Debug, Clone, Copy)]
pub struct Shape {
    /// Directions: the first `mirrors` of the default scanner, as lights and views.
    pub mirrors: usize,
    /// Texels per side.
    pub resolution: usize,
    /// Palette colours.
    pub colours: usize,
    /// Lights per index image.
    pub lights_per_index: usize,
}

/// Random palettes and indices over `shape`, seeded by `seed`.
pub fn synthetic(
    shape: &Shape,
    interpolation: Interpolation,
    half_vector_shift: f64,
    seed: u64,
) -> MaterialData {
    let &Shape { mirrors: n, resolution: s, colours: k, lights_per_index: g } = shape;
    let geometry = ScannerGeometry::default_scanner();
    let views: Vec<[f64; 3]> =
        (0..n).map(|v| geometry.mirror_direction(v).unwrap().to_array()).collect();
    let lights: Vec<[f64; 3]> =
        (0..n).map(|l| geometry.light_direction(l).unwrap().to_array()).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let tables = match interpolation {
        Interpolation::Default => DirectionTables::Triangles {
            views: triangulate(&views, "views").unwrap(),
            lights: triangulate(&lights, "lights").unwrap(),
        },
        Interpolation::Patent { columns, rows, points } => DirectionTables::Patent {
            views: patent_table(&views, columns, rows, points, 1),
            lights: patent_table(&lights, columns, rows, points, 2),
        },
    };
    let mirrors = |d: &[[f64; 3]]| -> Vec<Mirror> {
        d.iter().enumerate().map(|(i, &direction)| Mirror { mirror: i as u32, direction }).collect()
    };
    MaterialData {
        meta: Metadata {
            format: FORMAT.into(),
            version: VERSION,
            name: "synthetic".into(),
            sample_size_mm: 25.4,
            extent_mm: [25.4, 25.4],
            resolution: s as u32,
            colours: k as u32,
            lights_per_index: g as u32,
            interpolation,
            half_vector_shift,
            lights: mirrors(&lights),
            views: mirrors(&views),
            provenance: Provenance {
                scan_manifest_sha256: String::new(),
                geometry_sha256: geometry.hash(),
                calibration_sha256: String::new(),
                builder: "synthetic".into(),
                face: None,
            },
            texel_model: false,
            detail: false,
            detail_components: 0,
            enlargement: None,
        },
        palettes: (0..n * n * k).map(|_| [rng.random(), rng.random(), rng.random()]).collect(),
        indices: (0..n * s * s * n.div_ceil(g))
            .map(|_| rng.random_range(0..=(k - 1) as u8))
            .collect(),
        light_groups: (0..n).map(|l| (l / g) as u8).collect(),
        tables,
        texels: Vec::new(),
        detail: Vec::new(),
        detail_bases: Vec::new(),
        detail_coefficients: Vec::new(),
        enlargement: Vec::new(),
    }
}

/// `data` with a random detail layer (version 3, or 4 with `components`
/// light components): factors in [½, 2], components in [−1, 1] with
/// coefficients in [−0.3, 0.3].
pub fn with_detail(mut data: MaterialData, components: usize, seed: u64) -> MaterialData {
    let f = 2 * data.meta.resolution as usize;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    data.meta.version = if components > 0 {
        scanner_shading::format::VERSION_LIGHT_DETAIL
    } else {
        scanner_shading::format::VERSION_DETAIL
    };
    data.meta.detail = true;
    data.meta.detail_components = components as u32;
    data.detail = (0..f * f)
        .map(|_| std::array::from_fn(|_| 2f32.powf(rng.random_range(-1.0..1.0))))
        .collect();
    data.detail_bases = (0..components * f * f)
        .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0)))
        .collect();
    data.detail_coefficients =
        (0..data.meta.lights.len() * components).map(|_| rng.random_range(-0.3..0.3)).collect();
    data
}

/// `data` enlarged (version 5) to a `columns` × `rows` piece of
/// `extent_mm`, each texel matched at a random place on the sample.
#[allow(dead_code)] // not every includer enlarges
pub fn with_enlargement(
    mut data: MaterialData,
    columns: u32,
    rows: u32,
    extent_mm: [f64; 2],
    seed: u64,
) -> MaterialData {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    data.meta.version = scanner_shading::format::VERSION_ENLARGED;
    data.meta.extent_mm = extent_mm;
    data.meta.enlargement = Some(scanner_shading::format::Enlargement {
        columns,
        rows,
        signature: "colour".into(),
        directions: vec![[0.0, 0.0, 1.0]],
        direct_sha256: String::new(),
    });
    data.enlargement = (0..columns * rows).map(|_| [rng.random(), rng.random()]).collect();
    data
}

/// `data` with a random texel model (version 2): albedos and F0 in
/// [0, 1], α in [0.05, 0.5], normals within 20° of the sample's.
pub fn with_texel_model(mut data: MaterialData, seed: u64) -> MaterialData {
    use scanner_shading::texel::TexelParams;
    let s = data.meta.resolution as usize;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    data.meta.version = scanner_shading::format::VERSION_TEXEL_MODEL;
    data.meta.texel_model = true;
    data.texels = (0..s * s)
        .map(|_| {
            let (x, y): (f32, f32) = (rng.random_range(-0.25..0.25), rng.random_range(-0.25..0.25));
            TexelParams {
                diffuse: [rng.random(), rng.random(), rng.random()],
                specular: [rng.random(), rng.random(), rng.random()],
                alpha: rng.random_range(0.05..0.5),
                normal: [x, y, (1.0 - x * x - y * y).sqrt()],
            }
        })
        .collect();
    data
}
