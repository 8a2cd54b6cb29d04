//! Geometry calibration against the simulator's as-built truth: on three
//! as-built scanners, every view's corners within 0.25 px RMS by both the
//! patent's Fourier phase alignment and the inner-corner homography, from
//! the default 4096² sensor (errors of the nominal geometry reported).

use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, Sample};
use hil_sim::optics::{Exposure, OpticalSim};
use host::build::linalg::Homography;
use host::build::locate::{Checkerboard, locate, nominal_homography};
use host::build::plane::Plane;

/// Sum of the luminance of the checkerboard frames lit by `lights`.
fn checker_sum(sim: &OpticalSim, nominal: &ScannerGeometry, lights: &[usize]) -> Plane {
    let cam = &nominal.camera;
    let mut sum = Plane::new(cam.width as usize, cam.height as usize);
    for &l in lights {
        let axes = nominal.mirror_axes(l).unwrap();
        let f = sim.render(&Exposure { axes, exposure_s: 0.05, light: 1.0 });
        for (i, px) in f.rgb.chunks_exact(3).enumerate() {
            sum.data[i] += (px[0] + px[1] + px[2]) / 3.0;
        }
    }
    sum
}

/// The as-built scanner of `seed` and its checkerboard frames' sum, lit
/// through mirrors 0–3.
fn as_built_checker(nominal: &ScannerGeometry, seed: u64) -> (ScannerGeometry, Plane) {
    let checker = Sample::small(materials::by_name("checkerboard").unwrap());
    let sim = OpticalSim::as_built(nominal, checker, seed);
    let sum = checker_sum(&sim, nominal, &[0, 1, 2, 3]);
    (sim.geometry().clone(), sum)
}

