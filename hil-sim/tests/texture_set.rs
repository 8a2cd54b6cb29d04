//! Texture-set samples (docs/texture-set.md) and the ground-truth query
//! tool: maps decoded as documented, both forms, bad sets refused naming
//! the file, `hil-sim truth` answering f · cos θi.

use std::f64::consts::PI;
use std::path::Path;
use std::process::Command;

use glam::DVec3;
use hil_sim::materials::{Material, MaterialError, Sample, lookup};
use hil_sim::texture_set::TextureSet;

const W: u32 = 8;
const H: u32 = 4;

fn toml(dir: &Path, extra: &str) {
    std::fs::write(
        dir.join("material.toml"),
        format!("format = 1\nname = \"test set\"\nsize_mm = 16.0\n{extra}"),
    )
    .unwrap();
}

fn rgb8(dir: &Path, name: &str, f: impl Fn(u32, u32) -> [u8; 3]) {
    image::RgbImage::from_fn(W, H, |x, y| image::Rgb(f(x, y))).save(dir.join(name)).unwrap();
}

fn grey16(dir: &Path, name: &str, f: impl Fn(u32, u32) -> u16) {
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(W, H, |x, y| image::Luma([f(x, y)]))
        .save(dir.join(name))
        .unwrap();
}

fn exr(dir: &Path, name: &str, w: u32, h: u32, f: impl Fn(u32, u32) -> [f32; 3]) {
    image::Rgb32FImage::from_fn(w, h, |x, y| image::Rgb(f(x, y))).save(dir.join(name)).unwrap();
}

/// A channel's value at pixel (x, y).
type Values = fn(u32, u32) -> f32;

/// An EXR of W × H px with the named f32 channels.
fn exr_channels(dir: &Path, name: &str, channels: &[(&str, Values)]) {
    use exr::prelude::{AnyChannel, AnyChannels, FlatSamples, Image, SmallVec, WritableImage};
    let list = channels
        .iter()
        .map(|(n, f)| {
            let values = (0..W * H).map(|i| f(i % W, i / W)).collect();
            AnyChannel::new(*n, FlatSamples::F32(values))
        })
        .collect();
    let image =
        Image::from_channels((W as usize, H as usize), AnyChannels::sort(SmallVec::from_vec(list)));
    image.write().to_file(dir.join(name)).unwrap();
}

fn srgb(c: f64) -> f64 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// A valid set in the diffuse/specular form.
fn classic(dir: &Path) {
    toml(dir, "sample_offset_mm = [2.0, 3.0]\n");
    rgb8(dir, "diffuse.png", |x, _| [(x * 30) as u8, 128, 255]);
    rgb8(dir, "specular.png", |_, _| [10, 10, 10]);
    grey16(dir, "roughness.png", |x, _| (x as u16) * 8000);
    // Flat, except column 3 tilted towards +u.
    rgb8(dir, "normal.png", |x, _| if x == 3 { [218, 128, 218] } else { [128, 128, 255] });
}

/// The centre of pixel (c, r) of a 16 mm tile of W × H px, in mm.
fn centre(c: u32, r: u32) -> [f64; 2] {
    [(c as f64 + 0.5) / W as f64 * 16.0, (r as f64 + 0.5) / H as f64 * 16.0]
}

#[test]
fn maps_decode_as_documented_and_lookups_are_bilinear_and_periodic() {
    let dir = tempfile::tempdir().unwrap();
    classic(dir.path());
    let set = TextureSet::load(dir.path()).unwrap();
    assert_eq!(set.name(), "test set");
    assert_eq!(set.tile_mm(), 16.0);
    assert_eq!(set.sample_offset_mm(), [2.0, 3.0]);
    // Pixel centres give the pixel's own values: sRGB decoded colours,
    // α = roughness², the normal decoded and normalised.
    let t = set.texel(centre(2, 1));
    assert!((t.diffuse[0] - srgb(60.0 / 255.0)).abs() < 1e-6, "{:?}", t.diffuse);
    assert!((t.diffuse[2] - 1.0).abs() < 1e-6);
    assert!((t.specular[1] - srgb(10.0 / 255.0)).abs() < 1e-6);
    let r = 16_000.0 / 65_535.0;
    assert!((t.roughness - r * r).abs() < 1e-6, "{}", t.roughness);
    assert!((t.normal - DVec3::new(1.0 / 255.0, 1.0 / 255.0, 1.0).normalize()).length() < 1e-6);
    let tilted = set.texel(centre(3, 0)).normal;
    let want = DVec3::new(2.0 * 218.0 / 255.0 - 1.0, 1.0 / 255.0, 2.0 * 218.0 / 255.0 - 1.0);
    assert!((tilted - want.normalize()).length() < 1e-6, "{tilted:?}");
    // Halfway between pixel centres: the mean (bilinear).
    let mid = set.texel([(centre(1, 0)[0] + centre(2, 0)[0]) / 2.0, centre(1, 0)[1]]);
    let mean = (srgb(30.0 / 255.0) + srgb(60.0 / 255.0)) / 2.0;
    assert!((mid.diffuse[0] - mean).abs() < 1e-6);
    // Periodic: one tile further is the same texel; across the seam the
    // last and first columns mix.
    let far = set.texel([centre(2, 1)[0] + 32.0, centre(2, 1)[1] - 16.0]);
    assert_eq!(far, t);
    let seam = set.texel([0.0, centre(0, 0)[1]]);
    let mean = (srgb(0.0) + srgb(210.0 / 255.0)) / 2.0;
    assert!((seam.diffuse[0] - mean).abs() < 1e-6, "{:?}", seam.diffuse);
    // The small sample is cut at the offset; the large piece is whole
    // tiles, at least 80 mm.
    let set: std::sync::Arc<dyn Material> = std::sync::Arc::new(set);
    let small = Sample::small(set.clone());
    assert_eq!(small.point([0.0, 0.0]), [2.0, 3.0]);
    assert_eq!(small.point([1.0, 1.0]), [27.4, 28.4]);
    assert_eq!(Sample::large(set).size_mm, 80.0);
}

