//! The material builder's fidelity and speed table (docs/benchmarks.md):
//! scans of the three targets and the four library materials on the
//! simulator (HDR for the samples), calibration, region images, material
//! PSNR against `hil-sim truth` at the captured pairs, the calibration's
//! errors against the as-built scanner, and the metric's own limits: its
//! point sampling (the 3 × 3-point cell means against 12 × 12-point ones),
//! its nominal directions (the truth at the as-built scanner's directions
//! against the truth at the nominal ones) and its distant viewer (the
//! truth seen from the as-built virtual camera, whose direction varies
//! over the sample, against the truth from its direction at the centre).
//! Then how the error spreads over the pairs: the worst 5 %'s share, the
//! limits on those pairs, and each material's worst pair with the limits
//! computed on it alone.
//!
//! `cargo run --release -p tests --example builder_fidelity -- [--bin 1] [--mirrors 40] [--seed 1] [--out DIR] [--size S] [--detail all-views|own-view] [--materials a,b] [--targets-only] [--per-view]`
//! (scans in DIR are reused when complete). `--per-view`: each view's
//! phase alignment against the truth, px and in checker squares.

use std::path::PathBuf;
use std::time::Instant;

use hil_sim::materials::{Sample, lookup};
use hil_sim::optics::OpticalSim;
use host::build::calibrate::{CalibrateOptions, LocatedBy, Silent};
use host::build::fidelity::{material_psnr, pair_queries};
use host::build::scanread::ScanFrames;
use host::build::{calibrate, extract_regions};
use host::simulator::SimSetup;
use scanner_geometry::{DVec3, world_to_sample};

