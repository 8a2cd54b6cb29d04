//! Fig. 9's enlargement end to end: samples scanned on the simulator and
//! built, the direct images of their large pieces, `scanner enlarge`, and
//! the enlarged material scored against the large piece's ground truth.

mod common;

use std::path::Path;

use hil_sim::materials::lookup;
use host::build::enlarge::{EnlargeOptions, enlarge, read_direct_set};
use scanner_formats::direct::DirectManifest;
use scanner_shading::{Material, MaterialData};

fn sha256(path: &Path) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(std::fs::read(path).unwrap()).iter().map(|b| format!("{b:02x}")).collect()
}

#[test]
fn an_enlarged_material_shades_the_large_piece_as_the_truth_does() {
    let (bin, seed) = (4, 2);
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let d = |n: &str| p(n).display().to_string();
    let materials = ["leather", "rough-metal"];
    let (g, cal, _) = tests::scanned_and_calibrated(dir.path(), seed, bin, 40, &materials);
    let pairs = tests::random_pairs(32, 60.0, seed);
    for m in materials {
        let direct = p(&format!("direct-{m}"));
        let (data, manifest) = tests::built_and_photographed(
            dir.path(),
            &g,
            &cal,
            seed,
            m,
            &Default::default(),
            &direct,
        );
        let small_path = p(&format!("{m}.material"));
        std::fs::write(&small_path, data.to_bytes().unwrap()).unwrap();
        let truth = lookup(m).unwrap();
        assert_eq!(manifest, DirectManifest::read(&direct).unwrap());
        assert!(manifest.white.is_some());

        // The command line.
        let big_path = p(&format!("{m}-80mm.material"));
        let (code, out, err) = common::run(&[
            "enlarge",
            &small_path.display().to_string(),
            "--direct",
            &direct.display().to_string(),
            "-o",
            &big_path.display().to_string(),
        ]);
        assert_eq!(code, Some(0), "{err}");
        assert!(out.contains("101 × 101 texels over 80 × 80 mm from 4 direct images"), "{out}");
        let big = Material::open(&big_path).unwrap();
        let meta = big.metadata();
        assert_eq!(meta.version, scanner_shading::format::VERSION_ENLARGED);
        assert_eq!(meta.extent_mm, [80.0, 80.0]);
        let e = meta.enlargement.as_ref().unwrap();
        assert_eq!((e.columns, e.rows, e.signature.as_str()), (101, 101, "colour"));
        assert_eq!(e.direct_sha256, sha256(&direct.join("direct.toml")));
        assert_eq!(e.directions.len(), 4);
        // The same map in-process, byte for byte.
        let set = read_direct_set(&direct).unwrap();
        let (again, _) = enlarge(&data, &set, &EnlargeOptions::default()).unwrap();
        let same = again.to_bytes().unwrap() == std::fs::read(&big_path).unwrap();
        assert!(same, "the command's map and the library's differ");

        // Fidelity against the large piece's truth. Tiling the sample's
        // material over it (a renderer's fallback) misses its long-range
        // variation; the enlargement follows it, and over the window the
        // sample was cut from it nearly matches the sample's own material.
        let small = Material::open(&small_path).unwrap();
        let s = tests::enlargement_scores(&big, &small, truth, &pairs);
        eprintln!("{m}: {s:?}");
        assert!(s.enlarged >= s.tiled + 6.0, "{m}: {s:?}");
        assert!(s.enlarged >= 29.0, "{m}: {s:?}");
        assert!(s.window_enlarged >= s.window_sample - 3.0, "{m}: {s:?}");

        // Without the white reference the scale comes from the matches.
        let mut bare = set.clone();
        (bare.manifest.white, bare.white) = (None, None);
        let (unref, report) = enlarge(&data, &bare, &EnlargeOptions::default()).unwrap();
        let unref = Material::from_bytes(&unref.to_bytes().unwrap()).unwrap();
        let u = tests::enlargement_scores(&unref, &small, lookup(m).unwrap(), &pairs);
        eprintln!("{m} without a white reference: {u:?}, gain {:?}", report.gain);
        assert!(u.enlarged >= s.tiled + 3.0, "{m}: {u:?}");
        assert_eq!(report.channels, [true; 3]);
        // Direct images without the green the sample shows: refused,
        // the channel named.
        let mut greenless = set.clone();
        for im in &mut greenless.images {
            im.rgb.chunks_exact_mut(3).for_each(|px| px[1] = 0.0);
        }
        let Err(e) = enlarge(&data, &greenless, &EnlargeOptions::default()) else {
            panic!("{m}: direct images without green enlarged");
        };
        let e = e.to_string();
        assert!(e.contains("channel 1 is black in the direct images but not on the sample"), "{e}");

        // Photographs taken in perspective, rectified by `scanner rectify`,
        // enlarge as the rectified images do (measured in session 75: each
        // 36.0–36.7 dB against its image, two resamplings of pixel-sharp
        // detail apart; the enlargement 32.81 against 32.85 dB).
        if m == "leather" {
            let (photographed, rectified) = photographed_in_perspective(&direct, &p("photos"));
            eprintln!("rectified photographs against the images: {rectified:.2?} dB");
            for db in &rectified {
                assert!(*db >= 34.0, "a rectified photograph against its image: {db:.2} dB");
            }
            let set = read_direct_set(&photographed).unwrap();
            let (again, _) = enlarge(&data, &set, &EnlargeOptions::default()).unwrap();
            let again = Material::from_bytes(&again.to_bytes().unwrap()).unwrap();
            let r = tests::enlargement_scores(&again, &small, lookup(m).unwrap(), &pairs);
            eprintln!("from rectified photographs: {r:?}");
            assert!(r.enlarged >= s.enlarged - 1.0, "{r:?} against {s:?}");
        }
        // The simulator's own photographs from a tripod 400 mm away (the
        // view direction varies by ±5.7° over the piece), rectified by the
        // corners found in them, the camera's distance in the manifest.
        // Measured in session 75: leather 32.93 dB, rough-metal 31.99 dB
        // (from the direct images 32.85 and 32.04 dB); the metal without
        // the camera's distance 28.07 dB (docs/direct-images.md).
        let distance = hil_sim::direct::PHOTO_DISTANCE_MM;
        let pinhole = hil_sim::direct::PhotoSetup::pinhole(distance);
        let shot = rectified_photographs(&g, seed, m, pinhole, &p(&format!("tripod-{m}")));
        let mut set = read_direct_set(&shot).unwrap();
        let score = |set: &host::build::enlarge::DirectSet| {
            let (again, _) = enlarge(&data, set, &EnlargeOptions::default()).unwrap();
            let again = Material::from_bytes(&again.to_bytes().unwrap()).unwrap();
            tests::enlargement_scores(&again, &small, lookup(m).unwrap(), &pairs)
        };
        let t = score(&set);
        eprintln!("{m} from the simulator's photographs: {t:?}");
        assert!(t.enlarged >= s.enlarged - 1.0, "{t:?} against {s:?}");
        if m == "rough-metal" {
            // Without the camera's distance the glossy metal looks
            // different across the photograph than anywhere on the sample.
            set.manifest.image.iter_mut().for_each(|im| im.camera_distance_mm = None);
            let u = score(&set);
            eprintln!("{m} from the simulator's photographs, uncorrected: {u:?}");
            assert!(t.enlarged >= u.enlarged + 2.0, "{t:?} against {u:?}");
        }
        // Through a lens with 2 % barrel distortion at the photographs'
        // corners (their sides bow by ≈ 1 px, refused as a pinhole's),
        // the lens estimated from the piece's sides: the same (measured in
        // session 75: leather 32.96 dB, against 32.93 dB through a pinhole).
        if m == "leather" {
            let barrel = hil_sim::direct::PhotoSetup { distortion: [-0.02, 0.0], ..pinhole };
            let shot = rectified_photographs(&g, seed, m, barrel, &p(&format!("barrel-{m}")));
            let b = score(&read_direct_set(&shot).unwrap());
            eprintln!("{m} from the simulator's photographs through a barrel lens: {b:?}");
            assert!(b.enlarged >= t.enlarged - 0.3, "{b:?} against {t:?}");
        }

        // The patent's other signature: heights from photometric stereo,
        // on a 5 × 5 neighbourhood (docs/benchmarks.md, "Enlargement":
        // below the colour signature on every library material).
        let by_height = p(&format!("{m}-80mm-height.material"));
        let (code, out, err) = common::run(&[
            "enlarge",
            &small_path.display().to_string(),
            "--direct",
            &direct.display().to_string(),
            "-o",
            &by_height.display().to_string(),
            "--signature",
            "height",
            "--radius",
            "2",
        ]);
        assert_eq!(code, Some(0), "{err}");
        assert!(out.contains("by height") && out.contains("heights need no scale"), "{out}");
        let h = Material::open(&by_height).unwrap();
        assert_eq!(h.metadata().enlargement.as_ref().unwrap().signature, "height");
        let hs = tests::enlargement_scores(&h, &small, lookup(m).unwrap(), &pairs);
        eprintln!("{m} by height: {hs:?}");
        // Measured in session 75: +0.7 (leather) and +2.2 dB (rough-metal)
        // over tiling; a map of misplaced texels falls far below it (the
        // weave's: −5 dB).
        assert!(hs.enlarged >= s.tiled - 0.5, "{m}: {hs:?}");
    }

    // Bad input: a clear error, exit 3, nothing written.
    let small = d("leather.material");
    let direct = p("direct-leather");
    let enlarge_cli = |material: &str, direct: &Path, out: &str| {
        common::run_err(&[
            "enlarge",
            material,
            "--direct",
            &direct.display().to_string(),
            "-o",
            out,
        ])
    };
    let (code, err) = enlarge_cli(&d("leather-80mm.material"), &direct, &d("x.material"));
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("enlarged already"), "{err}");
    let (code, err) = common::run_err(&[
        "enlarge",
        &small,
        "--direct",
        &direct.display().to_string(),
        "-o",
        &d("x.material"),
        "--signature",
        "hue",
    ]);
    assert_eq!(code, Some(2), "{err}");
    let (code, err) = enlarge_cli(&small, &p("nowhere"), &d("x.material"));
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("direct.toml"), "{err}");
    // The output may not replace an input: the material, the manifest, an
    // image.
    let white = std::fs::read(direct.join("white.exr")).unwrap();
    for out in [small.clone(), d("direct-leather/direct.toml"), d("direct-leather/white.exr")] {
        let (code, err) = enlarge_cli(&small, &direct, &out);
        assert_eq!(code, Some(4), "{out}: {err}");
    }
    assert_eq!(std::fs::read(direct.join("white.exr")).unwrap(), white);
    let text = std::fs::read_to_string(direct.join("direct.toml")).unwrap();
    for (edit, want) in [
        (text.replace("albedo = 0.98", "albedo = 2.0"), "albedo 2 outside (0, 1]"),
        (text.replace("format = 1", "format = 7"), "format 7"),
        (text.replace("white.exr", "missing.exr"), "missing.exr"),
        (format!("{text}\nextra = 1\n"), "unknown field"),
    ] {
        std::fs::write(direct.join("direct.toml"), &edit).unwrap();
        let (code, err) = enlarge_cli(&small, &direct, &d("x.material"));
        assert_eq!(code, Some(3), "{want}: {err}");
        assert!(err.contains(want), "{want}: {err}");
    }
    // An image of another size than the others.
    std::fs::write(direct.join("direct.toml"), &text).unwrap();
    let first = &DirectManifest::read(&direct).unwrap().image[1].file;
    let small_white = hil_sim::optics::Frame { width: 5, height: 4, rgb: vec![0.5; 60] };
    hil_sim::camera::write_frame_exr(&small_white, &direct.join(first)).unwrap();
    let (code, err) = enlarge_cli(&small, &direct, &d("x.material"));
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("5 × 4 px, but"), "{err}");
    assert!(!p("x.material").exists());
    // `scanner rectify`'s bad input: options exit 2, a photograph that is
    // not one exit 3, an output that would replace it exit 4; nothing
    // written.
    let photo = d("photos/photo-0.exr");
    let rectify = |photo: &str, corners: &str, size: &str, out: &str| {
        common::run_err(&["rectify", photo, "--corners", corners, "--size-mm", size, "-o", out])
    };
    let square = "10,10,120,12,118,115,12,112";
    let flat = d("photos/flat.exr");
    let grey = hil_sim::optics::Frame { width: 32, height: 24, rgb: vec![0.5; 32 * 24 * 3] };
    hil_sim::camera::write_frame_exr(&grey, Path::new(&flat)).unwrap();
    for (photo, corners, size, out, code, want) in [
        (&photo, "10,10,120,12,118,115", "80", "r.exr", 2, "--corners: auto, or 8 numbers"),
        (&photo, square, "80,80,80", "r.exr", 2, "--size-mm: W,H"),
        (&photo, square, "0,80", "r.exr", 2, "--size-mm 0,80"),
        (&photo, "10,10,9000,12,118,115,12,112", "80", "r.exr", 2, "corner 1 at (9000, 12)"),
        (&photo, "10,10,118,115,120,12,12,112", "80", "r.exr", 2, "not a convex quadrilateral"),
        (&photo, square, "80", "r.png", 2, "must be .exr"),
        (&small, square, "80", "r.exr", 3, "leather.material"),
        (&d("photos/none.exr"), square, "80", "r.exr", 3, "none.exr"),
        (&photo, square, "80", "photos/photo-0.exr", 4, "photo-0.exr"),
        (&photo, "10,10,120,x,118,115,12,112", "80", "r.exr", 2, "\"x\" is not a number"),
        // Nothing to find in a plain grey photograph.
        (&flat, "auto", "80", "r.exr", 3, "the photograph is uniform"),
    ] {
        let (got, err) = rectify(photo, corners, size, &d(out));
        assert_eq!(got, Some(code), "{want}: {err}");
        assert!(err.contains(want), "{want}: {err}");
    }
    // Options that go together or not: --origin and --lens auto need found
    // corners, --refine marked ones; the lens' numbers in range that map
    // the photograph one to one. Exit 2, nothing written.
    for (corners, extra, want) in [
        (square, &["--origin", "top-left"][..], "--origin goes with --corners auto"),
        ("auto", &["--refine"], "--refine goes with marked corners"),
        (square, &["--lens", "auto"], "--lens auto estimates the lens from the piece's sides"),
        (square, &["--lens", "0.1,x"], "auto, or K1[,K2[,FOCAL_PX[,CX,CY]]]"),
        (square, &["--lens", "0.1,0,0,0"], "1, 2, 3 or 5 numbers"),
        (square, &["--lens", "0.1,0,500,-3,20"], "principal point (-3, 20) px lies outside"),
        (square, &["--lens", "12"], "within ±10"),
        (square, &["--lens", "0.1,0,0.5"], "a focal length ≥ 1 px"),
        (square, &["--lens", "-0.6"], "does not map the"),
        ("auto", &["--lens", "-0.6"], "does not map the"),
    ] {
        let out = d("r.exr");
        let args = [
            &["rectify", &photo, "--corners", corners][..],
            extra,
            &["--size-mm", "80", "-o", &out],
        ]
        .concat();
        let (got, err) = common::run_err(&args);
        assert_eq!(got, Some(2), "{extra:?}: {err}");
        assert!(err.contains(want), "{extra:?}: {err}");
        assert!(!Path::new(&out).exists());
    }
    // The outline picture: a PNG, not the photograph.
    for (show, code, want) in
        [("r.exr", 2, "must be .png"), ("photos/photo-0.exr", 4, "photo-0.exr")]
    {
        let (got, err) = common::run_err(&[
            "rectify",
            &photo,
            "--corners",
            square,
            "--size-mm",
            "80",
            "-o",
            &d("r.exr"),
            "--show",
            &d(show),
        ]);
        assert_eq!(got, Some(code), "{show}: {err}");
        assert!(err.contains(want), "{show}: {err}");
    }
    assert!(!p("r.exr").exists() && !p("r.png").exists());
    assert!(host::exrio::read_rgb(Path::new(&photo)).is_ok());
    // A material the reader refuses.
    let mut bytes = std::fs::read(&small).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(p("cut.material"), &bytes).unwrap();
    let (code, err) = enlarge_cli(&d("cut.material"), &p("direct-rough-metal"), &d("x.material"));
    assert_eq!(code, Some(3), "{err}");
    assert!(MaterialData::from_bytes(&bytes).is_err());
    assert!(!p("x.material").exists());
}

