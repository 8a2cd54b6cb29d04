//! The optical simulator (hil-sim part 2): geometry, kinematics, frames,
//! and the camera joined to the simulated board.

mod common;

use std::time::Duration;

use common::{Client, capture_all, load_mirror_table};
use hil_sim::camera::{SimCamera, exposure_of};
use hil_sim::{FaultEvent, FaultPlan, SimConfig};
use protocol::{Axis, Event, Reply, Request};

use glam::DVec3;
use hil_sim::geometry::{AxisValues, SampleFace, ScannerGeometry, world_to_sample};
use hil_sim::materials::{self, Sample};
use hil_sim::optics::{Exposure, Frame, OpticalSim, Surface};

const SEED: u64 = 7;

fn nominal() -> ScannerGeometry {
    ScannerGeometry::default_scanner()
}

fn sim(factor: u32, material: &str, seed: u64) -> OpticalSim {
    let nominal = nominal().with_sensor_scaled(factor);
    OpticalSim::as_built(&nominal, Sample::small(materials::by_name(material).unwrap()), seed)
}

fn exposure(axes: AxisValues) -> Exposure {
    Exposure { axes, exposure_s: 0.05, light: 1.0 }
}

#[test]
fn inverse_kinematics_puts_the_beam_through_each_mirror_onto_the_sample_centre() {
    let g = nominal();
    let axes = protocol::default_axes();
    for l in 0..g.mirrors.len() {
        let a = g.mirror_axes(l).unwrap();
        assert!((0.0..=200.0).contains(&a.track_mm) && a.tilt_deg.abs() <= 35.0, "{l}: {a:?}");
        let steps = a.to_steps(&axes).unwrap();
        for (what, values) in
            [("exact", a), ("in steps", AxisValues::from_steps(steps.map(i64::from), &axes))]
        {
            let beam = g.beam(values);
            let (k, q) = g.first_mirror(beam.origin, beam.dir).unwrap();
            assert_eq!(k, l, "{what}: first mirror");
            let r = g.mirrors[l].reflect_dir(beam.dir);
            // Where the reflected axis crosses the sample plane.
            let s = q + r * (-q.z / r.z);
            let tol = if what == "exact" { 1e-6 } else { 0.2 };
            assert!(s.truncate().length() < tol, "{l} {what}: lands {s:?} from the centre");
        }
    }
}

#[test]
fn each_mirror_sees_the_sample_at_least_96_px_across_by_default() {
    let g = nominal();
    assert_eq!((g.camera.width, g.camera.height), (4096, 4096));
    for l in 0..g.mirrors.len() {
        let c = g.sample_image_corners(l).unwrap();
        let side =
            |i: usize, j: usize| ((c[i][0] - c[j][0]).powi(2) + (c[i][1] - c[j][1]).powi(2)).sqrt();
        let across = side(0, 1).max(side(1, 2));
        assert!(across >= 96.0, "mirror {l}: {across:.1} px");
        for p in c {
            assert!(
                p[0] > 0.0 && p[1] > 0.0 && p[0] < 4096.0 && p[1] < 4096.0,
                "mirror {l} in view"
            );
        }
    }
}

#[test]
fn at_each_nominal_mirror_position_the_beam_lights_that_mirror_and_no_other() {
    for seed in [SEED, 8, 9] {
        let s = sim(8, "diffuse-white", seed);
        let g = nominal();
        for l in 0..g.mirrors.len() {
            let a = g.mirror_axes(l).unwrap();
            assert_eq!(s.mirrors_lighting_sample(a), vec![l], "seed {seed}, mirror {l}");
            // The whole sample is in the beam, its centre in the flat core.
            let h = g.sample.size_mm / 2.0;
            let centre = s.light_paths(a, DVec3::ZERO);
            assert!(centre.len() == 1 && centre[0].irradiance > 0.85, "{l}: {centre:?}");
            for (x, y) in [(-h, -h), (h, -h), (h, h), (-h, h)] {
                let e: f64 =
                    s.light_paths(a, DVec3::new(x, y, 0.0)).iter().map(|p| p.irradiance).sum();
                if e <= 0.05 {
                    let beam = s.geometry().beam(a);
                    let m = &s.geometry().mirrors[l];
                    let r = m.reflect_dir(beam.dir);
                    let q = m.intersect(DVec3::new(x, y, 0.0), -r);
                    eprintln!(
                        "q {q:?} dist {:?} centre dist {}",
                        q.map(|q| beam.distance(q.1)),
                        beam.distance(m.center())
                    );
                }
                assert!(e > 0.05, "seed {seed} mirror {l}: corner ({x}, {y}) unlit");
            }
        }
    }
}

