//! Seed inputs for the fuzz targets (`scripts/fuzz.sh`): small valid
//! material files, one per interpolation, in `DIR/material`, and small
//! query and answer files (`.npy` and `.csv`) in `DIR/queries`, and small
//! OpenEXR frames (PIZ and uncompressed, scan lines and tiles) in
//! `DIR/frame` and `DIR/texture_map`, the default scanner's geometry file
//! in `DIR/geometry`, axis configuration files in `DIR/axes`, and a calibration of it (the nominal views, a 2 × 2
//! colour grid) in `DIR/calibration`, and the manifests of two small
//! simulated scans (3 mirrors at one exposure — also as a watched strobe records it —, 2 with a bracket of three;
//! the sensor binned 64×) in `DIR/manifest`, two direct-image manifests in
//! `DIR/direct`, pictures of a piece on a background in `DIR/corners`,
//! scattered BRDF measurements
//! in `DIR/measurements` and an NPF model fitted to them in
//! `DIR/npf_model`, so that the fuzzer starts from files that pass the
//! container and header checks.
//!
//! `cargo run -p host --example fuzz_seeds -- DIR`

#[path = "../benches/support/synthetic.rs"]
mod synthetic;

use scanner_formats::queries::{Query, write_answers, write_queries};
use scanner_shading::Interpolation;
use synthetic::{Shape, synthetic, with_detail, with_enlargement, with_texel_model};

