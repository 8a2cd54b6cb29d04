//! Helpers of the end-to-end tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use hil_sim::{FaultPlan, PtyServer};
use host::scan::Manifest;
use host::simulator::SimSetup;

/// The small simulated scanner the tests use (512² sensor), served as a
/// USB board's port: it unplugs on a disconnect or a reset.
pub fn setup(material: &str, faults: FaultPlan) -> SimSetup {
    SimSetup { bin: 8, seed: 5, faults, port: hil_sim::Port::Usb(None), ..SimSetup::new(material) }
}

/// Simulated time per wall time on the pty: fast, yet the host's keep-alive
/// (50 ms after each answer: 150 simulated ms and a round trip) stays well
/// inside the device's 500 ms link timeout, with ≈ 100 ms of wall time to
/// spare for a host process not scheduled.
pub const SPEED: f64 = 3.0;

/// Serve `setup` on a pty; frames (OpenEXR) and the nominal geometry go to
/// `frames`.
pub fn serve(setup: &SimSetup, frames: &Path) -> PtyServer {
    serve_files(setup, frames, hil_sim::camera::FrameFiles::Exr)
}

/// [`serve`], the camera writing its frames as `files`.
pub fn serve_files(
    setup: &SimSetup,
    frames: &Path,
    files: hil_sim::camera::FrameFiles,
) -> PtyServer {
    let server = setup.serve(SPEED, frames.to_path_buf(), files).unwrap();
    std::fs::write(frames.join("geometry.toml"), setup.nominal().unwrap().to_toml()).unwrap();
    server
}

/// The scanner program.
pub fn scanner() -> Command {
    Command::new(env!("CARGO_BIN_EXE_scanner-e2e"))
}

/// `scanner ARGS` run to its end: (exit code, stdout, stderr).
pub fn run(args: &[&str]) -> (Option<i32>, String, String) {
    let out = scanner().args(args).output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// [`run`] without its stdout: (exit code, stderr).
pub fn run_err(args: &[&str]) -> (Option<i32>, String) {
    let (code, _, err) = run(args);
    (code, err)
}

/// Arguments of a scan on the in-process simulator (`--device sim`): a
/// sensor binned by `bin` (4096 / `bin` px a side), `mirrors` mirrors,
/// sample "s", into `out`.
pub fn sim_scan_args(bin: u32, mirrors: usize, out: &Path) -> Vec<String> {
    let (bin, mirrors) = (bin.to_string(), mirrors.to_string());
    let out = out.display().to_string();
    ["scan", "--device", "sim", "--sim-bin", &bin, "--sample-name", "s", "--out", &out]
        .into_iter()
        .chain(["--mirrors", &mirrors])
        .map(str::to_string)
        .collect()
}

/// [`sim_scan_args`] with `extra` options, run to its end: (exit code,
/// stdout, stderr).
pub fn sim_scan(
    bin: u32,
    mirrors: usize,
    out: &Path,
    extra: &[&str],
) -> (Option<i32>, String, String) {
    let args = sim_scan_args(bin, mirrors, out);
    let args: Vec<&str> = args.iter().map(String::as_str).chain(extra.iter().copied()).collect();
    run(&args)
}

/// `scanner calibrate --checkerboard CHECKER --white WHITE -o OUT` with
/// `extra` options, run to its end: (exit code, stdout, stderr).
pub fn calibrate(
    checker: &str,
    white: &str,
    out: &str,
    extra: &[&str],
) -> (Option<i32>, String, String) {
    let args = ["calibrate", "--checkerboard", checker, "--white", white, "-o", out];
    run(&[&args[..], extra].concat())
}

/// Arguments of a scan over `pty` with the folder camera.
pub fn scan_args(pty: &str, frames: &Path, out: &Path, mirrors: usize) -> Vec<String> {
    [
        "scan",
        "--device",
        pty,
        "--camera",
        &format!("folder:{}", frames.display()),
        "--geometry",
        &frames.join("geometry.toml").display().to_string(),
        "--sample-name",
        "e2e",
        "--out",
        &out.display().to_string(),
        "--mirrors",
        &mirrors.to_string(),
        "--frame-timeout",
        "3",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

/// The frame files of a scan directory and their bytes.
pub fn frames(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir.join("frames"))
        .unwrap()
        .flatten()
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap()))
        .collect();
    out.sort();
    out
}

