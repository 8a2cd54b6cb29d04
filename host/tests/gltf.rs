//! `scanner export --format gltf` checked by the Khronos glTF validator
//! (tests/gltf/validate.js; `scripts/setup.sh` installs Node.js and the
//! validator, pinned by tests/gltf/package-lock.json).

use std::path::{Path, PathBuf};
use std::process::Command;

use scanner_shading::Interpolation;

#[path = "../benches/support/synthetic.rs"]
mod synthetic;

use synthetic::{Shape, synthetic, with_detail, with_texel_model};

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// The validator's script, with its installation checked.
fn validator() -> PathBuf {
    let dir = root().join("tests/gltf");
    assert!(
        dir.join("node_modules/gltf-validator/package.json").is_file(),
        "{}: the glTF validator is missing: scripts/setup.sh installs it (npm ci)",
        dir.display()
    );
    dir.join("validate.js")
}

#[test]
fn exported_assets_pass_the_khronos_validator() {
    let script = validator();
    let dir = tempfile::tempdir().unwrap();
    let shape = |resolution| Shape { mirrors: 40, resolution, colours: 8, lights_per_index: 2 };
    let materials = [
        // The model's texels alone (S × S maps).
        ("model", with_texel_model(synthetic(&shape(8), Interpolation::Default, 0.5, 1), 2)),
        // With a detail layer: 2S × 2S maps.
        (
            "detail",
            with_detail(
                with_texel_model(synthetic(&shape(4), Interpolation::Default, 0.0, 3), 4),
                1,
                5,
            ),
        ),
    ];
    for (name, data) in materials {
        let material = dir.path().join(format!("{name}.material"));
        std::fs::write(&material, data.to_bytes().unwrap()).unwrap();
        let side = data.meta.resolution as u64 * if data.detail.is_empty() { 1 } else { 2 };
        // The directory form and the one-file form.
        for (format, out) in [
            ("gltf", dir.path().join(format!("{name}-gltf"))),
            ("glb", dir.path().join(format!("{name}.glb"))),
        ] {
            let what = format!("{name}, {format}");
            let run = Command::new(env!("CARGO_BIN_EXE_scanner"))
                .arg("export")
                .arg(&material)
                .arg("-o")
                .arg(&out)
                .args(["--format", format])
                .output()
                .unwrap();
            assert!(run.status.success(), "{what}: {}", String::from_utf8_lossy(&run.stderr));
            let asset = if format == "gltf" { out.join("material.gltf") } else { out };
            let run = Command::new("node")
                .arg(&script)
                .arg(&asset)
                .output()
                .expect("node runs (scripts/setup.sh installs it)");
            let report = String::from_utf8_lossy(&run.stdout);
            assert!(
                run.status.success(),
                "{what}: {report}{}",
                String::from_utf8_lossy(&run.stderr)
            );
            let report: serde_json::Value = serde_json::from_str(&report).unwrap();
            let issues = &report["issues"];
            // Not only no error: no warning, no note either. (Maps of a side
            // that is not a power of two, from `scanner build --size`, get the
            // validator's note IMAGE_NPOT_DIMENSIONS; glTF 2.0 allows them.)
            for count in ["numErrors", "numWarnings", "numInfos"] {
                assert_eq!(issues[count], 0, "{what}: {count}: {}", issues["messages"]);
            }
            // The validator read every map, at the set's size.
            let images: Vec<&serde_json::Value> = report["info"]["resources"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|r| r["mimeType"] == "image/png")
                .collect();
            assert_eq!(images.len(), 4, "{what}");
            for image in images {
                assert_eq!(image["image"]["width"].as_u64(), Some(side), "{what}: {image}");
                assert_eq!(image["image"]["height"].as_u64(), Some(side), "{what}: {image}");
            }
        }
    }
    // A .glb goes to a .glb (exit 2), never over its input (exit 4).
    let material = dir.path().join("model.material");
    let before = std::fs::read(&material).unwrap();
    for (out, code) in [(dir.path().join("model.gltf"), 2), (material.clone(), 4)] {
        let run = Command::new(env!("CARGO_BIN_EXE_scanner"))
            .arg("export")
            .arg(&material)
            .arg("-o")
            .arg(&out)
            .args(["--format", "glb"])
            .output()
            .unwrap();
        assert_eq!(run.status.code(), Some(code), "{}", String::from_utf8_lossy(&run.stderr));
    }
    assert_eq!(std::fs::read(&material).unwrap(), before);
    assert!(!dir.path().join("model.gltf").exists());
}
