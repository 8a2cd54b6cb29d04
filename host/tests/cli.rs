//! The `scanner` binary's BRDF commands, end to end.

use std::process::Command;

use host::brdf::Brdf;
use host::brdf::analytic::{ggx_conductor, two_lobe_ggx};
use host::brdf::fit::Measurement;
use host::brdf::measurements::write_csv;
use host::brdf::merl::MerlTable;
use host::brdf::npf::NpfModel;
use host::brdf::render::sphere_psnr;

fn scanner(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_scanner")).args(args).output().expect("run scanner")
}

#[test]
fn fit_render_and_plot_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let merl = dir.path().join("two-lobe.binary");
    let b = two_lobe_ggx();
    MerlTable::from_fn(|wi, wo| b.eval(wi, wo)).write(&merl).unwrap();
    let model = dir.path().join("two-lobe.json");
    let p = |p: &std::path::Path| p.to_str().unwrap().to_string();

    let out = scanner(&["fit", &p(&merl), "-o", &p(&model), "--g", "smith", "--p", "1.4"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("objective") && stdout.contains("iterations"), "summary: {stdout}");
    let fitted = NpfModel::load(&model).unwrap();
    assert_eq!(fitted.metadata["g"], "Smith");

    for image in ["sphere.png", "sphere.exr"] {
        let path = dir.path().join(image);
        let out = scanner(&["render-brdf", &p(&model), "-o", &p(&path), "--size", "64"]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let img = image::open(&path).unwrap();
        assert_eq!((img.width(), img.height()), (64, 64));
    }
    let from_table = dir.path().join("table.png");
    assert!(
        scanner(&["render-brdf", &p(&merl), "-o", &p(&from_table), "--size", "32"])
            .status
            .success()
    );

    let plot = dir.path().join("factors.png");
    let out = scanner(&["plot-npf", &p(&model), "-o", &p(&plot)]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&plot).unwrap().to_rgb8();
    assert_eq!((img.width(), img.height()), (1500, 500));
    // Something was drawn in each channel's colour.
    assert!(img.pixels().any(|p| p[0] > 150 && p[1] < 80 && p[2] < 80), "a red curve");
    assert!(img.pixels().any(|p| p[2] > 150 && p[0] < 80), "a blue curve");
}

#[test]
fn fit_from_scattered_measurements() {
    // A stratified grid of direction pairs, as a gonioreflectometer sweep.
    let dir = tempfile::tempdir().unwrap();
    let b = ggx_conductor(0.25);
    let mut measurements = Vec::new();
    let d = |t: f64, p: f64| [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()];
    for a in 0..24 {
        for c in 0..48 {
            for e in 0..24 {
                let ti = (a as f64 + 0.5) / 24.0 * 1.55;
                let to = (e as f64 + 0.5) / 24.0 * 1.55;
                let (wi, wo) = (d(ti, 0.0), d(to, (c as f64 + 0.5) / 48.0 * std::f64::consts::PI));
                measurements.push(Measurement { wi, wo, rgb: b.eval(wi, wo) });
            }
        }
    }
    let csv = dir.path().join("sweep.csv");
    write_csv(&csv, &measurements).unwrap();
    let model = dir.path().join("sweep.json");
    let out = scanner(&["fit", csv.to_str().unwrap(), "-o", model.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains(&format!("fitted {} samples", measurements.len())), "{stdout}");
    let fitted = NpfModel::load(&model).unwrap();
    let psnr = sphere_psnr(&b, &fitted);
    assert!(psnr > 35.0, "{psnr} dB from a {}-sample sweep", measurements.len());

    // A malformed row: exit 3, the line named, nothing written.
    let bad = dir.path().join("bad.csv");
    std::fs::write(
        &bad,
        "wi_x,wi_y,wi_z,wo_x,wo_y,wo_z,r,g,b\n0,0,1,0,0,1,0.1,0.1,0.1\n0,0,1,0,0,1,x,0,0\n",
    )
    .unwrap();
    let out_model = dir.path().join("bad.json");
    let out = scanner(&["fit", bad.to_str().unwrap(), "-o", out_model.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(3));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("line 3") && err.contains("r = \"x\""), "{err}");
    assert!(!out_model.exists());

    // Five measurements of a glossy material (two-lobe GGX × 10⁵, seeded
    // directions) leave the factors' peaks where no sample is: the model
    // would predict 10⁹ sr⁻¹ there. Exit 3, said so, nothing written.
    let sparse = dir.path().join("sparse.csv");
    std::fs::write(
        &sparse,
        "wi_x,wi_y,wi_z,wo_x,wo_y,wo_z,r,g,b\n\
         -0.6213933503123654,-0.6410605601614764,0.4504571704313607,0.409910324415312,-0.7712118961594076,0.4870377163628551,2180.7051917633157,1671.342109140192,1161.9790265170684\n\
         -0.3306250258226184,-0.9305079385186675,0.15761366899330953,-0.8039404493093119,-0.08577338277458724,0.5884918697584071,2790.8029282679063,2154.964364565874,1519.1258008638408\n\
         -0.4232602593388277,-0.5759725215377784,0.6993614282313844,-0.9224613269544814,-0.00029222330838346073,0.3860893871617239,2059.0921469267337,1578.382973339091,1097.673799751448\n\
         -0.7684750670845961,-0.14279291586102807,0.6237437410100648,-0.24972715264106288,0.06866265551772337,0.9658787651517357,3523.6926643043594,2716.6465732640017,1909.6004822236428\n\
         0.5410786334787583,-0.8404502448307083,0.029619222757560015,0.42090792766068036,-0.015625003668509038,0.9069687842989694,4293.7339408069,3426.5797093394362,2559.4254778719733\n",
    )
    .unwrap();
    let out = scanner(&["fit", sparse.to_str().unwrap(), "-o", out_model.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(3));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("the fitted model is out of range (`rho_s` holds")
            && err.contains("the measurements do not determine it"),
        "{err}"
    );
    assert!(!out_model.exists());
}

#[test]
fn bad_input_gets_a_clear_error_and_exit_code() {
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.binary");
    std::fs::write(&junk, b"not a table").unwrap();
    let out_model = dir.path().join("m.json");
    let out = scanner(&["fit", junk.to_str().unwrap(), "-o", out_model.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(3));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("34992012"), "names the expected size: {err}");
    assert!(!out_model.exists(), "nothing written");

    let out = scanner(&["plot-npf", junk.to_str().unwrap(), "-o", "x.png"]);
    assert_eq!(out.status.code(), Some(3));
    let out = scanner(&["fit", junk.to_str().unwrap(), "-o", "m.json", "--p", "3"]);
    assert_eq!(out.status.code(), Some(2));
    // An output type the command cannot write: usage, before any work.
    let out = scanner(&["render-brdf", junk.to_str().unwrap(), "-o", "x.tiff"]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn outputs_never_replace_devices_links_or_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n).display().to_string();
    let table = p("ggx.binary");
    let out = scanner(&["synth-merl", "--material", "ggx", "-o", &table]);
    assert!(out.status.success());
    let code = |args: &[&str]| {
        let o = scanner(args);
        (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    // A device node.
    let (c, err) = code(&["fit", &table, "-o", "/dev/null"]);
    assert_eq!(c, Some(4), "{err}");
    assert!(err.contains("a device node"), "{err}");
    let (c, err) = code(&["synth-merl", "--material", "ggx", "-o", "/dev/full"]);
    assert_eq!(c, Some(4), "{err}");
    assert!(err.contains("a device node"), "{err}");
    // A symbolic link: refused, its target untouched.
    let target = p("target.json");
    std::fs::write(&target, "keep").unwrap();
    std::os::unix::fs::symlink(&target, p("link.json")).unwrap();
    let (c, err) = code(&["fit", &table, "-o", &p("link.json"), "--max-iterations", "1"]);
    assert_eq!(c, Some(4), "{err}");
    assert!(err.contains("symbolic link"), "{err}");
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "keep");
    // The input itself.
    let model = p("m.json");
    let (c, err) = code(&["fit", &table, "-o", &model, "--max-iterations", "2"]);
    assert_eq!(c, Some(0), "{err}");
    let (c, err) = code(&["plot-npf", &model, "-o", &p("plot.exr")]);
    assert_eq!(c, Some(2), "{err}");
    assert!(!dir.path().join("plot.exr").exists());
    let (c, err) = code(&["render-brdf", &model, "-o", &p("sphere.jpg")]);
    assert_eq!(c, Some(2), "{err}");
    let (c, err) = code(&["render-brdf", &table, "-o", &table.replace(".binary", ".exr")]);
    assert_eq!(c, Some(0), "{err}");
    std::fs::hard_link(&model, p("same.png")).unwrap();
    let (c, err) = code(&["plot-npf", &model, "-o", &p("same.png")]);
    assert_eq!(c, Some(4), "{err}");
    assert!(err.contains("would replace the input"), "{err}");
}
