//! The material file's fidelity table (docs/benchmarks.md, "Material
//! files"): for each library material (HDR scans on the simulator), the
//! material PSNR against `hil-sim truth` at the captured pairs (the
//! as-built directions) — region images, palettised material with the
//! default and with the patent's interpolation — the palettisation error
//! alone, and both interpolations at random novel pairs (θ ≤ 60°).
//! With `--bands`, a second table: both interpolations at novel pairs
//! whose light, view or both lie beyond the outermost ring of mirrors
//! (65°–88° from the normal), where a renderer's grazing queries fall.
//!
//! `cargo run --release -p tests --example material_fidelity -- [--bin 1] [--mirrors 40] [--seed 1] [--novel 300] [--out DIR] [--materials a,b] [--no-patent] [--texel-model auto|on|off] [--detail all-views|own-view] [--lights-per-index 2] [--bands]`
//! (scans in DIR are reused when complete; `builder_fidelity` shares them).

use std::path::PathBuf;
use std::time::Instant;

use hil_sim::materials::{Sample, lookup};
use host::build::calibrate::Silent;
use host::build::material::{
    MaterialOptions, PATENT_DEFAULT, TexelModelChoice, build_material, shade,
};
use scanner_shading::Material;

fn main() {
    tests::check_region_args(
        &[
            "--bin",
            "--lights-per-index",
            "--materials",
            "--mirrors",
            "--novel",
            "--out",
            "--seed",
            "--texel-model",
        ],
        &["--bands", "--no-patent"],
    );
    let bin: u32 = tests::arg("--bin", 1);
    let mirrors: usize = tests::arg("--mirrors", 40);
    let seed: u64 = tests::arg("--seed", 1);
    let novel: usize = tests::arg("--novel", 300);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/builder-fidelity"));
    let list: String =
        tests::arg("--materials", "woven-fabric,leather,painted-wood,rough-metal".to_string());
    let materials: Vec<&str> = list.split(',').collect();
    let with_patent = !std::env::args().any(|a| a == "--no-patent");
    let with_bands = std::env::args().any(|a| a == "--bands");
    let lights_per_index: usize = tests::arg("--lights-per-index", 1);
    let texel_model: TexelModelChoice = tests::arg("--texel-model", "auto".to_string())
        .parse()
        .unwrap_or_else(|e| panic!("--texel-model: {e}"));
    let (g, cal, truth) = tests::scanned_and_calibrated(&out, seed, bin, mirrors, &materials);
    let pairs = tests::random_pairs(novel, 60.0, seed);
    println!(
        "sensor {0}², {mirrors} mirrors, seed {seed}; {novel} novel pairs θ ≤ 60°",
        4096 / bin
    );
    println!(
        "| material | regions dB | regions × detail dB | material dB (default) | material dB (patent) | palettes alone dB | \
         novel dB (default) | novel dB (patent) | file MB (default / patent) | palettes+tables s (default / patent) | β | texel model | light components | \
         captured, default: worst 5 % of pairs' share of the error | PSNR of the other 95 % dB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut band_rows = Vec::new();
    for &m in &materials {
        let regions = tests::scanned_regions(&out, &g, &cal, m);
        let provenance = tests::example_provenance(&g, &cal, "material_fidelity");
        let build = |opts: MaterialOptions| {
            let t = Instant::now();
            let data =
                build_material(&regions, m, 25.4, provenance.clone(), &opts, &Silent).unwrap();
            let bytes = data.to_bytes().unwrap();
            let m = Material::from_bytes(&bytes).unwrap();
            (m, bytes.len(), t.elapsed().as_secs_f64(), data.texels)
        };
        let (default, size_d, t_d, texels) =
            build(MaterialOptions { texel_model, lights_per_index, ..Default::default() });
        // The patent's material, unless --no-patent (then its columns say —,
        // and the scores below take the default in its place).
        let patent_built = with_patent.then(|| {
            build(MaterialOptions { interpolation: PATENT_DEFAULT, ..Default::default() })
        });
        let patent_material = patent_built.as_ref().map_or(&default, |b| &b.0);
        let sample = Sample::small(lookup(m).unwrap());
        let captured = tests::as_built_pairs(&truth, &cal, &regions);
        let tests::MaterialScores {
            regions: reg,
            regions_detail: reg_d,
            captured: [cap_d, cap_p],
            against_regions: [pal, _],
            novel: [nov_d, nov_p],
            worst_5: (share, without),
            ..
        } = tests::material_scores(
            &regions,
            [&default, patent_material],
            [&texels, &[]],
            &sample,
            &captured,
            &pairs,
        );
        let shift = default.metadata().half_vector_shift;
        let model = if default.metadata().texel_model { "yes" } else { "no" };
        let patent = |x: f64, digits: usize| match patent_built {
            Some(_) => format!("{x:.digits$}"),
            None => "—".to_string(),
        };
        let (size_p, t_p) = patent_built.as_ref().map_or((0, 0.0), |b| (b.1, b.2));
        println!(
            "| {m} | {reg:.2} | {reg_d:.2} | {cap_d:.2} | {} | {pal:.2} | {nov_d:.2} | {} | {:.1} / {} | {t_d:.1} / {} | {shift} | {model} | {} | {:.0} % | {without:.2} |",
            patent(cap_p, 2),
            patent(nov_p, 2),
            size_d as f64 / 1e6,
            patent(size_p as f64 / 1e6, 1),
            patent(t_p, 1),
            default.metadata().detail_components,
            100.0 * share
        );
        if with_bands {
            let scores: Vec<String> = BANDS
                .iter()
                .enumerate()
                .map(|(i, &(_, light, view))| {
                    let pairs =
                        tests::random_pairs_between(novel, light, view, seed + 1 + i as u64);
                    let t = tests::truth_answers(&pairs, &sample);
                    let psnr = |mat| tests::pairs_psnr(&pairs, &t, &|_, q| shade(mat, q)).0;
                    let p = patent_built
                        .as_ref()
                        .map_or("—".to_string(), |b| format!("{:.2}", psnr(&b.0)));
                    format!("{:.2} / {p}", psnr(&default))
                })
                .collect();
            band_rows.push(format!("| {m} | {} |", scores.join(" | ")));
        }
    }
    if with_bands {
        println!("\nnovel pairs by band, {novel} each (default / patent interpolation, dB)");
        let names: Vec<&str> = BANDS.iter().map(|b| b.0).collect();
        println!("| material | {} |", names.join(" | "));
        println!("|---|{}", "---|".repeat(BANDS.len()));
        for r in band_rows {
            println!("{r}");
        }
    }
}

/// The `--bands` table's columns: (name, light's band, view's band), degrees
/// from the normal. The default scanner's outermost ring is at 65°.
const BANDS: [(&str, [f64; 2], [f64; 2]); 4] = [
    ("both ≤ 60°", [0.0, 60.0], [0.0, 60.0]),
    ("light 65°–88°, view ≤ 60°", [65.0, 88.0], [0.0, 60.0]),
    ("light ≤ 60°, view 65°–88°", [0.0, 60.0], [65.0, 88.0]),
    ("both 65°–88°", [65.0, 88.0], [65.0, 88.0]),
];
