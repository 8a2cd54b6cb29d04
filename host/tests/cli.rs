//! The `scanner` binary's BRDF commands, end to end.

use std::process::Command;

use host::brdf::Brdf;
use host::brdf::analytic::two_lobe_ggx;
use host::brdf::merl::MerlTable;
use host::brdf::npf::NpfModel;

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
    let out = scanner(&["render-brdf", junk.to_str().unwrap(), "-o", "x.tiff"]);
    assert_eq!(out.status.code(), Some(3));
}