/// A manifest with the fields that record *when* a frame was taken (the
/// device's trigger counter and clock), where the camera put it, and the
/// run's position checks (a run with faults checks more) blanked: what must
/// match between two scans of the same sample.
pub fn normalised_manifest(dir: &Path) -> Manifest {
    let mut m = Manifest::load(dir).unwrap();
    m.camera.clear();
    assert!(m.checks.last().is_some_and(|c| c.passed), "the last position check passed");
    m.checks.clear();
    for f in &mut m.frames {
        f.trigger_seq = 0;
        f.device_timestamp_us = 0;
        f.strobe = None;
    }
    m
}

/// Assert two scan directories hold the same scan: the same files, frames
/// byte for byte, manifests equal but for when frames were taken.
pub fn assert_same_scan(a: &Path, b: &Path) {
    let fa = frames(a);
    let fb = frames(b);
    let names = |f: &[(String, Vec<u8>)]| f.iter().map(|x| x.0.clone()).collect::<Vec<_>>();
    assert_eq!(names(&fa), names(&fb), "frame files");
    for ((name, x), (_, y)) in fa.iter().zip(&fb) {
        if x != y {
            let ma = normalised_manifest(a);
            let mb = normalised_manifest(b);
            let fa = ma.frames.iter().find(|f| f.file.ends_with(name.as_str()));
            let fb = mb.frames.iter().find(|f| f.file.ends_with(name.as_str()));
            panic!("{name} differs:\n{fa:?}\n{fb:?}");
        }
    }
    assert_eq!(normalised_manifest(a), normalised_manifest(b));
    let top = |d: &Path| {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    assert_eq!(top(a), top(b), "top-level files");
}

/// A fresh temporary directory.
pub fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

/// `dir/name`.
pub fn sub(dir: &Path, name: &str) -> PathBuf {
    dir.join(name)
}

/// A texture set (docs/texture-set.md) of one flat, uniform material in
/// `dir`: 4 × 4 maps of linear values, GGX α = `roughness`².
pub fn uniform_set(
    dir: &Path,
    name: &str,
    size_mm: f64,
    diffuse: [f32; 3],
    f0: f32,
    roughness: f32,
) {
    write_set(dir, name, size_mm, 4, |_, _| diffuse, [f0; 3], roughness);
}

/// A texture set of `size_mm` in 64² linear maps, named as its directory:
/// the diffuse colour at each material point (x, y) mm, a uniform F0 and
/// roughness, flat.
pub fn texture_set(
    set: &Path,
    size_mm: f64,
    diffuse: impl Fn(f64, f64) -> [f32; 3],
    f0: [f32; 3],
    roughness: f32,
) {
    let name = set.file_name().unwrap().to_str().unwrap();
    write_set(set, name, size_mm, 64, diffuse, f0, roughness);
}

/// A flat texture set in `dir` of `w` × `w` linear maps: the diffuse
/// colour at each material point (x, y) mm, a uniform F0 and roughness.
fn write_set(
    dir: &Path,
    name: &str,
    size_mm: f64,
    w: u32,
    diffuse: impl Fn(f64, f64) -> [f32; 3],
    f0: [f32; 3],
    roughness: f32,
) {
    std::fs::create_dir_all(dir).unwrap();
    let toml = format!("format = 1\nname = \"{name}\"\nsize_mm = {size_mm:?}\n");
    std::fs::write(dir.join("material.toml"), toml).unwrap();
    let at = |c: u32| (c as f64 + 0.5) / w as f64 * size_mm;
    image::Rgb32FImage::from_fn(w, w, |c, r| image::Rgb(diffuse(at(c), at(r))))
        .save(dir.join("diffuse.exr"))
        .unwrap();
    let map = |name: &str, v: [f32; 3]| {
        image::Rgb32FImage::from_pixel(w, w, image::Rgb(v)).save(dir.join(name)).unwrap();
    };
    map("specular.exr", f0);
    map("roughness.exr", [roughness; 3]);
    map("normal.exr", [0.5, 0.5, 1.0]);
}
