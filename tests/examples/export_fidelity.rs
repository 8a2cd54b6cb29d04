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
//! tangent space); and as a viewer with `KHR_materials_specular` reads
//! it (diffuse and F0 from the decoded maps by the extension's formula,
//! written as a texture set).
//!
//! `cargo run --release -p tests --example export_fidelity -- [--bin 1] [--mirrors 40] [--seed 1] [--novel 300] [--out DIR] [--materials a,b] [--format exr|png] [--without-detail]`
//! (`--without-detail`: the set exported as if the file had no detail
//! layer, the model alone at S × S, for comparison)
//! (scans in DIR are reused when complete; `material_fidelity` shares them).

use std::path::PathBuf;

use hil_sim::materials::{Sample, lookup};
use host::build::calibrate::Silent;
use host::build::export::{MapFormat, texture_set};
use host::build::gltf::gltf_files;
use host::build::material::{MaterialOptions, build_material, shade};
use scanner_shading::Material;

fn main() {
    tests::check_region_args(
        &["--bin", "--format", "--materials", "--mirrors", "--novel", "--out", "--seed"],
        &["--without-detail"],
    );
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
        "| material | material file, captured dB | texture set, captured dB | glTF core, captured dB | glTF + KHR_materials_specular, captured dB | material file, novel dB | texture set, novel dB | glTF core, novel dB | glTF + specular, novel dB | maps |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for &m in &materials {
        let regions = tests::scanned_regions(&out, &g, &cal, m);
        let provenance = tests::example_provenance(&g, &cal, "export_fidelity");
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
                println!("| {m} | — | {e} | — | — | — | — | — | — | — |");
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
        // As a viewer with KHR_materials_specular reads it: the maps
        // decoded, then diffuse and F0 as the extension gives them.
        let ext_dir = dir.join("gltf-specular");
        std::fs::create_dir_all(&ext_dir).unwrap();
        with_specular(&set).write(&ext_dir, MapFormat::Exr).unwrap();
        let gltf_ext = Sample::small(lookup(ext_dir.to_str().unwrap()).unwrap());
        let sample = Sample::small(lookup(m).unwrap());
        let score = |pairs: &[([f64; 3], [f64; 3])]| {
            let t = tests::truth_answers(pairs, &sample);
            let file = tests::pairs_psnr(pairs, &t, &|_, q| shade(&material, q)).0;
            let maps = tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&exported, q)).0;
            let gltf = tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&gltf, q)).0;
            let ext = tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&gltf_ext, q)).0;
            (file, maps, gltf, ext)
        };
        let (cap_file, cap_maps, cap_gltf, cap_ext) =
            score(&tests::as_built_pairs(&truth, &cal, &regions));
        let (nov_file, nov_maps, nov_gltf, nov_ext) = score(&pairs);
        println!(
            "| {m} | {cap_file:.2} | {cap_maps:.2} | {cap_gltf:.2} | {cap_ext:.2} | {nov_file:.2} | {nov_maps:.2} | {nov_gltf:.2} | {nov_ext:.2} | {0}² |",
            set.side
        );
    }
}

/// The texture set a viewer with `KHR_materials_specular` makes of the glTF
/// asset's maps (decoded from its PNGs), with `set`'s own normal map.
fn with_specular(set: &host::build::export::TextureSet) -> host::build::export::TextureSet {
    use host::build::gltf::{gltf_files, model_with_specular};
    let files = gltf_files(set).unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&files[0].1).unwrap();
    let factor = doc["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"]
        [0]
    .as_f64()
    .unwrap() as f32;
    let decode = |name: &str| {
        let bytes = &files.iter().find(|f| f.0 == name).unwrap().1;
        image::load_from_memory(bytes).unwrap().to_rgb8()
    };
    let linear = |code: u8| hil_sim::texture_set::srgb_to_linear(code as f32 / 255.0);
    let (base, mr, spec) =
        (decode("baseColor.png"), decode("metallicRoughness.png"), decode("specularColor.png"));
    let mut out = set.clone();
    for (i, ((b, r), s)) in base.pixels().zip(mr.pixels()).zip(spec.pixels()).enumerate() {
        let m = r.0[2] as f32 / 255.0;
        let (d, f) = model_with_specular(b.0.map(linear), m, s.0.map(|c| factor * linear(c)));
        out.diffuse[i] = d;
        out.specular[i] = f.map(|v| v.clamp(0.0, 1.0));
        out.roughness[i] = r.0[1] as f32 / 255.0;
    }
    out
}
