//! Material builder II end to end on the simulator: `scanner build` on an
//! HDR scan → one material file; its fidelity against the ground truth at
//! the captured and at novel pairs, default and patent interpolation;
//! `scanner shade`; `scanner export`'s texture sets; bad inputs refused
//! with exit 3 and nothing written. The full-resolution tables are `cargo
//! run --release -p tests --example material_fidelity` and `--example
//! export_fidelity` (docs/benchmarks.md).

mod common;

use std::path::Path;

use hil_sim::materials::{Sample, lookup};
use hil_sim::optics::OpticalSim;
use host::build::Calibration;
use host::build::calibrate::Silent;
use host::build::material::{MaterialOptions, TexelModelChoice, build_material};
use host::build::scanread::ScanFrames;
use host::build::{RegionOptions, extract_regions};
use scanner_formats::queries::{Query, read_answers, write_queries};
use scanner_shading::{Interpolation, Material};

/// `scanner export` of `DIR/leather.material` (built with a texel model and
/// a detail layer) and of `DIR/plain.material` (without a model): the maps
/// as the simulator reads them hold the file's model; the simulator's copy
/// of the texel model shades them as the shading crate's does; scanned by
/// the simulator's truth, the set scores within 1 dB of the material file
/// (`file_db`: captured and novel pairs); bad inputs and outputs refused.
fn exported_texture_sets(
    dir: &Path,
    file_db: [f64; 2],
    sample: &Sample,
    captured: &[([f64; 3], [f64; 3])],
    novel: &[([f64; 3], [f64; 3])],
) {
    use host::build::export::texture_set;
    use scanner_shading::format::MaterialData;
    use scanner_shading::texel::{TexelParams, reflected};
    let p = |n: &str| dir.join(n);
    let d = |n: &str| p(n).display().to_string();
    let data = MaterialData::from_bytes(&std::fs::read(p("leather.material")).unwrap()).unwrap();
    let set = texture_set(&data).unwrap();
    let s = data.meta.resolution as usize;
    assert_eq!(set.side, 2 * s, "maps at the detail layer's resolution");
    let pairs: Vec<([f32; 3], [f32; 3])> =
        novel.iter().take(8).map(|(wi, wo)| (wi.map(|c| c as f32), wo.map(|c| c as f32))).collect();
    for (format, tolerance) in [("exr", 1e-6), ("png", 2e-4)] {
        let out = format!("set-{format}");
        let (code, err) = common::run_err(&[
            "export",
            &d("leather.material"),
            "-o",
            &d(&out),
            "--format",
            format,
        ]);
        assert_eq!(code, Some(0), "{err}");
        let read = Sample::small(lookup(&d(&out)).unwrap());
        for i in (0..set.side * set.side).step_by(7) {
            let (x, y) = (i % set.side, i / set.side);
            let uv = [(x as f64 + 0.5) / set.side as f64, (y as f64 + 0.5) / set.side as f64];
            let t = read.texel(uv);
            let close = |a: f64, b: f32, what: &str| {
                assert!(
                    (a - b as f64).abs() <= tolerance,
                    "{format} texel ({x}, {y}) {what}: {a} vs {b}"
                );
            };
            for c in 0..3 {
                close(t.diffuse[c], set.diffuse[i][c], "diffuse");
                close(t.specular[c], set.specular[i][c], "F0");
                close(t.normal[c], set.normal[i][c], "normal");
            }
            close(t.roughness.sqrt(), set.roughness[i], "roughness");
            // No texel loses its lobe: the simulator's model has none where
            // F0 is 0 in every channel (docs/texture-set.md).
            assert!(t.specular.iter().any(|&f| f > 0.0), "texel ({x}, {y}) lost its lobe");
            let params = TexelParams {
                diffuse: t.diffuse.map(|v| v as f32),
                specular: t.specular.map(|v| v as f32),
                alpha: t.roughness as f32,
                normal: t.normal.to_array().map(|v| v as f32),
            };
            for &(wi, wo) in &pairs {
                let host = reflected(&params, wi, wo);
                let sim = t.reflected(wi.map(f64::from).into(), wo.map(f64::from).into());
                for c in 0..3 {
                    let (a, b) = (host[c] as f64, sim[c]);
                    assert!(
                        (a - b).abs() <= 1e-4 * b.abs().max(0.1),
                        "texel ({x}, {y}): {host:?} vs {sim:?}"
                    );
                }
            }
        }
    }
    // Scanned by the simulator's truth, the set keeps what the file has.
    let exported = Sample::small(lookup(&d("set-exr")).unwrap());
    let score = |pairs: &[([f64; 3], [f64; 3])]| {
        let t = tests::truth_answers(pairs, sample);
        tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&exported, q)).0
    };
    let set_db = [score(captured), score(novel)];
    eprintln!(
        "leather, 1024² sensor: the exported texture set {:.2} dB at the captured pairs, {:.2} dB at novel pairs (the material file {:.2}, {:.2})",
        set_db[0], set_db[1], file_db[0], file_db[1]
    );
    for k in 0..2 {
        assert!(
            set_db[k] >= file_db[k] - 1.0,
            "texture set {:.2} dB, file {:.2} dB",
            set_db[k],
            file_db[k]
        );
    }

    // The glTF asset. Its base colour and metallic-roughness maps, read
    // by the simulator as a texture set in the glTF form (with the set's
    // own normal map: the asset's is in glTF's tangent space), give the
    // model's parameters as `metallic_form` converts them, to 8 bits; its
    // normal map is the set's with y flipped (up the image); and scanned,
    // that set scores within 1 dB of the file too.
    {
        use host::build::gltf::{gltf_normal, metallic_form, model_of, model_with_specular};
        let (code, err) = common::run_err(&[
            "export",
            &d("leather.material"),
            "-o",
            &d("gltf"),
            "--format",
            "gltf",
        ]);
        assert_eq!(code, Some(0), "{err}");
        let doc: serde_json::Value =
            serde_json::from_slice(&std::fs::read(p("gltf/material.gltf")).unwrap()).unwrap();
        assert_eq!(doc["asset"]["version"], "2.0");
        let bin = std::fs::metadata(p("gltf/material.bin")).unwrap().len();
        assert_eq!(doc["buffers"][0]["byteLength"].as_u64(), Some(bin));
        std::fs::create_dir(p("gltf-form")).unwrap();
        for (from, to) in [
            ("gltf/baseColor.png", "gltf-form/baseColor.png"),
            ("gltf/metallicRoughness.png", "gltf-form/metallicRoughness.png"),
            ("set-png/normal.png", "gltf-form/normal.png"),
            ("set-png/material.toml", "gltf-form/material.toml"),
        ] {
            std::fs::copy(p(from), p(to)).unwrap();
        }
        let read = Sample::small(lookup(&d("gltf-form")).unwrap());
        let normals = image::open(p("gltf/normal.png")).unwrap().to_rgb8();
        // KHR_materials_specular: its colour (factor × sRGB texture) gives a
        // viewer that reads it the set's own F0, where the metal's share of
        // it does not exceed F0 already.
        let factor =
            doc["materials"][0]["extensions"]["KHR_materials_specular"]["specularColorFactor"][0]
                .as_f64()
                .unwrap() as f32;
        let speculars = image::open(p("gltf/specularColor.png")).unwrap().to_rgb8();
        let linear = |code: u8| hil_sim::texture_set::srgb_to_linear(code as f32 / 255.0);
        let (mut f0_err, mut f0_core_err) = (0.0f64, 0.0f64);
        assert_eq!(normals.dimensions(), (set.side as u32, set.side as u32));
        let mut metallic = 0usize;
        for i in (0..set.side * set.side).step_by(7) {
            let (x, y) = (i % set.side, i / set.side);
            let uv = [(x as f64 + 0.5) / set.side as f64, (y as f64 + 0.5) / set.side as f64];
            let t = read.texel(uv);
            let (base, m) = metallic_form(set.diffuse[i], set.specular[i]);
            metallic += usize::from(m > 0.0);
            let (diffuse, f0) = model_of(base, m);
            for c in 0..3 {
                let (a, b) = (t.diffuse[c], diffuse[c] as f64);
                assert!((a - b).abs() < 5e-3, "texel ({x}, {y}) diffuse: {a} vs {b}");
                let (a, b) = (t.specular[c], f0[c] as f64);
                assert!((a - b).abs() < 5e-3, "texel ({x}, {y}) F0: {a} vs {b}");
            }
            assert!((t.roughness.sqrt() - set.roughness[i] as f64).abs() < 3e-3);
            let colour = speculars.get_pixel(x as u32, y as u32).0.map(|c| factor * linear(c));
            let (_, with) = model_with_specular(base, m, colour);
            for c in 0..3 {
                let want = set.specular[i][c].max(m * base[c]);
                let tolerance = 2e-3 + 0.02 * want;
                assert!(
                    (with[c] - want).abs() < tolerance,
                    "texel ({x}, {y}) F0: {with:?} vs {want}"
                );
                f0_err += ((with[c] - set.specular[i][c]) as f64).powi(2);
                f0_core_err += ((f0[c] - set.specular[i][c]) as f64).powi(2);
            }
            let code = normals.get_pixel(x as u32, y as u32).0;
            let g = gltf_normal(set.normal[i]);
            for c in 0..3 {
                let decoded = code[c] as f32 / 255.0 * 2.0 - 1.0;
                assert!((decoded - g[c]).abs() < 5e-3, "texel ({x}, {y}) normal: {code:?}, {g:?}");
            }
        }
        let texels = (set.side * set.side).div_ceil(7);
        eprintln!(
            "leather: {metallic} of {texels} texels checked have a metallic factor above 0; \
             F0's RMS error {:.2e} with KHR_materials_specular, {:.2e} without",
            (f0_err / (3 * texels) as f64).sqrt(),
            (f0_core_err / (3 * texels) as f64).sqrt()
        );
        assert!(f0_err < f0_core_err / 4.0, "{f0_err} vs {f0_core_err}");
        let gltf_db = {
            let score = |pairs: &[([f64; 3], [f64; 3])]| {
                let t = tests::truth_answers(pairs, sample);
                tests::pairs_psnr(pairs, &t, &|_, q| hil_sim::truth::answer(&read, q)).0
            };
            [score(captured), score(novel)]
        };
        eprintln!(
            "leather, 1024² sensor: the glTF asset's maps {:.2} dB at the captured pairs, {:.2} dB at novel pairs",
            gltf_db[0], gltf_db[1]
        );
        for k in 0..2 {
            assert!(
                gltf_db[k] >= file_db[k] - 1.0,
                "glTF {:.2} dB, file {:.2} dB",
                gltf_db[k],
                file_db[k]
            );
        }
        // Its directory is its own: a texture set's is not replaced by it.
        let (code, err) = common::run_err(&[
            "export",
            &d("leather.material"),
            "-o",
            &d("set-png"),
            "--format",
            "gltf",
        ]);
        assert_eq!(code, Some(4), "{err}");
        assert!(p("set-png/material.toml").is_file());
    }

    // Refused: a material without a model (exit 3), a damaged file (3),
    // an output that is not a texture set's directory (4); nothing written.
    let refused = |material: &str, out: &str, code: i32| -> String {
        let (c, err) = common::run_err(&["export", &d(material), "-o", &d(out)]);
        assert_eq!(c, Some(code), "{err}");
        err
    };
    let err = refused("plain.material", "plain-set", 3);
    assert!(err.contains("plain.material") && err.contains("no texel model"), "{err}");
    assert!(!p("plain-set").exists());
    let good = std::fs::read(p("leather.material")).unwrap();
    std::fs::write(p("half.material"), &good[..good.len() / 2]).unwrap();
    refused("half.material", "half-set", 3);
    assert!(!p("half-set").exists());
    std::fs::create_dir(p("mine")).unwrap();
    std::fs::write(p("mine/notes.txt"), "keep").unwrap();
    refused("leather.material", "mine", 4);
    assert_eq!(std::fs::read_to_string(p("mine/notes.txt")).unwrap(), "keep");
    refused("leather.material", "leather.material", 4);
    assert_eq!(std::fs::read(p("leather.material")).unwrap(), good);
    // A set exported again is replaced whole: PNG maps over EXR ones.
    let (code, err) = common::run_err(&[
        "export",
        &d("leather.material"),
        "-o",
        &d("set-exr"),
        "--format",
        "png",
    ]);
    assert_eq!(code, Some(0), "{err}");
    let mut names: Vec<String> = std::fs::read_dir(p("set-exr"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["diffuse.png", "material.toml", "normal.png", "roughness.png", "specular.png"]
    );
}

