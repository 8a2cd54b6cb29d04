//! `scanner geometry`, end to end: a scanner design checked (and written
//! from rings) before anything is built or scanned.

use std::path::Path;
use std::process::{Command, Output};

use scanner_geometry::ScannerGeometry;

fn scanner(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scanner")).args(args).output().expect("run scanner")
}

fn text(out: &Output) -> (String, String) {
    (String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

#[test]
fn a_sound_design_is_described_and_written() {
    let out = scanner(&["geometry"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let default = ScannerGeometry::default_scanner();
    assert!(stdout.contains(&default.hash()), "{stdout}");
    // A row per mirror: "     7 |  31.7, …".
    let rows = stdout.lines().filter(|l| l.split(" | ").count() == 7).count();
    assert_eq!(rows, 1 + 40, "a header and 40 mirrors: {stdout}");
    assert!(stdout.contains("closest views: mirrors 0 and 12, 223 px apart"), "{stdout}");
    assert!(stdout.trim_end().ends_with("no problem found"), "{stdout}");

    // Another scanner, from rings, written and read back.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("rings.toml");
    let out = scanner(&["geometry", "--rings", "18:5,38:8,58:11", "-o", p(&file)]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let written = ScannerGeometry::load(&file).unwrap();
    let rings = [(18.0, 5), (38.0, 8), (58.0, 11)];
    assert_eq!(written, ScannerGeometry::generate_with_rings(&rings));
    assert!(stdout.contains(&written.hash()) && stdout.contains("24 mirrors"), "{stdout}");
    let out = scanner(&["geometry", "--geometry", p(&file)]);
    assert!(out.status.success(), "{}", text(&out).1);
    // Rings on another scanner keep its camera: the other scanner's 4:3
    // sensor, with the default's rings.
    let mut other = written.clone();
    other.camera.width = 3072;
    other.camera.height = 2304;
    other.camera.focal_px = 4200.0;
    other.camera.principal_px = [1536.0, 1152.0];
    let base = dir.path().join("other.toml");
    std::fs::write(&base, other.to_toml()).unwrap();
    let again = dir.path().join("again.toml");
    let out = scanner(&[
        "geometry",
        "--geometry",
        p(&base),
        "--rings",
        // The default's rings, to the digit.
        "15:4,31.666666666666664:9,48.333333333333336:12,65:15",
        "-o",
        p(&again),
    ]);
    assert!(out.status.success(), "{}", text(&out).1);
    let again = ScannerGeometry::load(&again).unwrap();
    assert_eq!(again.camera, other.camera);
    assert_eq!(again.mirrors, default.mirrors);
}

#[test]
fn a_faulty_design_exits_3_naming_the_mirror_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut g = ScannerGeometry::default_scanner();
    g.mirrors[7].size_mm = 12.0;
    let small = dir.path().join("small-mirror.toml");
    std::fs::write(&small, g.to_toml()).unwrap();
    let out_file = dir.path().join("out.toml");
    let out = scanner(&["geometry", "--geometry", p(&small), "-o", p(&out_file)]);
    let (stdout, stderr) = text(&out);
    assert_eq!(out.status.code(), Some(3), "{stdout}{stderr}");
    assert!(stderr.contains("mirror 7: the camera sees part of the sample past the mirror's edge"));
    assert!(stderr.contains("mirror 7: lights part of the sample"), "{stderr}");
    assert!(stderr.contains("2 problems found; nothing written"), "{stderr}");
    assert!(!out_file.exists());

    // Mirrors crowded on two rings near the normal.
    let out = scanner(&["geometry", "--rings", "10:12,20:20", "-o", p(&out_file)]);
    let (_, stderr) = text(&out);
    assert_eq!(out.status.code(), Some(3));
    assert!(stderr.contains("overlapping"), "{stderr}");
    assert!(!out_file.exists());

    // The fold mirror's zero turned by 40°: three rings' tilts lie beyond
    // the default axes' −35°.
    let mut turned = ScannerGeometry::default_scanner();
    turned.source.tilt_zero_deg = 40.0;
    let file = dir.path().join("turned.toml");
    std::fs::write(&file, turned.to_toml()).unwrap();
    let out = scanner(&["geometry", "--geometry", p(&file)]);
    let (_, stderr) = text(&out);
    assert_eq!(out.status.code(), Some(3));
    assert!(
        stderr.contains(
            "mirror 0: tilt: -39.227° (-10461 steps) is outside its travel -35.00 … 35.00° \
             (-9333 … 9333 steps)"
        ),
        "{stderr}"
    );
    assert!(stderr.contains("25 problems found"), "{stderr}");

    // Usage, input and output errors.
    for (args, code) in [
        (vec!["geometry", "--rings", "18:x"], 2),
        (vec!["geometry", "--rings", "90:4"], 2),
        (vec!["geometry", "--rings", "18:0"], 2),
        (vec!["geometry", "--rings", "18:5", "-o", "x.txt"], 2),
        (vec!["geometry", "--geometry", "/nonexistent/g.toml"], 3),
        (vec!["geometry", "--geometry", p(&small), "--rings", "18:5", "-o", p(&small)], 4),
        (vec!["geometry", "--axes", "/nonexistent/axes.toml"], 3),
        (vec!["geometry", "--axes", p(&small)], 3),
        (vec!["geometry", "--axes", p(&small), "--device", "sim"], 2),
        (vec!["geometry", "--device", "/dev/no-such-scanner"], 5),
    ] {
        let out = scanner(&args);
        assert_eq!(out.status.code(), Some(code), "{args:?}: {}", text(&out).1);
    }
    assert_eq!(ScannerGeometry::load(&small).unwrap(), g, "the input is untouched");

    // A built scanner is what it is: `setup` (and `scan`) warn of its
    // design's faults and go on.
    let out = scanner(&["setup", "--device", "sim", "--geometry", p(&small)]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stdout}{stderr}");
    assert!(
        stderr.contains("warning: ") && stderr.contains("mirror 7: the camera sees"),
        "{stderr}"
    );
    let out = scanner(&["setup", "--device", "sim"]);
    assert!(out.status.success() && !text(&out).1.contains("warning"), "{}", text(&out).1);
}

#[test]
fn the_simulator_checked_as_a_device_takes_its_drives_and_its_boards_axes() {
    let dir = tempfile::tempdir().unwrap();
    // A tilt that stops at 5.63°: the outer ring needs 6.404°.
    let mut short = protocol::default_axes();
    short[2].max_steps = 1500;
    let file = dir.path().join("short.toml");
    std::fs::write(&file, scanner_geometry::axes_to_toml(&short)).unwrap();
    for option in ["--sim-axes", "--sim-board-axes"] {
        let out = scanner(&["geometry", "--device", "sim", option, p(&file)]);
        let (stdout, stderr) = text(&out);
        assert_eq!(out.status.code(), Some(3), "{option}: {stdout}{stderr}");
        assert!(stderr.contains("mirror 39: tilt: 6.404°"), "{option}: {stderr}");
        assert!(stdout.contains("checked against the axes of device sim"), "{stdout}");
    }
    // Built with the short tilt, its board configured with the spec's.
    let spec = dir.path().join("spec.toml");
    std::fs::write(&spec, scanner_geometry::axes_to_toml(&protocol::default_axes())).unwrap();
    let both = ["--sim-axes", p(&file), "--sim-board-axes", p(&spec)];
    let out = scanner(&[&["geometry", "--device", "sim"][..], &both].concat());
    assert!(out.status.success(), "{}", text(&out).1);
    for (args, code) in [
        (vec!["geometry", "--sim-axes", p(&file)], 2),
        (vec!["geometry", "--device", "/dev/no-such-scanner", "--sim-axes", p(&file)], 2),
        (vec!["geometry", "--device", "sim", "--sim-axes", "/nonexistent/axes.toml"], 3),
    ] {
        let out = scanner(&args);
        assert_eq!(out.status.code(), Some(code), "{args:?}: {}", text(&out).1);
    }
}