/// The images of the direct set `direct` photographed in perspective (each
/// from its own corners, on a canvas 1.4 × the image, a bright holder
/// around the piece), then rectified back by `scanner rectify` into a set
/// at `out` with the same manifest and white reference: the set, and each
/// rectified image's PSNR against its image (peak: the image's largest
/// value).
fn photographed_in_perspective(direct: &Path, out: &Path) -> (std::path::PathBuf, Vec<f64>) {
    use host::build::linalg::Homography;
    let manifest = DirectManifest::read(direct).unwrap();
    let set = out.join("set");
    std::fs::create_dir_all(&set).unwrap();
    std::fs::copy(direct.join("direct.toml"), set.join("direct.toml")).unwrap();
    let white = &manifest.white.as_ref().unwrap().file;
    std::fs::copy(direct.join(white), set.join(white)).unwrap();
    let mut scores = Vec::new();
    for (k, im) in manifest.image.iter().enumerate() {
        let image = host::exrio::read_rgb(&direct.join(&im.file)).unwrap();
        let (w, h) = (image.width as f64, image.height as f64);
        let (pw, ph) = ((1.4 * w) as u32, (1.4 * h) as u32);
        // A camera off to one side, turned a little: the far edge shorter.
        let t = k as f64 * 0.05;
        let corners = [
            [0.12 * w + t * w, 0.10 * h],
            [1.25 * w, 0.16 * h + t * h],
            [1.20 * w - t * w, 1.28 * h],
            [0.18 * w, 1.22 * h - t * h],
        ];
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        let inv = Homography::fit(&square, &corners).unwrap().inverse().unwrap();
        let bilinear = |uv: [f64; 2]| -> [f64; 3] {
            let x = (uv[0] * w - 0.5).clamp(0.0, w - 1.0);
            let y = (uv[1] * h - 0.5).clamp(0.0, h - 1.0);
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w as usize - 1), (y0 + 1).min(h as usize - 1));
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let at = |x: usize, y: usize, c: usize| image.rgb[3 * (y * w as usize + x) + c] as f64;
            std::array::from_fn(|c| {
                (1.0 - fy) * ((1.0 - fx) * at(x0, y0, c) + fx * at(x1, y0, c))
                    + fy * ((1.0 - fx) * at(x0, y1, c) + fx * at(x1, y1, c))
            })
        };
        let peak = image.rgb.iter().copied().fold(0.0f32, f32::max) as f64;
        let mut rgb = Vec::with_capacity((pw * ph * 3) as usize);
        for y in 0..ph {
            for x in 0..pw {
                let mut acc = [0.0f64; 3];
                for a in 0..4 {
                    for b in 0..4 {
                        let p =
                            [x as f64 + (a as f64 + 0.5) / 4.0, y as f64 + (b as f64 + 0.5) / 4.0];
                        let uv = inv.apply(p);
                        let v = if uv.iter().all(|u| (0.0..1.0).contains(u)) {
                            bilinear(uv)
                        } else {
                            [4.0 * peak; 3]
                        };
                        for c in 0..3 {
                            acc[c] += v[c] / 16.0;
                        }
                    }
                }
                rgb.extend(acc.map(|v| v as f32));
            }
        }
        let photo = out.join(format!("photo-{k}.exr"));
        let frame = hil_sim::optics::Frame { width: pw, height: ph, rgb };
        hil_sim::camera::write_frame_exr(&frame, &photo).unwrap();
        let corners: Vec<String> = corners.iter().flatten().map(|v| format!("{v}")).collect();
        let (code, stdout, err) = common::run(&[
            "rectify",
            &photo.display().to_string(),
            "--corners",
            &corners.join(","),
            "--size-mm",
            &format!("{},{}", manifest.size_mm[0], manifest.size_mm[1]),
            "--px-per-mm",
            &format!("{}", w / manifest.size_mm[0]),
            "-o",
            &set.join(&im.file).display().to_string(),
        ]);
        assert_eq!(code, Some(0), "{err}");
        assert!(stdout.contains(&format!("{} × {} px", image.width, image.height)), "{stdout}");
        let back = host::exrio::read_rgb(&set.join(&im.file)).unwrap();
        let peak = image.rgb.iter().copied().fold(0.0f32, f32::max) as f64;
        let mse = back
            .rgb
            .iter()
            .zip(&image.rgb)
            .map(|(a, b)| (*a as f64 - *b as f64).powi(2))
            .sum::<f64>()
            / image.rgb.len() as f64;
        scores.push(10.0 * (peak * peak / mse).log10());
    }
    (set, scores)
}

