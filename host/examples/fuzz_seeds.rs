//! Seed inputs for the fuzz targets (`scripts/fuzz.sh`): small valid
//! material files, one per interpolation, in `DIR/material`, and small
//! query and answer files (`.npy` and `.csv`) in `DIR/queries`, and small
//! OpenEXR frames (PIZ and uncompressed, scan lines and tiles) in
//! `DIR/frame` and `DIR/texture_map`, so that the fuzzer starts from files
//! that pass the container and header checks.
//!
//! `cargo run -p host --example fuzz_seeds -- DIR`

#[path = "../benches/support/synthetic.rs"]
mod synthetic;

use scanner_formats::queries::{Query, write_answers, write_queries};
use scanner_shading::Interpolation;
use synthetic::{Shape, synthetic, with_detail, with_texel_model};

fn main() {
    let root = std::path::PathBuf::from(std::env::args().nth(1).expect("usage: fuzz_seeds DIR"));
    let dir = root.join("material");
    std::fs::create_dir_all(&dir).unwrap();
    let patent = Interpolation::Patent { columns: 16, rows: 4, points: 20 };
    let shape = |mirrors, resolution, colours, lights_per_index| Shape {
        mirrors,
        resolution,
        colours,
        lights_per_index,
    };
    for (name, m) in [
        ("default-6", synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 6)),
        ("default-3", synthetic(&shape(3, 2, 2, 1), Interpolation::Default, 0.0, 3)),
        ("patent-5", synthetic(&shape(5, 4, 4, 2), patent, 0.5, 5)),
        (
            "texel-model-6",
            with_texel_model(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 7), 8),
        ),
        (
            "detail-6",
            with_detail(
                with_texel_model(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 9), 10),
                0,
                11,
            ),
        ),
        (
            "light-detail-6",
            with_detail(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 12), 2, 13),
        ),
    ] {
        let bytes = m.to_bytes().unwrap();
        // Every seed is a material the reader accepts.
        scanner_shading::Material::from_bytes(&bytes).unwrap();
        std::fs::write(dir.join(format!("{name}.material")), &bytes).unwrap();
        println!("{name}: {} bytes", bytes.len());
    }
    let dir = root.join("queries");
    std::fs::create_dir_all(&dir).unwrap();
    let queries: Vec<Query> = (0..3)
        .map(|i| {
            let t = i as f64 * 0.4;
            Query::from_row([0.1 * i as f64, 0.7, t.sin(), 0.0, t.cos(), 0.0, -t.sin(), t.cos()], i)
                .unwrap()
        })
        .collect();
    for name in ["q.npy", "q.csv"] {
        write_queries(&dir.join(name), &queries).unwrap();
    }
    let answers = [[0.25f32, 0.5, 1.0], [0.0, 1e-3, 7.5]];
    for name in ["a.npy", "a.csv"] {
        write_answers(&dir.join(name), &answers).unwrap();
    }
    println!("query and answer files in {}", dir.display());
    let (dir, maps) = (root.join("frame"), root.join("texture_map"));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::create_dir_all(&maps).unwrap();
    // A ramp with some noise, as a camera's (PIZ's Huffman and wavelet
    // stages both have work to do), or without: tiles (≥ 512 px a side)
    // small enough for the fuzzer to mutate quickly.
    let frame = |w: u32, h: u32, noise: f32| {
        let rgb = (0..w * h * 3)
            .map(|i| {
                let (x, y) = ((i / 3) % w, (i / 3) / w);
                let n = ((i as u64 * 2_654_435_761) % 97) as f32 / 97.0;
                0.1 + 0.002 * (x + y) as f32 + noise * n
            })
            .collect();
        host::camera::Frame { width: w, height: h, rgb }
    };
    let (lines, tiles) = (frame(48, 40, 0.01), frame(520, 300, 0.0));
    for (name, f, compressions) in [("lines-48x40", lines, 2), ("tiles-520x300", tiles, 1)] {
        for (kind, bytes) in [
            ("piz", host::exrio::encode_half(&f).unwrap()),
            ("raw", host::exrio::encode_half_uncompressed(&f).unwrap()),
        ]
        .into_iter()
        .take(compressions)
        {
            // Every seed is a frame the decoder reads back; the texture
            // maps' reader starts from the same files.
            let p = dir.join(format!("{name}-{kind}.exr"));
            std::fs::write(&p, &bytes).unwrap();
            assert!(host::exrio::read_rgb(&p).unwrap() == host::exrio::quantise_half(f.clone()));
            std::fs::write(maps.join(format!("{name}-{kind}.exr")), &bytes).unwrap();
            println!("{name}-{kind}: {} bytes", bytes.len());
        }
    }
}