/// Pixels whose four sub-pixel rays all see the sample through `mirror`
/// well inside it.
fn region(s: &OpticalSim, mirror: usize) -> Vec<(u32, u32)> {
    let g = s.geometry();
    // Search around where the as-built camera sees the sample's mirror image.
    let c = g.sample_image_corners(mirror).unwrap();
    let lo = |k: usize| c.iter().map(|p| p[k]).fold(f64::MAX, f64::min).floor().max(8.0) as u32 - 8;
    let hi = |k: usize| c.iter().map(|p| p[k]).fold(f64::MIN, f64::max).ceil() as u32 + 8;
    let mut out = Vec::new();
    for y in lo(1)..hi(1).min(g.camera.height) {
        for x in lo(0)..hi(0).min(g.camera.width) {
            let inside =
                [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)].iter().all(|&(dx, dy)| {
                    s.trace(x as f64 + dx, y as f64 + dy).is_some_and(|h| {
                        h.mirror == mirror && h.uv.iter().all(|&u| (0.2..=0.8).contains(&u))
                    })
                });
            if inside {
                out.push((x, y));
            }
        }
    }
    out
}

#[test]
fn a_diffuse_white_sample_reads_its_analytic_radiance_within_the_noise() {
    let s = sim(4, "diffuse-white", SEED);
    let g = s.geometry().clone();
    let n = nominal();
    let cam = &g.camera;
    let (_, _, forward) = cam.basis();
    let gain = g.sensor.max_code() / g.sensor.full_well_e;
    let views = [0usize, 5, 13, 22, 30, 39];
    let regions: Vec<Vec<(u32, u32)>> = views.iter().map(|&v| region(&s, v)).collect();
    for lit in [0usize, 13, 30] {
        let a = n.mirror_axes(lit).unwrap();
        let frame = s.render(&exposure(a));
        let beam = g.beam(a);
        let light = -g.mirrors[lit].reflect_dir(beam.dir);
        // Sample normal is -z: cos θi = light · (−z).
        let cos_i = -light.z;
        let e = g.source.irradiance * g.mirrors[lit].reflectance * cos_i;
        let radiance = 0.98 / std::f64::consts::PI * e;
        for (&view, pixels) in views.iter().zip(&regions) {
            assert!(pixels.len() > 60, "region {view}: {} px", pixels.len());
            let (mut expect, mut var) = (0.0, 0.0);
            for &(x, y) in pixels {
                let cos = cam.ray(x as f64 + 0.5, y as f64 + 0.5).dot(forward);
                let el = radiance
                    * g.mirrors[view].reflectance
                    * 0.05
                    * g.sensor.sensitivity_e
                    * cos.powf(g.sensor.vignetting_exponent);
                expect += el * gain / g.sensor.max_code();
                var += (el + g.sensor.read_noise_e.powi(2)) * (gain / g.sensor.max_code()).powi(2)
                    + 1.0 / 12.0 / g.sensor.max_code().powi(2);
            }
            let count = pixels.len() as f64;
            expect /= count;
            let sigma_pixel = (var / count).sqrt();
            let measured = frame.mean_luminance(pixels);
            let sigma_mean = sigma_pixel / (3.0 * count).sqrt();
            assert!(
                (measured - expect).abs() < 4.0 * sigma_mean + 1e-3 * expect,
                "lit {lit} view {view}: {measured:.5} vs {expect:.5} (σ {sigma_mean:.2e})"
            );
            // The pixel-to-pixel scatter is the sensor's noise.
            let values: Vec<f64> =
                pixels.iter().flat_map(|&(x, y)| frame.pixel(x, y)).map(|v| v as f64).collect();
            let m = values.iter().sum::<f64>() / values.len() as f64;
            let sd =
                (values.iter().map(|v| (v - m).powi(2)).sum::<f64>() / values.len() as f64).sqrt();
            assert!(
                (sd / sigma_pixel - 1.0).abs() < 0.2,
                "lit {lit} view {view}: noise {sd:.2e} vs {sigma_pixel:.2e}"
            );
        }
    }
}

#[test]
fn the_same_seed_gives_identical_frames_and_another_seed_does_not() {
    let a = nominal().mirror_axes(9).unwrap();
    let f1 = sim(8, "leather", SEED).render(&exposure(a));
    let f2 = sim(8, "leather", SEED).render(&exposure(a));
    assert!(f1 == f2, "same seed, same frame");
    let f3 = sim(8, "leather", SEED + 1).render(&exposure(a));
    assert!(f1 != f3);
    // Thread count does not matter either.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let f4 = pool.install(|| sim(8, "leather", SEED).render(&exposure(a)));
    assert!(f1 == f4, "one thread, same frame");
}

