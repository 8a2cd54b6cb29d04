//! End-to-end tests across firmware, simulator and host live in `tests/tests/`;
//! this library holds what they share with the long-running examples.

use std::path::{Path, PathBuf};

use hil_sim::materials::Sample;
use host::build::Calibration;
use host::build::fidelity::{CELLS, cell_means, material_psnr, pair_queries};
use host::build::height::SampleHeight;
use host::build::regions::{EdgePixels, SampleSides};
use host::build::superres::SharpenOptions;
use host::build::{RegionOptions, RegionSet};
use host::camera::SimCamera;
use host::link::{Device, SimTransport};
use host::scan::{Quiet, ScanOptions, scan};
use host::simulator::SimSetup;
use rand::{Rng, SeedableRng};
use scanner_formats::queries::Query;
use scanner_geometry::{AxisValues, DVec3, SampleFace, ScannerGeometry, world_to_sample};

/// The value after `--name` on the command line, or `default` (the
/// examples' options). A value that does not parse ends the example with
/// status 2, naming it, rather than running with the default.
pub fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    let args: Vec<String> = std::env::args().collect();
    let Some(i) = args.iter().position(|a| a == name) else {
        return default;
    };
    let Some(v) = args.get(i + 1) else {
        usage_error(&format!("{name} needs a value"));
    };
    v.parse().unwrap_or_else(|_| usage_error(&format!("{name} {v:?}: not a valid value")))
}

/// The options [`region_options`] reads.
const SIZE: &str = "--size";
const DETAIL: &str = "--detail";
const EDGE: &str = "--edge-pixels";
/// The simulated samples' face above the holder's plane, mm (the targets
/// stay in it): [`sim_scan_at`].
const SAMPLE_HEIGHT: &str = "--sample-height";
/// Where the builder reads the sample's face: `auto` (measured) or mm.
const HEIGHT: &str = "--height";
/// The simulated samples' face tilted, degrees along u and v: `U,V`.
const SAMPLE_TILT: &str = "--sample-tilt";
/// The simulated samples' thickness, mm: their sides show below the face.
const SAMPLE_THICKNESS: &str = "--sample-thickness";
/// The simulated holder's albedo around every scan's sample, the targets'
/// too (default 0: black).
const HOLDER_ALBEDO: &str = "--holder-albedo";
/// The simulated board's fold-mirror home position this many steps off
/// the default axes' (every scan, the targets' too): its beams land off
/// their mirrors' centres and leave part of the sample unlit.
const TILT_HOME_STEPS: &str = "--tilt-home-steps";
/// Whether the builder reads the sample's sides as shown: `auto`
/// (default), `hidden` or `shown`.
const SIDES: &str = "--sides";
const REGION_OPTIONS: [&str; 11] = [
    SIZE,
    DETAIL,
    EDGE,
    SAMPLE_HEIGHT,
    SAMPLE_TILT,
    SAMPLE_THICKNESS,
    HOLDER_ALBEDO,
    TILT_HOME_STEPS,
    HEIGHT,
    TILT,
    SIDES,
];

/// With a given `--height MM`: the face's tilt the builder reads it at,
/// `U,V` degrees.
const TILT: &str = "--tilt";

/// `--sample-tilt U,V` (degrees; default level).
fn sample_tilt() -> [f64; 2] {
    degrees_pair(SAMPLE_TILT)
}

/// Option `name`'s `U,V` in degrees (default 0, 0).
fn degrees_pair(name: &str) -> [f64; 2] {
    let s = arg(name, "0,0".to_string());
    let t: Vec<f64> = s.split(',').filter_map(|x| x.trim().parse().ok()).collect();
    match t[..] {
        [u, v] if u.is_finite() && v.is_finite() => [u, v],
        _ => usage_error(&format!("{name} {s:?}: two numbers, degrees along u and v")),
    }
}

/// The calibration targets, which lie in the holder's plane.
const TARGETS: [&str; 3] = ["checkerboard", "diffuse-white", "glossy-black"];

/// [`check_args`] for an example that also reads [`region_options`]; their
/// values are checked here too, before the run starts.
pub fn check_region_args(values: &[&str], flags: &[&str]) {
    check_args(&[values, &REGION_OPTIONS].concat(), flags);
    region_options();
    sample_tilt();
}