fn main() {
    let root = std::path::PathBuf::from(std::env::args().nth(1).expect("usage: fuzz_seeds DIR"));
    let dir = root.join("material");
    std::fs::create_dir_all(&dir).unwrap();
    let patent = Interpolation::Patent { columns: 16, rows: 4, points: 20 };
    let shape = |mirrors, resolution, colours, lights_per_index| Shape {
        mirrors,
        resolution,
        colours,
        lights_per_index,
    };
    for (name, m) in [
        ("default-6", synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 6)),
        ("default-3", synthetic(&shape(3, 2, 2, 1), Interpolation::Default, 0.0, 3)),
        ("patent-5", synthetic(&shape(5, 4, 4, 2), patent, 0.5, 5)),
        (
            "texel-model-6",
            with_texel_model(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 7), 8),
        ),
        (
            "detail-6",
            with_detail(
                with_texel_model(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 9), 10),
                0,
                11,
            ),
        ),
        (
            "light-detail-6",
            with_detail(synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 12), 2, 13),
        ),
        (
            "enlarged-6",
            with_enlargement(
                with_texel_model(
                    synthetic(&shape(6, 4, 4, 2), Interpolation::Default, 0.5, 14),
                    15,
                ),
                5,
                3,
                [40.0, 24.0],
                16,
            ),
        ),
    ] {
        // Without the content digest, which would stop nearly every
        // mutation before the checks behind it.
        let bytes = scanner_shading::format::without_digest(&m.to_bytes().unwrap()).unwrap();
        // Every seed is a material the reader accepts.
        scanner_shading::Material::from_bytes(&bytes).unwrap();
        std::fs::write(dir.join(format!("{name}.material")), &bytes).unwrap();
        println!("{name}: {} bytes", bytes.len());
    }
    let dir = root.join("queries");
    std::fs::create_dir_all(&dir).unwrap();
    let queries: Vec<Query> = (0..3)
        .map(|i| {
            let t = i as f64 * 0.4;
            Query::from_row([0.1 * i as f64, 0.7, t.sin(), 0.0, t.cos(), 0.0, -t.sin(), t.cos()], i)
                .unwrap()
        })
        .collect();
    for name in ["q.npy", "q.csv"] {
        write_queries(&dir.join(name), &queries).unwrap();
    }
    let answers = [[0.25f32, 0.5, 1.0], [0.0, 1e-3, 7.5]];
    for name in ["a.npy", "a.csv"] {
        write_answers(&dir.join(name), &answers).unwrap();
    }
    println!("query and answer files in {}", dir.display());
    let (dir, maps) = (root.join("frame"), root.join("texture_map"));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::create_dir_all(&maps).unwrap();
    // A ramp with some noise, as a camera's (PIZ's Huffman and wavelet
    // stages both have work to do), or without: tiles (≥ 512 px a side)
    // small enough for the fuzzer to mutate quickly.
    let frame = |w: u32, h: u32, noise: f32| {
        let rgb = (0..w * h * 3)
            .map(|i| {
                let (x, y) = ((i / 3) % w, (i / 3) / w);
                let n = ((i as u64 * 2_654_435_761) % 97) as f32 / 97.0;
                0.1 + 0.002 * (x + y) as f32 + noise * n
            })
            .collect();
        host::camera::Frame { width: w, height: h, rgb }
    };
    let (lines, tiles) = (frame(48, 40, 0.01), frame(520, 300, 0.0));
    for (name, f, compressions) in [("lines-48x40", lines, 2), ("tiles-520x300", tiles, 1)] {
        for (kind, bytes) in [
            ("piz", host::exrio::encode_half(&f).unwrap()),
            ("raw", host::exrio::encode_half_uncompressed(&f).unwrap()),
        ]
        .into_iter()
        .take(compressions)
        {
            // Every seed is a frame the decoder reads back; the texture
            // maps' reader starts from the same files.
            let p = dir.join(format!("{name}-{kind}.exr"));
            std::fs::write(&p, &bytes).unwrap();
            assert!(host::exrio::read_rgb(&p).unwrap() == host::exrio::quantise_half(f.clone()));
            std::fs::write(maps.join(format!("{name}-{kind}.exr")), &bytes).unwrap();
            println!("{name}-{kind}: {} bytes", bytes.len());
        }
    }
    // PNG and TIFF frames as capture programs write them (16-bit codes,
    // grey and RGB; 8-bit; 32-bit float TIFF), each behind the byte that
    // tells the `frame_file` target how to read it.
    let dir = root.join("frame_file");
    std::fs::create_dir_all(&dir).unwrap();
    let sensor = host::geometry::ScannerGeometry::default_scanner().sensor;
    let codes: Vec<u16> =
        (0..48 * 40 * 3).map(|i| ((i * 2_654_435_761usize) % 4096) as u16).collect();
    let rgb16 = image::ImageBuffer::from_raw(48, 40, codes.clone()).unwrap();
    let grey16 = image::ImageBuffer::from_raw(48, 40, codes[..48 * 40].to_vec()).unwrap();
    let rgb8 =
        image::ImageBuffer::from_raw(48, 40, codes.iter().map(|&c| c as u8).collect()).unwrap();
    let float: Vec<f32> = codes.iter().map(|&c| c as f32 / 4095.0).collect();
    let rgbf = image::ImageBuffer::from_raw(48, 40, float).unwrap();
    for (name, picture, how) in [
        ("rgb16.png", image::DynamicImage::ImageRgb16(rgb16), 0b0_1000u8),
        ("grey16.png", image::DynamicImage::ImageLuma16(grey16), 0),
        ("rgb8.png", image::DynamicImage::ImageRgb8(rgb8), 0b1_0000),
    ]
    .into_iter()
    .flat_map(|(n, p, how)| {
        let tiff = (n.replace(".png", ".tiff"), p.clone(), how | 1);
        [(n.to_string(), p, how), tiff]
    })
    .chain([("rgbf.tiff".to_string(), image::DynamicImage::ImageRgb32F(rgbf), 1)])
    {
        let format = if how & 1 == 0 { image::ImageFormat::Png } else { image::ImageFormat::Tiff };
        let mut file = Vec::new();
        picture.write_to(&mut std::io::Cursor::new(&mut file), format).unwrap();
        let bytes = [&[how][..], &file].concat();
        // Every seed is a frame the reader takes.
        let mut s = sensor.clone();
        s.bits = if how & 16 != 0 { 8 } else { 12 };
        let size = (how & 8 != 0).then_some([48, 40]);
        let file = if how & 1 == 0 { "f.png" } else { "f.tiff" };
        let f =
            host::frame_file::decode_frame_file(file, &bytes[1..], &s, Default::default(), size)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!([f.width, f.height], [48, 40]);
        std::fs::write(dir.join(format!("{name}.bin")), &bytes).unwrap();
    }
    println!("frame files in {}", dir.display());
    let dir = root.join("geometry");
    std::fs::create_dir_all(&dir).unwrap();
    let g = host::geometry::ScannerGeometry::default_scanner();
    std::fs::write(dir.join("default.toml"), g.to_toml()).unwrap();
    // Axis configuration files: the defaults, and a tilt too short for the
    // default design's outer ring.
    let dir = root.join("axes");
    std::fs::create_dir_all(&dir).unwrap();
    let mut short = protocol::default_axes();
    short[2].max_steps = 1_500;
    for (name, axes) in [("default", protocol::default_axes()), ("short-tilt", short)] {
        let text = host::geometry::axes_to_toml(&axes);
        assert_eq!(host::geometry::axes_from_toml(&text).unwrap(), axes);
        std::fs::write(dir.join(format!("{name}.toml")), text).unwrap();
    }
    let dir = root.join("calibration");
    std::fs::create_dir_all(&dir).unwrap();
    let text = serde_json::to_string(&nominal_calibration(&g)).unwrap();
    // Every seed is a calibration the builder accepts for that scanner.
    let cal = host::build::Calibration::parse(&text).unwrap();
    cal.check_geometry(&g).unwrap();
    std::fs::write(dir.join("nominal.json"), &text).unwrap();
    println!("geometry and calibration in {}", root.display());
    let dir = root.join("manifest");
    std::fs::create_dir_all(&dir).unwrap();
    for (name, mirrors, bracket) in
        [("fixed-3", 3, vec![]), ("bracket-2", 2, vec![2000, 10_000, 50_000])]
    {
        let scan = tempfile::tempdir().unwrap();
        let mut opts = host::scan::ScanOptions::new(name, scan.path());
        (opts.mirrors, opts.bracket_us) = (Some(mirrors), bracket);
        let sim =
            host::simulator::SimSetup { bin: 64, ..host::simulator::SimSetup::new("leather") };
        let rig = sim.rig().unwrap();
        let transport = Box::new(host::link::SimTransport(rig.clone()));
        let mut dev = host::link::Device::connect(transport).unwrap();
        let mut camera = host::camera::SimCamera(rig);
        let g = sim.nominal().unwrap();
        host::scan::scan(&mut dev, &mut camera, &g, &opts, &mut host::scan::Quiet).unwrap();
        std::fs::copy(scan.path().join("manifest.json"), dir.join(format!("{name}.json"))).unwrap();
        if name == "fixed-3" {
            // The same scan as a camera whose exposure strobe is watched
            // records it: every frame's window, the dark frame's and the
            // black level's bias frame's (`--black-level auto`).
            let text = std::fs::read_to_string(scan.path().join("manifest.json")).unwrap();
            let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
            let window = serde_json::json!({ "delay_us": 1000, "length_us": 50_000 });
            for f in m["frames"].as_array_mut().unwrap() {
                f["strobe"] = window.clone();
            }
            m["settings"]["dark"]["strobe"] = window.clone();
            m["settings"]["black_level_auto"] =
                serde_json::json!({ "exposure_us": 1000, "strobe": window });
            let bytes = serde_json::to_vec_pretty(&m).unwrap();
            std::fs::write(scan.path().join("manifest.json"), &bytes).unwrap();
            let read = host::scan::Manifest::load(scan.path()).unwrap();
            assert!(read.settings.dark.unwrap().strobe.is_some());
            assert!(read.frames.iter().all(|f| f.strobe.is_some()));
            std::fs::write(dir.join(format!("{name}-strobe.json")), bytes).unwrap();
        }
    }
    println!("scan manifests in {}", dir.display());
    // Direct-image manifests: the simulator's photographs' (a white
    // reference, the camera's distance) and a bare one.
    let dir = root.join("direct");
    std::fs::create_dir_all(&dir).unwrap();
    use scanner_formats::direct::{DirectImage, DirectManifest, FORMAT, WhiteImage};
    let image = |k: usize, distance| DirectImage {
        file: format!("image-{k}.exr"),
        direction: [
            0.25 * (k as f64 - 1.5),
            0.1,
            1.0 - 0.5 * 0.0625 * (k as f64 - 1.5).powi(2) - 0.005,
        ],
        exposure_s: 0.02,
        mirror: Some(k as u32),
        camera_distance_mm: distance,
    };
    let unit = |mut im: DirectImage| {
        let len = im.direction.iter().map(|x| x * x).sum::<f64>().sqrt();
        im.direction = im.direction.map(|x| x / len);
        im
    };
    let photographed = DirectManifest {
        format: FORMAT,
        size_mm: [80.0, 80.0],
        image: (0..4).map(|k| unit(image(k, Some(400.0)))).collect(),
        white: Some(WhiteImage {
            file: "white.exr".into(),
            direction: [0.0, 0.0, 1.0],
            exposure_s: 0.01,
            albedo: 0.98,
        }),
    };
    let bare = DirectManifest {
        format: FORMAT,
        size_mm: [30.0, 12.5],
        image: (0..3).map(|k| unit(image(k, None))).collect(),
        white: None,
    };
    for (name, m) in [("photographed", photographed), ("bare", bare)] {
        let text = m.to_toml();
        assert_eq!(DirectManifest::parse(text.as_bytes()), Ok(m));
        std::fs::write(dir.join(format!("{name}.toml")), text).unwrap();
    }
    println!("direct-image manifests in {}", dir.display());
    corner_seeds(&root);
    brdf_seeds(&root);
}