fn assert_dark(frame: &Frame, g: &ScannerGeometry, what: &str) {
    // Only read noise: nothing above 6 σ.
    let limit = (6.0 * g.sensor.read_noise_e * g.sensor.max_code() / g.sensor.full_well_e).ceil()
        / g.sensor.max_code();
    let max = frame.rgb.iter().fold(0.0f32, |m, &v| m.max(v)) as f64;
    assert!(max <= limit, "{what}: max {max} > {limit}");
}

#[test]
fn a_beam_that_misses_every_mirror_gives_a_dark_frame() {
    let s = sim(8, "diffuse-white", SEED);
    let mut a = nominal().mirror_axes(3).unwrap();
    a.tilt_deg = -35.0; // at the home switch: the beam goes out over the rim
    assert!(s.mirrors_lighting_sample(a).is_empty());
    assert_dark(&s.render(&exposure(a)), s.geometry(), "tilt at home");
    // Light off: dark too.
    let lit = nominal().mirror_axes(3).unwrap();
    assert_dark(&s.render(&Exposure { light: 0.0, ..exposure(lit) }), s.geometry(), "light off");
    // And the same position with the light on is not.
    let f = s.render(&exposure(lit));
    assert!(f.rgb.iter().fold(0.0f32, |m, &v| m.max(v)) > 0.1);
}

#[test]
fn a_slightly_wrong_position_lights_part_of_the_sample_or_the_wrong_mirror() {
    let s = sim(8, "diffuse-white", SEED);
    let g = nominal();
    let a = g.mirror_axes(20).unwrap();
    // 5° of disk: the beam's edge moves off the mirror, part of the sample goes dark.
    let off = AxisValues { disk_deg: a.disk_deg + 5.0, ..a };
    let h = g.sample.size_mm / 2.0;
    let lit = |axes| {
        [(-h, -h), (h, -h), (h, h), (-h, h), (0.0, 0.0)]
            .iter()
            .filter(|&&(x, y)| !s.light_paths(axes, DVec3::new(x, y, 0.0)).is_empty())
            .count()
    };
    assert_eq!(lit(a), 5);
    assert!(lit(off) < 5, "5° off lights the whole sample");
    // Half way to the next mirror of the ring: a neighbour or nothing.
    let between = AxisValues { disk_deg: a.disk_deg + 15.0, ..a };
    assert!(!s.mirrors_lighting_sample(between).contains(&20));
}

#[test]
fn ground_truth_radiance_of_the_white_is_lambertian() {
    let white = Sample::small(materials::by_name("diffuse-white").unwrap());
    let light = DVec3::new(0.4, 0.1, 0.8).normalize();
    let view = DVec3::new(-0.2, 0.5, 0.7).normalize();
    let r = white.reflected_radiance([0.3, 0.6], view, light);
    assert!((r[1] - 0.98 / std::f64::consts::PI * light.z).abs() < 1e-12);
}

#[test]
fn svbrdf_samples_vary_in_albedo_roughness_and_normal() {
    for name in materials::SVBRDF_NAMES {
        let piece = Sample::small(materials::by_name(name).unwrap());
        let texels: Vec<_> = (0..400)
            .map(|i| piece.texel([(i % 20) as f64 / 20.0 + 0.013, (i / 20) as f64 / 20.0 + 0.007]))
            .collect();
        let spread = |f: &dyn Fn(&materials::Texel) -> f64| {
            let v: Vec<f64> = texels.iter().map(f).collect();
            v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
        };
        assert!(
            spread(&|t| t.diffuse[0] + t.diffuse[1] + t.diffuse[2] + t.specular[0]) > 0.05,
            "{name}: albedo"
        );
        assert!(spread(&|t| t.normal.x) > 0.05, "{name}: normals");
        if name != "woven-fabric" {
            assert!(spread(&|t| t.roughness) > 0.02, "{name}: roughness");
        }
    }
}

#[test]
fn direct_images_of_the_large_piece_from_the_four_mirrors_nearest_the_axis() {
    let g = nominal();
    let s = sim(8, "woven-fabric", SEED);
    let mut dirs: Vec<(usize, DVec3)> =
        (0..g.mirrors.len()).map(|l| (l, g.mirror_direction(l).unwrap())).collect();
    dirs.sort_by(|a, b| b.1.z.total_cmp(&a.1.z));
    let nearest: Vec<usize> = dirs[..4].iter().map(|d| d.0).collect();
    assert_eq!(
        nearest.iter().copied().collect::<std::collections::BTreeSet<_>>(),
        (0..4).collect()
    );
    let large = Sample::large(materials::by_name("woven-fabric").unwrap());
    // The mirror views' scale: f / 2a px per mm.
    let ppm = g.camera.focal_px / (2.0 * g.ellipsoid.semi_major_mm);
    let images: Vec<Frame> =
        dirs[..4].iter().map(|&(_, d)| s.direct_image(&large, d, ppm / 2.0, 0.05)).collect();
    for im in &images {
        assert_eq!(im.width, (80.0 * ppm / 2.0_f64).round() as u32);
        assert!(im.rgb.iter().any(|&v| v > 0.05));
    }
    // Different light directions shade the relief differently.
    assert!(images[0] != images[1] && images[0] != images[2]);
}

