//! End-to-end tests across firmware, simulator and host live in `tests/tests/`;
//! this library holds what they share with the long-running examples.

use std::path::Path;

use hil_sim::materials::Sample;
use host::build::Calibration;
use host::build::RegionSet;
use host::build::fidelity::{material_psnr, pair_queries};
use host::camera::SimCamera;
use host::link::{Device, SimTransport};
use host::scan::{Quiet, ScanOptions, scan};
use host::simulator::SimSetup;
use rand::{Rng, SeedableRng};
use scanner_formats::queries::Query;
use scanner_geometry::{AxisValues, DVec3, ScannerGeometry, world_to_sample};
use scanner_shading::Material;

/// The value after `--name` on the command line, or `default` (the
/// examples' options).
pub fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Scan `material` on the simulator into `out` (HDR if asked), unless a
/// complete scan is there already; returns the nominal geometry.
pub fn sim_scan(
    material: &str,
    seed: u64,
    bin: u32,
    mirrors: usize,
    hdr: bool,
    out: &Path,
) -> ScannerGeometry {
    let s = SimSetup { bin, seed, ..SimSetup::new(material) };
    let nominal = s.nominal().expect("the simulator's geometry");
    if host::scan::Manifest::load(out).is_ok_and(|m| m.complete) {
        return nominal;
    }
    let rig = s.rig().expect("a simulated scanner");
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).expect("connected");
    let mut opts = ScanOptions::new(material, out);
    opts.mirrors = Some(mirrors);
    opts.resume = true;
    if hdr {
        opts.bracket_us = host::hdr::default_bracket(opts.exposure_us);
    }
    scan(&mut dev, &mut SimCamera(rig), &nominal, &opts, &mut Quiet).expect("a clean scan");
    nominal
}

/// The captured pairs as the as-built scanner `truth` took them, in the
/// order of `regions` (light-major): (wi, wo), sample-local.
pub fn as_built_pairs(
    truth: &ScannerGeometry,
    cal: &Calibration,
    regions: &RegionSet,
) -> Vec<([f64; 3], [f64; 3])> {
    let mut out = Vec::new();
    for &l in &regions.lights {
        let lc = cal.lights.iter().find(|c| c.light == l).expect("a calibrated light");
        let beam = truth.beam(AxisValues::from_array(lc.axes));
        let n = DVec3::from(truth.mirrors[l].normal).normalize();
        let wi = world_to_sample(-(beam.dir - 2.0 * beam.dir.dot(n) * n)).normalize();
        for &v in &regions.views {
            let c = truth.mirrors[v].reflect_point(DVec3::from(truth.camera.position_mm));
            let wo = world_to_sample(c.normalize()).normalize();
            out.push((wi.to_array(), wo.to_array()));
        }
    }
    out
}

/// `n` random pairs of directions within `max_theta_deg` of the normal,
/// uniform in solid angle, seeded.
pub fn random_pairs(n: usize, max_theta_deg: f64, seed: u64) -> Vec<([f64; 3], [f64; 3])> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let cos_max = max_theta_deg.to_radians().cos();
    let mut dir = || {
        let z = 1.0 - rng.random::<f64>() * (1.0 - cos_max);
        let p = rng.random::<f64>() * std::f64::consts::TAU;
        let r = (1.0 - z * z).max(0.0).sqrt();
        [r * p.cos(), r * p.sin(), z]
    };
    (0..n).map(|_| (dir(), dir())).collect()
}

/// The ground truth of `sample` at every [`pair_queries`] of `pairs`.
pub fn truth_answers(pairs: &[([f64; 3], [f64; 3])], sample: &Sample) -> Vec<[f32; 3]> {
    pairs
        .iter()
        .flat_map(|&(wi, wo)| hil_sim::truth::answer(sample, &pair_queries(wi, wo)))
        .collect()
}