#[test]
fn the_gltf_form_converts_to_diffuse_and_f0() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    toml(d, "");
    exr(d, "baseColor.exr", W, H, |x, _| [0.8, 0.5, if x == 0 { 0.2 } else { 0.6 }]);
    // G = roughness, B = metallic (half the tile metal).
    exr(d, "metallicRoughness.exr", W, H, |x, _| [0.0, 0.5, if x < 4 { 0.0 } else { 1.0 }]);
    exr(d, "normal.exr", W, H, |_, _| [0.5, 0.5, 1.0]);
    let set = TextureSet::load(d).unwrap();
    let dielectric = set.texel(centre(1, 2));
    assert_eq!(dielectric.diffuse.map(|v| (v * 1e6).round() / 1e6), [0.8, 0.5, 0.6]);
    assert!(dielectric.specular.iter().all(|&f| (f - 0.04).abs() < 1e-7));
    assert!((dielectric.roughness - 0.25).abs() < 1e-7);
    let metal = set.texel(centre(6, 2));
    assert!(metal.diffuse.iter().all(|&v| v.abs() < 1e-7));
    assert!((metal.specular[0] - 0.8).abs() < 1e-6 && (metal.specular[2] - 0.6).abs() < 1e-6);
    assert_eq!(metal.normal, DVec3::Z);
}

/// The same roughness (a 16-bit grey ramp) stored every way a tool may write
/// a grey map, and a grey + alpha diffuse map: each loads exactly as the
/// grey PNG does.
#[test]
fn grey_maps_load_however_they_are_stored() {
    fn ramp(x: u32, _: u32) -> f32 {
        (x * 8000) as f32 / 65535.0
    }
    let reference = {
        let dir = tempfile::tempdir().unwrap();
        classic(dir.path());
        TextureSet::load(dir.path()).unwrap()
    };
    type Write = fn(&Path);
    let variants: [(&str, Write); 5] = [
        ("RGB PNG, R = G = B", |d| {
            image::ImageBuffer::<image::Rgb<u16>, Vec<u16>>::from_fn(W, H, |x, _| {
                image::Rgb([(x * 8000) as u16; 3])
            })
            .save(d.join("roughness.png"))
            .unwrap()
        }),
        ("grey + alpha PNG", |d| {
            image::ImageBuffer::<image::LumaA<u16>, Vec<u16>>::from_fn(W, H, |x, _| {
                image::LumaA([(x * 8000) as u16, 1000])
            })
            .save(d.join("roughness.png"))
            .unwrap()
        }),
        ("EXR with Y alone", |d| {
            std::fs::remove_file(d.join("roughness.png")).unwrap();
            exr_channels(d, "roughness.exr", &[("Y", ramp)]);
        }),
        ("EXR with one channel and alpha", |d| {
            std::fs::remove_file(d.join("roughness.png")).unwrap();
            exr_channels(d, "roughness.exr", &[("roughness", ramp), ("A", |_, _| 0.25)]);
        }),
        ("EXR, R = G = B", |d| {
            std::fs::remove_file(d.join("roughness.png")).unwrap();
            exr(d, "roughness.exr", W, H, |x, y| [ramp(x, y); 3]);
        }),
    ];
    for (what, write) in variants {
        let dir = tempfile::tempdir().unwrap();
        classic(dir.path());
        write(dir.path());
        let set = TextureSet::load(dir.path()).unwrap_or_else(|e| panic!("{what}: {e}"));
        for (c, r) in [(0, 0), (3, 1), (7, 3)] {
            let (a, b) = (set.texel(centre(c, r)), reference.texel(centre(c, r)));
            assert!(
                (a.roughness - b.roughness).abs() < 1e-6,
                "{what} at ({c}, {r}): {a:?} against {b:?}"
            );
        }
    }
    // A grey + alpha colour map is grey: R = G = B, alpha ignored.
    let dir = tempfile::tempdir().unwrap();
    classic(dir.path());
    image::GrayAlphaImage::from_fn(W, H, |x, _| image::LumaA([(x * 30) as u8, 7]))
        .save(dir.path().join("diffuse.png"))
        .unwrap();
    let set = TextureSet::load(dir.path()).unwrap();
    let d = set.texel(centre(4, 2)).diffuse;
    assert!((d[0] - srgb(120.0 / 255.0)).abs() < 1e-6 && d[0] == d[1] && d[1] == d[2], "{d:?}");
}