/// A lens with barrel distortion pulls the piece's corners in towards the
/// photograph's centre by k1 · (r / half-diagonal)² of their radius, and
/// a pixel still goes back to its point on the piece.
#[test]
fn a_photograph_through_a_lens_shows_the_corners_pulled_in() {
    use hil_sim::direct::PhotoSetup;
    use hil_sim::optics::PhotoCamera;
    let d = nominal().mirror_direction(0).unwrap();
    let pinhole = PhotoCamera::framing(d, 300.0, 160, 80.0, 0.8);
    let lens = PhotoCamera { distortion: [-0.05, 0.0], ..pinhole };
    for p in [DVec3::new(0.0, 0.0, 0.0), DVec3::new(31.0, -12.5, 0.0), DVec3::new(-40.0, 40.0, 0.0)]
    {
        let back = lens.on_plane(lens.project(p)).unwrap();
        assert!((back - p).length() < 1e-9, "{p:?} → {back:?}");
    }
    let half_diagonal = 80.0 * std::f64::consts::SQRT_2;
    for (a, b) in pinhole.corners(80.0).iter().zip(lens.corners(80.0)) {
        let (ra, rb) = ((a[0] - 80.0).hypot(a[1] - 80.0), (b[0] - 80.0).hypot(b[1] - 80.0));
        let want = ra * (1.0 - 0.05 * (ra / half_diagonal).powi(2));
        assert!((rb - want).abs() < 1e-9, "{a:?} → {b:?}: {rb} against {want}");
    }
    // A lens that folds the photograph is refused.
    let fold = PhotoSetup { distortion: [-0.4, 0.0], ..PhotoSetup::pinhole(400.0) };
    assert!(fold.check().unwrap_err().contains("one to one"));
    assert!(PhotoSetup { distortion: [-0.05, 0.0], ..fold }.check().is_ok());
    // So is a background that reflects more than all the light, or less than none.
    for b in [-0.1, 1.5, f64::NAN] {
        let card = PhotoSetup { background_albedo: b, ..PhotoSetup::pinhole(400.0) };
        assert!(card.check().unwrap_err().contains("background albedo"), "{b}");
    }
}

#[test]
fn photographs_in_perspective_see_the_piece_where_its_corners_project() {
    use hil_sim::optics::{HOLDER_ALBEDO, PhotoCamera};
    let g = nominal();
    let s = sim(8, "diffuse-white", SEED);
    let d = g.mirror_direction(0).unwrap();
    let cam = PhotoCamera::framing(d, 300.0, 160, 80.0, 0.8);
    // A point and its pixel, both ways.
    for p in [DVec3::new(0.0, 0.0, 0.0), DVec3::new(31.0, -12.5, 0.0), DVec3::new(-40.0, 40.0, 0.0)]
    {
        let back = cam.on_plane(cam.project(p)).unwrap();
        assert!((back - p).length() < 1e-9, "{p:?} → {back:?}");
    }
    let corners = cam.corners(80.0);
    // Seen from above, u runs along the rows and v up the photograph (a
    // camera makes no mirror image).
    assert!(corners[1][0] > corners[0][0] + 100.0, "{corners:?}");
    assert!(corners[3][1] < corners[0][1] - 100.0, "{corners:?}");
    // The white piece inside its corners, the black holder outside.
    let white = Sample::large(materials::by_name("diffuse-white").unwrap());
    let photo = s.photograph(&white, &cam, 0.1, HOLDER_ALBEDO);
    let at = |px: [f64; 2]| photo.rgb[3 * (px[1] as usize * 160 + px[0] as usize)];
    let centre = at(cam.project(DVec3::ZERO));
    let outside = at(cam.project(DVec3::new(44.0, 0.0, 0.0)));
    assert!(centre > 0.1, "{centre}");
    let ratio = (outside / centre) as f64;
    let want = HOLDER_ALBEDO / 0.98;
    assert!((ratio - want).abs() < 0.3 * want, "holder / white {ratio} against {want}");
    // On a light card instead, the piece alike, the card around it.
    let card = s.photograph(&white, &cam, 0.1, 0.5);
    let at = |px: [f64; 2]| card.rgb[3 * (px[1] as usize * 160 + px[0] as usize)];
    let ratio = (at(cam.project(DVec3::new(44.0, 0.0, 0.0))) / centre) as f64;
    assert!((at(cam.project(DVec3::ZERO)) / centre - 1.0).abs() < 0.05);
    assert!((ratio - 0.5 / 0.98).abs() < 0.05, "card / white {ratio}");
}

