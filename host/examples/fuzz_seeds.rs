//! Seed inputs for the material reader's fuzz target (`scripts/fuzz.sh`):
//! small valid material files, one per interpolation, so that the fuzzer
//! starts from files that pass the container and metadata checks.
//!
//! `cargo run -p host --example fuzz_seeds -- DIR`

use host::build::material::{patent_table, triangulate};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scanner_geometry::ScannerGeometry;
use scanner_shading::format::{DirectionTables, FORMAT, Mirror, Provenance, VERSION};
use scanner_shading::{Interpolation, MaterialData, Metadata};

/// A material over the first `n` mirrors of the default scanner, `s`² texels,
/// `k` colours, random content.
fn material(interpolation: Interpolation, n: usize, s: usize, k: usize, g: usize) -> MaterialData {
    let geometry = ScannerGeometry::default_scanner();
    let views: Vec<[f64; 3]> =
        (0..n).map(|v| geometry.mirror_direction(v).unwrap().to_array()).collect();
    let lights: Vec<[f64; 3]> =
        (0..n).map(|l| geometry.light_direction(l).unwrap().to_array()).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(n as u64);
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
            name: "seed".into(),
            sample_size_mm: 25.4,
            extent_mm: [25.4, 25.4],
            resolution: s as u32,
            colours: k as u32,
            lights_per_index: g as u32,
            interpolation,
            half_vector_shift: 0.5,
            lights: mirrors(&lights),
            views: mirrors(&views),
            provenance: Provenance {
                scan_manifest_sha256: String::new(),
                geometry_sha256: geometry.hash(),
                calibration_sha256: String::new(),
                builder: "fuzz seed".into(),
            },
        },
        palettes: (0..n * n * k).map(|_| [rng.random(), rng.random(), rng.random()]).collect(),
        indices: (0..n * s * s * n.div_ceil(g)).map(|_| rng.random_range(0..k as u8)).collect(),
        light_groups: (0..n).map(|l| (l / g) as u8).collect(),
        tables,
    }
}

fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("usage: fuzz_seeds DIR"));
    std::fs::create_dir_all(&dir).unwrap();
    let patent = Interpolation::Patent { columns: 16, rows: 4, points: 20 };
    for (name, m) in [
        ("default-6", material(Interpolation::Default, 6, 4, 4, 2)),
        ("default-3", material(Interpolation::Default, 3, 2, 2, 1)),
        ("patent-5", material(patent, 5, 4, 4, 2)),
    ] {
        let bytes = m.to_bytes().unwrap();
        // Every seed is a material the reader accepts.
        scanner_shading::Material::from_bytes(&bytes).unwrap();
        std::fs::write(dir.join(format!("{name}.material")), &bytes).unwrap();
        println!("{name}: {} bytes", bytes.len());
    }
}
