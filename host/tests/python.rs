//! The material file read and shaded in Python from docs/material-format.md
//! alone (`tests/python/shade_from_spec.py`, numpy and safetensors), against
//! `scanner shade`, on files of every kind the format has.

use std::path::{Path, PathBuf};
use std::process::Command;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use scanner_formats::queries::{Query, read_answers, write_queries};
use scanner_shading::{Interpolation, MaterialData};

#[path = "../benches/support/synthetic.rs"]
mod synthetic;

use synthetic::{Shape, synthetic, with_detail, with_enlargement, with_texel_model};

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// The Python that `scripts/setup.sh` prepares (`.venv`), or `$SCANNER_PYTHON`.
fn python() -> PathBuf {
    let p = std::env::var_os("SCANNER_PYTHON")
        .map_or_else(|| root().join(".venv/bin/python"), PathBuf::from);
    assert!(
        p.exists(),
        "{} is missing: scripts/setup.sh installs Python with numpy and safetensors there \
         (or set SCANNER_PYTHON)",
        p.display()
    );
    p
}

fn direction(rng: &mut ChaCha8Rng, max_theta_deg: f64) -> [f64; 3] {
    let z = 1.0 - rng.random::<f64>() * (1.0 - max_theta_deg.to_radians().cos());
    let p = rng.random::<f64>() * std::f64::consts::TAU;
    let r = (1.0 - z * z).max(0.0).sqrt();
    [r * p.cos(), r * p.sin(), z]
}

/// Queries of every kind: over the whole hemisphere (beyond the outermost
/// ring too), within 60°, exactly at captured pairs, below the horizon,
/// not unit length; uv over [−1, 2]², so that it wraps.
fn queries(data: &MaterialData, n: usize, seed: u64) -> Vec<Query> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (lights, views) = (&data.meta.lights, &data.meta.views);
    (0..n)
        .map(|k| {
            let uv = [rng.random_range(-1.0..2.0), rng.random_range(-1.0..2.0)];
            let (mut wi, mut wo) = match k % 5 {
                0 | 1 => (direction(&mut rng, 89.0), direction(&mut rng, 89.0)),
                2 => (direction(&mut rng, 60.0), direction(&mut rng, 60.0)),
                3 => (
                    lights[rng.random_range(0..lights.len())].direction,
                    views[rng.random_range(0..views.len())].direction,
                ),
                _ => {
                    let (a, mut b) = (direction(&mut rng, 80.0), direction(&mut rng, 80.0));
                    b[2] = -b[2];
                    if rng.random() { (a, b) } else { (b, a) }
                }
            };
            if k % 7 == 0 {
                let s = if rng.random() { 1e3 } else { 1e-3 };
                wi = wi.map(|x| x * s);
                wo = wo.map(|x| x * s * 0.5);
            }
            Query { uv, wi, wo }
        })
        .collect()
}

fn shape(resolution: usize, colours: usize, lights_per_index: usize) -> Shape {
    Shape { mirrors: 40, resolution, colours, lights_per_index }
}

#[test]
fn python_reads_the_material_file_from_the_spec() {
    let python = python();
    let script = root().join("tests/python/shade_from_spec.py");
    let dir = tempfile::tempdir().unwrap();
    let patent = Interpolation::Patent { columns: 61, rows: 17, points: 200 };
    let materials = [
        // Version 4: texel model, detail layer, two light components, β = ½.
        (
            "model-detail-components",
            with_detail(
                with_texel_model(synthetic(&shape(8, 8, 2), Interpolation::Default, 0.5, 1), 2),
                2,
                3,
            ),
        ),
        // Version 2: texel model alone, β = 1.
        ("model", with_texel_model(synthetic(&shape(6, 16, 3), Interpolation::Default, 1.0, 4), 5)),
        // Version 1: images alone, β = 0.
        ("plain", synthetic(&shape(4, 4, 1), Interpolation::Default, 0.0, 6)),
        // The patent's cell tables, with a detail layer of one component.
        ("patent", with_detail(synthetic(&shape(4, 8, 2), patent, 0.0, 7), 1, 8)),
        // Version 5: enlarged to a piece of 3 × 2 samples' widths, 17 × 9
        // texels, over a texel model and a detail layer.
        (
            "enlarged",
            with_enlargement(
                with_detail(
                    with_texel_model(
                        synthetic(&shape(8, 8, 2), Interpolation::Default, 0.5, 11),
                        12,
                    ),
                    1,
                    13,
                ),
                17,
                9,
                [76.2, 50.8],
                14,
            ),
        ),
    ];
    for (k, (name, data)) in materials.iter().enumerate() {
        let material = dir.path().join(format!("{name}.material"));
        std::fs::write(&material, data.to_bytes().unwrap()).unwrap();
        let q = queries(data, 1500, 10 + k as u64);
        let qpath = dir.path().join(format!("{name}-queries.npy"));
        write_queries(&qpath, &q).unwrap();
        let (ours, theirs) = (
            dir.path().join(format!("{name}-rust.npy")),
            dir.path().join(format!("{name}-py.npy")),
        );
        let out = Command::new(env!("CARGO_BIN_EXE_scanner"))
            .args(["shade".as_ref(), material.as_os_str(), "--queries".as_ref(), qpath.as_os_str()])
            .args(["-o".as_ref(), ours.as_os_str()])
            .output()
            .unwrap();
        assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
        let out =
            Command::new(&python).arg(&script).args([&material, &qpath, &theirs]).output().unwrap();
        assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
        let (a, b) = (read_answers(&ours).unwrap(), read_answers(&theirs).unwrap());
        assert_eq!(a.len(), q.len());
        assert_eq!(b.len(), q.len());
        // f32 (Rust) against f64 (numpy): agreement to a few 10⁻⁵ of the
        // answers' mean, or of the answer itself.
        let mean = a.iter().flatten().map(|x| x.abs() as f64).sum::<f64>() / (3 * a.len()) as f64;
        assert!(mean > 0.0, "{name}: answers are not all black");
        let bad: Vec<String> = (0..q.len())
            .filter(|&i| {
                (0..3).any(|c| {
                    let (x, y) = (a[i][c] as f64, b[i][c] as f64);
                    (x - y).abs() > 2e-5 * mean + 1e-4 * x.abs()
                })
            })
            .map(|i| format!("query {i} {:?}: scanner {:?}, Python {:?}", q[i], a[i], b[i]))
            .collect();
        assert!(bad.is_empty(), "{name}: {} of {} differ:\n{}", bad.len(), q.len(), bad.join("\n"));
        let black = a.iter().filter(|x| **x == [0.0; 3]).count();
        assert!(black < q.len() / 2, "{name}: {black} black answers");
    }
}