/// A photograph's pixels integrate over their area, as a sensor's do: a
/// pixel on the piece's outline holds the piece and the holder in the
/// shares its square covers, so the outline's position within the pixel
/// is not rounded to the subpixels (2 × 2 points put a side anywhere
/// within a quarter pixel, which bent the sides found from them).
#[test]
fn a_photograph_places_the_pieces_sides_within_its_pixels() {
    use hil_sim::optics::{HOLDER_ALBEDO, PhotoCamera};
    let s = sim(8, "diffuse-white", SEED);
    let d = nominal().mirror_direction(0).unwrap();
    let cam = PhotoCamera::framing(d, 300.0, 160, 80.0, 0.8);
    let white = Sample::large(materials::by_name("diffuse-white").unwrap());
    let photo = s.photograph(&white, &cam, 0.1, HOLDER_ALBEDO);
    let at = |c: usize, r: usize| photo.rgb[3 * (r * 160 + c) + 1] as f64;
    let [c0, c1, c2, c3] = cam.corners(80.0);
    let (top, bottom) = (c3[1].max(c2[1]).ceil() as usize + 3, c0[1].min(c1[1]) as usize - 3);
    let mut worst: f64 = 0.0;
    for r in (top..bottom).step_by(7) {
        // The sides at the row's middle: a pinhole keeps them straight.
        let y = r as f64 + 0.5;
        let x_at = |a: [f64; 2], b: [f64; 2]| a[0] + (b[0] - a[0]) * (y - a[1]) / (b[1] - a[1]);
        let (left, right) = (x_at(c0, c3), x_at(c1, c2));
        let mid = ((left + right) / 2.0) as usize;
        let piece = (mid - 10..mid + 10).map(|c| at(c, r)).sum::<f64>() / 20.0;
        let holder = (0..4).map(|c| at(c, r)).sum::<f64>() / 4.0;
        // Where the piece's share of the pixels across each side puts it.
        let share = |c: usize| (at(c, r) - holder) / (piece - holder);
        let (l0, r0) = (left as usize - 4, right as usize - 4);
        let found_left = l0 as f64 + 9.0 - (l0..l0 + 9).map(share).sum::<f64>();
        let found_right = r0 as f64 + (r0..r0 + 9).map(share).sum::<f64>();
        worst = worst.max((found_left - left).abs()).max((found_right - right).abs());
    }
    eprintln!("the sides within {worst:.4} px of where they project");
    assert!(worst < 0.05, "{worst:.4} px");
}

fn frame_max(f: &Frame) -> f32 {
    f.rgb.iter().fold(0.0f32, |m, &v| m.max(v))
}

#[test]
fn the_camera_renders_every_trigger_from_the_physical_axis_positions() {
    let mut camera = SimCamera::new(sim(8, "diffuse-white", SEED));
    let mut c = Client::new(SimConfig::new(SEED));
    c.home_all();
    // At home the tilt is at −35°: the beam misses every mirror.
    assert_eq!(c.request(Request::Trigger { exposure_us: 50_000 }), Reply::Ack);
    c.wait_event(Duration::from_secs(2), |e| matches!(e, Event::TriggerFired(_))).unwrap();
    c.sleep(Duration::from_millis(100));
    let dark = c.device(|d| camera.collect(d.truth()));
    assert_eq!(dark.len(), 1);
    assert_dark(&dark[0].1, camera.optics().geometry(), "trigger at home");
    load_mirror_table(&mut c);
    capture_all(&mut c, 40);
    let frames = c.device(|d| camera.collect(d.truth()));
    assert_eq!(frames.len(), 40);
    for (l, (index, frame)) in frames.iter().enumerate() {
        let record = &c.device(|d| d.truth().clone()).triggers[*index];
        let light = c.device(|d| d.truth().light.clone());
        let e = exposure_of(record, &light, 0, &protocol::default_axes()).unwrap();
        assert!((e.exposure_s - 0.05).abs() < 1e-3 && e.light == 1.0);
        assert_eq!(camera.optics().mirrors_lighting_sample(e.axes), vec![l]);
        assert!(frame_max(frame) > 0.03, "mirror {l} lit");
    }
}