/// Checks an example's command line before it starts a long run: every
/// argument is one of `values` followed by its value, or one of `flags`.
/// Anything else (a mistyped option) ends it with status 2, naming the
/// argument; `--help` prints the options.
pub fn check_args(values: &[&str], flags: &[&str]) {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args_problem(&args, values, flags) {
        Ok(None) => {}
        Ok(Some(options)) => {
            println!("{options}");
            std::process::exit(0);
        }
        Err(message) => usage_error(&message),
    }
}

/// [`check_args`] on `args`: `Ok(None)` when they are right,
/// `Ok(Some(options))` when they ask for help, the problem otherwise.
fn args_problem(
    args: &[String],
    values: &[&str],
    flags: &[&str],
) -> Result<Option<String>, String> {
    let options = format!("options: {} (each with a value); {}", values.join(" "), flags.join(" "));
    let mut i = 0;
    while i < args.len() {
        let a = args[i].as_str();
        if a == "--help" || a == "-h" {
            return Ok(Some(options));
        } else if values.contains(&a) {
            if i + 1 == args.len() {
                return Err(format!("{a} needs a value"));
            }
            i += 2;
        } else if flags.contains(&a) {
            i += 1;
        } else {
            return Err(format!("unknown argument {a:?}; {options}"));
        }
    }
    Ok(None)
}

/// Ends an example whose command line is wrong: the message, status 2.
fn usage_error(message: &str) -> ! {
    eprintln!("error: {message}");
    std::process::exit(2);
}

/// The examples' region options: `--detail all-views|own-view` (default
/// all-views) and `--size S` (default 0: the builder's choice).
pub fn region_options() -> RegionOptions {
    let size: usize = arg(SIZE, 0);
    let sharpen = match arg(DETAIL, "all-views".to_string()).as_str() {
        "all-views" => Some(SharpenOptions::default()),
        "own-view" => None,
        other => usage_error(&format!("{DETAIL} {other:?}: all-views or own-view")),
    };
    let edge = match arg(EDGE, "precise".to_string()).as_str() {
        "inside" => EdgePixels::Inside,
        "straddling" => EdgePixels::Straddling,
        "precise" => EdgePixels::Precise,
        other => usage_error(&format!("{EDGE} {other:?}: precise, inside or straddling")),
    };
    let height = match arg(HEIGHT, "auto".to_string()).as_str() {
        "auto" => SampleHeight::Measure,
        mm => SampleHeight::Given(SampleFace {
            height_mm: mm.parse().unwrap_or_else(|_| {
                usage_error(&format!("{HEIGHT} {mm:?}: auto or a height in mm"))
            }),
            slope: scanner_geometry::face::slopes_of(degrees_pair(TILT)),
        }),
    };
    let sides = match arg(SIDES, "auto".to_string()).as_str() {
        "auto" => SampleSides::Auto,
        "hidden" => SampleSides::Hidden,
        "shown" => SampleSides::Shown,
        other => usage_error(&format!("{SIDES} {other:?}: auto, hidden or shown")),
    };
    RegionOptions { size: (size > 0).then_some(size), sharpen, edge, height, sides }
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
    sim_scan_at(material, seed, bin, mirrors, protocol::DEFAULT_EXPOSURE_US, hdr, out)
}

/// The exposure of the glossy target's scans, µs (its highlight flanks
/// stay below full scale).
pub const GLOSSY_EXPOSURE_US: u32 = 2_000;

/// [`sim_scan`] at exposure `exposure_us`; with `hdr`, auto exposure's
/// metered bracket (as `scanner demo` scans its sample), metered at
/// `exposure_us`. A sample other than the targets stands `--sample-height`
/// mm proud of the holder's plane if the command line says so.
pub fn sim_scan_at(
    material: &str,
    seed: u64,
    bin: u32,
    mirrors: usize,
    exposure_us: u32,
    hdr: bool,
    out: &Path,
) -> ScannerGeometry {
    let target = TARGETS.contains(&material);
    let sample_height_mm = if target { 0.0 } else { arg(SAMPLE_HEIGHT, 0.0) };
    let sample_tilt_deg = if target { [0.0; 2] } else { sample_tilt() };
    let sample_thickness_mm = if target { 0.0 } else { arg(SAMPLE_THICKNESS, 0.0) };
    let s = SimSetup {
        bin,
        seed,
        sample_height_mm,
        sample_tilt_deg,
        sample_thickness_mm,
        holder_albedo: arg(HOLDER_ALBEDO, 0.0),
        lens_distortion: [arg("--lens-k1", 0.0), 0.0],
        board_axes: match arg(TILT_HOME_STEPS, 0i32) {
            0 => None,
            steps => {
                let mut axes = protocol::default_axes();
                axes[2].homing.home_position += steps;
                Some(axes)
            }
        },
        ..SimSetup::new(material)
    };
    let nominal = s.nominal().expect("the simulator's geometry");
    // A complete scan of this very simulated scanner is reused; another's
    // (another seed, say) is refused by the resume below.
    let simulator = s.describe();
    if let Ok(m) = host::scan::Manifest::load(out) {
        let theirs = m.settings.simulator.as_deref().unwrap_or("no simulator recorded");
        assert!(
            theirs == simulator,
            "{}: a scan of another simulated scanner ({theirs}; this is {simulator}): delete it \
             or choose another --out",
            out.display()
        );
        if m.complete {
            return nominal;
        }
    }
    let rig = s.rig().expect("a simulated scanner");
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).expect("connected");
    let mut opts = ScanOptions::new(material, out);
    opts.mirrors = Some(mirrors);
    opts.exposure_us = exposure_us;
    opts.resume = true;
    opts.simulator = Some(simulator);
    if hdr {
        opts.auto_exposure = Some(host::scan::AutoExposure::Hdr);
    }
    scan(&mut dev, &mut SimCamera(rig), &nominal, &opts, &mut Quiet).expect("a clean scan");
    nominal
}