/// The simulator's photographs of `m`'s large piece taken as `setup` says
/// (`hil_sim::direct::write_photographs`), rectified by `scanner rectify
/// --corners auto` (and `--lens auto` if the lens distorts) into a direct
/// set, as a user would: its directory. The corners found lie within
/// 0.35 px of the simulator's (measured: 0.10 px at worst on leather,
/// 0.13 px on rough-metal, 0.002 px on the white card).
fn rectified_photographs(
    g: &hil_sim::geometry::ScannerGeometry,
    seed: u64,
    m: &str,
    setup: hil_sim::direct::PhotoSetup,
    out: &Path,
) -> std::path::PathBuf {
    use hil_sim::direct::{mirror_view_scale, write_photographs};
    use host::build::corners::{Origin, find_corners};
    use host::build::lens::{Lens, LensChoice};
    let truth = lookup(m).unwrap();
    let sim = hil_sim::optics::OpticalSim::as_built(
        g,
        hil_sim::materials::Sample::small(truth.clone()),
        seed,
    );
    let scale = mirror_view_scale(g);
    let photos = out.join("photographs");
    let shots = write_photographs(&sim, g, truth, 4, scale, setup, &photos).unwrap();
    let (lens, lens_arg) = if setup.distortion == [0.0; 2] {
        (LensChoice::Known(Lens::PINHOLE), "0")
    } else {
        (LensChoice::Estimate, "auto")
    };
    let set = out.join("direct");
    std::fs::create_dir_all(&set).unwrap();
    // What every `scanner rectify` below is given besides the corners.
    let (size, density) = (shots.size_mm.to_string(), scale.to_string());
    let shared = ["--lens", lens_arg, "--size-mm", &size, "--px-per-mm", &density];
    for ph in shots.photo.iter().chain([&shots.white]) {
        let frame = host::exrio::read_rgb(&photos.join(&ph.file)).unwrap();
        let found = find_corners(&frame, Origin::BottomLeft, lens).unwrap();
        let k1 = found.lens.k[0];
        if let Some(sigma) = found.lens_k1_sigma {
            eprintln!(
                "{m}, {}: lens k1 {k1:.5} ± {sigma:.5} against {:?}",
                ph.file, setup.distortion
            );
            // Its standard error from what the small photograph's sides
            // show. The white card's plain sides give k1 within 3 of it
            // (measured: 0.00000 ± 0.00006); the piece's own textured
            // ones within 0.003 (measured: at most 0.0015, 0.6 σ; up to
            // 6 σ on other photographs of this size: docs/direct-images.md,
            // "Lens distortion").
            let err = (k1 - setup.distortion[0]).abs();
            assert!(sigma < 0.005, "{m}, {}: {found:?}", ph.file);
            if ph.file == shots.white.file {
                assert!(err < 3.0 * sigma, "{m}, {}: {found:?}", ph.file);
            } else {
                assert!(err < 0.003, "{m}, {}: {found:?}", ph.file);
            }
        }
        let worst = (0..4)
            .map(|k| {
                let (a, b) = (found.corners[k], ph.corners[k]);
                (a[0] - b[0]).hypot(a[1] - b[1])
            })
            .fold(0.0, f64::max);
        eprintln!("{m}, {}: corners found within {worst:.3} px", ph.file);
        assert!(worst <= 0.35, "{m}, {}: {found:?} against {:?}", ph.file, ph.corners);
        let show = photos.join(format!("{}-corners.png", ph.file));
        let (show_arg, photo) =
            (show.display().to_string(), photos.join(&ph.file).display().to_string());
        let target = set.join(&ph.file).display().to_string();
        let args =
            [&["rectify", "--show", &show_arg, &photo, "--corners", "auto"][..], &shared].concat();
        let (code, err) = common::run_err(&[&args[..], &["-o", &target]].concat());
        assert_eq!(code, Some(0), "{err}");
        // The photograph with the outline drawn: its size, red on the
        // found (1, 0) corner.
        let png = image::open(&show).unwrap().to_rgb8();
        assert_eq!(png.dimensions(), (frame.width, frame.height));
        let [x, y] = found.corners[1].map(|v| v.round() as u32 - 5);
        let red = |p: &image::Rgb<u8>| p[0] > 200 && p[1] < 100 && p[2] < 100;
        assert!((0..3).any(|d| red(png.get_pixel(x + d, y + 5))), "{}", show.display());
        // Corners marked 2 px off and refined rectify it as the found ones
        // (measured in session 75: leather 82.9 dB through the pinhole and
        // 79.8 dB through the barrel lens, rough-metal 73.2 dB).
        if ph.file == shots.photo[0].file {
            let marked: Vec<String> = ph
                .corners
                .iter()
                .enumerate()
                .flat_map(|(k, c)| [c[0] + [2.0, -2.0][k % 2], c[1] - 1.5])
                .map(|v| v.to_string())
                .collect();
            let refined = out.join("refined.exr");
            let (marked, refined_arg) = (marked.join(","), refined.display().to_string());
            let args =
                [&["rectify", &photo, "--corners", &marked, "--refine"][..], &shared].concat();
            let (code, stdout, err) = common::run(&[&args[..], &["-o", &refined_arg]].concat());
            assert_eq!(code, Some(0), "{err}");
            assert!(stdout.contains("the marked corners moved"), "{stdout}");
            let a = host::exrio::read_rgb(&refined).unwrap();
            let b = host::exrio::read_rgb(&set.join(&ph.file)).unwrap();
            let peak = b.rgb.iter().copied().fold(0.0f32, f32::max) as f64;
            let mse =
                a.rgb.iter().zip(&b.rgb).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum::<f64>()
                    / a.rgb.len() as f64;
            let psnr = 10.0 * (peak * peak / mse).log10();
            eprintln!(
                "{m}: the first photograph rectified by refined marks: {psnr:.1} dB against auto"
            );
            assert!(psnr >= 40.0, "{psnr:.1} dB");
        }
    }
    let manifest = shots.manifest();
    std::fs::write(set.join("direct.toml"), manifest.to_toml()).unwrap();
    set
}