#[test]
fn lost_steps_visibly_change_the_frame() {
    let run = |faults: FaultPlan| {
        let mut camera = SimCamera::new(sim(8, "painted-wood", SEED));
        let mut config = SimConfig::new(SEED);
        config.faults = faults;
        let mut c = Client::new(config);
        c.home_all();
        load_mirror_table(&mut c);
        capture_all(&mut c, 4);
        let frames = c.device(|d| camera.collect(d.truth()));
        let lit: Vec<Vec<usize>> = c.device(|d| {
            d.truth()
                .triggers
                .iter()
                .map(|r| {
                    let e = exposure_of(r, &d.truth().light, 0, &protocol::default_axes()).unwrap();
                    camera.optics().mirrors_lighting_sample(e.axes)
                })
                .collect()
        });
        (frames, lit)
    };
    let (clean, clean_lit) = run(FaultPlan::none());
    // 20° of disk steps lost while moving to mirror 3.
    let (faulty, faulty_lit) =
        run(FaultPlan::none()
            .after_triggers(3, FaultEvent::LoseSteps { axis: Axis::Disk, steps: 900 }));
    for l in 0..3 {
        assert!(clean[l].1 == faulty[l].1, "frame {l} before the fault is identical");
    }
    // (Further mirrors would cross the disk's index flag where the
    // firmware does not expect it, and it stops with a fault.)
    for l in 3..4 {
        assert_eq!(clean_lit[l], vec![l]);
        let diff: f64 = clean[l]
            .1
            .rgb
            .iter()
            .zip(&faulty[l].1.rgb)
            .map(|(a, b)| (a - b).abs() as f64)
            .sum::<f64>();
        let total: f64 = clean[l].1.rgb.iter().map(|&v| v as f64).sum();
        assert!(diff > 0.3 * total, "frame {l}: changed by {:.1} %", 100.0 * diff / total);
        eprintln!(
            "mirror {l}: lit via {:?}, frame changed by {:.0} %",
            faulty_lit[l],
            100.0 * diff / total
        );
    }
}

#[test]
fn bad_geometry_files_are_refused_with_the_reason() {
    let good = ScannerGeometry::default_scanner().to_toml();
    let cases = [
        (good.replace("format = 1", "format = 2"), "format 2"),
        (good.replace("[sensor]", "[sensor]\ncolour = \"mono\""), "unknown field"),
        (good.replace("focal_distance_mm = 800.0", "focal_distance_mm = 1300.0"), "focal_distance"),
        (good.replace("width = 4096", "width = 0"), "camera"),
        (good[..good.len() / 3].to_string(), ""),
    ];
    for (text, why) in cases {
        let e = ScannerGeometry::from_toml(&text).unwrap_err().to_string();
        assert!(e.contains(why), "{e}");
    }
    let mut g = ScannerGeometry::default_scanner();
    g.mirrors.clear();
    assert!(ScannerGeometry::from_toml(&g.to_toml()).unwrap_err().to_string().contains("mirrors"));
    g = ScannerGeometry::default_scanner();
    g.mirrors[3].normal = [0.0, 0.0, 2.0];
    assert!(ScannerGeometry::from_toml(&g.to_toml()).unwrap_err().to_string().contains("mirror 3"));
    assert!(matches!(
        ScannerGeometry::default_scanner().mirror_axes(40),
        Err(hil_sim::geometry::GeometryError::NoMirror(40, 40))
    ));
}

/// `scanner geometry`'s design check (`ScannerGeometry::check_design`)
/// against the optics: for beams of several widths, a mirror's beam lights
/// another mirror whose light reaches the sample exactly where the check
/// says so.
#[test]
fn the_design_check_finds_the_stray_light_the_optics_render() {
    use hil_sim::geometry::DesignProblem;
    let mut stray_found = 0;
    for radius in [24.0, 45.0, 60.0, 80.0] {
        let mut g = nominal();
        g.source.beam_radius_mm = radius;
        let s = OpticalSim::new(
            g.clone(),
            Sample::small(materials::by_name("diffuse-white").unwrap()),
            SEED,
        );
        let check = g.check_design();
        for l in 0..g.mirrors.len() {
            let lit = s.mirrors_lighting_sample(g.mirror_axes(l).unwrap());
            let others: Vec<usize> = lit.iter().copied().filter(|&k| k != l).collect();
            let said = check
                .problems
                .iter()
                .any(|p| matches!(p, DesignProblem::StrayLight { mirror, .. } if *mirror == l));
            eprintln!("radius {radius}, mirror {l}: optics {lit:?}, check {said}");
            assert_eq!(
                said,
                !others.is_empty(),
                "radius {radius}, mirror {l}: the optics light {lit:?}"
            );
            stray_found += usize::from(said);
        }
    }
    assert!(stray_found > 0, "the wider beams light neighbours");
}