/// The examples' common start: the three targets scanned into `out` (the
/// glossy one at [`GLOSSY_EXPOSURE_US`]) and each of `materials` with auto
/// HDR (scans already complete are kept), then calibrated with the glossy
/// target. Returns the nominal geometry, the calibration and the as-built
/// geometry (the truth the simulator scanned with).
pub fn scanned_and_calibrated(
    out: &Path,
    seed: u64,
    bin: u32,
    mirrors: usize,
    materials: &[&str],
) -> (ScannerGeometry, Calibration, ScannerGeometry) {
    use host::build::calibrate::{CalibrateOptions, Silent, calibrate};
    use host::build::scanread::ScanFrames;
    let g = sim_scan("checkerboard", seed, bin, mirrors, false, &out.join("checkerboard"));
    sim_scan("diffuse-white", seed, bin, mirrors, false, &out.join("diffuse-white"));
    let glossy = out.join("glossy-black");
    sim_scan_at("glossy-black", seed, bin, mirrors, GLOSSY_EXPOSURE_US, false, &glossy);
    for &m in materials {
        sim_scan(m, seed, bin, mirrors, true, &scan_dir(out, m));
    }
    let open = |name: &str| ScanFrames::open(&out.join(name), &g).unwrap();
    let (checker, white, glossy) =
        (open("checkerboard"), open("diffuse-white"), open("glossy-black"));
    let opts = CalibrateOptions::default();
    let cal = calibrate(&g, &checker, &white, Some(&glossy), &opts, &Silent).unwrap();
    let target = hil_sim::materials::lookup("checkerboard").unwrap();
    let truth =
        hil_sim::optics::OpticalSim::as_built(&g, Sample::small(target), seed).geometry().clone();
    (g, cal, truth)
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
    random_pairs_between(n, [0.0, max_theta_deg], [0.0, max_theta_deg], seed)
}

/// `n` random pairs of directions, the light's between `light_deg[0]` and
/// `light_deg[1]` from the normal and the view's within `view_deg`, each
/// uniform in solid angle over its band, seeded.
pub fn random_pairs_between(
    n: usize,
    light_deg: [f64; 2],
    view_deg: [f64; 2],
    seed: u64,
) -> Vec<([f64; 3], [f64; 3])> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut dir = |band: [f64; 2]| {
        let [c0, c1] = band.map(|t: f64| t.to_radians().cos());
        let z = c0 - rng.random::<f64>() * (c0 - c1);
        let p = rng.random::<f64>() * std::f64::consts::TAU;
        let r = (1.0 - z * z).max(0.0).sqrt();
        [r * p.cos(), r * p.sin(), z]
    };
    (0..n).map(|_| (dir(light_deg), dir(view_deg))).collect()
}

/// The ground truth of `sample` at every [`pair_queries`] of `pairs`.
pub fn truth_answers(pairs: &[([f64; 3], [f64; 3])], sample: &Sample) -> Vec<[f32; 3]> {
    pairs
        .iter()
        .flat_map(|&(wi, wo)| hil_sim::truth::answer(sample, &pair_queries(wi, wo)))
        .collect()
}