/// Pictures for the `corners` target (its input: width − 1, height − 1,
/// origin, then a byte per pixel on its log scale): a textured piece in
/// perspective on a dark background, the same dark on a light one, and a
/// piece turned by 45°.
fn corner_seeds(root: &std::path::Path) {
    let dir = root.join("corners");
    std::fs::create_dir_all(&dir).unwrap();
    let (w, h) = (80usize, 64usize);
    let quads: [(&str, [[f64; 2]; 4], u8, u8); 3] = [
        ("bright", [[12.0, 55.0], [70.0, 58.0], [66.0, 8.0], [15.0, 10.0]], 176, 40),
        ("dark", [[12.0, 55.0], [70.0, 58.0], [66.0, 8.0], [15.0, 10.0]], 60, 200),
        ("turned", [[40.0, 60.0], [68.0, 32.0], [40.0, 4.0], [12.0, 32.0]], 176, 40),
    ];
    for (name, q, piece, background) in quads {
        let inside = |x: f64, y: f64| {
            (0..4).all(|k| {
                let (a, b) = (q[k], q[(k + 1) % 4]);
                (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) <= 0.0
            })
        };
        // Through a pinhole, and through a lens of 6 % barrel distortion
        // (the pinhole point at q · (1 + 0.06 (r / half-diagonal)²)) with
        // the lens to be estimated (bit 2 of the third byte).
        for (lens, k1, flags) in [("", 0.0, 0u8), ("-barrel", 0.06, 4u8)] {
            let (cx, cy, r2) = (w as f64 / 2.0, h as f64 / 2.0, ((w * w + h * h) / 4) as f64);
            let mut bytes = vec![(w - 1) as u8, (h - 1) as u8, flags];
            for y in 0..h {
                for x in 0..w {
                    let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                    let s = 1.0 + k1 * (dx * dx + dy * dy) / r2;
                    let on = inside(cx + s * dx, cy + s * dy);
                    let v = if on { piece + ((x * 7 + y * 3) % 16) as u8 } else { background };
                    bytes.push(v);
                }
            }
            std::fs::write(dir.join(format!("{name}{lens}.bin")), bytes).unwrap();
        }
    }
    println!("pictures in {}", dir.display());
}