fn main() {
    tests::check_region_args(
        &["--bin", "--lens-k1", "--materials", "--mirrors", "--out", "--seed"],
        &["--per-view", "--targets-only"],
    );
    let per_view = std::env::args().any(|a| a == "--per-view");
    let bin: u32 = tests::arg("--bin", 1);
    let mirrors: usize = tests::arg("--mirrors", 40);
    let seed: u64 = tests::arg("--seed", 1);
    let out: PathBuf = tests::arg("--out", PathBuf::from("target/builder-fidelity"));
    // `--targets-only`: the calibration's errors alone (three target scans).
    // `--materials a,b`: library names or texture-set directories.
    let list: String =
        tests::arg("--materials", "woven-fabric,leather,painted-wood,rough-metal".to_string());
    let materials: Vec<&str> = if std::env::args().any(|a| a == "--targets-only") {
        Vec::new()
    } else {
        list.split(',').collect()
    };
    for (m, hdr) in [("checkerboard", false), ("diffuse-white", false)]
        .into_iter()
        .chain(materials.iter().map(|m| (*m, true)))
    {
        let t = Instant::now();
        tests::sim_scan(m, seed, bin, mirrors, hdr, &tests::scan_dir(&out, m));
        eprintln!("scan {m}: {:.1} s", t.elapsed().as_secs_f64());
    }
    let exposure = tests::GLOSSY_EXPOSURE_US;
    tests::sim_scan_at(
        "glossy-black",
        seed,
        bin,
        mirrors,
        exposure,
        false,
        &out.join("glossy-black"),
    );
    let g = SimSetup { bin, seed, ..SimSetup::new("checkerboard") }.nominal().unwrap();
    let t = Instant::now();
    let checker = ScanFrames::open(&out.join("checkerboard"), &g).unwrap();
    let white = ScanFrames::open(&out.join("diffuse-white"), &g).unwrap();
    let glossy = ScanFrames::open(&out.join("glossy-black"), &g).unwrap();
    let opts = CalibrateOptions::default();
    let cal = calibrate(&g, &checker, &white, Some(&glossy), &opts, &Silent).unwrap();
    let t_cal = t.elapsed().as_secs_f64();
    // Calibration against the as-built scanner.
    let truth = OpticalSim::as_built(&g, Sample::small(lookup("checkerboard").unwrap()), seed)
        .with_lens_distortion([tests::arg("--lens-k1", 0.0), 0.0])
        .geometry()
        .clone();
    let (mut corner, mut corner_phase, mut corner_nominal) = (Vec::new(), Vec::new(), Vec::new());
    for v in &cal.views {
        if per_view {
            // The phase alignment's mean offset from the truth over the
            // sample's corners, px and in squares of the checker.
            let t = |uv| truth.view_point(v.view, uv).unwrap();
            let (a, b, c) = (t([0.0, 0.0]), t([1.0, 0.0]), t([0.0, 1.0]));
            let mut d = [0.0; 2];
            for uv in [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]] {
                let (p, q) = (v.homography_phase.apply(uv), t(uv));
                d = [d[0] + (p[0] - q[0]) / 4.0, d[1] + (p[1] - q[1]) / 4.0];
            }
            let (e, f) = ([b[0] - a[0], b[1] - a[1]], [c[0] - a[0], c[1] - a[1]]);
            let det = e[0] * f[1] - e[1] * f[0];
            let squares = opts.target.squares as f64;
            let du = (d[0] * f[1] - d[1] * f[0]) / det * squares;
            let dv = (e[0] * d[1] - e[1] * d[0]) / det * squares;
            println!(
                "view {:2}: the phase alignment off by [{:+.2}, {:+.2}] px = [{du:+.2}, {dv:+.2}] \
                 squares; sides {:.1} × {:.1} px; located by {:?}",
                v.view,
                d[0],
                d[1],
                e[0].hypot(e[1]),
                f[0].hypot(f[1]),
                v.located_by
            );
        }
        let nominal_h = host::build::locate::nominal_homography(&g, v.view).unwrap();
        for uv in [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]] {
            let t = truth.view_point(v.view, uv).unwrap();
            for (h, list) in [
                (&v.homography, &mut corner),
                (&v.homography_phase, &mut corner_phase),
                (&nominal_h, &mut corner_nominal),
            ] {
                let p = h.apply(uv);
                list.push((p[0] - t[0]).hypot(p[1] - t[1]));
            }
        }
    }
    let tests::DirectionErrors { view, view_nominal, light, light_nominal_source, light_nominal } =
        tests::direction_errors(&g, &truth, &cal);
    let rms = |v: &[f64]| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
    let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    println!("sensor {0}², {mirrors} mirrors, seed {seed}", 4096 / bin);
    println!(
        "corners RMS: the better of the corner fit and the phase alignment {:.3} px (the phase \
         alignment's at {} of {} views; a corner fit at {}), the phase alignment alone {:.3} px, \
         nominal {:.2} px",
        rms(&corner),
        cal.views.iter().filter(|v| v.located_by == Some(LocatedBy::Phase)).count(),
        cal.views.len(),
        cal.views.iter().filter(|v| v.corners_used > 0).count(),
        rms(&corner_phase),
        rms(&corner_nominal),
    );
    println!(
        "view directions: RMS {:.3}° max {:.3}° (nominal RMS {:.3}° max {:.3}°)",
        rms(&view),
        max(&view),
        rms(&view_nominal),
        max(&view_nominal)
    );
    println!(
        "light directions: RMS {:.3}° max {:.3}° (nominal source home positions RMS {:.3}° max {:.3}°; \
         nominal RMS {:.3}° max {:.3}°); {:?}",
        rms(&light),
        max(&light),
        rms(&light_nominal_source),
        max(&light_nominal_source),
        rms(&light_nominal),
        max(&light_nominal),
        cal.source_offsets
    );
    println!(
        "as built: disk home {:+.3}°, tilt home {:+.3}°",
        truth.source.disk_zero_deg - g.source.disk_zero_deg,
        truth.source.tilt_zero_deg - g.source.tilt_zero_deg
    );
    println!("calibrate: {t_cal:.1} s; lens k1 {:+.4}", cal.lens_distortion[0]);
    println!(
        "| material | regions s | PSNR dB | gain-free dB | gain | point-sampling limit dB | \
         nominal-direction limit dB | distant-viewer limit dB | PSNR at the as-built directions dB | \
         worst 5 % of pairs: share of the error | PSNR without them dB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let mut worst_lines = Vec::new();
    for &m in &materials {
        let t = Instant::now();
        let scan = ScanFrames::open(&tests::scan_dir(&out, m), &g).unwrap();
        let regions = extract_regions(&g, &cal, &scan, &tests::region_options(), &Silent).unwrap();
        let t_reg = t.elapsed().as_secs_f64();
        let face = tests::face_report(m, &regions);
        worst_lines.extend(face.lines().map(str::to_string));
        let sample = Sample::small(lookup(m).unwrap());
        let pairs = tests::captured_pairs(&g, &regions);
        let truth_at = tests::truth_answers(&pairs, &sample);
        let answers = tests::region_answers(&pairs, &regions);
        let (psnr, gain_free, gain) = material_psnr(&answers, &truth_at);
        let errors = tests::PairErrors::new(&answers, &truth_at);
        let (share, without) = errors.concentration(0.05);
        // The metric's limits on every 17th pair (every view, most lights):
        // 3 × 3 points vs 12 × 12, and so on; and on the worst pair.
        let as_built = tests::as_built_pairs(&truth, &cal, &regions);
        let truth_built = tests::truth_answers(&as_built, &sample);
        // One pair's answers within answers to all pairs.
        let per = truth_at.len() / pairs.len();
        let of = |all: &[[f32; 3]], p: usize| all[p * per..(p + 1) * per].to_vec();
        let worst = errors.worst_first()[0];
        let limits = |chosen: &[usize]| {
            let (mut three, mut dense) = (Vec::new(), Vec::new());
            let (mut built, mut per_point) = (Vec::new(), Vec::new());
            for &p in chosen {
                let (wi, wo) = pairs[p];
                three.extend(of(&truth_at, p));
                built.extend(of(&truth_built, p));
                let v = regions.views[p % regions.views.len()];
                let mut q = pair_queries(as_built[p].0, as_built[p].1);
                // The virtual camera's direction from each point.
                let c = truth.mirrors[v].reflect_point(DVec3::from(truth.camera.position_mm));
                for q in &mut q {
                    q.wo = world_to_sample((c - truth.sample_point(q.uv)).normalize()).to_array();
                }
                per_point.extend(hil_sim::truth::answer(&sample, &q));
                dense.extend(tests::dense_cell_answers(&sample, wi, wo, 12));
            }
            // Against the whole set's peak, so that one pair's figures compare.
            let db = |a: &[[f32; 3]], b: &[[f32; 3]]| {
                let e = tests::PairErrors::new(a, b).mse;
                errors.db(e.iter().sum::<f64>() / e.len() as f64)
            };
            (db(&dense, &three), db(&built, &three), db(&per_point, &built))
        };
        let every_17th: Vec<usize> = (0..pairs.len()).step_by(17).collect();
        let (limit, direction_limit, viewer_limit) = limits(&every_17th);
        let (at_built, _, _) = tests::regions_psnr(&as_built, &truth_built, &regions);
        println!(
            "| {m} | {t_reg:.1} | {psnr:.2} | {gain_free:.2} | {gain:.4} | {limit:.2} | \
             {direction_limit:.2} | {viewer_limit:.2} | {at_built:.2} | {:.0} % | {without:.2} |",
            100.0 * share
        );
        // The same limits on the worst 5 % of the pairs, beside the region
        // images' own error there: where the error concentrates (a glossy
        // sample's highlight pairs), every 17th pair may hold none of them.
        let top: Vec<usize> = {
            let order = errors.worst_first();
            let k = ((order.len() as f64 * 0.05).round() as usize).clamp(1, order.len());
            order[..k].to_vec()
        };
        let (tl, td, tv) = limits(&top);
        let top_db = errors.db(top.iter().map(|&p| errors.mse[p]).sum::<f64>() / top.len() as f64);
        worst_lines.push(format!(
            "{m}: the worst 5 % ({} pairs): {top_db:.2} dB; their point-sampling limit {tl:.2} dB, \
             nominal-direction limit {td:.2} dB, distant-viewer limit {tv:.2} dB",
            top.len()
        ));
        let (wl, wd, wv) = limits(&[worst]);
        let (wi, wo) = pairs[worst];
        let mirror_angle = (-wi[0] * wo[0] - wi[1] * wo[1] + wi[2] * wo[2]).clamp(-1.0, 1.0);
        let at_built_worst = {
            let q = pair_queries(as_built[worst].0, as_built[worst].1);
            let est = tests::region_pair_answers(&regions, worst, &q);
            errors.db(tests::PairErrors::new(&est, &of(&truth_built, worst)).mse[0])
        };
        worst_lines.push(format!(
            "{m}: worst pair light {} view {} (θi {:.0}°, θo {:.0}°, {:.1}° from the mirror direction): \
             {:.2} dB; its point-sampling limit {wl:.2} dB, nominal-direction limit {wd:.2} dB, \
             distant-viewer limit {wv:.2} dB, at the as-built directions {at_built_worst:.2} dB",
            regions.lights[worst / regions.views.len()],
            regions.views[worst % regions.views.len()],
            wi[2].acos().to_degrees(),
            wo[2].acos().to_degrees(),
            mirror_angle.acos().to_degrees(),
            errors.db(errors.mse[worst]),
        ));
    }
    for l in worst_lines {
        println!("{l}");
    }
}