/// The region images of material `m`'s scan under `out` ([`scan_dir`]),
/// with the examples' [`region_options`].
pub fn scanned_regions(out: &Path, g: &ScannerGeometry, cal: &Calibration, m: &str) -> RegionSet {
    let scan = host::build::scanread::ScanFrames::open(&scan_dir(out, m), g).unwrap();
    let regions = host::build::extract_regions(
        g,
        cal,
        &scan,
        &region_options(),
        &host::build::calibrate::Silent,
    )
    .unwrap();
    print!("{}", face_report(m, &regions));
    regions
}

/// What the builder measured of `m`'s face in `regions` (height, tilt, the
/// cue, the band beyond the edges, the outline), a line each; empty for
/// a face given.
pub fn face_report(m: &str, regions: &RegionSet) -> String {
    use std::fmt::Write;
    let mut r = String::new();
    if let Some(f) = regions.height_fit {
        let deg = scanner_geometry::face::angles_of;
        writeln!(
            r,
            "{m}: face measured {:.4} ± {:.4} mm above the holder's plane ({:.2} px/mm of \
             parallax, agreement {:.3}), tilted {:.3?}° ± {:.3?}° ({} patches, {:.4} mm from a \
             plane, {:.2} px at the corners); read at {:?}",
            f.height_mm,
            f.sigma_mm,
            f.parallax_px_per_mm,
            f.agreement,
            deg(f.slope),
            deg(f.slope_sigma),
            f.patches,
            f.flatness_mm,
            f.tilt_px,
            regions.face
        )
        .unwrap();
        writeln!(
            r,
            "{m}: the face's cue {}{}; beyond the edges {:?}",
            f.cue.name(),
            if f.thin_sides {
                " (its disagreement with the outline told as thin sides)"
            } else {
                ""
            },
            f.beyond
        )
        .unwrap();
        if let Some(o) = f.outline {
            writeln!(
                r,
                "{m}: outline {:.4} mm, tilted {:.3?}° ± {:.4} mm, {:.3?}° ({} points in {} \
                 views, rms {:.3} px; shift {:.3?} mm, size {:+.3} mm)",
                o.face.height_mm,
                deg(o.face.slope),
                o.sigma[0],
                deg([o.sigma[1], o.sigma[2]]),
                o.points,
                o.views,
                o.rms_px,
                o.shift_mm,
                o.size_error_mm
            )
            .unwrap();
        }
    }
    r
}

/// The provenance an example writes into the materials it builds.
pub fn example_provenance(
    g: &ScannerGeometry,
    cal: &Calibration,
    builder: &str,
) -> scanner_shading::format::Provenance {
    scanner_shading::format::Provenance {
        scan_manifest_sha256: "-".into(),
        geometry_sha256: g.hash(),
        calibration_sha256: cal.hash(),
        builder: builder.into(),
        face: None,
    }
}

/// A perfect area-integrating estimate of `sample` at one pair: each
/// metric cell's mean over `n` × `n` points, repeated for the cell's
/// [`pair_queries`] (the metric's point-sampling limit scores it against
/// [`truth_answers`]).
pub fn dense_cell_answers(sample: &Sample, wi: [f64; 3], wo: [f64; 3], n: usize) -> Vec<[f32; 3]> {
    let fine: Vec<Query> = (0..CELLS * CELLS)
        .flat_map(|c| {
            let (i, k) = (c % CELLS, c / CELLS);
            (0..n * n).map(move |s| Query {
                uv: [
                    (i as f64 + ((s % n) as f64 + 0.5) / n as f64) / CELLS as f64,
                    (k as f64 + ((s / n) as f64 + 0.5) / n as f64) / CELLS as f64,
                ],
                wi,
                wo,
            })
        })
        .collect();
    let per_cell = pair_queries(wi, wo).len() / (CELLS * CELLS);
    hil_sim::truth::answer(sample, &fine)
        .chunks(n * n)
        .flat_map(|cell| {
            let mut m = [0.0f32; 3];
            for x in cell {
                for k in 0..3 {
                    m[k] += x[k] / (n * n) as f32;
                }
            }
            std::iter::repeat_n(m, per_cell)
        })
        .collect()
}

/// Answers to one pair's queries, given the pair's index.
pub type Estimate<'a> = dyn Fn(usize, &[Query]) -> Vec<[f32; 3]> + Sync + 'a;

/// `estimate`'s answers (given the pair's index and its queries) to every
/// [`pair_queries`] of `pairs`, concatenated.
pub fn pairs_answers(pairs: &[([f64; 3], [f64; 3])], estimate: &Estimate<'_>) -> Vec<[f32; 3]> {
    use rayon::prelude::*;
    pairs
        .par_iter()
        .enumerate()
        .flat_map_iter(|(p, &(wi, wo))| estimate(p, &pair_queries(wi, wo)))
        .collect()
}