fn sha256(path: &Path) -> String {
    use sha2::Digest;
    host::scan::hex(&sha2::Sha256::digest(std::fs::read(path).unwrap()))
}

#[test]
fn a_built_material_shades_like_the_sample() {
    let (bin, mirrors, seed) = (4, 40, 3);
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let d = |n: &str| p(n).display().to_string();
    let g = tests::sim_scan("checkerboard", seed, bin, mirrors, false, &p("checker"));
    tests::sim_scan("diffuse-white", seed, bin, mirrors, false, &p("white"));
    tests::sim_scan("leather", seed, bin, mirrors, true, &p("leather"));
    let (code, _, err) = common::calibrate(&d("checker"), &d("white"), &d("cal.json"), &[]);
    assert_eq!(code, Some(0), "{err}");
    // `scanner build` of scan SCAN with the calibration into OUT.
    let build_cli = |scan: &str, out: &str, extra: &[&str]| {
        let (scan, out) = (d(scan), d(out));
        let args = ["build", "--scan", &scan, "--calibration", &d("cal.json"), "-o", &out];
        common::run_err(&[&args[..], extra].concat())
    };
    let (code, err) = build_cli("leather", "leather.material", &[]);
    assert_eq!(code, Some(0), "{err}");

    // The file: what it says it is, where it came from.
    let m = Material::open(&p("leather.material")).unwrap();
    let meta = m.metadata();
    assert_eq!((meta.lights.len(), meta.views.len(), meta.colours), (40, 40, 256));
    assert_eq!(meta.interpolation, Interpolation::Default);
    assert_eq!(meta.provenance.geometry_sha256, g.hash());
    assert_eq!(meta.provenance.calibration_sha256, sha256(&p("cal.json")));
    assert_eq!(meta.provenance.scan_manifest_sha256, sha256(&p("leather/manifest.json")));
    // The flush leather was read in the holder's plane, measured so.
    let face = meta.provenance.face.as_ref().expect("the face it was read on");
    assert_eq!((face.height_mm, face.slope), (0.0, [0.0; 2]), "{face:?}");
    assert_ne!(face.measured_on, "given");
    assert_eq!(meta.name, "leather");

    // Fidelity. The same region images, built again in-process with both
    // interpolations (the CLI's file is the default one, byte for byte).
    let cal = Calibration::load(&p("cal.json")).unwrap();
    let scan = ScanFrames::open(&p("leather"), &g).unwrap();
    let regions = extract_regions(&g, &cal, &scan, &RegionOptions::default(), &Silent).unwrap();
    let prov = meta.provenance.clone();
    let build_with = |opts: MaterialOptions| {
        let data = build_material(&regions, "leather", 25.4, prov.clone(), &opts, &Silent).unwrap();
        let bytes = data.to_bytes().unwrap();
        (Material::from_bytes(&bytes).unwrap(), bytes, data.texels)
    };
    let build = |interpolation| build_with(MaterialOptions { interpolation, ..Default::default() });
    // On one thread (every parallel reduction split otherwise than the
    // CLI's on the machine's threads): the same file, byte for byte.
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let (default, bytes, texels) = one.install(|| build(Interpolation::Default));
    assert_eq!(bytes, std::fs::read(p("leather.material")).unwrap(), "deterministic");
    // The views' detail beyond S × S is in the file, and the file within 16 MB.
    assert!(default.metadata().detail, "a detail layer");
    assert!(bytes.len() <= 16_000_000, "{} bytes", bytes.len());
    // Within the budget every pair has its own index image; a budget
    // smaller by four index images makes four fewer light groups, four of
    // them of two lights.
    assert_eq!(meta.lights_per_index, 1);
    let s = meta.resolution as usize;
    let budget = bytes.len() - 4 * meta.views.len() * s * s;
    let (tight, tight_bytes, _) = build_with(MaterialOptions {
        max_bytes: Some(budget),
        texel_model: TexelModelChoice::On,
        ..Default::default()
    });
    assert!(tight_bytes.len() <= budget, "{} > {budget} bytes", tight_bytes.len());
    assert_eq!(tight.metadata().lights_per_index, 2);
    let patent_interp = Interpolation::Patent { columns: 256, rows: 64, points: 500 };
    let (patent, ..) = build(patent_interp);
    let sample = Sample::small(lookup("leather").unwrap());
    let truth_geometry =
        OpticalSim::as_built(&g, Sample::small(lookup("checkerboard").unwrap()), seed)
            .geometry()
            .clone();
    let captured = tests::as_built_pairs(&truth_geometry, &cal, &regions);
    let novel = tests::random_pairs(60, 60.0, 7);
    let scores = tests::material_scores(
        &regions,
        [&default, &patent],
        [&texels, &[]],
        &sample,
        &captured,
        &novel,
    );
    // The layer's light components are in the file as the builder kept them
    // (at this sensor's 1024² none are kept for the leather; at 4096², two:
    // docs/benchmarks.md, "What changes with the light").
    let layer = regions.detail.as_ref().expect("a detail layer");
    eprintln!("leather detail layer: {} light components", layer.bases.len());
    assert_eq!(meta.detail_components as usize, layer.bases.len());
    assert_eq!(meta.version > scanner_shading::format::VERSION_DETAIL, !layer.bases.is_empty());
    let tests::MaterialScores {
        regions: reg,
        captured: [cap_d, cap_p],
        gain,
        against_regions: [pal, pal_patent],
        novel: [nov_d, nov_p],
        ..
    } = scores;
    eprintln!(
        "leather, 1024² sensor: regions {reg:.2} dB; material at the captured pairs {cap_d:.2} dB \
         (patent {cap_p:.2}), gain {gain:.4}; against the region images {pal:.2} dB (patent \
         {pal_patent:.2}); novel pairs {nov_d:.2} dB (patent {nov_p:.2})"
    );
    assert!(reg - cap_d <= 1.0, "palettes cost {:.2} dB", reg - cap_d);
    assert!((gain - 1.0).abs() < 0.02, "absolute units: gain {gain}");
    assert!(pal > 40.0, "palettisation {pal}");
    assert!(pal - pal_patent > 10.0, "default {pal} vs patent {pal_patent} at captured pairs");
    assert!(nov_d >= nov_p - 0.1, "novel pairs: default {nov_d} vs patent {nov_p}");

    // The texel model: kept by the leave-one-light-out choice, and no worse
    // at novel pairs than the same interpolation without it (the glossy
    // sample's gain is tested below).
    let (plain, plain_bytes, _) =
        build_with(MaterialOptions { texel_model: TexelModelChoice::Off, ..Default::default() });
    let with_without = tests::material_scores(
        &regions,
        [&default, &plain],
        [&texels, &[]],
        &sample,
        &captured,
        &novel,
    );
    let [nov_m, nov_plain] = with_without.novel;
    eprintln!(
        "leather texel model: {} (β {}); novel pairs {nov_m:.2} dB, without the model \
         {nov_plain:.2} dB (β {})",
        meta.texel_model,
        meta.half_vector_shift,
        plain.metadata().half_vector_shift
    );
    assert!(meta.texel_model, "leather: the builder kept no texel model");
    assert!(!plain.metadata().texel_model);
    assert!(nov_m >= nov_plain - 0.1, "novel pairs: {nov_m} with the model, {nov_plain} without");
    std::fs::write(p("plain.material"), &plain_bytes).unwrap();
    exported_texture_sets(dir.path(), [cap_d, nov_d], &sample, &captured, &novel);

    // A glossy sample: the model carries the highlights between mirrors.
    tests::sim_scan("rough-metal", seed, bin, mirrors, true, &p("metal"));
    let scan = ScanFrames::open(&p("metal"), &g).unwrap();
    let metal_regions =
        extract_regions(&g, &cal, &scan, &RegionOptions::default(), &Silent).unwrap();
    let build_metal = |texel_model| {
        let opts = MaterialOptions { texel_model, ..Default::default() };
        let data =
            build_material(&metal_regions, "rough-metal", 25.4, prov.clone(), &opts, &Silent)
                .unwrap();
        (Material::from_bytes(&data.to_bytes().unwrap()).unwrap(), data.texels)
    };
    let ((auto, auto_texels), (off, _)) =
        (build_metal(TexelModelChoice::Auto), build_metal(TexelModelChoice::Off));
    let metal = Sample::small(lookup("rough-metal").unwrap());
    let metal_captured = tests::as_built_pairs(&truth_geometry, &cal, &metal_regions);
    let sc = tests::material_scores(
        &metal_regions,
        [&auto, &off],
        [&auto_texels, &[]],
        &metal,
        &metal_captured,
        &novel,
    );
    eprintln!(
        "rough-metal, 1024² sensor: texel model {} (β {}): captured pairs {:.2} dB, novel pairs \
         {:.2} dB; without the model (β {}) {:.2} and {:.2} dB",
        auto.metadata().texel_model,
        auto.metadata().half_vector_shift,
        sc.captured[0],
        sc.novel[0],
        off.metadata().half_vector_shift,
        sc.captured[1],
        sc.novel[1]
    );
    assert!(auto.metadata().texel_model, "rough-metal: the builder kept no texel model");
    // At the captured pairs the model only carries each texel's value from
    // the direction it was seen under to the pair's central one; across the
    // highlights' flanks that is worth something (measured +0.78 dB).
    assert!(
        sc.captured[0] >= sc.captured[1] + 0.3,
        "rough-metal captured pairs: {:.2} dB with the model, {:.2} without",
        sc.captured[0],
        sc.captured[1]
    );
    assert!(
        sc.novel[0] >= sc.novel[1] + 6.0,
        "rough-metal novel pairs: {:.2} dB with the model, {:.2} without",
        sc.novel[0],
        sc.novel[1]
    );

    // Importance sampling on the scanned materials: unbiased at every
    // (uv, wo) asked, and against cosine sampling a geometric-mean variance
    // below it on the leather and far below on the glossy metal, with and
    // without a texel model (measured 0.85, 0.028 and 0.042 at this 1024²
    // sensor; docs/benchmarks.md, "Importance sampling").
    for (name, mat, most) in [
        ("leather", &m, 1.0),
        ("rough-metal", &auto, 0.1),
        ("rough-metal without a model", &off, 0.1),
    ] {
        mat.prepare_importance();
        let mut log_ratio = 0.0;
        for k in 0..8u64 {
            let (t, p) = (k as f32 * 0.19 % 1.1, k as f32 * 2.4);
            let wo = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
            let uv = [(k as f32 * 0.37).fract(), (k as f32 * 0.61 + 0.2).fract()];
            let c = tests::sampling_check(mat, uv, wo, 5_000, 40 + k);
            assert!(c.deviation.abs() < 4.0, "{name} at {uv:?} {wo:?}: biased, {c:?}");
            log_ratio += c.variance_ratio.ln() / 8.0;
        }
        let ratio = log_ratio.exp();
        eprintln!("{name}: importance sampling's variance {ratio:.3} of cosine sampling's");
        assert!(ratio < most, "{name}: variance {ratio:.3} of cosine sampling's");
    }

    // `scanner shade` answers what `Material::eval` answers.
    let queries: Vec<Query> = novel
        .iter()
        .take(20)
        .enumerate()
        .map(|(i, &(wi, wo))| Query {
            uv: [(i as f64 * 0.37).fract(), (i as f64 * 0.61).fract()],
            wi,
            wo,
        })
        .collect();
    write_queries(&p("q.npy"), &queries).unwrap();
    let (code, err) = common::run_err(&[
        "shade",
        &d("leather.material"),
        "--queries",
        &d("q.npy"),
        "-o",
        &d("a.npy"),
    ]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(read_answers(&p("a.npy")).unwrap(), host::build::material::shade(&m, &queries));

    // The patent's table through the command line.
    let (code, err) = build_cli(
        "leather",
        "p.material",
        &[
            "--interpolation",
            "patent",
            "--patent-columns",
            "64",
            "--patent-rows",
            "16",
            "--patent-points",
            "50",
        ],
    );
    assert_eq!(code, Some(0), "{err}");
    let pm = Material::open(&p("p.material")).unwrap();
    assert_eq!(
        pm.metadata().interpolation,
        Interpolation::Patent { columns: 64, rows: 16, points: 50 }
    );
    let (code, err) =
        build_cli("leather", "p0.material", &["--interpolation", "patent", "--patent-points", "0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(!p("p0.material").exists());

    // A preview of the material file.
    let (code, err) =
        common::run_err(&["preview", &d("leather.material"), "-o", &d("leather.png")]);
    assert_eq!(code, Some(0), "{err}");
    let png = image::open(p("leather.png")).unwrap().to_rgb8();
    // Three 256² panels 6 px apart, under a line of title and a caption.
    assert_eq!(png.dimensions(), (3 * 262 + 6, 23 + 20 + 256 + 6));
    // The title and the captions are drawn (light text on the dark ground).
    let lit = |y0: u32, y1: u32| {
        (y0..y1)
            .flat_map(|y| (0..png.width()).map(move |x| (x, y)))
            .filter(|&(x, y)| png.get_pixel(x, y).0.iter().all(|&c| c > 150))
            .count()
    };
    assert!(lit(0, 23) > 200 && lit(23, 43) > 100, "{} and {}", lit(0, 23), lit(23, 43));
    let (code, err) =
        common::run_err(&["preview", &d("leather.material"), "-o", &d("leather.exr")]);
    assert_eq!(code, Some(2), "{err}");

    // Bad input: exit 3, nothing written.
    let shade_refused = |material: &str, queries: &str, out: &str, code: i32| -> String {
        let (c, err) =
            common::run_err(&["shade", &d(material), "--queries", &d(queries), "-o", &d(out)]);
        assert_eq!(c, Some(code), "{err}");
        assert!(!p(out).exists(), "{out} written");
        err
    };
    let good = std::fs::read(p("leather.material")).unwrap();
    std::fs::write(p("cut.material"), &good[..good.len() / 2]).unwrap();
    let err = shade_refused("cut.material", "q.npy", "x1.npy", 3);
    assert!(err.contains("not a safetensors file"), "{err}");
    let (c, err) = common::run_err(&["preview", &d("cut.material"), "-o", &d("cut.png")]);
    assert_eq!(c, Some(3), "{err}");
    assert!(!p("cut.png").exists());
    let mut flipped = good.clone();
    let header = u64::from_le_bytes(good[..8].try_into().unwrap()) as usize;
    // A palette index beyond K = 256 cannot be written in U8; flip a header
    // byte instead (the JSON breaks).
    flipped[8 + header / 2] ^= 0x5a;
    std::fs::write(p("bad.material"), &flipped).unwrap();
    shade_refused("bad.material", "q.npy", "x2.npy", 3);
    // One bit of the tensors' data, which any value might hold: the
    // content digest tells.
    let mut altered = good.clone();
    altered[8 + header + (good.len() - 8 - header) / 3] ^= 0x01;
    std::fs::write(p("altered.material"), &altered).unwrap();
    let err = shade_refused("altered.material", "q.npy", "x5.npy", 3);
    assert!(err.contains("altered or damaged"), "{err}");
    std::fs::write(p("cols.csv"), "u,v,wi_x,wi_y,wi_z,wo_x,wo_y\n0.5,0.5,0,0,1,0,0\n").unwrap();
    let err = shade_refused("leather.material", "cols.csv", "x3.csv", 3);
    assert!(err.contains("wo_z"), "{err}");
    std::fs::write(p("nan.csv"), "u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n0.5,0.5,0,0,NaN,0,0,1\n")
        .unwrap();
    let err = shade_refused("leather.material", "nan.csv", "x4.csv", 3);
    assert!(err.contains("row 0"), "{err}");
    // The output may not be the material.
    let (c, err) = common::run_err(&[
        "shade",
        &d("leather.material"),
        "--queries",
        &d("q.npy"),
        "-o",
        &d("leather.material"),
    ]);
    assert_eq!(c, Some(2), "{err}"); // not a query/answer file type
    // A scan of another geometry than the calibration: exit 3, no material.
    tests::sim_scan("leather", seed, 8, 3, false, &p("other"));
    let (c, err) = build_cli("other", "other.material", &[]);
    assert_eq!(c, Some(3), "{err}");
    assert!(err.contains("geometry"), "{err}");
    assert!(!p("other.material").exists());
    // Out-of-range options: usage errors before any work.
    for (flag, v) in [("--colours", "0"), ("--colours", "257"), ("--lights-per-index", "5")] {
        let (c, err) = build_cli("leather", "o.material", &[flag, v]);
        assert_eq!(c, Some(2), "{flag} {v}: {err}");
        assert!(!p("o.material").exists());
    }
    // The output may not replace the calibration (an input).
    let (c, err) = build_cli("leather", "cal.json", &[]);
    assert_eq!(c, Some(4), "{err}");
    assert_eq!(Calibration::load(&p("cal.json")).map(|c| c.hash()).ok(), Some(cal.hash()));
}
