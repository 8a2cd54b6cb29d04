//! How much of a scanned material its exported texture set keeps
//! (docs/benchmarks.md, "Texture-set export"): for each library material
//! (HDR scans on the simulator), the material file and the texture set
//! `scanner export` writes from it, both scored against `hil-sim truth`
//! with the material PSNR at the captured pairs (as-built directions) and
//! at random novel pairs (θ ≤ 60°). The texture set is scored through the
//! simulator's own texture-set reader and texel model, as a renderer would
//! shade it. So are the maps of the glTF asset (`--format gltf`): its
//! base colour and metallic-roughness maps read back as a texture set in
//! the glTF form, with the set's own normal map (the asset's is in glTF's
//! tangent space).
//!
//! `cargo run --release -p tests --example export_fidelity -- [--bin 1] [--mirrors 40] [--seed 1] [--novel 300] [--out DIR] [--materials a,b] [--format exr|png] [--without-detail]`
//! (`--without-detail`: the set exported as if the file had no detail
//! layer, the model alone at S × S, for comparison)
//! (scans in DIR are reused when complete; `material_fidelity` shares them).

use std::path::PathBuf;

use hil_sim::materials::{Sample, lookup};
use host::build::calibrate::Silent;
use host::build::export::{MapFormat, texture_set};
use host::build::extract_regions;
use host::build::gltf::gltf_files;
use host::build::material::{MaterialOptions, build_material, shade};
use host::build::scanread::ScanFrames;
use scanner_shading::Material;
use scanner_shading::format::Provenance;

fn main() {
    let bin: u32 = tests::arg("--bin", 1);
    let mirrors: usize = tests::arg("--mirrors", 40);
    let seed: u64 = tests::arg("--seed", 1);
    let novel: usize = tests::arg("--novel", 300);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/builder-fidelity"));
    let list: String =
        tests::arg("--materials", "woven-fabric,leather,painted-wood,rough-metal".to_string());
    let format: MapFormat = tests::arg("--format", MapFormat::Exr);
    let without_detail = std::env::args().any(|a| a == "--without-detail");
    let materials: Vec<&str> = list.split(',').collect();
    let (g, cal, truth) = tests::scanned_and_calibrated(&out, seed, bin, mirrors, &materials);
    let pairs = tests::random_pairs(novel, 60.0, seed);
    println!(
        "sensor {0}², {mirrors} mirrors, seed {seed}; {novel} novel pairs θ ≤ 60°; maps as {1}",
        4096 / bin,
        format.extension()
    );
    println!(
        "| material | material file, captured dB | texture set, captured dB | glTF maps, captured dB | material file, novel dB | texture set, novel dB | glTF maps, novel dB | maps |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for &m in &materials {
        let scan = ScanFrames::open(&tests::scan_dir(&out, m), &g).unwrap();
        let regions = extract_regions(&g, &cal, &scan, &tests::region_options(), &Silent).unwrap();
        let provenance = Provenance {
            scan_manifest_sha256: "-".into(),
            geometry_sha256: g.hash(),
            calibration_sha256: cal.hash(),
            builder: "export_fidelity".into(),
        };
        let data =
            build_material(&regions, m, 25.4, provenance, &MaterialOptions::default(), &Silent)
                .unwrap();
        let material = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
        let mut data = data;
        if without_detail {
            data.detail.clear();
        }
        let set = match texture_set(&data) {
            Ok(set) => set,
            Err(e) => {
                println!("| {m} | — | {e} | — | — | — | — | — |");
                continue;
            }
        };
        let dir = out.join(format!("{}-export-{}", m.replace('/', "_"), format.extension()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        set.write(&dir, format).unwrap();
        let exported = Sample::small(lookup(dir.to_str().unwrap()).unwrap());
        // The glTF asset's maps as a texture set in the glTF form.
        let gltf_dir = dir.join("gltf-form");
        std::fs::create_dir_all(&gltf_dir).unwrap();
        for (name, bytes) in gltf_files(&set).unwrap() {
            if name == "baseColor.png" || name == "metallicRoughness.png" {
                std::fs::write(gltf_dir.join(name), bytes).unwrap();
            }
        }
        for name in ["material.toml".to_string(), format!("normal.{}", format.extension())] {
            std::fs::copy(dir.join(&name), gltf_dir.join(&name)).unwrap();
        }
        let gltf = Sample::small(lookup(gltf_dir.to_str().unwrap()).unwrap());
        let sample = Sample::small(lookup(m).unwrap());
        let score = |pairs: &[([f64; 3], [f64; 3])]| {
            let t = tests::truth_answers(pairs, &sample);
            let file = tests::pairs_psnr(pairs, &t, &|_, q| shade(&material, q)).0;
            let maps = tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&exported, q)).0;
            let gltf = tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&gltf, q)).0;
            (file, maps, gltf)
        };
        let (cap_file, cap_maps, cap_gltf) = score(&tests::as_built_pairs(&truth, &cal, &regions));
        let (nov_file, nov_maps, nov_gltf) = score(&pairs);
        println!(
            "| {m} | {cap_file:.2} | {cap_maps:.2} | {cap_gltf:.2} | {nov_file:.2} | {nov_maps:.2} | {nov_gltf:.2} | {0}² |",
            set.side
        );
    }
}