/// Material PSNR (PSNR, gain-free, gain) of `estimate`'s answers (given
/// the pair's index and its queries) against `truth` ([`truth_answers`]).
pub fn pairs_psnr(
    pairs: &[([f64; 3], [f64; 3])],
    truth: &[[f32; 3]],
    estimate: &Estimate<'_>,
) -> (f64, f64, f64) {
    material_psnr(&pairs_answers(pairs, estimate), truth)
}

/// The captured pairs of `regions` at the nominal mirror directions (light:
/// towards where the inverse kinematics' beam meets the mirror; view:
/// towards the mirror's centre), light-major like the region images.
pub fn captured_pairs(g: &ScannerGeometry, regions: &RegionSet) -> Vec<([f64; 3], [f64; 3])> {
    regions
        .lights
        .iter()
        .flat_map(|&l| {
            let wi = g.light_direction(l).expect("a reachable mirror").to_array();
            regions
                .views
                .iter()
                .map(move |&v| (wi, g.mirror_direction(v).expect("a mirror").to_array()))
        })
        .collect()
}

/// Material PSNR of `regions` against the ground truth of `sample` at the
/// captured pairs ([`captured_pairs`]): (PSNR, gain-free PSNR, gain).
pub fn captured_pair_psnr(
    g: &ScannerGeometry,
    regions: &RegionSet,
    sample: &Sample,
) -> (f64, f64, f64) {
    captured_pair_psnr_on(g, regions, sample, SampleFace::FLUSH)
}

/// [`captured_pair_psnr`] of a sample whose face lies at `face` (ground
/// truth): the captured pairs in the face's frame, where its texels see
/// them.
pub fn captured_pair_psnr_on(
    g: &ScannerGeometry,
    regions: &RegionSet,
    sample: &Sample,
    face: SampleFace,
) -> (f64, f64, f64) {
    let in_face = |d: [f64; 3]| face.to_face(DVec3::from(d)).to_array();
    let pairs: Vec<_> =
        captured_pairs(g, regions).into_iter().map(|(i, o)| (in_face(i), in_face(o))).collect();
    regions_psnr(&pairs, &truth_answers(&pairs, sample), regions)
}

/// Region image `image` (light-major: light · views + view) at `queries`.
pub fn region_pair_answers(regions: &RegionSet, image: usize, queries: &[Query]) -> Vec<[f32; 3]> {
    let nv = regions.views.len();
    queries.iter().map(|q| regions.sample(image / nv, image % nv, q.uv).map(|x| x as f32)).collect()
}

/// [`region_pair_answers`] times the region set's detail layer
/// ([`RegionSet::detail_at`]): what the images and the layer hold together.
pub fn detailed_pair_answers(
    regions: &RegionSet,
    image: usize,
    queries: &[Query],
) -> Vec<[f32; 3]> {
    let nv = regions.views.len();
    queries
        .iter()
        .map(|q| {
            let (v, d) =
                (regions.sample(image / nv, image % nv, q.uv), regions.detail_at(image / nv, q.uv));
            std::array::from_fn(|k| (v[k] * d[k]) as f32)
        })
        .collect()
}

/// The region images' answers to every [`pair_queries`] of `pairs`, one
/// pair per region image in `regions` order (light-major).
pub fn region_answers(pairs: &[([f64; 3], [f64; 3])], regions: &RegionSet) -> Vec<[f32; 3]> {
    pairs_answers(pairs, &|p, q| region_pair_answers(regions, p, q))
}

/// Material PSNR of the region images against `truth` at `pairs`, one pair
/// per region image in `regions` order (light-major).
pub fn regions_psnr(
    pairs: &[([f64; 3], [f64; 3])],
    truth: &[[f32; 3]],
    regions: &RegionSet,
) -> (f64, f64, f64) {
    material_psnr(&region_answers(pairs, regions), truth)
}

/// How the error of an estimate spreads over the pairs: both arguments
/// answer the same [`pair_queries`] concatenated over the pairs, as for
/// [`material_psnr`].
#[derive(Debug, Clone)]
pub struct PairErrors {
    /// Each pair's squared error over its cells and channels, mean.
    pub mse: Vec<f64>,
    /// The material PSNR's peak (99th percentile of the truth's cells).
    pub peak: f64,
}

