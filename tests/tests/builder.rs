//! Material builder I end to end on the simulator: three scans →
//! calibration → region images, scored against the ground truth.

use std::path::Path;

use hil_sim::materials::{Sample, lookup};
use hil_sim::optics::OpticalSim;
use host::build::calibrate::{CalibrateOptions, Silent};
use host::build::fidelity::{material_psnr, pair_queries};
use host::build::scanread::ScanFrames;
use host::build::{calibrate, extract_regions};
use host::camera::SimCamera;
use host::link::{Device, SimTransport};
use host::scan::{Quiet, ScanOptions, scan};
use host::simulator::SimSetup;
use scanner_geometry::ScannerGeometry;

fn take_scan(material: &str, seed: u64, bin: u32, mirrors: usize, out: &Path) -> ScannerGeometry {
    let s = SimSetup { bin, seed, ..SimSetup::new(material) };
    let rig = s.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let mut opts = ScanOptions::new(material, out);
    opts.mirrors = Some(mirrors);
    let nominal = s.nominal().unwrap();
    scan(&mut dev, &mut SimCamera(rig), &nominal, &opts, &mut Quiet).unwrap();
    nominal
}

#[test]
fn region_images_match_the_ground_truth() {
    let bin: u32 = std::env::var("BUILDER_BIN").ok().and_then(|v| v.parse().ok()).unwrap_or(2);
    let mirrors = 8;
    let seed = 5;
    let dir = tempfile::tempdir().unwrap();
    let g = take_scan("checkerboard", seed, bin, mirrors, &dir.path().join("checker"));
    take_scan("diffuse-white", seed, bin, mirrors, &dir.path().join("white"));
    let checker = ScanFrames::open(&dir.path().join("checker"), &g).unwrap();
    let white = ScanFrames::open(&dir.path().join("white"), &g).unwrap();
    let cal = calibrate(&g, &checker, &white, &CalibrateOptions::default(), &Silent).unwrap();
    // Truth for directions.
    let sim = OpticalSim::as_built(&g, Sample::small(lookup("checkerboard").unwrap()), seed);
    let truth = sim.geometry();
    let mut view_err = Vec::new();
    let mut nominal_view_err = Vec::new();
    for v in &cal.views {
        let m = &truth.mirrors[v.view];
        let c = m.reflect_point(scanner_geometry::DVec3::from(truth.camera.position_mm));
        let t = scanner_geometry::world_to_sample(c.normalize());
        let d = scanner_geometry::DVec3::from(v.direction);
        view_err.push(d.angle_between(t).to_degrees());
        nominal_view_err.push(g.mirror_direction(v.view).unwrap().angle_between(t).to_degrees());
    }
    eprintln!("view dir error: max {:.3}°, nominal max {:.3}°", view_err.iter().cloned().fold(0.0, f64::max), nominal_view_err.iter().cloned().fold(0.0, f64::max));
    for material in ["woven-fabric", "leather", "painted-wood", "rough-metal", "diffuse-white"] {
        let out = dir.path().join(material);
        take_scan(material, seed, bin, mirrors, &out);
        let scan = ScanFrames::open(&out, &g).unwrap();
        let regions = extract_regions(&g, &cal, &scan, None, &Silent).unwrap();
        let sample = Sample::small(lookup(material).unwrap());
        let mut est = Vec::new();
        let mut tru = Vec::new();
        for (li, &l) in regions.lights.iter().enumerate() {
            for (vi, &v) in regions.views.iter().enumerate() {
                let q = pair_queries(g.light_direction(l).unwrap().to_array(), g.mirror_direction(v).unwrap().to_array());
                tru.extend(hil_sim::truth::answer(&sample, &q));
                est.extend(q.iter().map(|q| regions.sample(li, vi, q.uv).map(|x| x as f32)));
            }
        }
        let (psnr, gain_free, gain) = material_psnr(&est, &tru);
        eprintln!("{material}: S = {}, PSNR {psnr:.2} dB, gain-free {gain_free:.2} dB (gain {gain:.4})", regions.size);
    }
}

/// How far the metric's own 3 × 3 point sampling of a cell is from the
/// cell's area mean, per material (the limit of any camera-based estimate,
/// which integrates over pixels).
#[test]
fn point_sampling_limit_of_the_metric() {
    let g = ScannerGeometry::default_scanner();
    for material in ["woven-fabric", "leather", "painted-wood", "rough-metal"] {
        let sample = Sample::small(lookup(material).unwrap());
        let mut three = Vec::new();
        let mut dense = Vec::new();
        for l in 0..8 {
            for v in 0..40 {
                let (li, vi) = (g.light_direction(l).unwrap().to_array(), g.mirror_direction(v).unwrap().to_array());
                let q = pair_queries(li, vi);
                three.extend(hil_sim::truth::answer(&sample, &q));
                // 12 × 12 points per cell, averaged down to the 3 × 3 layout.
                let n = 12;
                let fine: Vec<scanner_formats::queries::Query> = q
                    .chunks(9)
                    .enumerate()
                    .flat_map(|(c, _)| {
                        let (i, k) = (c % 32, c / 32);
                        (0..n * n).map(move |s| scanner_formats::queries::Query {
                            uv: [(i as f64 + ((s % n) as f64 + 0.5) / n as f64) / 32.0, (k as f64 + ((s / n) as f64 + 0.5) / n as f64) / 32.0],
                            wi: li,
                            wo: vi,
                        })
                    })
                    .collect();
                let a = hil_sim::truth::answer(&sample, &fine);
                for cell in a.chunks(n * n) {
                    let mut m = [0.0f32; 3];
                    for x in cell {
                        for k in 0..3 {
                            m[k] += x[k] / (n * n) as f32;
                        }
                    }
                    dense.extend(std::iter::repeat_n(m, 9));
                }
            }
        }
        let (psnr, _, _) = material_psnr(&dense, &three);
        eprintln!("{material}: area mean vs 3 × 3 points: {psnr:.2} dB");
    }
}