fn corner_errors(h: &Homography, truth: &ScannerGeometry, l: usize) -> Vec<f64> {
    [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
        .iter()
        .map(|&uv| {
            let t = truth.view_point(l, uv).unwrap();
            let p = h.apply(uv);
            (p[0] - t[0]).hypot(p[1] - t[1])
        })
        .collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

#[test]
fn regions_are_located_against_the_as_built_truth() {
    let nominal = ScannerGeometry::default_scanner();
    let target = Checkerboard::default();
    for seed in [1u64, 2, 3] {
        let (truth, sum) = as_built_checker(&nominal, seed);
        let (mut e_nom, mut e_phase, mut e_corner) = (Vec::new(), Vec::new(), Vec::new());
        let (mut e_fit, mut chose_phase) = (Vec::new(), 0);
        for l in 0..nominal.mirrors.len() {
            let fit = locate(&nominal, l, &sum, &target).unwrap();
            e_nom.extend(corner_errors(&nominal_homography(&nominal, l).unwrap(), &truth, l));
            e_phase.extend(corner_errors(&fit.phase, &truth, l));
            e_corner.extend(corner_errors(&fit.best(), &truth, l));
            e_fit.extend(corner_errors(&fit.corners.unwrap_or(fit.phase), &truth, l));
            chose_phase += usize::from(fit.corners.is_some() && !fit.by_corners);
            if corner_errors(&fit.best(), &truth, l).iter().any(|&e| e > 0.5) {
                eprintln!(
                    "seed {seed} view {l}: corners {} rms {:.3} errs {:?}",
                    fit.corners_used,
                    fit.corner_rms_px,
                    corner_errors(&fit.best(), &truth, l)
                );
            }
        }
        eprintln!(
            "seed {seed}: corner RMS nominal {:.2} px, phase {:.3} px, corner homography {:.3} px, \
             the better of the two {:.3} px (the phase alignment's at {chose_phase} of 40 views)",
            rms(&e_nom),
            rms(&e_phase),
            rms(&e_fit),
            rms(&e_corner)
        );
        assert!(rms(&e_nom) > 5.0, "the as-built errors are real");
        assert!(rms(&e_phase) < 0.25, "phase: {}", rms(&e_phase));
        assert!(rms(&e_fit) < 0.25, "corners: {}", rms(&e_fit));
        assert!(rms(&e_corner) < 0.25, "the better of the two: {}", rms(&e_corner));
    }
}

/// On a coarse sensor the checker's squares span a few pixels and the
/// corner fit loses its precision first: where it explains the pixels
/// worse than the phase alignment, the phase alignment is taken.
#[test]
fn on_a_coarse_sensor_the_better_of_the_two_estimates_is_taken() {
    let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(4);
    let target = Checkerboard::default();
    let (mut e_fit, mut e_best, mut chose_phase) = (Vec::new(), Vec::new(), 0);
    for seed in [1u64, 2, 3] {
        let (truth, sum) = as_built_checker(&nominal, seed);
        for l in 0..nominal.mirrors.len() {
            let fit = locate(&nominal, l, &sum, &target).unwrap();
            if let Some(c) = fit.corners {
                e_fit.extend(corner_errors(&c, &truth, l));
                e_best.extend(corner_errors(&fit.best(), &truth, l));
                chose_phase += usize::from(!fit.by_corners);
            }
        }
    }
    eprintln!(
        "1024² sensor, the {} views with a corner fit (3 seeds): corner fit {:.3} px RMS, the \
         better of the two {:.3} px (the phase alignment's at {chose_phase})",
        e_fit.len() / 4,
        rms(&e_fit),
        rms(&e_best)
    );
    assert!(rms(&e_best) < 0.85 * rms(&e_fit), "{} against {}", rms(&e_best), rms(&e_fit));
}

/// How far each side of the sample lies inside the edge `h` puts it, px:
/// per side (v 0, u 1, v 1, u 0) the mean over 9 points along it of the
/// true point's distance inside the line through `h`'s corners.
fn edge_offsets(h: &Homography, truth: &ScannerGeometry, l: usize) -> [f64; 4] {
    let ends = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let centre = h.apply([0.5, 0.5]);
    std::array::from_fn(|k| {
        let (a, b) = (ends[k], ends[(k + 1) % 4]);
        let (p, q) = (h.apply(a), h.apply(b));
        let len = (q[0] - p[0]).hypot(q[1] - p[1]);
        // Unit normal of the side, pointing into the sample.
        let mut n = [-(q[1] - p[1]) / len, (q[0] - p[0]) / len];
        if n[0] * (centre[0] - p[0]) + n[1] * (centre[1] - p[1]) < 0.0 {
            n = [-n[0], -n[1]];
        }
        (1..10)
            .map(|i| {
                let t = i as f64 / 10.0;
                let uv = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
                let x = truth.view_point(l, uv).unwrap();
                n[0] * (x[0] - p[0]) + n[1] * (x[1] - p[1])
            })
            .sum::<f64>()
            / 9.0
    })
}

/// The phase alignment's residual ranks the views by how precisely their
/// edges are placed: on a 1024² sensor (three as-built scanners), the
/// views whose residual is at most `EDGE_PRECISE_PX` — those the region
/// images read straddling pixels in by default — have their edges within
/// a third of the others' RMS error, and to ≈ 0.01 px.
#[test]
fn the_phase_residual_picks_the_views_whose_edges_are_precise() {
    use host::build::calibrate::EDGE_PRECISE_PX;
    let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(4);
    let target = Checkerboard::default();
    let (mut precise, mut others) = (Vec::new(), Vec::new());
    for seed in [1u64, 2, 3] {
        let (truth, sum) = as_built_checker(&nominal, seed);
        for l in 0..nominal.mirrors.len() {
            let fit = locate(&nominal, l, &sum, &target).unwrap();
            assert!(fit.phase_rms_px.is_finite() && fit.phase_rms_px >= 0.0);
            let e = edge_offsets(&fit.best(), &truth, l);
            if fit.phase_rms_px <= EDGE_PRECISE_PX { &mut precise } else { &mut others }.extend(e);
        }
    }
    eprintln!(
        "1024² sensor, 3 seeds: {} views with a phase residual ≤ {EDGE_PRECISE_PX} px, their edges \
         {:.4} px RMS; the other {} views' {:.4} px",
        precise.len() / 4,
        rms(&precise),
        others.len() / 4,
        rms(&others)
    );
    assert!(precise.len() >= 4 * 12, "{} precise views of 120", precise.len() / 4);
    assert!(rms(&precise) < rms(&others) / 3.0, "{} against {}", rms(&precise), rms(&others));
    assert!(rms(&precise) < 0.015, "{}", rms(&precise));
}