impl PairErrors {
    pub fn new(estimate: &[[f32; 3]], truth: &[[f32; 3]]) -> PairErrors {
        let (e, t) = (cell_means(estimate), cell_means(truth));
        let peak = host::build::fidelity::peak(&t);
        let cells = CELLS * CELLS;
        let mse = e
            .chunks(cells)
            .zip(t.chunks(cells))
            .map(|(a, b)| {
                a.iter()
                    .zip(b)
                    .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>())
                    .sum::<f64>()
                    / (3 * cells) as f64
            })
            .collect();
        PairErrors { mse, peak }
    }

    /// PSNR of a mean squared error against the peak, dB.
    pub fn db(&self, mse: f64) -> f64 {
        10.0 * (self.peak * self.peak / mse).log10()
    }

    /// The pairs, worst first.
    pub fn worst_first(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.mse.len()).collect();
        order.sort_by(|&a, &b| self.mse[b].total_cmp(&self.mse[a]));
        order
    }

    /// The share of the total squared error in the worst `fraction` of the
    /// pairs, and the PSNR of the others.
    pub fn concentration(&self, fraction: f64) -> (f64, f64) {
        let order = self.worst_first();
        let k = ((order.len() as f64 * fraction).round() as usize).min(order.len() - 1);
        let total: f64 = self.mse.iter().sum();
        let top: f64 = order[..k].iter().map(|&p| self.mse[p]).sum();
        (top / total, self.db((total - top) / (order.len() - k) as f64))
    }
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
    /// Per light, the calibrated mirror planes with the source's nominal
    /// home positions.
    pub light_nominal_source: Vec<f64>,
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
        let view = cal.views.iter().find(|v| v.view == l.light).expect("a calibrated view");
        let plane = DVec3::from(view.mirror_normal);
        e.light_nominal_source.push(
            host::build::calibrate::light_direction(g, l.axes, plane).angle_between(t).to_degrees(),
        );
        e.light_nominal.push(
            g.light_direction(l.light).expect("a reachable mirror").angle_between(t).to_degrees(),
        );
    }
    e
}

/// Material PSNRs of one sample's material files (docs/benchmarks.md,
/// "Material builder II"), each as [default, patent] interpolation.
#[derive(Debug, Clone, Copy)]
pub struct MaterialScores {
    /// The region images against the truth at the captured pairs.
    pub regions: f64,
    /// The region images times the detail layer there.
    pub regions_detail: f64,
    /// The materials against the truth at the captured pairs.
    pub captured: [f64; 2],
    /// The default material's best gain against the truth there.
    pub gain: f64,
    /// The materials against the images they were built from at the
    /// captured pairs (the palettisation error alone).
    pub against_regions: [f64; 2],
    /// The materials against the truth at the novel pairs.
    pub novel: [f64; 2],
    /// The default material at the captured pairs: the worst 5 % of the
    /// pairs' share of the squared error, and the PSNR of the others.
    pub worst_5: (f64, f64),
}

/// Score `materials` ([default, patent]) built from `regions` against the
/// ground truth of `sample` at the `captured` pairs (in `regions` order,
/// [`as_built_pairs`]) and at the `novel` ones; `texels` are the texel
/// models the builder fitted for each (`MaterialData::texels`, empty for
/// none), which the palettisation error is measured with.
pub fn material_scores(
    regions: &RegionSet,
    materials: [&scanner_shading::Material; 2],
    texels: [&[scanner_shading::texel::TexelParams]; 2],
    sample: &Sample,
    captured: &[([f64; 3], [f64; 3])],
    novel: &[([f64; 3], [f64; 3])],
) -> MaterialScores {
    use host::build::fidelity::captured_pair_answers;
    use host::build::material::shade;
    let (t_cap, t_nov) = (truth_answers(captured, sample), truth_answers(novel, sample));
    let (regions_db, _, _) = regions_psnr(captured, &t_cap, regions);
    let detailed = pairs_answers(captured, &|p, q| detailed_pair_answers(regions, p, q));
    let (regions_detail_db, _, _) = material_psnr(&detailed, &t_cap);
    let answers = materials.map(|m| pairs_answers(captured, &|_, q| shade(m, q)));
    let captured_db = answers.each_ref().map(|a| material_psnr(a, &t_cap));
    MaterialScores {
        worst_5: PairErrors::new(&answers[0], &t_cap).concentration(0.05),
        regions: regions_db,
        regions_detail: regions_detail_db,
        captured: captured_db.map(|x| x.0),
        gain: captured_db[0].2,
        against_regions: [0, 1].map(|i| {
            let (a, b) = captured_pair_answers(materials[i], regions, texels[i]);
            material_psnr(&a, &b).0
        }),
        novel: materials.map(|m| pairs_psnr(novel, &t_nov, &|_, q| shade(m, q)).0),
    }
}