/// Scattered measurements of the two-lobe GGX mixture (one row missing a
/// channel, one below the horizon) in `DIR/measurements`, and the NPF model
/// a short fit of them gives in `DIR/npf_model`.
fn brdf_seeds(root: &std::path::Path) {
    use host::brdf::Brdf;
    use host::brdf::fit::{FitOptions, Measurement, Samples, fit};
    let b = host::brdf::analytic::two_lobe_ggx();
    let mut measurements: Vec<Measurement> = (0..60)
        .map(|k| {
            let (t, p) = (k as f64 * 0.023, k as f64 * 0.71);
            let wi = [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
            let wo = [(1.2 - t).sin(), 0.0, (1.2 - t).cos()];
            Measurement { wi, wo, rgb: b.eval(wi, wo) }
        })
        .collect();
    measurements[3].rgb[1] = -1.0;
    measurements[7].wo = [1.0, 0.0, 0.0];
    let dir = root.join("measurements");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("two-lobe.csv");
    host::brdf::measurements::write_csv(&path, &measurements).unwrap();
    let samples = Samples::from_measurements(&measurements).unwrap();
    let opts = FitOptions { max_iterations: 3, ..FitOptions::default() };
    let (model, _) = fit(&samples, &opts, &|_, _, _| {});
    let dir = root.join("npf_model");
    std::fs::create_dir_all(&dir).unwrap();
    let bytes = model.to_json();
    // Every seed is a model the reader accepts.
    host::brdf::npf::NpfModel::from_json(&bytes, "seed").unwrap();
    std::fs::write(dir.join("two-lobe.json"), &bytes).unwrap();
    println!("BRDF measurements and model in {}", root.display());
}

/// A calibration of scanner `g` as built: the nominal views and light
/// directions, a uniform white response on a 2 × 2 grid.
fn nominal_calibration(g: &host::geometry::ScannerGeometry) -> host::build::Calibration {
    use host::build::calibrate::{
        CALIBRATION_FORMAT, CALIBRATION_VERSION, ColourCalibration, LightCalibration, ScanRef,
        ViewCalibration,
    };
    let scan = |name: &str| ScanRef { sample_name: name.into(), manifest_sha256: "0".repeat(64) };
    let n = g.mirrors.len();
    let views = (0..n)
        .map(|l| {
            let h = host::build::locate::nominal_homography(g, l).unwrap();
            let m = &g.mirrors[l];
            ViewCalibration {
                view: l,
                homography: h,
                homography_phase: h,
                corners_used: 49,
                corner_rms_px: 0.1,
                phase_rms_px: Some(0.01),
                edge_offsets_px: Some([[0.01, -0.02], [0.0, 0.03], [-0.01, 0.0], [0.02, 0.01]]),
                phase_relocked_squares: None,
                located_by: Some(host::build::calibrate::LocatedBy::Corners),
                direction: g.mirror_direction(l).unwrap().to_array(),
                mirror_point_mm: m.center_mm,
                mirror_normal: m.frame().0.to_array(),
            }
        })
        .collect();
    let lights = (0..n)
        .map(|l| LightCalibration {
            light: l,
            direction: g.light_direction(l).unwrap().to_array(),
            axes: g.mirror_axes(l).unwrap().to_array(),
        })
        .collect();
    host::build::Calibration {
        format: CALIBRATION_FORMAT.into(),
        version: CALIBRATION_VERSION,
        geometry_sha256: g.hash(),
        camera_px: [g.camera.width, g.camera.height],
        target: Default::default(),
        checkerboard_scan: scan("checkerboard"),
        white_scan: scan("diffuse-white"),
        glossy_scan: None,
        source_offsets: None,
        views,
        lights,
        colour: ColourCalibration {
            grid: 2,
            white_albedo: 0.98,
            view_response: vec![vec![2.5; 12]; n],
            light_field: vec![vec![1.0; 4]; n],
        },
        defects: Vec::new(),
        lens_distortion: [0.0; 2],
        lens_k1_held: false,
    }
}
