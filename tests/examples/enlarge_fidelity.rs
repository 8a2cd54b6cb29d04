//! The enlargement's fidelity table (docs/benchmarks.md, "Enlargement"):
//! the targets and each library material scanned on the simulator (HDR),
//! calibrated, built; the direct images of each material's large piece
//! rendered from the four mirror directions nearest the axis; the material
//! enlarged to the piece; then material PSNR against the large piece's
//! ground truth, beside the sample's material tiled over it, and over the
//! window the sample is cut from, beside the sample's own material.
//!
//! `cargo run --release -p tests --example enlarge_fidelity -- [--bin 4] [--seed 1] [--out DIR] [--pairs 48] [--materials a,b]`

use std::path::PathBuf;
use std::time::Instant;

use hil_sim::materials::lookup;
use host::build::enlarge::{EnlargeOptions, enlarge, read_direct_set};
use scanner_shading::Material;

fn main() {
    tests::check_region_args(
        &[
            "--bin",
            "--materials",
            "--out",
            "--pairs",
            "--radius",
            "--seed",
            "--signature",
            "--subtexel",
        ],
        &[],
    );
    let bin: u32 = tests::arg("--bin", 4);
    let seed: u64 = tests::arg("--seed", 1);
    let n_pairs: usize = tests::arg("--pairs", 48);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/enlarge-fidelity"));
    let list: String =
        tests::arg("--materials", "woven-fabric,leather,painted-wood,rough-metal".to_string());
    let materials: Vec<&str> = list.split(',').collect();
    let (g, cal, _) = tests::scanned_and_calibrated(&out, seed, bin, 40, &materials);
    let pairs = tests::random_pairs(n_pairs, 60.0, seed);
    println!(
        "| material | S | map | enlarge | signature distance (median / 90th) | enlarged | tiled | \
         window: enlarged | window: the sample's material | own place |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for m in materials {
        let dir = out.join(format!(
            "direct-{}",
            tests::scan_dir(&out, m).file_name().unwrap().to_string_lossy()
        ));
        let (data, _) =
            tests::built_and_photographed(&out, &g, &cal, seed, m, &tests::region_options(), &dir);
        let small = Material::from_bytes(&data.to_bytes().unwrap()).unwrap();
        let truth = lookup(m).unwrap();
        let set = read_direct_set(&dir).unwrap();
        let t = Instant::now();
        let opts = EnlargeOptions {
            radius: tests::arg("--radius", EnlargeOptions::default().radius),
            subtexel: tests::arg("--subtexel", EnlargeOptions::default().subtexel),
            signature: tests::arg("--signature", "colour".to_string()).parse().unwrap(),
        };
        let (big, report) = enlarge(&data, &set, &opts).unwrap();
        let secs = t.elapsed().as_secs_f64();
        let big = Material::from_bytes(&big.to_bytes().unwrap()).unwrap();
        let own = own_place(&big, truth.clone());
        let s = tests::enlargement_scores(&big, &small, truth, &pairs);
        println!(
            "| {m} | {} | {} × {} | {secs:.2} s | {:.3} / {:.3} | **{:.2} dB** | {:.2} dB | {:.2} dB | \
             {:.2} dB | {:.1} % |",
            data.meta.resolution,
            report.columns,
            report.rows,
            report.distance[0],
            report.distance[1],
            s.enlarged,
            s.tiled,
            s.window_enlarged,
            s.window_sample,
            100.0 * own
        );
    }
}

/// The share of the map's texels within the window the small sample is cut
/// from (but its outermost 2 %) matched within a texel of their own place
/// on the sample.
fn own_place(big: &Material, truth: std::sync::Arc<dyn hil_sim::materials::Material>) -> f64 {
    use hil_sim::materials::Sample;
    let (small, large) = (Sample::small(truth.clone()), Sample::large(truth));
    let meta = big.metadata();
    let e = meta.enlargement.as_ref().expect("an enlarged material");
    let (cols, rows) = (e.columns as usize, e.rows as usize);
    let texel = 1.0 / meta.resolution as f64;
    let (mut inside, mut own) = (0usize, 0usize);
    for r in 0..rows {
        for c in 0..cols {
            let piece = [(c as f64 + 0.5) / cols as f64, (r as f64 + 0.5) / rows as f64];
            let uv = [0, 1].map(|k| {
                (large.offset_mm[k] + piece[k] * large.size_mm - small.offset_mm[k]) / small.size_mm
            });
            if uv.iter().any(|u| !(0.02..0.98).contains(u)) {
                continue;
            }
            inside += 1;
            let at = big.scanned_uv(piece.map(|u| u as f32));
            own += usize::from((0..2).all(|k| (at[k] as f64 - uv[k]).abs() <= texel));
        }
    }
    own as f64 / inside.max(1) as f64
}
