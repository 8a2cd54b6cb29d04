//! HDR capture: a glossy sample (GGX α = 0.1, F0 = 0.9: highlights ≈ 20×
//! a white target) clips a single 50 ms exposure; a bracket merges to a
//! frame with no clipped value whose highlight matches the simulator's
//! noise-free truth within the sensor noise.

mod common;

use hil_sim::materials::{Sample, lookup};
use hil_sim::optics::{Exposure, OpticalSim};
use scanner_geometry::AxisValues;

fn glossy_set(dir: &std::path::Path) {
    common::uniform_set(dir, "gloss", 40.0, [0.05; 3], 0.9, 0.1f32.sqrt());
}

fn scan(set: &str, out: &std::path::Path, extra: &[&str]) -> (Option<i32>, String) {
    let mut args = vec![
        "scan",
        "--sim-material",
        set,
        "--sim-bin",
        "4",
        "--sim-seed",
        "3",
        "--mirrors",
        "4",
        "--sample-name",
        "gloss",
        "--out",
    ];
    let o = out.display().to_string();
    args.push(&o);
    args.extend_from_slice(extra);
    common::run_err(&args)
}

#[test]
fn a_bracket_merges_without_clipping_and_matches_the_truth() {
    let dir = common::tmp();
    let set = dir.path().join("gloss");
    glossy_set(&set);
    let set = set.display().to_string();
    // One exposure: the highlights clip at the top code.
    let single = dir.path().join("single");
    let (code, err) = scan(&set, &single, &[]);
    assert_eq!(code, Some(0), "{err}");
    let m = host::scan::Manifest::load(&single).unwrap();
    let clipped: usize = m
        .frames
        .iter()
        .map(|f| {
            let fr = host::exrio::read_rgb(&single.join(&f.file)).unwrap();
            fr.rgb.iter().filter(|&&v| v >= 1.0).count()
        })
        .sum();
    assert!(clipped > 50, "the single exposure clips ({clipped} values)");
    // A bracket.
    let hdr = dir.path().join("hdr");
    let (code, err) = scan(&set, &hdr, &["--exposures", "2000,10000,50000"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated"), "{err}");
    let m = host::scan::Manifest::load(&hdr).unwrap();
    assert_eq!(m.settings.bracket_us, vec![2000, 10000, 50000]);
    assert!(m.exposures.is_empty(), "single exposures are removed once merged");
    assert_eq!(std::fs::read_dir(hdr.join("frames/raw")).unwrap().count(), 0);
    for f in &m.frames {
        assert_eq!(f.exposure_us, 50_000);
    }
    let (n, rms, mean, peak) = highlights_against_truth(&set, &hdr, 3);
    assert!(n > 50, "highlight values: {n}");
    assert!(peak > 5.0, "a real highlight: {peak}");
    assert!(rms < 1.3 && mean.abs() < 0.15, "within noise: RMS z {rms}, mean z {mean}");
}

/// The merged frames of HDR scan `dir` (simulated `set`, seed `seed`, bin 4)
/// against the simulator's noise-free truth of the same as-built scanner,
/// where one exposure would clip (truth above 1.2 of the longest's full
/// scale): (values, RMS and mean of their z-scores, the largest truth).
/// Each value's noise is that of the longest exposure of its frame's
/// bracket it does not saturate.
fn highlights_against_truth(set: &str, dir: &std::path::Path, seed: u64) -> (usize, f64, f64, f64) {
    let m = host::scan::Manifest::load(dir).unwrap();
    let g = scanner_geometry::ScannerGeometry::default_scanner().with_sensor_scaled(4);
    let sim = OpticalSim::as_built(&g, Sample::small(lookup(set).unwrap()), seed);
    let s = &g.sensor;
    let (mut n, mut z2, mut zsum, mut peak) = (0usize, 0.0, 0.0, 0.0f64);
    for f in &m.frames {
        let bracket = if f.bracket_us.is_empty() { &m.settings.bracket_us } else { &f.bracket_us };
        let reference = f.exposure_us as f64;
        assert_eq!(f.exposure_us, *bracket.iter().max().unwrap());
        let merged = host::exrio::read_rgb(&dir.join(&f.file)).unwrap();
        let truth = sim.expected(&Exposure {
            axes: AxisValues::from_array(f.axis_units),
            exposure_s: reference * 1e-6,
            light: 1.0,
        });
        for (v, t) in merged.rgb.iter().zip(&truth.rgb) {
            let t = *t as f64;
            if t < 1.2 {
                continue; // only what one exposure would clip
            }
            let Some(k) =
                bracket.iter().rev().map(|&e| reference / e as f64).find(|k| t / k < 0.95)
            else {
                panic!("{}: a value of {t:.1}× full scale saturates every exposure", f.file)
            };
            let e = t / k * s.full_well_e;
            let sigma = (e + s.read_noise_e.powi(2)).sqrt() / s.full_well_e * k;
            let z = (*v as f64 - t) / sigma;
            n += 1;
            z2 += z * z;
            zsum += z;
            peak = peak.max(t);
        }
    }
    let (rms, mean) = ((z2 / n.max(1) as f64).sqrt(), zsum / n.max(1) as f64);
    eprintln!("{n} highlight values up to {peak:.1}× full scale: z RMS {rms:.2}, mean {mean:.3}");
    (n, rms, mean, peak)
}

/// Auto exposure (docs/scan-format.md): a dark matte sample gets a longer
/// exposure than the default, a glossy one a bracket reaching down to its
/// highlights; the choice is recorded, kept on resume, and merged without
/// saturation.
#[test]
fn auto_exposure_meters_the_sample_and_a_resume_keeps_its_choice() {
    let dir = common::tmp();
    let gloss = dir.path().join("gloss");
    glossy_set(&gloss);
    let dark = dir.path().join("dark");
    common::uniform_set(&dark, "dark", 40.0, [0.03; 3], 0.02, 0.9);
    // The dark sample, HDR, stopped by an E-stop after metering (triggers
    // 1–4, the dark frame 5) and in the middle of mirror 1's bracket: the
    // resume takes the directory's bracket and is not metered again.
    let out = dir.path().join("dark-hdr");
    let dark_set = dark.display().to_string();
    let (code, err) = scan(
        &dark_set,
        &out,
        &["--exposure-us", "auto", "--hdr", "--sim-fault", "estop:on@trigger=9"],
    );
    assert_ne!(code, Some(0), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let bracket = m.settings.bracket_us.clone();
    assert_eq!(bracket.len(), 3, "{:?}", m.settings.metering);
    assert!(!m.complete && !m.frames.is_empty(), "{err}");
    let (code, err) = scan(&dark_set, &out, &["--exposure-us", "auto", "--hdr", "--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("metered"), "not metered again: {err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    assert!(m.complete && m.frames.len() == 4 && m.exposures.is_empty());
    assert_eq!(m.settings.bracket_us, bracket);
    assert!(m.frames.iter().all(|f| f.exposure_us == *bracket.last().unwrap()));
    // The dark sample, one exposure: longer than the default 50 ms.
    let out = dir.path().join("dark-scan");
    let (code, err) = scan(&dark.display().to_string(), &out, &["--exposure-us", "auto"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("metered mirrors 0–3"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let metering = m.settings.metering.clone().expect("metering recorded");
    assert_eq!(m.settings.auto_exposure, Some(host::scan::AutoExposure::Single));
    assert!(m.settings.bracket_us.is_empty());
    assert!(m.settings.exposure_us > 200_000, "{metering:?} → {} µs", m.settings.exposure_us);
    assert!(m.frames.iter().all(|f| f.exposure_us == m.settings.exposure_us));
    // The glossy sample, HDR: a bracket of 5× steps reaching below 2 ms.
    let out = dir.path().join("gloss-scan");
    let gloss = gloss.display().to_string();
    let (code, err) = scan(&gloss, &out, &["--exposure-us", "auto", "--hdr"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let b = m.settings.bracket_us.clone();
    let metering = m.settings.metering.clone().expect("metering recorded");
    assert!((3..=5).contains(&b.len()), "{b:?} from {metering:?}");
    assert!(b.windows(2).all(|w| w[1] as f64 / w[0] as f64 <= 5.0 + 1e-3), "steps ≤ 5×: {b:?}");
    assert_eq!(*b.last().unwrap(), m.settings.exposure_us);
    // Its highlights, ≈ 20× a white target's level, pass 50 ms's full scale
    // at the metered mirrors; the shortest exposure holds them.
    let fits =
        metering.peak.is_some_and(|p| p * b[0] as f64 / metering.exposure_us as f64 <= 0.8 + 1e-3);
    assert!(fits || b[0] == 1_000 || b.len() == 5, "{b:?} from {metering:?}");
    assert!(b[0] < 10_000, "{b:?} from {metering:?}");
    // A resume keeps the directory's choice (nothing to take: it is
    // complete), whatever metering would say now; fixed exposures are refused.
    let (code, err) = scan(&gloss, &out, &["--exposure-us", "auto", "--hdr", "--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("metered"), "not metered again: {err}");
    assert_eq!(host::scan::Manifest::load(&out).unwrap().settings.bracket_us, b);
    let (code, err) = scan(&gloss, &out, &["--hdr", "--resume"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("exposure choice"), "{err}");
    let (code, err) = scan(&gloss, &out, &["--exposure-us", "auto", "--exposures", "2000,5000"]);
    assert_eq!(code, Some(2), "{err}");
}

/// A grey matte sample with a small glossy patch at uv 0.05…0.16, outside
/// the central half metering reads: the metered bracket clips the patch's
/// highlights, so auto HDR adds shorter exposures at the mirrors where
/// they show (recorded per frame), down to where nothing saturates, and
/// the merge matches the truth within noise — also when an E-stop stops
/// the scan between a bracket and its extension.
#[test]
fn auto_hdr_extends_the_bracket_where_highlights_metering_missed_clip() {
    let dir = common::tmp();
    let set = dir.path().join("patch");
    std::fs::create_dir_all(&set).unwrap();
    std::fs::write(set.join("material.toml"), "format = 1\nname = \"patch\"\nsize_mm = 25.4\n")
        .unwrap();
    let patch = |x: u32, y: u32| (3..10).contains(&x) && (3..10).contains(&y);
    let map = |name: &str, on: [f32; 3], off: [f32; 3]| {
        image::Rgb32FImage::from_fn(64, 64, |x, y| image::Rgb(if patch(x, y) { on } else { off }))
            .save(set.join(name))
            .unwrap();
    };
    map("diffuse.exr", [0.02; 3], [0.3; 3]);
    map("specular.exr", [0.9; 3], [0.04; 3]);
    map("roughness.exr", [0.1f32.sqrt(); 3], [0.9; 3]);
    map("normal.exr", [0.5, 0.5, 1.0], [0.5, 0.5, 1.0]);
    let set = set.display().to_string();
    let out = dir.path().join("scan");
    let (code, err) = scan(&set, &out, &["--exposure-us", "auto", "--hdr"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("saturated on the sample"), "{err}");
    assert!(!err.contains("saturated even"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let b = m.settings.bracket_us.clone();
    let extended: Vec<_> = m.frames.iter().filter(|f| !f.bracket_us.is_empty()).collect();
    assert!(!extended.is_empty(), "no mirror extended its bracket {b:?}");
    for f in &extended {
        // The scan's bracket and shorter ones, each ≤ 5× below the last.
        let e = &f.bracket_us;
        assert_eq!(&e[e.len() - b.len()..], &b[..], "{e:?} extends {b:?}");
        assert!(e.windows(2).all(|w| w[1] <= 5 * w[0] + 5), "{e:?}");
    }
    let (n, rms, mean, peak) = highlights_against_truth(&set, &out, 3);
    assert!(n > 10 && peak > 1.0 / (b[0] as f64 / b[b.len() - 1] as f64), "{n} values to {peak}");
    assert!(rms < 1.3 && mean.abs() < 0.2, "within noise: RMS z {rms}, mean z {mean}");
    // Stopped by an E-stop during the longest exposure of the first
    // extended mirror (at its rise, `trigger_seq` triggers in: the light
    // goes off mid-exposure): that frame is discarded, not stored; the
    // resume takes it again, decides the same extension from the stored
    // frames, and is not metered again.
    let first = extended[0];
    let trigger = first.trigger_seq;
    let out2 = dir.path().join("stopped");
    let fault = format!("estop:on@trigger={trigger}");
    let (code, err) = scan(&set, &out2, &["--exposure-us", "auto", "--hdr", "--sim-fault", &fault]);
    assert_ne!(code, Some(0), "{err}");
    assert!(err.contains("emergency stop during mirror") && err.contains("discarded"), "{err}");
    let stopped = host::scan::Manifest::load(&out2).unwrap();
    assert!(!stopped.frames.iter().any(|f| f.mirror == first.mirror), "{err}");
    let (code, err) = scan(&set, &out2, &["--exposure-us", "auto", "--hdr", "--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("metered"), "{err}");
    let resumed = host::scan::Manifest::load(&out2).unwrap();
    let again = resumed.frames.iter().find(|f| f.mirror == first.mirror).unwrap();
    assert_eq!(again.bracket_us, first.bracket_us);
    assert!(resumed.complete && resumed.exposures.is_empty());
    let (_, rms, mean, _) = highlights_against_truth(&set, &out2, 3);
    assert!(rms < 1.3 && mean.abs() < 0.2, "resumed: RMS z {rms}, mean z {mean}");
}

/// A near-mirror (GGX α = 0.01, F0 = 0.95: highlights ≈ 2 500× a white
/// target) saturates even the device's shortest exposure, 1 ms. Exposures
/// below it are taken at 1 ms with the light dimmed in proportion
/// (docs/scan-format.md, "HDR"): a fixed bracket reaching 100 µs and the
/// auto bracket's extension both merge to frames whose highlights match
/// the truth within noise — which they would miss tenfold if the light
/// were not dimmed as recorded.
#[test]
fn a_near_mirror_is_held_by_exposures_below_1_ms_with_the_light_dimmed() {
    let dir = common::tmp();
    let set = dir.path().join("mirror");
    common::uniform_set(&set, "mirror", 40.0, [0.0; 3], 0.95, 0.1);
    let set = set.display().to_string();
    // The device's shortest exposure at full light clips the highlights.
    let (code, err) = scan(&set, &dir.path().join("ms"), &["--exposures", "1000,5000,25000"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("saturated even at 1000 µs"), "{err}");
    // 100 µs: 1 ms at 100 ‰.
    let fixed = dir.path().join("fixed");
    let (code, err) = scan(&set, &fixed, &["--exposures", "100,1000,10000"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated"), "{err}");
    let (n, rms, mean, peak) = highlights_against_truth(&set, &fixed, 3);
    // Above 1 ms's full scale (in units of the longest, 10 ms).
    assert!(n > 50 && peak > 2.0 * 10_000.0 / 1_000.0, "{n} values up to {peak}");
    assert!(rms < 1.3 && mean.abs() < 0.2, "within noise: RMS z {rms}, mean z {mean}");
    // Each merged frame records how its exposures agreed: the dimmed
    // 100 µs with the 1 ms, the 1 ms with the 10 ms.
    let ratios = |dir: &std::path::Path| -> Vec<host::hdr::ExposureRatio> {
        let m = host::scan::Manifest::load(dir).unwrap();
        m.frames.iter().flat_map(|f| f.exposure_ratios.clone()).collect()
    };
    let clean = ratios(&fixed);
    assert!(clean.iter().any(|r| r.shorter_us == 100), "{clean:?}");
    assert!(clean.iter().all(|r| (r.ratio - 1.0).abs() < 0.015), "{clean:?}");
    assert!(!err.contains("the merge assumes 1"), "{err}");
    // A light driver that loses 0.5 µs of every 5 µs pulse at 100 ‰ gives
    // 0.9 of its duty: said, and recorded.
    let slow = dir.path().join("slow");
    let (code, err) =
        scan(&set, &slow, &["--exposures", "100,1000,10000", "--sim-fault", "slow-light:500@ms=0"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("the 100 µs exposure (taken at 1 ms with the light at 100 ‰) measured 0.9")
            && err.contains("check the light's linearity at low duty"),
        "{err}"
    );
    let dimmed: Vec<_> = ratios(&slow).into_iter().filter(|r| r.shorter_us == 100).collect();
    assert!(!dimmed.is_empty(), "{:?}", ratios(&slow));
    assert!(dimmed.iter().all(|r| (r.ratio - 0.9).abs() < 0.015), "{dimmed:?}");
    // Auto HDR extends the metered bracket below 1 ms where it clips.
    let auto = dir.path().join("auto");
    let (code, err) = scan(&set, &auto, &["--exposure-us", "auto", "--hdr"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated even"), "{err}");
    let m = host::scan::Manifest::load(&auto).unwrap();
    let shortest =
        |f: &host::scan::FrameRecord| *f.bracket_us.first().unwrap_or(&m.settings.bracket_us[0]);
    assert!(m.frames.iter().any(|f| shortest(f) < 1_000), "{err}");
    let (n, rms, mean, _) = highlights_against_truth(&set, &auto, 3);
    assert!(n > 50 && rms < 1.3 && mean.abs() < 0.2, "{n} values: RMS z {rms}, mean z {mean}");
    // Below the dimmest duty: refused before anything moves.
    let (code, err) = scan(&set, &dir.path().join("x"), &["--exposures", "10,1000"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("10 µs outside 20…2000000"), "{err}");
}

/// The board's light follows the trigger pulse; a camera that exposes
/// later than its trigger's edges (an opto-isolated input's delay, a
/// trigger debounce set in the camera) misses the light's last µs: a fixed
/// time, so a larger share of the shorter exposures. The merge's exposure
/// agreement sees it and says what to check; on time, the same bracket
/// agrees to 1.5 %.
#[test]
fn a_camera_that_exposes_later_than_its_trigger_is_reported() {
    let dir = common::tmp();
    let ratios = |extra: &[&str]| {
        let out = dir.path().join(format!("s{}", extra.len()));
        let mut args = vec!["--exposures", "20000,100000"];
        args.extend_from_slice(extra);
        let (code, err) = scan("diffuse-white", &out, &args);
        assert_eq!(code, Some(0), "{err}");
        let m = host::scan::Manifest::load(&out).unwrap();
        let r: Vec<f64> =
            m.frames.iter().flat_map(|f| f.exposure_ratios.iter().map(|r| r.ratio)).collect();
        assert_eq!(r.len(), 4, "every mirror's pair measured: {r:?}");
        (r, err)
    };
    let (on_time, err) = ratios(&[]);
    assert!(on_time.iter().all(|r| (r - 1.0).abs() < 0.015), "{on_time:?}");
    assert!(!err.contains("the merge assumes 1"), "{err}");
    // 2 ms late: (20 − 2) / 20 of the light per µs against (100 − 2) / 100.
    let (late, err) = ratios(&["--sim-trigger-latency-us", "2000"]);
    let expected = (18.0 / 20.0) / (98.0 / 100.0);
    assert!(late.iter().all(|r| (r - expected).abs() < 0.01), "{late:?} against {expected}");
    assert!(
        err.contains("the 20000 µs exposure measured 0.91")
            && err.contains("that the camera exposes while its trigger is high"),
        "{err}"
    );
    // The delay it would be, and the margin that covers it, are said.
    let suggested: Vec<u32> = err
        .split("--light-margin-us ")
        .skip(1)
        .map(|rest| rest.split(' ').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(suggested.len(), 4, "{err}");
    assert!(suggested.iter().all(|&m| (2_000..=2_800).contains(&m)), "{suggested:?}");
    // The light on 2.5 ms around each pulse (protocol 1.3) covers the late
    // exposure: the bracket agrees again, and the manifest says how.
    let (mended, err) = ratios(&["--sim-trigger-latency-us", "2000", "--light-margin-us", "2500"]);
    assert!(mended.iter().all(|r| (r - 1.0).abs() < 0.015), "{mended:?}");
    assert!(!err.contains("the merge assumes 1"), "{err}");
    let m = host::scan::Manifest::load(&dir.path().join("s4")).unwrap();
    assert_eq!(m.settings.light_margin_us, 2500);
    let again = [
        "--exposures",
        "20000,100000",
        "--sim-trigger-latency-us",
        "2000",
        "--light-margin-us",
        "100",
        "--resume",
    ];
    let (code, err) = scan("diffuse-white", &dir.path().join("s4"), &again);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("light margin 2500 µs (the directory's) vs 100 µs"), "{err}");
    let (code, err) = scan("diffuse-white", &dir.path().join("x"), &["--light-margin-us", "10001"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("light margin 10001 µs: at most 10000 µs"), "{err}");
}

/// A real sensor's stuck pixels read the top code at every exposure; on
/// the sample's views they look like highlights no exposure holds. Auto
/// exposure finds them (and dead pixels) in its metering frames, and hot
/// ones in a dark frame (docs/scan-format.md, "Sensor defects"): no mirror's bracket is
/// extended for them, nothing is reported saturated, the merged frames
/// (and a single auto exposure) hold their neighbours' mean — within a few
/// per cent of the light's truth there — while the raw exposures keep what
/// the sensor read.
#[test]
fn stuck_dead_and_hot_sensor_pixels_are_found_while_metering_and_replaced() {
    use host::defects::{DefectKind, PixelDefect};
    let dir = common::tmp();
    let set = dir.path().join("matte");
    common::uniform_set(&set, "matte", 25.4, [0.4, 0.3, 0.2], 0.04, 0.9);
    let set = set.display().to_string();
    let g = scanner_geometry::ScannerGeometry::default_scanner().with_sensor_scaled(4);
    let at = |view: usize, uv: [f64; 2]| {
        let p = g.view_point(view, uv).unwrap();
        (p[0] as u32, p[1] as u32)
    };
    let placed = [
        (DefectKind::Stuck, at(0, [0.5, 0.5])),
        (DefectKind::Stuck, at(2, [0.3, 0.7])),
        (DefectKind::Stuck, at(3, [0.8, 0.2])),
        (DefectKind::Dead, at(1, [0.5, 0.5])),
        (DefectKind::Hot, at(1, [0.7, 0.3])),
    ];
    // The hot pixel: 5 000 dark electrons per second (26 codes at 200 ms on
    // this 4×-binned sensor's 160 000 e⁻ full well).
    let specs: Vec<String> = placed
        .iter()
        .map(|(k, (x, y))| match k {
            DefectKind::Stuck => format!("stuck:{x},{y}"),
            DefectKind::Dead => format!("dead:{x},{y}"),
            DefectKind::Hot => format!("hot:{x},{y},5000"),
        })
        .chain(["random:40".to_string()])
        .collect();
    let mut args = vec!["--exposure-us", "auto", "--hdr"];
    for s in &specs {
        args.extend(["--sim-defect", s.as_str()]);
    }
    let out = dir.path().join("scan");
    let (code, err) = scan(&set, &out, &args);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let found = &m.settings.defects();
    let dark = m.settings.dark.as_ref().expect("a dark frame recorded");
    assert_eq!(Some(&dark.exposure_us), m.settings.bracket_us.last(), "{dark:?}");
    assert!(err.contains("sensor defects:"), "{err}");
    // Every placed defect is found, and nothing the sensor does not have.
    let parsed: Vec<hil_sim::defects::DefectSpec> =
        specs.iter().map(|s| s.parse().unwrap()).collect();
    let truth = hil_sim::defects::place(&parsed, g.camera.width, g.camera.height, 3).unwrap();
    let truth: Vec<PixelDefect> = truth
        .iter()
        .map(|d| match *d {
            hil_sim::defects::PixelDefect::Stuck { x, y } => {
                PixelDefect { x, y, kind: DefectKind::Stuck }
            }
            hil_sim::defects::PixelDefect::Dead { x, y } => {
                PixelDefect { x, y, kind: DefectKind::Dead }
            }
            hil_sim::defects::PixelDefect::Hot { x, y, .. } => {
                PixelDefect { x, y, kind: DefectKind::Hot }
            }
        })
        .collect();
    for (kind, (x, y)) in placed {
        assert!(
            found.contains(&PixelDefect { x, y, kind }),
            "{kind:?} ({x}, {y}) not in {found:?}"
        );
    }
    assert!(found.iter().all(|d| truth.contains(d)), "{found:?}");
    eprintln!(
        "{} defects found ({} placed, 80 at random over the frame)",
        found.len(),
        placed.len()
    );
    // No mirror's bracket was extended.
    assert!(m.frames.iter().all(|f| f.bracket_us.is_empty()), "{:?}", m.frames);
    let sim = OpticalSim::as_built(&g, Sample::small(lookup(&set).unwrap()), 3);
    let check = |dir: &std::path::Path, m: &host::scan::Manifest, found: &[PixelDefect]| {
        let mut worst = 0.0f64;
        for f in &m.frames {
            let frame = host::exrio::read_rgb(&dir.join(&f.file)).unwrap();
            let truth = sim.expected(&Exposure {
                axes: AxisValues::from_array(f.axis_units),
                exposure_s: f.exposure_us as f64 * 1e-6,
                light: 1.0,
            });
            for d in found {
                let i = 3 * (d.y * frame.width + d.x) as usize;
                let t = truth.rgb[i..i + 3].iter().map(|&v| v as f64).sum::<f64>();
                if t < 0.05 {
                    continue; // not lit in this frame
                }
                let v = frame.rgb[i..i + 3].iter().map(|&v| v as f64).sum::<f64>();
                worst = worst.max((v / t - 1.0).abs());
            }
        }
        worst
    };
    let worst = check(&out, &m, found);
    eprintln!("replaced pixels: at most {:.2} % from the truth", 100.0 * worst);
    assert!(worst < 0.05, "a replaced pixel {:.1} % from the truth", 100.0 * worst);
    // Stopped during mirror 2's exposures and resumed: not metered again,
    // the recorded defects replaced in the mirrors merged after the resume,
    // to the same bytes.
    let stopped = dir.path().join("stopped");
    let trigger = m.frames.iter().find(|f| f.mirror == 2).unwrap().trigger_seq;
    let fault = format!("estop:on@trigger={trigger}");
    let mut stop_args = args.clone();
    stop_args.extend(["--sim-fault", fault.as_str()]);
    let (code, err) = scan(&set, &stopped, &stop_args);
    assert_ne!(code, Some(0), "{err}");
    let mut resume_args = args.clone();
    resume_args.push("--resume");
    let (code, err) = scan(&set, &stopped, &resume_args);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("metered") && !err.contains("saturated"), "{err}");
    let resumed = host::scan::Manifest::load(&stopped).unwrap();
    assert_eq!(&resumed.settings.defects(), found);
    for f in &m.frames {
        let again = resumed.frames.iter().find(|r| r.mirror == f.mirror).unwrap();
        assert_eq!(again.sha256, f.sha256, "mirror {}", f.mirror);
    }
    // A fixed bracket meters nothing but takes its dark frame too: the
    // stuck pixels it shows are replaced, and nothing is reported
    // saturated. At its 20 ms the hot pixel's dark signal is 2.6 codes,
    // within the read noise's reach and not recorded; a hotter one (100 000
    // e⁻/s, 51 codes) is found and replaced. The dead ones, which a dark
    // frame cannot tell, stay at 0 (the calibration's white frames find
    // those).
    let fixed = dir.path().join("fixed");
    let hotter = at(2, [0.5, 0.5]);
    let hotter_spec = format!("hot:{},{},100000", hotter.0, hotter.1);
    let mut fixed_args = vec!["--exposures", "2000,20000", "--sim-defect", &hotter_spec];
    for s in &specs {
        fixed_args.extend(["--sim-defect", s.as_str()]);
    }
    let (code, err) = scan(&set, &fixed, &fixed_args);
    assert_eq!(code, Some(0), "{err}");
    assert!(!err.contains("saturated"), "{err}");
    let mf = host::scan::Manifest::load(&fixed).unwrap();
    let dark = mf.settings.dark.as_ref().expect("a dark frame recorded");
    assert_eq!(dark.exposure_us, 20_000);
    let stuck: Vec<PixelDefect> =
        found.iter().copied().filter(|d| d.kind == DefectKind::Stuck).collect();
    let hotter = PixelDefect { x: hotter.0, y: hotter.1, kind: DefectKind::Hot };
    assert_eq!(dark.defects, host::defects::union(&stuck, &[hotter]));
    let worst = check(&fixed, &mf, &dark.defects);
    assert!(worst < 0.05, "fixed bracket: a replaced pixel {:.1} % from the truth", 100.0 * worst);
    let frame = host::exrio::read_rgb(&fixed.join(&mf.frames[0].file)).unwrap();
    let (x, y) = placed[3].1;
    let i = 3 * (y * frame.width + x) as usize;
    assert_eq!(&frame.rgb[i..i + 3], &[0.0; 3], "the dead pixel, not replaced");
    // One auto exposure: its frames are replaced too.
    let single = dir.path().join("single");
    args.retain(|a| *a != "--hdr");
    let (code, err) = scan(&set, &single, &args);
    assert_eq!(code, Some(0), "{err}");
    let m1 = host::scan::Manifest::load(&single).unwrap();
    assert_eq!(&m1.settings.defects(), found);
    let worst = check(&single, &m1, found);
    assert!(
        worst < 0.05,
        "single exposure: a replaced pixel {:.1} % from the truth",
        100.0 * worst
    );
}