/// A sample whose face is tilted about its centre: each view still sees
/// the centre where a flush one's is (the plane passes through it), its
/// directions turned into the face's frame, and a point off the centre on
/// the face's plane at the uv measured along it.
#[test]
fn a_tilted_face_is_seen_on_its_plane_and_in_its_frame() {
    let flush = sim(8, "leather", SEED);
    let face = SampleFace { height_mm: 0.0, slope: [0.035, -0.017] };
    let tilted = flush.clone().with_sample_face(face);
    let g = flush.geometry().clone();
    for l in [0, 7, 23, 39] {
        let [x, y] = g.view_point(l, [0.5, 0.5]).unwrap();
        let (a, b) = (flush.trace(x, y).unwrap(), tilted.trace(x, y).unwrap());
        assert!((a.point - b.point).length() < 1e-9, "{l}");
        assert!((a.uv[0] - b.uv[0]).abs() < 1e-9 && (a.uv[1] - b.uv[1]).abs() < 1e-9);
        assert!((face.to_face(a.view) - b.view).length() < 1e-12, "{l}");
        // Off the centre: on the plane, where the face's uv puts it.
        let [x, y] = g.view_point(l, [0.2, 0.7]).unwrap();
        let hit = tilted.trace(x, y).unwrap();
        let p = world_to_sample(hit.point);
        assert!((p.z - face.height_at(p.x, p.y)).abs() < 1e-9, "{l}: {p}");
        assert!((face.point(g.sample.size_mm, hit.uv) - p).length() < 1e-9, "{l}");
        // A ray towards the raised side meets the face before the holder's plane.
        assert!((hit.uv[0] - 0.2).abs() > 1e-4, "{l}: {:?}", hit.uv);
    }
}

/// A thick sample standing on the holder: a view sees its sides beyond the
/// edges that face it, between the face's outline and the dark holder,
/// each side at the depth and the edge's uv where the ray meets it; the
/// edges facing away hide them. The frames show them there and nowhere
/// else. The same slab recessed into the holder (its face flush) shows no
/// side: the holder hides what lies beyond its plane.
#[test]
fn a_thick_sample_shows_its_sides_beyond_the_edges_facing_a_view() {
    let thickness = 6.0;
    let flush = sim(4, "leather", SEED);
    let flat = flush.clone().with_sample_height(thickness);
    let thick = flat.clone().with_sample_thickness(thickness);
    let recessed = flush.clone().with_sample_thickness(thickness);
    let g = flat.geometry().clone();
    let size = g.sample.size_mm;
    let outward = [[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]];
    let (mut near, mut far, mut wide) = (0, 0, 0);
    for l in [3, 17, 23, 39] {
        let [x, y] = g.view_point(l, [0.5, 0.5]).unwrap();
        let view = flat.trace(x, y).unwrap().view;
        let e = exposure(g.mirror_axes(l).unwrap());
        let (lit_flat, lit_thick) = (flat.expected(&e), thick.expected(&e));
        let (lit_flush, lit_recessed) = (flush.expected(&e), recessed.expected(&e));
        // Where the holder's plane shows a point of the face's height.
        let shift = [-thickness * view.x / view.z / size, -thickness * view.y / view.z / size];
        for (k, n) in outward.iter().enumerate() {
            let facing = n[0] * view.x + n[1] * view.y;
            if facing.abs() < 0.1 {
                continue;
            }
            // Half the side's width beyond the middle of the edge, where
            // the flush face's side would show below the holder's plane.
            let out = 0.5 * thickness * facing.abs() / view.z / size;
            let below = [0.5 + n[0] * (0.5 + out), 0.5 + n[1] * (0.5 + out)];
            let [x, y] = g.view_point(l, below).unwrap();
            assert!(recessed.trace(x, y).is_none(), "view {l}, side {k}: recessed, hidden");
            let (px, py) = (x as u32, y as u32);
            assert_eq!(lit_flush.pixel(px, py), lit_recessed.pixel(px, py), "view {l}, side {k}");
            // The same point of the slab standing on the holder.
            let uv = [below[0] + shift[0], below[1] + shift[1]];
            let [x, y] = g.view_point(l, uv).unwrap();
            assert!(flat.trace(x, y).is_none(), "view {l}, side {k}: beyond the face");
            let hit = thick.trace(x, y);
            let (px, py) = (x as u32, y as u32);
            let (a, b) = (lit_flat.pixel(px, py), lit_thick.pixel(px, py));
            // Whether the pixel lies clear of the edge's.
            let edge = [0.5 + 0.5 * n[0] + shift[0], 0.5 + 0.5 * n[1] + shift[1]];
            let [ex, ey] = g.view_point(l, edge).unwrap();
            let clear = (x - ex).hypot(y - ey) > 2.0;
            if facing > 0.0 {
                near += 1;
                let hit = hit.unwrap_or_else(|| panic!("view {l}: side {k} facing it not seen"));
                assert_eq!(hit.surface, Surface::Side(k), "view {l}");
                let depth = world_to_sample(hit.point).z;
                assert!((depth - 0.5 * thickness).abs() < 0.05 * thickness, "view {l}, {depth}");
                let along = if n[0] != 0.0 { hit.uv[0] } else { hit.uv[1] };
                assert_eq!(along, if n[0] + n[1] > 0.0 { 1.0 } else { 0.0 }, "view {l}");
                assert!(
                    (hit.view.z - facing).abs() < 0.02,
                    "view {l}: in the side's frame: {}",
                    hit.view
                );
                assert!(
                    !clear || b.iter().sum::<f32>() > 10.0 * a.iter().sum::<f32>().max(1e-6),
                    "view {l}, side {k}: {a:?} → {b:?}"
                );
                wide += usize::from(clear);
            } else {
                far += 1;
                assert!(hit.is_none(), "view {l}: side {k} faces away, hidden: {hit:?}");
                assert_eq!(a, b, "view {l}, side {k}: nothing beyond an edge facing away");
            }
        }
        // The face itself is the same.
        let [x, y] = g.view_point(l, [0.3 + shift[0], 0.6 + shift[1]]).unwrap();
        assert_eq!(lit_flat.pixel(x as u32, y as u32), lit_thick.pixel(x as u32, y as u32));
    }
    assert!(
        near >= 4 && far >= 4 && wide >= 2,
        "{near} sides facing views ({wide} wide), {far} away"
    );
}

