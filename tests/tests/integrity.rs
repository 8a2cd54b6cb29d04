//! Capture integrity: one writer per scan directory, outputs that never
//! destroy what is at their path, damaged manifests recovered, directory
//! syncs after renames, interruption, and the exit codes and messages the
//! README's table documents. (Lost steps: `tests/scan.rs`.)

mod common;

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use common::*;
use hil_sim::FaultPlan;
use host::scan::Manifest;

/// Every file under `dir` and its bytes.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

// ----- 2. one writer per scan directory -------------------------------------------

#[test]
fn a_second_scan_in_a_directory_in_use_exits_3_and_touches_nothing() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let (code, _, err) = sim_scan(64, 3, &out, &[]);
    assert_eq!(code, Some(0), "{err}");
    // Damage a frame so that a resume would write; then hold the scan's
    // lock as a running scan does (flock: another open file description).
    std::fs::write(out.join("frames/mirror-01.exr"), b"damaged").unwrap();
    let lock = std::fs::File::options().write(true).open(out.join(".lock")).unwrap();
    lock.lock().unwrap();
    let before = snapshot(&out);
    for extra in [&["--resume"][..], &[][..]] {
        let (code, _, err) = sim_scan(64, 3, &out, extra);
        assert_eq!(code, Some(3), "{extra:?}: {err}");
        assert!(err.contains("another scan is using"), "{err}");
        assert_eq!(snapshot(&out), before, "{extra:?}: nothing written");
    }
    // A new directory being created by another scan: the same.
    let fresh = sub(dir.path(), "fresh");
    std::fs::create_dir_all(&fresh).unwrap();
    let lock2 = std::fs::File::create(fresh.join(".lock")).unwrap();
    lock2.lock().unwrap();
    let (code, _, err) = sim_scan(64, 2, &fresh, &[]);
    assert_eq!(code, Some(3), "{err}");
    assert!(!fresh.join("manifest.json").exists());
    drop((lock, lock2));
    // Released: the resume repairs the frame.
    let (code, _, err) = sim_scan(64, 3, &out, &["--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(run(&["verify", &out.display().to_string()]).0, Some(0));
}

#[test]
fn two_scans_started_together_do_not_both_write_the_directory() {
    // Two processes race for one directory: the lock lets exactly one scan.
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let mut args = sim_scan_args(16, 12, &out);
    args.extend(["--check-every", "1"].map(String::from));
    let a = scanner().args(&args).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let b = scanner().args(&args).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let (a, b) = (a.wait_with_output().unwrap(), b.wait_with_output().unwrap());
    let codes = [a.status.code(), b.status.code()];
    let errs = [&a.stderr, &b.stderr].map(|e| String::from_utf8_lossy(e).into_owned());
    // One wins; the other finds the directory locked (3) or, if it came
    // second, already holding a scan (3). Never two exit 0.
    assert!(codes.contains(&Some(0)) && codes.contains(&Some(3)), "{codes:?} {errs:?}");
    let m = Manifest::load(&out).unwrap();
    assert!(m.complete && m.frames.len() == 12);
    assert_eq!(run(&["verify", &out.display().to_string()]).0, Some(0));
}

// ----- 3. outputs never destroy what is at the path --------------------------------

#[test]
fn outputs_refuse_device_nodes_symlinks_and_their_inputs_before_any_work() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tmp();
    let p = |n: &str| dir.path().join(n).display().to_string();
    let (code, _, err) = run(&["synth-merl", "--material", "ggx", "-o", &p("t.binary")]);
    assert_eq!(code, Some(0), "{err}");
    let (code, _, err) = run(&["fit", &p("t.binary"), "-o", &p("m.json"), "--max-iterations", "2"]);
    assert_eq!(code, Some(0), "{err}");
    // A device node stays a device node.
    for dev in ["/dev/full", "/dev/null"] {
        let (code, _, err) = run(&["fit", &p("t.binary"), "-o", dev, "--max-iterations", "1"]);
        assert_eq!(code, Some(4), "{dev}: {err}");
        assert!(err.contains("a device node"), "{err}");
        assert!(std::fs::metadata(dev).unwrap().file_type().is_char_device(), "{dev} replaced");
        let (code, _, err) = run(&["synth-merl", "--material", "ggx", "-o", dev]);
        assert_eq!(code, Some(4), "{dev}: {err}");
    }
    // A symbolic link: neither the link nor its target changes.
    std::fs::write(dir.path().join("target.json"), b"precious").unwrap();
    std::os::unix::fs::symlink(dir.path().join("target.json"), dir.path().join("link.json"))
        .unwrap();
    let (code, _, err) = run(&["fit", &p("t.binary"), "-o", &p("link.json")]);
    assert_eq!(code, Some(4), "{err}");
    assert!(err.contains("symbolic link"), "{err}");
    assert_eq!(std::fs::read(dir.path().join("target.json")).unwrap(), b"precious");
    assert!(std::fs::symlink_metadata(dir.path().join("link.json")).unwrap().is_symlink());
    // The input, also under another name.
    std::fs::hard_link(dir.path().join("m.json"), dir.path().join("same.json")).unwrap();
    let model = std::fs::read(dir.path().join("m.json")).unwrap();
    let (code, _, err) = run(&["plot-npf", &p("m.json"), "-o", &p("m.json")]);
    assert_eq!(code, Some(4), "{err}");
    assert!(err.contains("would replace the input"), "{err}");
    let (code, _, err) = run(&["render-brdf", &p("m.json"), "-o", &p("same.json")]);
    assert_eq!(code, Some(4), "another name of the input: {err}");
    let (code, _, err) = run(&["fit", &p("t.binary"), "-o", &p("same.json")]);
    assert_eq!(code, Some(0), "another file may be replaced: {err}");
    let (code, _, err) = run(&["synth-merl", "--material", "ggx", "-o", &p("t.binary")]);
    assert_eq!(code, Some(0), "{err}");
    std::fs::write(dir.path().join("m.json"), &model).unwrap();
    let (code, _, err) = run(&["fit", &p("m.json"), "-o", &p("m.json")]);
    assert_ne!(code, Some(0), "{err}");
    assert_eq!(std::fs::read(dir.path().join("m.json")).unwrap(), model);
    // Output formats are checked before the work, not after.
    let t = Instant::now();
    let (code, _, err) = run(&["render-brdf", &p("m.json"), "-o", &p("x.jpg"), "--size", "4096"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains(".png or .exr"), "{err}");
    assert!(t.elapsed() < Duration::from_secs(5), "refused before rendering");
    let (code, _, err) = run(&["plot-npf", &p("m.json"), "-o", &p("x.exr")]);
    assert_eq!(code, Some(2), "{err}");
    assert!(!dir.path().join("x.jpg").exists() && !dir.path().join("x.exr").exists());
}

// ----- 4. a folder that holds something else ----------------------------------------

/// `scanner ARGS`, killed (and the test failed) if it has not ended
/// within 60 s: a command that reads an endless device or waits on a FIFO
/// would otherwise hang the test run.
fn run_bounded(args: &[&str]) -> (Option<i32>, String) {
    let mut child =
        scanner().args(args).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > Duration::from_secs(60) {
            child.kill().unwrap();
            panic!("scanner {args:?} still running after 60 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    (out.status.code(), String::from_utf8_lossy(&out.stderr).into_owned())
}

// ----- 4. inputs are read only from regular files --------------------------------

#[test]
fn inputs_that_are_devices_or_fifos_are_refused_before_anything_is_read() {
    let dir = tmp();
    let p = |n: &str| dir.path().join(n).display().to_string();
    // An endless device behind a name that looks like an input: reading
    // it to the end would fill the memory.
    for name in ["zero.binary", "zero.json", "zero.toml"] {
        std::os::unix::fs::symlink("/dev/zero", dir.path().join(name)).unwrap();
    }
    // A FIFO with no writer: opening it to read would wait for ever.
    let fifo = std::ffi::CString::new(p("fifo.csv")).unwrap();
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o600) }, 0);
    let scan = dir.path().join("scan");
    std::fs::create_dir(&scan).unwrap();
    std::os::unix::fs::symlink("/dev/zero", scan.join("manifest.json")).unwrap();
    let o = scan.display().to_string();
    let cases: [(&[&str], &str); 6] = [
        (&["fit", &p("zero.binary"), "-o", &p("m.json")], "a device, not a regular file"),
        (&["fit", &p("fifo.csv"), "-o", &p("m.json")], "a FIFO, not a regular file"),
        (&["render-brdf", &p("zero.json"), "-o", &p("s.png")], "a device, not a regular file"),
        (&["verify", &o], "a device, not a regular file"),
        (
            &[
                "scan",
                "--sim-bin",
                "64",
                "--geometry",
                &p("zero.toml"),
                "--sample-name",
                "s",
                "--out",
                &p("s"),
            ],
            "a device, not a regular file",
        ),
        (
            &["calibrate", "--checkerboard", &o, "--white", &o, "-o", &p("c.json")],
            "a device, not a regular file",
        ),
    ];
    for (args, said) in cases {
        let (code, err) = run_bounded(args);
        assert_eq!(code, Some(3), "{args:?}: {err}");
        assert!(err.contains(said), "{args:?}: {err}");
    }
    // Nothing was written.
    for name in ["m.json", "s.png", "s", "c.json"] {
        assert!(!dir.path().join(name).exists(), "{name} written");
    }
}