/// `scanner demo` of texture set `set` on a 512² sensor with 12 lights
/// into `out`: what it said.
fn quick_demo(set: &Path, out: &Path) -> String {
    let (code, said, err) = common::run(&[
        "demo",
        "--bin",
        "8",
        "--mirrors",
        "12",
        "--material",
        set.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(0), "{said}{err}");
    said
}

/// A texture set unlike the library's in the three ways the demo's
/// enlargement once failed on (session 91): an 8 mm tile, smaller than
/// the sample, so the large piece is ten tiles by ten (80 mm, not the
/// tile); a piece as dark as the black holder, so that its corners cannot
/// be found there and the demo photographs it again on a white card; and
/// a red that reflects no green or blue, so that the colour signature
/// matches by red alone. The enlargement must still follow the tile's
/// pattern across the piece, where the sample tiled (25.4 mm is no
/// multiple of 8) does not. A piece found on neither background (wide
/// stripes as dark as the holder and as light as the card) ends the demo
/// without the enlargement, saying so.
#[test]
fn the_demo_enlarges_a_dark_red_tile_smaller_than_the_sample() {
    let dir = common::tmp();
    let set = dir.path().join("dark-red");
    let tau = std::f64::consts::TAU;
    let red = |x: f64, y: f64| {
        [(0.05 + 0.04 * (tau * x / 8.0).sin() * (tau * y / 4.0).cos()) as f32, 0.0, 0.0]
    };
    common::texture_set(&set, 8.0, red, [0.02, 0.0, 0.0], 0.7);
    let out = dir.path().join("demo");
    let said = quick_demo(&set, &out);
    assert!(said.contains("the piece photographed again on a white card (albedo 0.8)"), "{said}");
    assert!(said.contains("101 × 101 texels over 80 × 80 mm from 4 direct images"), "{said}");
    assert!(said.contains("by red alone (green and blue black on the sample)"), "{said}");
    assert!(said.contains("dark-red-large-preview.png"), "{said}");
    assert!(out.join("dark-red-large-preview.png").is_file());
    let shots = std::fs::read_to_string(out.join("dark-red-photographs/photographs.toml")).unwrap();
    assert!(
        shots.contains("size_mm = 80.0") && shots.contains("background_albedo = 0.8"),
        "{shots}"
    );

    let big = Material::open(&out.join("dark-red-large.material")).unwrap();
    let small = Material::open(&out.join("dark-red.material")).unwrap();
    let pairs = tests::random_pairs(32, 60.0, 1);
    let s = tests::enlargement_scores(&big, &small, lookup(set.to_str().unwrap()).unwrap(), &pairs);
    eprintln!("dark-red: {s:?}");
    assert!(s.enlarged >= s.tiled + 3.0, "{s:?}");

    let set = dir.path().join("stripes");
    let stripe = |_: f64, y: f64| [if y % 8.0 < 4.0 { 0.04 } else { 0.8 }; 3];
    common::texture_set(&set, 16.0, stripe, [0.04; 3], 0.9);
    let out = dir.path().join("stripes-demo");
    let said = quick_demo(&set, &out);
    assert!(said.contains("found on neither the black holder nor a white card"), "{said}");
    assert!(!said.contains("stripes-large-preview.png"), "{said}");
    assert!(out.join("stripes-preview.png").is_file());
    assert!(!out.join("stripes-large.material").exists());
}