/// A holder that reflects: the views see it around the sample's outline,
/// Lambertian with its albedo under the beam paths that reach it (the
/// analytic radiance within 1 %), where a black holder leaves them dark;
/// the face's pixels clear of the outline are the same.
#[test]
fn a_light_holder_is_seen_around_the_sample_with_its_albedo() {
    let albedo = 0.5;
    let black = sim(4, "leather", SEED);
    let light = black.clone().with_holder_albedo(albedo);
    let g = black.geometry().clone();
    let cam = &g.camera;
    let (_, _, forward) = cam.basis();
    let gain = g.sensor.max_code() / g.sensor.full_well_e;
    let (mut holder, mut face) = (0, 0);
    for lit in [0usize, 13, 30] {
        let axes = g.mirror_axes(lit).unwrap();
        let e = exposure(axes);
        let (dark, seen) = (black.expected(&e), light.expected(&e));
        for view in [3usize, 17, 23, 39] {
            // Points beyond the middle of each edge, 1.5 mm out, and on the
            // face 3 mm in.
            for (k, uv) in [[0.5, -0.06], [1.06, 0.5], [0.5, 1.06], [-0.06, 0.5], [0.38, 0.62]]
                .iter()
                .enumerate()
            {
                let Some([x, y]) = g.view_point(view, *uv) else { continue };
                let (px, py) = (x.floor(), y.floor());
                // Every corner of the pixel, and its centre, on one surface.
                let corners = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (0.5, 0.5)];
                let hits: Vec<_> =
                    corners.iter().map(|(dx, dy)| light.trace(px + dx, py + dy)).collect();
                let (xu, yu) = (px as u32, py as u32);
                if k == 4 {
                    assert!(hits.iter().all(|h| h.is_some_and(|h| h.surface == Surface::Face)));
                    assert_eq!(dark.pixel(xu, yu), seen.pixel(xu, yu), "lit {lit} view {view}");
                    face += 1;
                    continue;
                }
                assert!(
                    hits.iter().all(|h| h.is_some_and(|h| h.surface == Surface::Holder)),
                    "lit {lit} view {view} beyond edge {k}: {hits:?}"
                );
                assert!(black.trace(x, y).is_none());
                assert_eq!(dark.pixel(xu, yu), [0.0; 3], "lit {lit} view {view}: a black holder");
                let hit = hits[4].unwrap();
                let radiance: f64 = light
                    .light_paths(axes, hit.point)
                    .iter()
                    .map(|p| albedo / std::f64::consts::PI * p.light.z.max(0.0) * p.irradiance)
                    .sum();
                let cos = cam.ray(px + 0.5, py + 0.5).dot(forward);
                let el = radiance
                    * hit.transmission
                    * e.exposure_s
                    * g.sensor.sensitivity_e
                    * cos.powf(g.sensor.vignetting_exponent);
                let expect = el * gain / g.sensor.max_code();
                for (c, v) in seen.pixel(xu, yu).iter().enumerate() {
                    assert!(
                        (*v as f64 - expect).abs() <= 0.01 * expect,
                        "lit {lit} view {view} beyond edge {k}, channel {c}: {v} vs {expect}"
                    );
                }
                holder += usize::from(expect > 0.0);
            }
        }
    }
    assert!(holder >= 24 && face >= 8, "{holder} lit holder pixels, {face} face pixels");
}
