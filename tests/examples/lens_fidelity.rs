//! How well `scanner rectify --lens auto` estimates a lens from a piece's
//! own sides (docs/benchmarks.md, "Enlargement", "The lens from the
//! piece's sides"): the simulator photographs each material's large piece
//! and the white card through a lens of known k1 at several sizes, and
//! `find_corners` estimates k1 and the corners from each photograph. Per
//! photograph the estimate, its standard error, the error in standard
//! errors and the worst corner against the simulator's; per material and
//! size the RMS and the largest of those.
//!
//! With `--lens given`, the corners are found through the true lens
//! instead (no estimate: the σ columns stay empty).
//!
//! `cargo run --release -p tests --example lens_fidelity -- [--k1 -0.02] [--lens auto|given] [--bins 5,4,3,2,1] [--seed 1] [--out DIR] [--materials a,b]`

use std::path::PathBuf;

use hil_sim::direct::{PHOTO_DISTANCE_MM, PhotoSetup, mirror_view_scale, write_photographs};
use hil_sim::geometry::ScannerGeometry;
use host::build::corners::{Origin, find_corners};
use host::build::lens::{Lens, LensChoice};

fn main() {
    tests::check_args(&["--bins", "--k1", "--lens", "--materials", "--out", "--seed"], &[]);
    let k1: f64 = tests::arg("--k1", -0.02);
    let choice = match tests::arg("--lens", "auto".to_string()).as_str() {
        "auto" => LensChoice::Estimate,
        "given" => LensChoice::Known(Lens::radial([k1, 0.0])),
        other => panic!("--lens {other}: auto or given"),
    };
    let seed: u64 = tests::arg("--seed", 1);
    let bins: String = tests::arg("--bins", "5,4,3,2,1".to_string());
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/lens-fidelity"));
    let list: String =
        tests::arg("--materials", "woven-fabric,leather,painted-wood,rough-metal".to_string());
    println!("| photograph | size | material | k1 | ± σ | error | in σ | worst corner |");
    println!("|---|---|---|---|---|---|---|---|");
    let mut summary = Vec::new();
    for bin in bins.split(',').map(|b| b.parse::<u32>().expect("--bins: numbers")) {
        let g = ScannerGeometry::default_scanner().with_sensor_scaled(bin);
        let scale = mirror_view_scale(&g);
        for m in list.split(',') {
            let truth = hil_sim::materials::lookup(m).unwrap();
            let small = hil_sim::materials::Sample::small(truth.clone());
            let sim = hil_sim::optics::OpticalSim::as_built(&g, small, seed);
            let dir = out.join(format!("{m}-bin{bin}"));
            let setup =
                PhotoSetup { distortion: [k1, 0.0], ..PhotoSetup::pinhole(PHOTO_DISTANCE_MM) };
            let shots = write_photographs(&sim, &g, truth, 4, scale, setup, &dir).unwrap();
            let (mut zs, mut worst, mut side) = (Vec::new(), 0.0f64, 0);
            for ph in shots.photo.iter().chain([&shots.white]) {
                let frame = host::exrio::read_rgb(&dir.join(&ph.file)).unwrap();
                side = frame.width;
                let size = format!("{side} px");
                match find_corners(&frame, Origin::BottomLeft, choice) {
                    Ok(f) => {
                        let e = f.lens.k[0] - k1;
                        let corner = (0..4)
                            .map(|k| {
                                let (a, b) = (f.corners[k], ph.corners[k]);
                                (a[0] - b[0]).hypot(a[1] - b[1])
                            })
                            .fold(0.0, f64::max);
                        let (sigma, z) = match f.lens_k1_sigma {
                            Some(s) => (format!("{s:.5}"), format!("{:+.2}", e / s)),
                            None => ("—".into(), "—".into()),
                        };
                        println!(
                            "| {} | {size} | {m} | {:.5} | {sigma} | {e:+.5} | {z} | {corner:.3} px |",
                            ph.file, f.lens.k[0],
                        );
                        if ph.file != shots.white.file {
                            if let Some(s) = f.lens_k1_sigma {
                                zs.push(e / s);
                            }
                            worst = worst.max(corner);
                        }
                    }
                    Err(e) => println!("| {} | {size} | {m} | failed: {e} | | | | |", ph.file),
                }
            }
            let rms = (zs.iter().map(|z| z * z).sum::<f64>() / zs.len().max(1) as f64).sqrt();
            let most = zs.iter().fold(0.0f64, |a, z| a.max(z.abs()));
            summary.push(format!(
                "| {m} | {side} px | {}/{} | {rms:.2} | {most:.2} | {worst:.3} px |",
                zs.len(),
                shots.photo.len()
            ));
        }
    }
    println!("\nThe pieces' photographs (the white card left out), k1 = {k1}:\n");
    println!("| material | size | estimated | RMS of error / σ | largest | worst corner |");
    println!("|---|---|---|---|---|---|");
    for line in summary {
        println!("{line}");
    }
}
