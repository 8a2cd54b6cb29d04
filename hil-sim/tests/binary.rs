//! The `hil-sim` binary: prints the pty path, serves the protocol on it, and
//! refuses bad options with a clear message.

mod common;

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

#[test]
fn serves_on_the_printed_pty_until_killed() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["--seed", "3"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let path = line.trim().to_string();
    assert!(path.starts_with("/dev/"), "prints the pty path first: {path:?}");

    let answered = common::connect_over_serial(&path);
    child.kill().unwrap();
    let _ = child.wait();
    assert!(answered.is_ok(), "the simulated controller answered the handshake: {answered:?}");
}

#[test]
fn bad_options_are_refused() {
    let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["--fault", "explode@ms=1"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown kind"));
    let out =
        Command::new(env!("CARGO_BIN_EXE_hil-sim")).args(["--corrupt", "1.5"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn render_and_direct_write_their_frames() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("frames");
    let status = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["render", "--bin", "16", "--mirrors", "2", "--material", "leather", "--out"])
        .arg(&out)
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let frame = image::open(out.join("frame-01.exr")).unwrap();
    assert_eq!((frame.width(), frame.height()), (256, 256));
    // Only the two frames: no temporary file left behind.
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 2);
    // A symlink where a frame goes is refused, its target untouched.
    #[cfg(unix)]
    {
        let target = dir.path().join("precious");
        std::fs::write(&target, b"keep").unwrap();
        std::fs::remove_file(out.join("frame-00.exr")).unwrap();
        std::os::unix::fs::symlink(&target, out.join("frame-00.exr")).unwrap();
        let o = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(["render", "--bin", "16", "--mirrors", "1", "--material", "leather", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(4));
        assert!(
            String::from_utf8_lossy(&o.stderr).contains("frame-00.exr: a symbolic link; refusing"),
            "{o:?}"
        );
        assert_eq!(std::fs::read(&target).unwrap(), b"keep");
    }
    let direct = dir.path().join("direct");
    let status = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["direct", "--material", "rough-metal", "--out"])
        .arg(&direct)
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let mut names: Vec<String> = std::fs::read_dir(&direct)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "direct-0-mirror-00.exr",
            "direct-1-mirror-01.exr",
            "direct-2-mirror-02.exr",
            "direct-3-mirror-03.exr",
            "direct.toml",
            "white.exr"
        ]
    );
    let manifest = scanner_formats::direct::DirectManifest::read(&direct).unwrap();
    assert_eq!(manifest.size_mm, [80.0, 80.0]);
    let mirrors: Vec<Option<u32>> = manifest.image.iter().map(|i| i.mirror).collect();
    assert_eq!(mirrors, [Some(0), Some(1), Some(2), Some(3)]);
    let white = manifest.white.as_ref().unwrap();
    assert_eq!((white.file.as_str(), white.albedo), ("white.exr", 0.98));
    // Photographs in perspective instead: the set's description, read back.
    let photos = dir.path().join("photos");
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(args)
            .stderr(Stdio::null())
            .status()
            .unwrap()
    };
    let p = photos.to_str().unwrap();
    let args = ["direct", "--material", "leather", "--out", p, "--photographs"];
    assert!(run(&args).success());
    let text = std::fs::read_to_string(photos.join(hil_sim::direct::PHOTOGRAPHS)).unwrap();
    let set: hil_sim::direct::Photographs = toml::from_str(&text).unwrap();
    assert_eq!((set.size_mm, set.distance_mm, set.photo.len()), (80.0, 400.0, 4));
    for ph in set.photo.iter().chain([&set.white]) {
        assert!(photos.join(&ph.file).exists(), "{}", ph.file);
        assert!(ph.corners.iter().flatten().all(|v| v.is_finite() && *v > 0.0), "{ph:?}");
    }
    assert_eq!(run(&["direct", "--out", p, "--photographs", "5"]).code(), Some(2));
    // Through a lens: its distortion in the description; a lens that folds
    // the photograph, too many numbers, or a lens without photographs
    // refused.
    let bent = dir.path().join("bent");
    let b = bent.to_str().unwrap();
    let args = ["direct", "--material", "leather", "--out", b, "--photographs", "--lens", "-0.02"];
    assert!(run(&args).success());
    let text = std::fs::read_to_string(bent.join(hil_sim::direct::PHOTOGRAPHS)).unwrap();
    let bent_set: hil_sim::direct::Photographs = toml::from_str(&text).unwrap();
    assert_eq!(bent_set.distortion, [-0.02, 0.0]);
    assert_eq!(set.distortion, [0.0, 0.0]);
    // The corners pulled in towards the photograph's centre.
    let (a, c) = (set.photo[0].corners[0], bent_set.photo[0].corners[0]);
    assert!(a[0] < c[0] && a[1] > c[1], "{a:?} against {c:?}");
    for bad in [&["--lens", "-0.6"][..], &["--lens", "0.1,0,0"]] {
        let args = [&["direct", "--out", b, "--photographs"][..], bad].concat();
        assert_eq!(run(&args).code(), Some(2), "{bad:?}");
    }
    assert_eq!(run(&["direct", "--out", b, "--lens", "-0.02"]).code(), Some(2));
    // The truth of the large piece: uv across the 80 mm piece. Its point
    // (27.3 + 12.7, 31.9 + 12.7) mm is the small sample's centre.
    let queries = dir.path().join("q.csv");
    let at = |u: f64, v: f64| format!("{u},{v},0.3,0.1,0.95,-0.2,0.1,0.97\n");
    std::fs::write(
        &queries,
        format!("u,v,wi_x,wi_y,wi_z,wo_x,wo_y,wo_z\n{}{}", at(0.5, 0.5), at(0.5, 0.5575)),
    )
    .unwrap();
    let truth = |piece: &str| {
        let out = dir.path().join(format!("{piece}.csv"));
        let o = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(["truth", "--material", "painted-wood", "--piece", piece, "--queries"])
            .arg(&queries)
            .arg("-o")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{o:?}");
        scanner_formats::queries::read_answers(&out).unwrap()
    };
    let (small, large) = (truth("small"), truth("large"));
    assert_ne!(small[0], large[0]);
    for c in 0..3 {
        let (a, b) = (small[0][c], large[1][c]);
        assert!((a - b).abs() <= 1e-5 * a.abs(), "the sample's centre on the piece: {a} {b}");
    }
    let bad = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(["render", "--material", "cheese"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("unknown material"));
}