/// Where the fidelity examples keep the scan of material `m` under `out`:
/// `out/NAME`, NAME being a library name or a texture-set directory's last
/// component (never the texture set's own directory).
pub fn scan_dir(out: &Path, m: &str) -> PathBuf {
    let name = Path::new(m).file_name().map_or_else(|| m.into(), |n| n.to_owned());
    out.join(name)
}

/// A scanner other than the default, for tests that the pipeline holds
/// for any scanner: 24 mirrors on three rings (18°, 38°, 58°; 5, 8 and 11
/// mirrors) instead of 40 on four, and a 4:3 sensor of 3072 × 2304 px
/// with a shorter lens than the default's 4096² at 5 600 px.
pub fn other_scanner() -> ScannerGeometry {
    let mut g = ScannerGeometry::generate_with_rings(&[(18.0, 5), (38.0, 8), (58.0, 11)]);
    g.camera.width = 3072;
    g.camera.height = 2304;
    g.camera.focal_px = 4200.0;
    g.camera.principal_px = [1536.0, 1152.0];
    g.validate().expect("a valid scanner");
    g
}

/// [`sampling_check`]'s answer: ∫ f cos θi dωi (luminance) at one uv and
/// wo by quadrature and by the material's own samples, and the samples'
/// variance against cosine-weighted sampling's.
#[derive(Debug, Clone, Copy)]
pub struct SamplingCheck {
    /// By quadrature over a 256 × 512 (θ, φ) grid.
    pub truth: f64,
    /// The mean of `Material::sample`'s weights.
    pub mean: f64,
    /// (mean − truth) over the mean's standard error.
    pub deviation: f64,
    /// The weights' variance over cosine sampling's, same count.
    pub variance_ratio: f64,
}

/// Estimate ∫ f cos θi dωi of `m` at (uv, wo) from `n` of its samples and
/// from `n` cosine-weighted directions (seeded), against quadrature.
pub fn sampling_check(
    m: &scanner_shading::Material,
    uv: [f32; 2],
    wo: [f32; 3],
    n: usize,
    seed: u64,
) -> SamplingCheck {
    use std::f64::consts::{FRAC_PI_2, PI, TAU};
    let lum = |c: [f32; 3]| c.iter().map(|&x| x as f64).sum::<f64>() / 3.0;
    let (nt, np) = (256, 512);
    let (dt, dp) = (FRAC_PI_2 / nt as f64, TAU / np as f64);
    let truth: f64 = (0..nt)
        .map(|a| {
            let t = (a as f64 + 0.5) * dt;
            let row: f64 = (0..np)
                .map(|b| {
                    let p = (b as f64 + 0.5) * dp;
                    let wi = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()].map(|x| x as f32);
                    lum(m.eval(uv, wi, wo))
                })
                .sum();
            row * t.sin() * dt * dp
        })
        .sum();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let (mut s, mut c) = ([0.0f64; 2], [0.0f64; 2]);
    for _ in 0..n {
        let x = m
            .sample(uv, wo, rng.random(), [rng.random(), rng.random()])
            .map_or(0.0, |x| lum(x.weight()));
        s = [s[0] + x, s[1] + x * x];
        let wi = scanner_shading::importance::cosine_direction([rng.random(), rng.random()]);
        let y = if wi[2] > 0.0 { lum(m.eval(uv, wi, wo)) * PI / wi[2] as f64 } else { 0.0 };
        c = [c[0] + y, c[1] + y * y];
    }
    let nf = n as f64;
    let var = |m: [f64; 2]| m[1] / nf - (m[0] / nf).powi(2);
    SamplingCheck {
        truth,
        mean: s[0] / nf,
        deviation: (s[0] / nf - truth) / (var(s) / nf).sqrt(),
        variance_ratio: var(s) / var(c),
    }
}

/// Material PSNRs over a large piece (docs/benchmarks.md, "Enlargement").
#[derive(Debug, Clone, Copy)]
pub struct EnlargementScores {
    /// The enlarged material against the large piece's truth.
    pub enlarged: f64,
    /// The sample's material tiled over the piece (uv scaled by the piece's
    /// side over the sample's and wrapped): what a renderer shows without
    /// an enlargement.
    pub tiled: f64,
    /// The enlarged material over the window of the piece the small sample
    /// is cut from, against the truth there (uv over the window).
    pub window_enlarged: f64,
    /// The sample's own material over the same window: the scan's ceiling.
    pub window_sample: f64,
}