fn refusal(setup: impl Fn(&Path)) -> String {
    let dir = tempfile::tempdir().unwrap();
    classic(dir.path());
    setup(dir.path());
    let name = dir.path().to_str().unwrap().to_string();
    match lookup(&name) {
        Err(e @ MaterialError::TextureSet(_)) => e.to_string(),
        other => panic!("expected a texture-set error, got {other:?}"),
    }
}

#[test]
fn bad_sets_are_refused_naming_the_file() {
    let e = refusal(|d| std::fs::remove_file(d.join("specular.png")).unwrap());
    assert!(e.contains("specular.png: missing"), "{e}");
    let e = refusal(|d| {
        image::RgbImage::new(W, H + 1).save(d.join("specular.png")).unwrap();
    });
    assert!(e.contains("specular.png: 8×5 px, but diffuse.png is 8×4"), "{e}");
    let e = refusal(|d| {
        std::fs::remove_file(d.join("diffuse.png")).unwrap();
        exr(d, "diffuse.exr", W, H, |x, _| [if x == 5 { f32::NAN } else { 0.5 }, 0.5, 0.5]);
    });
    assert!(e.contains("diffuse.exr: pixel (5, 0) is NaN"), "{e}");
    let e = refusal(|d| rgb8(d, "roughness.png", |x, _| [9, 9, if x == 2 { 8 } else { 9 }]));
    assert!(
        e.contains("roughness.png: 3 different channels at pixel (2, 0), expected one (grey"),
        "{e}"
    );
    let e = refusal(|d| {
        image::GrayAlphaImage::new(W, H).save(d.join("normal.png")).unwrap();
    });
    assert!(e.contains("normal.png: 1 channel(s), expected RGB"), "{e}");
    let e = refusal(|d| {
        std::fs::remove_file(d.join("roughness.png")).unwrap();
        exr_channels(d, "roughness.exr", &[("U", |_, _| 0.5), ("V", |_, _| 0.5)]);
    });
    assert!(
        e.contains("roughness.exr: channels [U, V]: expected R, G and B, or one channel"),
        "{e}"
    );
    let e = refusal(|d| {
        std::fs::remove_file(d.join("diffuse.png")).unwrap();
        exr_channels(
            d,
            "diffuse.exr",
            &[("Y", |_, _| 0.5), ("RY", |_, _| 0.0), ("BY", |_, _| 0.0)],
        );
    });
    assert!(e.contains("diffuse.exr: luminance/chroma"), "{e}");
    let e = refusal(|d| {
        std::fs::remove_file(d.join("roughness.png")).unwrap();
        exr(d, "roughness.exr", W, H, |x, _| [if x == 7 { 1.5 } else { 0.5 }; 3]);
    });
    assert!(e.contains("roughness.exr: pixel (7, 0): roughness 1.5 outside [0, 1]"), "{e}");
    let e = refusal(|d| toml(d, "sample_offset_mm = [2.0, 1e13]\n"));
    assert!(
        e.contains("material.toml")
            && e.contains("sample_offset_mm [2e0, 1e13] must be finite and within ±1e9 mm"),
        "{e}"
    );
    let e = refusal(|d| toml(d, "sample_offset_mm = [nan, 0.0]\n"));
    assert!(e.contains("sample_offset_mm [NaN, 0e0] must be finite"), "{e}");
    let e = refusal(|d| toml(d, "colour = \"red\"\n"));
    assert!(e.contains("material.toml") && e.contains("unknown field `colour`"), "{e}");
    let e = refusal(|d| {
        std::fs::write(d.join("material.toml"), "format = 2\nname = \"x\"\nsize_mm = 1.0\n")
            .unwrap()
    });
    assert!(e.contains("format 2"), "{e}");
    let e = refusal(|d| rgb8(d, "normal.png", |_, _| [128, 128, 0]));
    assert!(
        e.contains("normal.png: pixel (0, 0) decodes to (0.0039, 0.0039, -1.0000)")
            && e.contains("z > 0"),
        "{e}"
    );
    let e = refusal(|d| {
        std::fs::remove_file(d.join("normal.png")).unwrap();
        exr(d, "normal.exr", W, H, |x, _| if x == 3 { [0.5; 3] } else { [0.5, 0.5, 1.0] })
    });
    assert!(e.contains("normal.exr: pixel (3, 0)") && e.contains("no direction"), "{e}");
    let e = refusal(|d| rgb8(d, "baseColor.png", |_, _| [1, 1, 1]));
    assert!(e.contains("keep one form"), "{e}");
    let e = refusal(|d| exr(d, "normal.exr", W, H, |_, _| [0.5, 0.5, 1.0]));
    assert!(e.contains("both normal.png and normal.exr"), "{e}");
    // Not a directory and not a name: a usage error.
    assert!(matches!(lookup("velvet"), Err(MaterialError::Unknown(_))));
}