/// Answers to one pair's queries, given the pair's index.
pub type Estimate<'a> = dyn Fn(usize, &[Query]) -> Vec<[f32; 3]> + Sync + 'a;

/// Material PSNR (PSNR, gain-free, gain) of `estimate`'s answers (given
/// the pair's index and its queries) against `truth` ([`truth_answers`]).
pub fn pairs_psnr(
    pairs: &[([f64; 3], [f64; 3])],
    truth: &[[f32; 3]],
    estimate: &Estimate<'_>,
) -> (f64, f64, f64) {
    use rayon::prelude::*;
    let est: Vec<[f32; 3]> = pairs
        .par_iter()
        .enumerate()
        .flat_map_iter(|(p, &(wi, wo))| estimate(p, &pair_queries(wi, wo)))
        .collect();
    material_psnr(&est, truth)
}

/// A material's answers to queries.
pub fn shade(m: &Material, q: &[Query]) -> Vec<[f32; 3]> {
    let f = |d: [f64; 3]| d.map(|x| x as f32);
    q.iter().map(|q| m.eval(q.uv.map(|x| x as f32), f(q.wi), f(q.wo))).collect()
}

/// Material PSNR of `regions` against the ground truth of `sample` at the
/// captured pairs (the nominal mirror directions): (PSNR, gain-free PSNR,
/// gain).
pub fn captured_pair_psnr(
    g: &ScannerGeometry,
    regions: &RegionSet,
    sample: &Sample,
) -> (f64, f64, f64) {
    let (mut est, mut tru) = (Vec::new(), Vec::new());
    for (li, &l) in regions.lights.iter().enumerate() {
        for (vi, &v) in regions.views.iter().enumerate() {
            let q = pair_queries(
                g.light_direction(l).expect("a reachable mirror").to_array(),
                g.mirror_direction(v).expect("a mirror").to_array(),
            );
            tru.extend(hil_sim::truth::answer(sample, &q));
            est.extend(q.iter().map(|q| regions.sample(li, vi, q.uv).map(|x| x as f32)));
        }
    }
    material_psnr(&est, &tru)
}

/// Angles (degrees) between a calibration's directions and the as-built
/// scanner's, beside those of the nominal geometry alone.
#[derive(Debug, Clone, Default)]
pub struct DirectionErrors {
    /// Per view, calibrated.
    pub view: Vec<f64>,
    /// Per view, nominal (towards the mirror's centre).
    pub view_nominal: Vec<f64>,
    /// Per light, calibrated.
    pub light: Vec<f64>,
    /// Per light, nominal (towards where the inverse kinematics' beam meets the mirror).
    pub light_nominal: Vec<f64>,
}

/// The direction errors of `cal` (made with nominal geometry `g`) against
/// the as-built scanner `truth`: views towards the camera mirrored in the
/// as-built mirror, lights along the as-built beam at the commanded axes.
pub fn direction_errors(
    g: &ScannerGeometry,
    truth: &ScannerGeometry,
    cal: &Calibration,
) -> DirectionErrors {
    let mut e = DirectionErrors::default();
    for v in &cal.views {
        let c = truth.mirrors[v.view].reflect_point(DVec3::from(truth.camera.position_mm));
        let t = world_to_sample(c.normalize());
        e.view.push(DVec3::from(v.direction).angle_between(t).to_degrees());
        e.view_nominal
            .push(g.mirror_direction(v.view).expect("a mirror").angle_between(t).to_degrees());
    }
    for l in &cal.lights {
        let beam = truth.beam(AxisValues::from_array(l.axes));
        let n = DVec3::from(truth.mirrors[l.light].normal).normalize();
        let t = world_to_sample(-(beam.dir - 2.0 * beam.dir.dot(n) * n));
        e.light.push(DVec3::from(l.direction).angle_between(t).to_degrees());
        e.light_nominal.push(
            g.light_direction(l.light).expect("a reachable mirror").angle_between(t).to_degrees(),
        );
    }
    e
}