/// Score `enlarged` (uv over the large piece of `material`) and `small`
/// (uv over its small sample) against the ground truth at `pairs`.
pub fn enlargement_scores(
    enlarged: &scanner_shading::Material,
    small: &scanner_shading::Material,
    material: std::sync::Arc<dyn hil_sim::materials::Material>,
    pairs: &[([f64; 3], [f64; 3])],
) -> EnlargementScores {
    use host::build::material::shade;
    let large = Sample::large(material.clone());
    let sample = Sample::small(material);
    let ratio = large.size_mm / sample.size_mm;
    let t_large = truth_answers(pairs, &large);
    let enlarged_db = pairs_psnr(pairs, &t_large, &|_, q| shade(enlarged, q)).0;
    let tiled_db = pairs_psnr(pairs, &t_large, &|_, q| {
        let q: Vec<Query> = q.iter().map(|x| Query { uv: x.uv.map(|u| u * ratio), ..*x }).collect();
        shade(small, &q)
    })
    .0;
    // The window: uv over the small sample, moved onto the piece.
    let to_piece = |x: &Query| {
        let uv = [0, 1].map(|k| {
            (sample.offset_mm[k] - large.offset_mm[k] + x.uv[k] * sample.size_mm) / large.size_mm
        });
        Query { uv, ..*x }
    };
    let t_small = truth_answers(pairs, &sample);
    let window_enlarged = pairs_psnr(pairs, &t_small, &|_, q| {
        shade(enlarged, &q.iter().map(to_piece).collect::<Vec<_>>())
    })
    .0;
    let window_sample = pairs_psnr(pairs, &t_small, &|_, q| shade(small, q)).0;
    EnlargementScores { enlarged: enlarged_db, tiled: tiled_db, window_enlarged, window_sample }
}

/// Where the enlargement's test and example start: material `m` built
/// from its scan under `out` (region options `regions`, the builder's
/// defaults), and the direct images of its large piece written to `direct`
/// from the design `g`'s four mirror directions nearest the normal, with a
/// white reference (as `hil-sim direct` writes them).
pub fn built_and_photographed(
    out: &Path,
    g: &ScannerGeometry,
    cal: &Calibration,
    seed: u64,
    m: &str,
    regions: &RegionOptions,
    direct: &Path,
) -> (scanner_shading::MaterialData, scanner_formats::direct::DirectManifest) {
    use host::build::calibrate::Silent;
    use host::build::material::{MaterialOptions, build_material};
    let scan = host::build::scanread::ScanFrames::open(&scan_dir(out, m), g).unwrap();
    let regions = host::build::extract_regions(g, cal, &scan, regions, &Silent).unwrap();
    let prov = scanner_shading::format::Provenance {
        scan_manifest_sha256: String::new(),
        geometry_sha256: g.hash(),
        calibration_sha256: String::new(),
        builder: "tests".into(),
        face: None,
    };
    let data =
        build_material(&regions, m, 25.4, prov, &MaterialOptions::default(), &Silent).unwrap();
    let truth = hil_sim::materials::lookup(m).unwrap();
    let sim = hil_sim::optics::OpticalSim::as_built(g, Sample::small(truth.clone()), seed);
    let scale = hil_sim::direct::mirror_view_scale(g);
    let manifest = hil_sim::direct::write_set(&sim, g, truth, 4, scale, direct).unwrap();
    (data, manifest)
}

#[cfg(test)]
mod tests {
    use super::args_problem;

    #[test]
    fn an_example_refuses_what_it_does_not_read() {
        let check = |args: &[&str]| {
            let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
            args_problem(&args, &["--seed", "--out"], &["--no-patent"])
        };
        assert_eq!(check(&[]), Ok(None));
        assert_eq!(check(&["--seed", "2", "--no-patent", "--out", "--x"]), Ok(None));
        assert!(check(&["--no-patent", "--help"]).unwrap().unwrap().contains("--seed --out"));
        let unknown = check(&["--seed", "2", "--no-patnet"]).unwrap_err();
        assert!(unknown.starts_with("unknown argument \"--no-patnet\""), "{unknown}");
        assert_eq!(check(&["--out", "d", "--seed"]), Err("--seed needs a value".into()));
        // A flag given a value: the value is an unknown argument.
        assert!(check(&["--no-patent", "yes"]).unwrap_err().contains("\"yes\""));
    }
}