#[test]
fn a_non_empty_folder_without_a_manifest_is_refused_unless_forced() {
    let dir = tmp();
    let out = sub(dir.path(), "photos");
    std::fs::create_dir_all(out.join("frames")).unwrap();
    std::fs::write(out.join("frames/mirror-00.exr"), b"someone's file").unwrap();
    std::fs::write(out.join("notes.txt"), b"keep me").unwrap();
    let before = snapshot(&out);
    for extra in [&[][..], &["--resume"][..]] {
        let (code, _, err) = sim_scan(64, 2, &out, extra);
        assert_eq!(code, Some(3), "{extra:?}: {err}");
        assert!(err.contains("is not empty") && err.contains("--force"), "{err}");
        assert_eq!(snapshot(&out), before, "nothing touched");
    }
    let (code, _, err) = sim_scan(64, 2, &out, &["--force"]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(std::fs::read(out.join("notes.txt")).unwrap(), b"keep me");
    // An empty folder needs no --force.
    let empty = sub(dir.path(), "empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert_eq!(sim_scan(64, 1, &empty, &[]).0, Some(0));
    // A file where the directory should be.
    let file = dir.path().join("file");
    std::fs::write(&file, b"x").unwrap();
    let (code, _, err) = sim_scan(64, 1, &file, &[]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("not a directory"), "{err}");
}

// ----- 5. a damaged manifest ----------------------------------------------------------

#[test]
fn a_damaged_manifest_is_recovered_from_the_previous_one() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let o = out.display().to_string();
    let (code, _, err) = sim_scan(64, 4, &out, &[]);
    assert_eq!(code, Some(0), "{err}");
    let prev = Manifest::load(&out).unwrap();
    assert!(out.join("manifest.json.prev").is_file(), "rotated on every save");
    // Not UTF-8: damaged (3), not a write error (4); nothing changes.
    std::fs::write(out.join("manifest.json"), b"{\"format\": \"\xff\xfe\"}").unwrap();
    let before = snapshot(&out);
    let (code, _, err) = run(&["verify", &o]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("damaged") && err.contains("not UTF-8"), "{err}");
    let (code, _, err) = sim_scan(64, 4, &out, &[]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("`--resume` recovers"), "{err}");
    assert_eq!(snapshot(&out), before);
    // --resume recovers from manifest.json.prev, re-verifying its frames;
    // the damaged file is kept aside.
    let (code, text, err) = sim_scan(64, 4, &out, &["--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("recovering from manifest.json.prev"), "{err}");
    assert!(text.contains("0 frames taken, 4 kept"), "{text}");
    assert!(out.join("manifest.json.damaged").is_file());
    let m = Manifest::load(&out).unwrap();
    assert_eq!(m.frames, prev.frames);
    assert_eq!(run(&["verify", &o]).0, Some(0));
    // Both gone or damaged: refused, still exit 3.
    std::fs::write(out.join("manifest.json"), b"[").unwrap();
    std::fs::write(out.join("manifest.json.prev"), b"[").unwrap();
    let (code, _, err) = sim_scan(64, 4, &out, &["--resume"]);
    assert_eq!(code, Some(3), "{err}");
}

#[test]
fn resume_refuses_another_simulator_a_foreign_mirror_and_names_what_differs() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let o = out.display().to_string();
    let (code, _, err) = sim_scan(64, 3, &out, &[]);
    assert_eq!(code, Some(0), "{err}");
    let m = Manifest::load(&out).unwrap();
    assert_eq!(m.settings.simulator.as_deref(), Some("simulated woven-fabric, seed 1, binning 64"));
    // Another simulator seed: another scanner.
    let (code, _, err) = sim_scan(64, 3, &out, &["--resume", "--sim-seed", "2"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("scanner simulated woven-fabric, seed 1"), "{err}");
    // Another exposure: named, no Rust debug output.
    let (code, _, err) = sim_scan(64, 3, &out, &["--resume", "--exposure-us", "20000"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("exposure 50000 µs (the directory's) vs 20000 µs"), "{err}");
    assert!(!err.contains("ScanSettings") && !err.contains("Some("), "{err}");
    // A deleted frame is missing, not damaged.
    std::fs::remove_file(out.join("frames/mirror-02.exr")).unwrap();
    let (code, text, _) = run(&["verify", &o]);
    assert_eq!(code, Some(3));
    assert!(text.contains("missing: mirror 2") && !text.contains("damaged"), "{text}");
    // A manifest that lists a mirror outside the scan is damaged.
    let text = std::fs::read_to_string(out.join("manifest.json")).unwrap();
    std::fs::write(out.join("manifest.json"), text.replace("\"mirror\": 1,", "\"mirror\": 57,"))
        .unwrap();
    let (code, _, err) = run(&["verify", &o]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("mirror 57 in a scan of mirrors 0…2"), "{err}");
    let (code, _, err) = sim_scan(64, 3, &out, &[]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("mirror 57"), "{err}");
}

#[test]
fn a_manifest_that_reads_one_file_twice_or_a_bracket_out_of_order_is_damaged() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let o = out.display().to_string();
    let (code, _, err) = sim_scan(64, 3, &out, &[]);
    assert_eq!(code, Some(0), "{err}");
    let text = std::fs::read_to_string(out.join("manifest.json")).unwrap();
    let edited = |edit: &dyn Fn(&mut serde_json::Value)| -> String {
        let mut m: serde_json::Value = serde_json::from_str(&text).unwrap();
        edit(&mut m);
        std::fs::write(out.join("manifest.json"), m.to_string()).unwrap();
        let (code, _, err) = run(&["verify", &o]);
        assert_eq!(code, Some(3), "{err}");
        err
    };
    // Mirror 1's entry on mirror 2's file: mirror 2's light read as mirror 1's.
    let err = edited(&|m| m["frames"][1]["file"] = m["frames"][2]["file"].clone());
    assert!(err.contains("damaged: frame file \"frames/mirror-02.exr\" is listed twice"), "{err}");
    let err = edited(&|m| m["settings"]["bracket_us"] = serde_json::json!([2000, 1000]));
    assert!(
        err.contains("damaged: the scan's bracket [2000, 1000] µs is not of ascending exposures"),
        "{err}"
    );
    let err = edited(&|m| m["frames"][0]["bracket_us"] = serde_json::json!([0, 1000]));
    assert!(err.contains("damaged: mirror 0's bracket [0, 1000] µs"), "{err}");
    // A mirror count no device has: `verify` used to count through 10¹⁵
    // missing mirrors (a hang, then out of memory).
    for n in [1_000_000_000_000_000u64, 0] {
        let err = edited(&|m| m["settings"]["mirror_count"] = n.into());
        assert!(
            err.contains(&format!("damaged: a scan of {n} mirrors (a device has 1…64)")),
            "{err}"
        );
    }
    // As written, it reads.
    std::fs::write(out.join("manifest.json"), &text).unwrap();
    let (code, _, err) = run(&["verify", &o]);
    assert_eq!(code, Some(0), "{err}");
}

// ----- 6. directory fsync after every rename ---------------------------------------

#[test]
fn every_rename_into_the_scan_is_followed_by_a_directory_fsync() {
    // strace (installed by scripts/setup.sh) records the system calls.
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let trace = dir.path().join("trace");
    let status = std::process::Command::new("strace")
        .args(["-f", "-qq", "-e", "trace=openat,rename,renameat,renameat2,fsync,close", "-o"])
        .arg(&trace)
        .arg(env!("CARGO_BIN_EXE_scanner-e2e"))
        .args(sim_scan_args(64, 3, &out))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("strace runs (scripts/setup.sh installs it)");
    assert!(status.success());
    let trace = std::fs::read_to_string(&trace).unwrap();
    let out_s = out.display().to_string();
    // Per process: fd → path of directories opened; after each rename into
    // the scan, an fsync of an fd opened on the destination's directory
    // must come before that process' next rename.
    let lines: Vec<&str> = trace.lines().collect();
    let mut renames = 0;
    for (i, l) in lines.iter().enumerate() {
        if !(l.contains("rename") && l.contains(&out_s)) || l.contains("= -1") {
            continue;
        }
        renames += 1;
        let pid = l.split_whitespace().next().unwrap();
        let dest = l.rsplit('"').nth(1).unwrap();
        let parent = Path::new(dest).parent().unwrap().display().to_string();
        let mut synced = false;
        let mut fds = Vec::new();
        for m in &lines[i + 1..] {
            if !m.starts_with(pid) {
                continue;
            }
            if m.contains(&format!("openat(AT_FDCWD, \"{parent}\""))
                && let Some(fd) = m.rsplit("= ").next()
            {
                fds.push(fd.trim().to_string());
            }
            if m.contains("fsync(") && fds.iter().any(|fd| m.contains(&format!("fsync({fd})"))) {
                synced = true;
                break;
            }
            if m.contains("rename") {
                break;
            }
        }
        assert!(synced, "no fsync of {parent} after {l}");
    }
    assert!(renames >= 3 + 2, "frames and manifests renamed: {renames}");
}

// ----- exit codes and messages -------------------------------------------------------

#[test]
fn bad_values_are_refused_before_anything_moves_or_is_written() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    for (extra, what) in [
        (&["--exposure-us", "0"][..], "--exposure-us 0 outside"),
        (&["--exposures", "10,50000"][..], "--exposures: 10 µs outside"),
        (&["--mirrors", "1000"][..], "--mirrors 1000: this scanner has mirrors 1…40"),
        (&["--mirrors", "0"][..], "--mirrors 0"),
        (&["--frame-timeout", "5000"][..], "--frame-timeout"),
        (&["--sim-defect", "warm:1,2"][..], "sensor defect `warm:1,2`: unknown kind"),
        (&["--sim-defect", "hot:1,2"][..], "`hot:1,2`: a hot pixel is X,Y,RATE"),
        (&["--sim-defect", "stuck:64,0"][..], "sensor defect at (64, 0) outside the 64 × 64 frame"),
    ] {
        let mut args =
            vec!["scan", "--device", "sim", "--sim-bin", "64", "--sample-name", "s", "--out"];
        let o = out.display().to_string();
        args.push(&o);
        args.extend_from_slice(extra);
        let (code, _, err) = run(&args);
        assert_eq!(code, Some(2), "{extra:?}: {err}");
        assert!(err.contains(what), "{extra:?}: {err}");
        assert!(!out.exists(), "{extra:?}: nothing written");
    }
    // The corrected command then runs.
    let (code, _, err) = sim_scan(64, 1, &out, &["--exposure-us", "20000"]);
    assert_eq!(code, Some(0), "{err}");
    // verify: no scan at a missing or empty folder, or a file.
    let empty = sub(dir.path(), "empty");
    std::fs::create_dir_all(&empty).unwrap();
    let file = dir.path().join("f");
    std::fs::write(&file, b"x").unwrap();
    for d in [dir.path().join("nothing"), empty, file] {
        let (code, _, err) = run(&["verify", &d.display().to_string()]);
        assert_eq!(code, Some(3), "{err}");
        assert!(err.contains("no scan at"), "{err}");
    }
}

#[test]
fn device_errors_are_said_in_words_once() {
    let dir = tmp();
    // Homing that fails on a stuck switch: words, not HomingFailed(Track, SwitchStuck).
    let (code, _, err) =
        sim_scan(64, 2, &sub(dir.path(), "a"), &["--sim-fault", "stuck:track:on@ms=0"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("failed on the track axis: its switch stayed pressed"), "{err}");
    assert!(!err.contains("HomingFailed") && !err.contains("SwitchStuck"), "{err}");
    // An emergency stop while homing says so.
    let (code, _, err) =
        sim_scan(64, 2, &sub(dir.path(), "b"), &["--sim-fault", "estop:on@ms=300"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("emergency stop"), "{err}");
    // The error once.
    let last = err.lines().last().unwrap();
    assert_eq!(err.matches(last).count(), 1, "printed twice: {err}");
    // Logs to a pipe carry no colour codes.
    let out = scanner()
        .args(sim_scan_args(64, 2, &dir.path().join("c")))
        .args(["--sim-fault", "disconnect:1500@trigger=1"])
        .output()
        .unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && log.contains("WARN") && log.contains("lost"), "{log}");
    assert!(!log.contains('\x1b'), "colour codes in a pipe: {log:?}");
    // Not a serial port.
    let file = dir.path().join("not-a-port");
    std::fs::write(&file, b"x").unwrap();
    for dev in ["/dev/null", &file.display().to_string()] {
        let (code, _, err) = run(&["info", "--device", dev]);
        assert_eq!(code, Some(5), "{err}");
        assert!(err.contains("not a serial port"), "{err}");
    }
}

#[test]
fn fit_refuses_data_it_cannot_fit_and_names_the_channel() {
    let dir = tmp();
    let csv = |name: &str, rgb: [f64; 3]| {
        let mut text = String::from("wi_x,wi_y,wi_z,wo_x,wo_y,wo_z,r,g,b\n");
        for k in 0..200 {
            let t = 0.1 + 1.2 * (k as f64 / 200.0);
            let s = 0.02 + (k % 7) as f64 * 0.05;
            text.push_str(&format!(
                "{},0,{},{},0,{},{},{},{}\n",
                t.sin(),
                t.cos(),
                -(t * 0.7).sin(),
                (t * 0.7).cos(),
                rgb[0] * s,
                rgb[1] * s,
                rgb[2] * s
            ));
        }
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p.display().to_string()
    };
    let out = dir.path().join("m.json").display().to_string();
    let (code, _, err) = run(&["fit", &csv("big.csv", [1e200, 1e200, 1e200]), "-o", &out]);
    assert_eq!(code, Some(3), "{err}");
    // The reader names the line and the channel's column.
    assert!(err.contains("line 2: r = ") && err.contains("beyond any BRDF"), "{err}");
    let (code, _, err) = run(&["fit", &csv("huge.csv", [1.0, 1e30, 1.0]), "-o", &out]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("line 2: g = ") && err.contains("at most 1e8 sr⁻¹"), "{err}");
    let (code, _, err) = run(&["fit", &csv("nog.csv", [1.0, -1.0, 1.0]), "-o", &out]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("channel G has no measurement"), "{err}");
    assert!(!dir.path().join("m.json").exists());
    let (code, _, err) =
        run(&["fit", &csv("zerob.csv", [1.0, 0.5, 0.0]), "-o", &out, "--max-iterations", "3"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(err.contains("channel B is zero wherever measured"), "{err}");
}

#[test]
fn ctrl_c_keeps_the_frames_and_prints_the_resume_command() {
    // A scanner in real time on a pty, so that the scan is still running
    // when the signal comes.
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let out = sub(dir.path(), "scan");
    let s = setup("leather", FaultPlan::none());
    let server = serve(&s, &frames_dir);
    let args = scan_args(server.path(), &frames_dir, &out, 6);
    let child =
        scanner().args(&args).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let end = Instant::now() + Duration::from_secs(60);
    while Manifest::load(&out).map(|m| m.frames.len()).unwrap_or(0) < 1 {
        assert!(Instant::now() < end, "no frame within 60 s");
        std::thread::sleep(Duration::from_millis(50));
    }
    let pid = child.id().to_string();
    assert!(std::process::Command::new("kill").args(["-INT", &pid]).status().unwrap().success());
    let r = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(130), "{err}");
    let m = Manifest::load(&out).unwrap();
    assert!(!m.complete && !m.frames.is_empty());
    assert!(err.contains(&format!("interrupted: {} of 6 frames kept", m.frames.len())), "{err}");
    // The printed command continues the scan.
    let command = err.lines().last().unwrap().trim();
    assert!(command.ends_with("--resume"), "{err}");
    let status = std::process::Command::new("sh").args(["-c", command]).status().unwrap();
    assert!(status.success(), "{command}");
    assert!(Manifest::load(&out).unwrap().complete);
    drop(server);
}

#[test]
fn on_a_terminal_log_lines_and_notes_never_share_the_progress_bar_line() {
    // stderr on a pty: the progress bar is drawn, with colour allowed.
    use serialport::SerialPort;
    use std::io::Read;
    use std::os::fd::{AsRawFd, BorrowedFd};
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    // SAFETY: the slave outlives the child's copy of its descriptor.
    let fd = unsafe { BorrowedFd::borrow_raw(slave.as_raw_fd()) }.try_clone_to_owned().unwrap();
    let dir = tmp();
    let mut child = scanner()
        .args(sim_scan_args(16, 12, &dir.path().join("scan")))
        .args(["--sim-fault", "disconnect:1500@trigger=4", "--check-every", "4"])
        .stdout(Stdio::null())
        .stderr(Stdio::from(fd))
        .spawn()
        .unwrap();
    let mut text = Vec::new();
    let mut buf = [0u8; 4096];
    master.set_timeout(Duration::from_millis(100)).unwrap();
    let end = Instant::now() + Duration::from_secs(120);
    loop {
        match master.read(&mut buf) {
            Ok(n) => text.extend_from_slice(&buf[..n]),
            Err(_) if child.try_wait().unwrap().is_some() => break,
            Err(_) => assert!(Instant::now() < end, "the scan did not end"),
        }
    }
    assert!(child.wait().unwrap().success());
    let text = String::from_utf8_lossy(&text);
    assert!(text.contains("frames,") && text.contains("\r\x1b[2K"), "no bar drawn: {text:?}");
    // Whatever else is printed starts on a line of its own: after the bar
    // was erased (`\r`, erase line) or after a newline, never after bar text.
    let own_line = |what: &str| {
        let at = text.find(what).unwrap_or_else(|| panic!("no {what:?} in {text:?}"));
        let before = &text[..at];
        let start = [before.rfind('\n'), before.rfind("\x1b[2K")].into_iter().flatten().max();
        let segment = &before[start.unwrap_or(0)..];
        assert!(!segment.contains("frames,"), "{what:?} printed on the bar's line: {segment:?}");
    };
    own_line(" WARN");
    own_line("s: homing");
    own_line("s: wrote 40 mirror table entries");
    // On a terminal, colour is allowed.
    assert!(text.contains("\x1b[33m WARN"), "{text:?}");
}