fn hil_sim() -> Command {
    Command::new(env!("CARGO_BIN_EXE_hil-sim"))
}

#[test]
fn truth_answers_queries_with_f_cos_theta_i() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("white");
    std::fs::create_dir(&set).unwrap();
    toml(&set, "");
    exr(&set, "diffuse.exr", 2, 2, |_, _| [0.5, 0.25, 0.125]);
    exr(&set, "specular.exr", 2, 2, |_, _| [0.0; 3]);
    exr(&set, "roughness.exr", 2, 2, |_, _| [0.5; 3]);
    exr(&set, "normal.exr", 2, 2, |_, _| [0.5, 0.5, 1.0]);
    let queries = dir.path().join("q.csv");
    std::fs::write(
        &queries,
        "wo_x,wo_y,wo_z,u,v,wi_x,wi_y,wi_z\n0,0,1,0.5,0.5,0,0,1\n0.6,0,0.8,0.1,0.9,0,3,4\n0,0,1,0.5,0.5,0,0,-1\n",
    )
    .unwrap();
    let out = dir.path().join("a.npy");
    let run = hil_sim()
        .args(["truth", "--material", set.to_str().unwrap(), "--queries"])
        .arg(&queries)
        .arg("-o")
        .arg(&out)
        .output()
        .unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let a = scanner_formats::queries::read_answers(&out).unwrap();
    let lambert = |albedo: f64, cos: f64| (albedo / PI * cos) as f32;
    assert_eq!(a.len(), 3);
    assert!((a[0][0] - lambert(0.5, 1.0)).abs() < 1e-7, "{:?}", a[0]);
    assert!((a[1][1] - lambert(0.25, 0.8)).abs() < 1e-7, "{:?}", a[1]);
    assert_eq!(a[2], [0.0; 3], "light below the horizon");
    // A library material by name, answers as CSV.
    let csv = dir.path().join("a.csv");
    let run = hil_sim()
        .args(["truth", "--material", "diffuse-white", "--queries"])
        .arg(&queries)
        .arg("-o")
        .arg(&csv)
        .output()
        .unwrap();
    assert!(run.status.success());
    let a = scanner_formats::queries::read_answers(&csv).unwrap();
    assert!((a[0][0] - lambert(0.98, 1.0)).abs() < 1e-6);
    // Exit codes: unknown name 2, bad set 3, bad queries 3, output = input 4.
    let code = |args: &[&std::ffi::OsStr]| hil_sim().arg("truth").args(args).output().unwrap();
    let q = queries.as_os_str();
    let o = out.as_os_str();
    let r = code(&[
        "--material".as_ref(),
        "velvet".as_ref(),
        "--queries".as_ref(),
        q,
        "-o".as_ref(),
        o,
    ]);
    assert_eq!(r.status.code(), Some(2));
    std::fs::remove_file(set.join("normal.exr")).unwrap();
    let r =
        code(&["--material".as_ref(), set.as_os_str(), "--queries".as_ref(), q, "-o".as_ref(), o]);
    assert_eq!(r.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&r.stderr).contains("normal.png: missing"));
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, "u,v\n0,0\n").unwrap();
    let r = code(&[
        "--material".as_ref(),
        "leather".as_ref(),
        "--queries".as_ref(),
        bad.as_os_str(),
        "-o".as_ref(),
        o,
    ]);
    assert_eq!(r.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&r.stderr).contains("missing column \"wi_x\""));
    let r = code(&[
        "--material".as_ref(),
        "leather".as_ref(),
        "--queries".as_ref(),
        q,
        "-o".as_ref(),
        q,
    ]);
    assert_eq!(r.status.code(), Some(4));
    assert!(std::fs::read_to_string(&queries).unwrap().starts_with("wo_x"), "input untouched");
}
