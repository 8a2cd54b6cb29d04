//! The `scanner` bench commands and its documented exit codes.

mod common;

use std::io::{Read, Write};

use serialport::SerialPort;
use std::time::Duration;

use common::*;
use hil_sim::FaultPlan;
use protocol::{
    DeviceError, FrameDecoder, MAX_FRAME_LEN, ProtocolVersion, Reply, Request, ToHost, encode_frame,
};

#[test]
fn bench_commands_drive_a_scanner_on_a_pty() {
    let dir = tmp();
    let server = serve(&setup("leather", FaultPlan::none()), &sub(dir.path(), "camera"));
    let pty = server.path().to_string();
    let (code, out, err) = run(&["info", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    let version = format!("protocol {}", protocol::PROTOCOL_VERSION);
    assert!(out.contains(&version) && out.contains("track"), "{out}");
    let (code, out, _) = run(&["status", "--device", &pty]);
    assert_eq!(code, Some(0));
    assert!(out.contains("not homed"), "{out}");
    // The board's wiring options: set, saved, read back by another process.
    let (code, out, err) = run(&["config", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("active low"), "{out}");
    // Its drivers hold the fault line high when all is well (active low):
    // read active high, that is a fault, and no such polarity is saved.
    let (code, _, err) = run(&["config", "--device", &pty, "--driver-fault", "active-high"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(
        err.contains("the driver fault line is high, a fault read active high")
            && err.contains("nothing changed"),
        "{err}"
    );
    let (_, out, _) = run(&["config", "--device", &pty]);
    assert!(out.contains("driver fault line: active low (DRV8825 nFAULT)"), "{out}");
    let (_, out, _) = run(&["status", "--device", &pty]);
    assert!(!out.contains("driver fault"), "the moment read the wrong way is cleared: {out}");
    let (code, out, err) = run(&["config", "--device", &pty, "--driver-fault", "active-low"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("saved"), "{out}");
    let (code, _, _) = run(&["config", "--device", &pty, "--driver-fault", "inverted"]);
    assert_eq!(code, Some(2));
    // Moving before homing is refused by the device, with its reason.
    let (code, _, err) = run(&["move", "--device", &pty, "--disk", "90"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("disk not homed") && err.contains("`scanner home` first"), "{err}");
    let (code, out, err) = run(&["home", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("homing: done"), "{out}");
    let (code, _, err) = run(&["move", "--device", &pty, "--disk", "90", "--tilt", "-2.5"]);
    assert_eq!(code, Some(0), "{err}");
    let (_, out, _) = run(&["status", "--device", &pty]);
    assert!(out.contains("4000 steps") && out.contains("-667 steps"), "{out}");
    // The continuous disk wraps: −90° is 270°, 360° is the index.
    let (code, _, err) = run(&["move", "--device", &pty, "--disk", "-90"]);
    assert_eq!(code, Some(0), "{err}");
    let (_, out, _) = run(&["status", "--device", &pty]);
    assert!(out.contains("12000 steps"), "{out}");
    let (code, _, err) = run(&["move", "--device", &pty, "--disk", "360"]);
    assert_eq!(code, Some(0), "{err}");
    let (_, out, _) = run(&["status", "--device", &pty]);
    assert!(!out.contains("12000 steps") && out.contains("-667 steps"), "{out}");
    let (code, _, _) = run(&["light", "--device", &pty, "on", "--duty", "500"]);
    assert_eq!(code, Some(0));
    let (_, out, _) = run(&["status", "--device", &pty]);
    assert!(out.contains("light on, 500"), "{out}");
    let (code, out, err) = run(&["trigger", "--device", &pty, "--exposure-us", "2000"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("trigger 1") && out.contains("exposure 2000"), "{out}");
    let (code, out, err) = run(&["setup", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("40 entries written"), "{out}");
    let (_, out, _) = run(&["setup", "--device", &pty]);
    assert!(out.contains("0 entries written"), "set-up is idempotent: {out}");
    // Out-of-range values get a clear refusal.
    let (code, _, err) = run(&["move", "--device", &pty, "--track", "500"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("track: 500") && err.contains("outside its travel"), "{err}");
    let (code, _, err) = run(&["light", "--device", &pty, "on", "--duty", "0"]);
    assert_eq!(code, Some(2), "{err}");
}

#[test]
fn axis_configurations_are_set_saved_read_back_and_checked_on_a_pty() {
    let dir = tmp();
    let server = serve(&setup("leather", FaultPlan::none()), &sub(dir.path(), "camera"));
    let pty = server.path().to_string();
    let file = |name: &str| dir.path().join(name).display().to_string();
    let load = |name: &str| scanner_geometry::load_axes(std::path::Path::new(&file(name)));
    // The device's own, written to a file.
    let (code, out, err) = run(&["axes", "--device", &pty, "-o", &file("device.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("tilt   266.66666 steps/°, -35.00 … 35.00° (-9333 … 9333 steps)"),
        "{out}"
    );
    assert_eq!(load("device.toml").unwrap(), protocol::default_axes());
    let (code, _, err) = run(&["geometry", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    // A tilt that stops at 1500 steps (5.63°): the default design's outer
    // ring needs 6.404°.
    let mut short = protocol::default_axes();
    short[2].max_steps = 1500;
    std::fs::write(file("short.toml"), scanner_geometry::axes_to_toml(&short)).unwrap();
    for command in ["home", "setup"] {
        let (code, _, err) = run(&[command, "--device", &pty]);
        assert_eq!(code, Some(0), "{err}");
    }
    // To a mirror's table entry (the outer ring's tilt is 6.404°).
    let (code, out, err) = run(&["move", "--device", &pty, "--mirror", "39"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("tilt   6.405°  = [") && out.contains("mirror 39: done at ["), "{out}");
    let (code, _, err) = run(&["move", "--device", &pty, "--mirror", "3", "--tilt", "1"]);
    assert_eq!(code, Some(2), "{err}");
    let (code, out, err) = run(&["axes", "--device", &pty, "--set", &file("short.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("set tilt: saved to the device's flash; must be homed again"), "{out}");
    // The mirror table keeps its positions; the outer ring's are unset.
    assert!(out.contains("mirror table: 0 of 40 entries in the new steps"), "{out}");
    assert!(err.contains("mirrors 25–39: tilt: 6.405° (1708 steps) is outside"), "{err}");
    assert!(err.contains("15 of 40 mirror-table entries lie outside the new travel"), "{err}");
    let (code, _, err) = run(&["move", "--device", &pty, "--mirror", "39"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(
        err.contains("mirror 39 is not set in the device's mirror table (40 entries)"),
        "{err}"
    );
    let (code, out, err) = run(&["info", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("mirrors 40 (mirrors 25–39 unset: `scanner setup` writes them)"), "{out}");
    let (_, out, _) = run(&["status", "--device", &pty]);
    let homed = |axis: &str| out.lines().any(|l| l.starts_with(axis) && !l.contains("not homed"));
    assert!(homed("disk") && homed("track") && !homed("tilt"), "{out}");
    // Another process reads it back, and the design check uses it.
    let (code, _, err) = run(&["axes", "--device", &pty, "-o", &file("back.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(load("back.toml").unwrap(), short);
    let outer = "mirror 39: tilt: 6.404° (1708 steps) is outside its travel -35.00 … 5.63° \
                 (-9333 … 1500 steps)";
    for by in [["--device", &pty], ["--axes", &file("short.toml")]] {
        let (code, out, err) = run(&["geometry", by[0], by[1]]);
        assert_eq!(code, Some(3), "{err}");
        assert!(err.contains(outer) && err.contains("15 problems found"), "{err}");
        assert!(out.contains("axes: checked against the axes of"), "{out}");
    }
    // Writing the mirror table for these axes is refused, naming the mirror.
    let (code, _, err) = run(&["setup", "--device", &pty]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("tilt: 6.404°"), "{err}");
    // A file no controller accepts changes nothing.
    let fast = std::fs::read_to_string(file("device.toml")).unwrap().replacen(
        "v_max = 5333",
        "v_max = 500000",
        1,
    );
    std::fs::write(file("fast.toml"), fast).unwrap();
    let (code, _, err) = run(&["axes", "--device", &pty, "--set", &file("fast.toml")]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("fast.toml: tilt: v_max must be 10 … 100000 steps/s"), "{err}");
    let (code, _, err) =
        run(&["axes", "--device", &pty, "--set", &file("device.toml"), "-o", &file("device.toml")]);
    assert_eq!(code, Some(4), "{err}");
    let (code, _, err) = run(&["axes", "--device", &pty, "-o", &file("back.txt")]);
    assert_eq!(code, Some(2), "{err}");
    assert_eq!(load("back.toml").unwrap(), short, "nothing changed");
    // Back to the defaults; again, nothing to write.
    let (code, out, err) = run(&["axes", "--device", &pty, "--set", &file("device.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("set tilt"), "{out}");
    assert!(out.contains("mirror table: 0 of 25 entries"), "{out}");
    let (code, out, err) = run(&["setup", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("15 entries written"), "{out}");
    let (code, out, err) = run(&["axes", "--device", &pty, "--set", &file("device.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("the device's axes are already these"), "{out}");
    let (code, _, err) = run(&["geometry", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    // A lead screw measured short: told 100 mm, it went 98.7 mm.
    let (code, out, err) =
        run(&["axes", "--device", &pty, "--correct", "track=100:98.7", "-o", &file("fixed.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("track: 1600 → 1621.074 steps/mm (told 100 mm, moved 98.7 mm)"), "{out}");
    assert!(out.contains("set track: saved") && out.contains("of 40 entries in the new"), "{out}");
    let mut fixed = protocol::default_axes();
    let m = "track=100:98.7".parse().unwrap();
    fixed[1] = scanner_geometry::correct_axis(&fixed[1], m).unwrap();
    assert_eq!(load("fixed.toml").unwrap(), fixed);
    let (code, _, err) = run(&["axes", "--device", &pty, "--correct", "track=100:-98.7"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("moved the other way"), "{err}");
    let (code, _, err) = run(&["axes", "--device", &pty, "--set", &file("device.toml")]);
    assert_eq!(code, Some(0), "{err}");

    // Travel past the home switch is set, with a warning.
    let mut beyond = protocol::default_axes();
    beyond[1].min_steps = -1_600;
    std::fs::write(file("beyond.toml"), scanner_geometry::axes_to_toml(&beyond)).unwrap();
    let (code, _, err) = run(&["axes", "--device", "sim", "--set", &file("beyond.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("warning: track: the travel reaches -1.00 mm (-1600 steps), below the home"),
        "{err}"
    );
    // A device with a latched fault saves nothing: nothing is changed.
    let estop = FaultPlan::none().at_ms(0, hil_sim::FaultEvent::EmergencyStop(true));
    let stopped = serve(&setup("leather", estop), &sub(dir.path(), "camera2"));
    let pty = stopped.path().to_string();
    let (code, _, err) = run(&["axes", "--device", &pty, "--set", &file("short.toml")]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("emergency stop latched") && err.contains("nothing changed"), "{err}");
    let (code, _, err) = run(&["axes", "--device", &pty, "-o", &file("stopped.toml")]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(load("stopped.toml").unwrap(), protocol::default_axes());
}

#[test]
fn devices_lists_without_hardware() {
    let (code, out, _) = run(&["devices"]);
    assert_eq!(code, Some(0));
    assert!(out.contains("serial") && out.contains("usb"), "{out}");
}

/// The shells' completion scripts name every command and its options; bash
/// reads its script without a syntax error; an unknown shell is a usage
/// error.
#[test]
fn completion_scripts_cover_every_command() {
    let (code, bash, err) = run(&["completions", "bash"]);
    assert_eq!(code, Some(0), "{err}");
    for word in ["scan", "check", "calibrate", "build", "shade", "bootloader", "--frame-timeout"] {
        assert!(bash.contains(word), "{word} not completed");
    }
    let dir = tmp();
    let script = sub(dir.path(), "scanner.bash");
    std::fs::write(&script, &bash).unwrap();
    let syntax = std::process::Command::new("bash").arg("-n").arg(&script).output().unwrap();
    assert!(syntax.status.success(), "{}", String::from_utf8_lossy(&syntax.stderr));
    let (code, fish, _) = run(&["completions", "fish"]);
    assert_eq!(code, Some(0));
    assert!(fish.contains("complete -c scanner") && fish.contains("calibrate"), "{fish}");
    let (code, _, err) = run(&["completions", "tcsh"]);
    assert_eq!(code, Some(2), "{err}");
}

/// The manual pages: one for the program and one for every command,
/// rendered from the parser; written again over its own pages, refused
/// over a directory holding anything else.
#[test]
fn manual_pages_cover_every_command() {
    let dir = tmp();
    let man = sub(dir.path(), "man1");
    let (code, out, err) = run(&["man", man.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("manual pages in"), "{out}");
    for page in ["scanner.1", "scanner-scan.1", "scanner-check.1", "scanner-build.1"] {
        let roff = std::fs::read_to_string(man.join(page)).unwrap();
        assert!(roff.contains("\n.TH "), "{page}: {roff}");
    }
    let check = std::fs::read_to_string(man.join("scanner-check.1")).unwrap();
    assert!(check.contains("\\fB\\-\\-capture\\-all\\fR"), "{check}");
    let pages = std::fs::read_dir(&man).unwrap().count();
    let (code, _, err) = run(&["man", man.to_str().unwrap()]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(std::fs::read_dir(&man).unwrap().count(), pages);
    std::fs::write(man.join("notes.txt"), "mine").unwrap();
    let (code, _, err) = run(&["man", man.to_str().unwrap()]);
    assert_eq!(code, Some(4), "{err}");
    assert_eq!(std::fs::read_to_string(man.join("notes.txt")).unwrap(), "mine");
}

#[test]
fn no_device_exits_5() {
    let (code, _, err) = run(&["status", "--device", "/dev/no-such-scanner"]);
    assert_eq!(code, Some(5), "{err}");
    assert!(err.contains("no device"), "{err}");
    let (code, _, err) = run(&["info", "--device", "0123456789AB"]);
    assert_eq!(code, Some(5), "{err}");
}

/// A device that speaks protocol 2.0: refuses our handshake.
fn incompatible_device() -> (String, std::thread::JoinHandle<()>, serialport::TTYPort) {
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    let path = slave.name().unwrap();
    master.set_timeout(Duration::from_millis(20)).unwrap();
    let thread =
        std::thread::spawn(move || {
            let mut decoder = FrameDecoder::<Request>::new();
            let mut buf = [0u8; 256];
            let end = std::time::Instant::now() + Duration::from_secs(20);
            while std::time::Instant::now() < end {
                let n = match master.read(&mut buf) {
                    Ok(n) => n,
                    Err(e) if e.kind() == std::io::ErrorKind::TimedOut => continue,
                    Err(_) => {
                        std::thread::sleep(Duration::from_millis(5));
                        continue;
                    }
                };
                for f in decoder.feed(&buf[..n]).flatten() {
                    let reply = ToHost::Reply(Reply::Error(DeviceError::UnsupportedVersion(
                        ProtocolVersion { major: 2, minor: 0 },
                    )));
                    let mut out = [0u8; MAX_FRAME_LEN];
                    let len = encode_frame(f.seq, &reply, &mut out).unwrap();
                    let _ = master.write_all(&out[..len]);
                    if matches!(f.msg, Request::Hello { .. }) {
                        return;
                    }
                }
            }
        });
    (path, thread, slave)
}

#[test]
fn incompatible_firmware_exits_6_with_both_versions() {
    let (path, thread, _slave) = incompatible_device();
    let (code, _, err) = run(&["info", "--device", &path]);
    thread.join().unwrap();
    assert_eq!(code, Some(6), "{err}");
    assert!(
        err.contains("incompatible firmware")
            && err.contains("2.0")
            && err.contains(&protocol::PROTOCOL_VERSION.to_string()),
        "{err}"
    );
}

/// A 4-mirror 512² simulated scan into `out`, with `extra` options.
fn sim_scan_with(out: &std::path::Path, extra: &[&str]) -> (Option<i32>, String, String) {
    sim_scan(8, 4, out, extra)
}

/// [`sim_scan_with`] under the simulator's `fault`.
fn scan_with_fault(out: &std::path::Path, fault: &str) -> (Option<i32>, String, String) {
    sim_scan_with(out, &["--sim-fault", fault, "--frame-timeout", "1"])
}

#[test]
fn an_emergency_stop_exits_7_and_keeps_the_frames_taken() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    // Trigger 1 is the dark frame, 2 mirror 0's exposure.
    let (code, _, err) = scan_with_fault(&out, "estop:on@trigger=3");
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("emergency stop"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    assert!(!m.complete);
    assert!(!m.frames.is_empty(), "frames before the stop are kept");
}

#[test]
fn a_camera_that_never_delivers_exits_8() {
    let dir = tmp();
    let (code, _, err) = scan_with_fault(&sub(dir.path(), "scan"), "ignore-trigger:100@trigger=0");
    assert_eq!(code, Some(8), "{err}");
    assert!(err.contains("camera timeout at mirror 0 after 3 attempts"), "{err}");
}

#[test]
fn a_dark_frame_the_camera_misses_is_said_and_taken_on_resuming() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    // The camera misses the first three triggers: the dark frame's three
    // attempts.
    let (code, _, err) = scan_with_fault(&out, "ignore-trigger:3@trigger=0");
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(
        err.matches("dark frame: camera: no frame within 1s; taking it again").count(),
        2,
        "{err}"
    );
    assert!(err.contains("no dark frame (after 3 attempts: camera: no frame within 1s)"), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    assert!(m.complete && m.settings.dark.is_none(), "{:?}", m.settings.dark);
    // Resumed, the scan takes it: a flawless sensor's, at the scan's exposure.
    let (code, _, err) = sim_scan_with(&out, &["--resume"]);
    assert_eq!(code, Some(0), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    let dark = m.settings.dark.expect("a dark frame on resuming");
    assert_eq!((dark.exposure_us, dark.defects.len()), (protocol::DEFAULT_EXPOSURE_US, 0));
}

#[test]
fn a_camera_that_leaves_its_black_level_in_gets_no_hot_pixels_and_is_told() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let (code, _, err) = sim_scan_with(&out, &["--sim-black-level", "64"]);
    assert_eq!(code, Some(0), "{err}");
    // Read noise around 64 codes: the median is 64; the scan says how to
    // take it out.
    assert!(
        err.contains("dark frame: its median pixel reads 64 codes, not 0: the camera's frames carry a black level (scan with --black-level 64"),
        "{err}"
    );
    let m = host::scan::Manifest::load(&out).unwrap();
    let dark = m.settings.dark.expect("the dark frame recorded");
    assert!(dark.defects.is_empty(), "{:?}", dark.defects);
    // A level at or above the top code is refused before anything is written.
    let bad = sub(dir.path(), "bad");
    let (code, _, err) = sim_scan_with(&bad, &["--sim-black-level", "4095"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("not below the top code 4095"), "{err}");
    assert!(!bad.join("manifest.json").exists());
    let (code, _, err) = sim_scan_with(&bad, &["--black-level", "4095"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--black-level 4095: at or above the sensor's top code"), "{err}");
    assert!(!bad.join("manifest.json").exists());
}

#[test]
fn black_level_subtracts_what_the_camera_left_in() {
    let dir = tmp();
    let (clean, offset, fixed) =
        (sub(dir.path(), "clean"), sub(dir.path(), "offset"), sub(dir.path(), "fixed"));
    let (auto, clean_auto) = (sub(dir.path(), "auto"), sub(dir.path(), "clean-auto"));
    for (out, extra) in [
        (&clean, &[][..]),
        (&offset, &["--sim-black-level", "64"][..]),
        (&fixed, &["--sim-black-level", "64", "--black-level", "64"][..]),
        (&auto, &["--sim-black-level", "64", "--black-level", "auto"][..]),
        (&clean_auto, &["--black-level", "auto"][..]),
    ] {
        let (code, _, err) = sim_scan_with(out, extra);
        assert_eq!(code, Some(0), "{err}");
        if out != &offset {
            assert!(!err.contains("median pixel"), "the dark frame is dark: {err}");
        }
        if out == &auto {
            assert!(
                err.contains(
                    "black level: 64 codes (the median of a 1000 µs frame with the light off)"
                ),
                "{err}"
            );
        }
    }
    // Auto on a camera without a black level measures none: read noise
    // alone is not taken for one.
    let m = host::scan::Manifest::load(&clean_auto).unwrap();
    assert_eq!(m.settings.black_level_codes, 0);
    let m = host::scan::Manifest::load(&auto).unwrap();
    assert_eq!(m.settings.black_level_codes, 64);
    assert_eq!(m.settings.black_level_auto.unwrap().exposure_us, Some(1000));
    let fixed_manifest = host::scan::Manifest::load(&fixed).unwrap();
    assert_eq!(fixed_manifest.settings.black_level_codes, 64);
    assert!(fixed_manifest.settings.dark.is_some());
    assert_eq!(host::scan::Manifest::load(&clean).unwrap().settings.black_level_codes, 0);
    // The same seed renders the same light and noise: with the level taken
    // out, every value below the offset camera's clipping point is the clean
    // camera's to the code; left in, the frames read 64 codes high.
    let codes = |dir: &std::path::Path, l: usize| {
        let f = host::exrio::read_rgb(&dir.join(format!("frames/mirror-{l:02}.exr"))).unwrap();
        f.rgb.iter().map(|v| v * 4095.0).collect::<Vec<f32>>()
    };
    for l in 0..4 {
        let (c, o, x) = (codes(&clean, l), codes(&offset, l), codes(&fixed, l));
        // Auto's extra frame shifts the simulator's noise: within noise of
        // the clean camera, not to the code.
        let (a, ca) = (codes(&auto, l), codes(&clean_auto, l));
        let mean_diff = |p: &[f32], q: &[f32]| {
            p.iter().zip(q).map(|(p, q)| (p - q) as f64).sum::<f64>() / p.len() as f64
        };
        assert!(mean_diff(&a, &c).abs() < 0.1, "mirror {l}: auto {}", mean_diff(&a, &c));
        assert!(mean_diff(&ca, &c).abs() < 0.1, "mirror {l}: {}", mean_diff(&ca, &c));
        let mut worst = 0.0f32;
        let (mut bias_left, mut n) = (0.0f64, 0usize);
        for ((&c, &o), &x) in c.iter().zip(&o).zip(&x) {
            if c > 0.5 && c < 4095.0 - 64.0 - 1.0 {
                worst = worst.max((x - c).abs());
                bias_left += (o - c) as f64;
                n += 1;
            }
        }
        assert!(n > 1000, "mirror {l}: {n} lit values");
        assert!(worst <= 1.0, "mirror {l}: {worst} codes from the clean camera's");
        let bias = bias_left / n as f64;
        assert!((bias - 64.0).abs() < 1.0, "mirror {l}: left in, {bias} codes high");
    }
    // A resume with another level is refused.
    let (code, _, err) = sim_scan_with(&fixed, &["--sim-black-level", "64", "--resume"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("black level 64 codes (the directory's) vs 0 codes"), "{err}");
    let (code, _, err) = sim_scan_with(&auto, &["--sim-black-level", "64", "--resume"]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("black level auto (the directory's) vs 0 codes"), "{err}");
}

/// A sample height the simulator cannot hold, or one `regions` cannot
/// read at, is a usage error naming the value.
#[test]
fn a_sample_height_out_of_range_is_a_usage_error() {
    let dir = tmp();
    let (code, _, err) = sim_scan_with(&sub(dir.path(), "scan"), &["--sim-sample-height", "7"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("a sample height of 7 mm is outside ±5 mm"), "{err}");
    for bad in ["nan", "11", "high"] {
        let (code, _, err) = run(&[
            "regions",
            "--scan",
            "s",
            "--calibration",
            "c.json",
            "-o",
            "r",
            "--sample-height",
            bad,
        ]);
        assert_eq!(code, Some(2), "{err}");
        assert!(err.contains("`auto` or a height in mm within ±10"), "{bad}: {err}");
    }
    // A tilt: the simulator's within ±10°, a given one with a given height
    // and within ±20°, two numbers.
    let (code, _, err) = sim_scan_with(&sub(dir.path(), "tilted"), &["--sim-sample-tilt", "12,0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("a sample tilt of 12° is outside ±10°"), "{err}");
    for t in ["25", "-1"] {
        let (code, _, err) =
            sim_scan_with(&sub(dir.path(), "thick"), &["--sim-sample-thickness", t]);
        assert_eq!(code, Some(2), "{err}");
        assert!(err.contains(&format!("a sample thickness of {t} mm is outside 0…20 mm")), "{err}");
    }
    for a in ["1.5", "-0.1", "NaN"] {
        let (code, _, err) = sim_scan_with(&sub(dir.path(), "holder"), &["--sim-holder-albedo", a]);
        assert_eq!(code, Some(2), "{err}");
        assert!(err.contains(&format!("a holder albedo of {a} is outside 0…1")), "{err}");
    }
    let regions = ["regions", "--scan", "s", "--calibration", "c.json", "-o", "r"];
    for (extra, says) in [
        (&["--sample-tilt", "1,1"][..], "--sample-tilt needs a given --sample-height"),
        (&["--sample-height", "0", "--sample-tilt", "30,0"][..], "within ±20°"),
        (&["--sample-height", "0", "--sample-tilt", "1"][..], "give two finite numbers"),
    ] {
        let (code, _, err) = run(&[&regions[..], extra].concat());
        assert_eq!(code, Some(2), "{extra:?}: {err}");
        assert!(err.contains(says), "{extra:?}: {err}");
    }
}

#[test]
fn a_bad_fault_spec_is_a_usage_error() {
    let dir = tmp();
    let (code, _, err) = scan_with_fault(&sub(dir.path(), "scan"), "explode@trigger=1");
    assert_eq!(code, Some(2), "{err}");
}

/// `scanner home --repeat`: the spec's drives keep their steps; a track
/// told to run beyond its motor's pull-out loses them (exit 7).
#[test]
fn repeated_homing_reports_drives_that_keep_or_lose_their_steps() {
    let (code, out, err) = run(&["home", "--repeat", "2"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("homing 2: disk from 231.41°: +0 steps, track from 180.00 mm"), "{out}");
    assert_eq!(out.matches("(tolerance ±32): keeps its steps").count(), 3, "{out}");
    let dir = tmp();
    let fast = dir.path().join("fast.toml");
    let mut axes = protocol::default_axes();
    axes[1].v_max = 100_000;
    std::fs::write(&fast, scanner_geometry::axes_to_toml(&axes)).unwrap();
    let fast = fast.display().to_string();
    let (code, out, err) = run(&["home", "--repeat", "1", "--axes", "track", "--sim-axes", &fast]);
    assert_eq!(code, Some(7), "{out}{err}");
    assert!(out.contains("track  count at the switch") && out.contains("LOST STEPS"), "{out}");
    assert!(err.contains("track lost steps") && err.contains("lower its v_max"), "{err}");
    let (code, _, err) = run(&["home", "--repeat", "0"]);
    assert_eq!(code, Some(2), "{err}");
}

/// `scanner sim` at 512² with `options`, its frames into `frames`, its
/// standard error to `stderr`; the process and its pty.
fn scanner_sim(
    frames: &std::path::Path,
    options: &[&str],
    stderr: std::process::Stdio,
) -> (std::process::Child, String) {
    use std::io::BufRead;
    let mut child = scanner()
        .args(["sim", "--sim-bin", "8", "--frames", &frames.display().to_string()])
        .args(options)
        .stdout(std::process::Stdio::piped())
        .stderr(stderr)
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    (child, line.trim().to_string())
}

/// A second program on a scanner's port is refused with the reason, and
/// once the first has ended it is served.
#[test]
fn a_port_in_use_by_another_program_is_said_so() {
    use std::io::BufRead;
    let dir = tmp();
    let server = serve(&setup("leather", FaultPlan::none()), &sub(dir.path(), "camera"));
    let pty = server.path().to_string();
    let mut holder = scanner()
        .args(["inputs", "--device", &pty, "--watch", "600"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Connected once it prints the inputs.
    let mut lines = std::io::BufReader::new(holder.stdout.take().unwrap()).lines();
    assert!(lines.any(|l| l.is_ok_and(|l| l.starts_with("watching"))), "the first program runs");
    let (code, _, err) = run(&["status", "--device", &pty]);
    holder.kill().unwrap();
    let _ = holder.wait();
    assert_eq!(code, Some(5), "{err}");
    assert!(err.contains(&format!("{pty}: in use by another program")), "{err}");
    let (code, out, err) = run(&["status", "--device", &pty]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("not homed"), "{out}");
}

#[test]
fn scanner_sim_serves_a_scanner_on_a_pty_with_its_geometry() {
    let dir = tmp();
    let frames = sub(dir.path(), "frames");
    let (mut child, pty) = scanner_sim(&frames, &["--speed", "3"], std::process::Stdio::null());
    let (code, out, err) = run(&["info", "--device", &pty]);
    let geometry = hil_sim::geometry::ScannerGeometry::load(&frames.join("geometry.toml"));
    let (tcode, _, terr) = run(&["trigger", "--device", &pty]);
    // The camera drops the trigger's frame into the folder.
    let end = std::time::Instant::now() + Duration::from_secs(10);
    let mut exr = 0;
    while exr == 0 && std::time::Instant::now() < end {
        std::thread::sleep(Duration::from_millis(50));
        exr = std::fs::read_dir(&frames)
            .unwrap()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().ends_with(".exr"))
            .count();
    }
    child.kill().unwrap();
    let _ = child.wait();
    assert!(pty.starts_with("/dev/"), "{pty:?}");
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("board 0x5100"), "{out}");
    assert_eq!(geometry.unwrap().camera.width, 512);
    assert_eq!(tcode, Some(0), "{terr}");
    assert_eq!(exr, 1, "one frame per trigger");
}

/// A simulator process the machine does not schedule for a while (here:
/// stopped by SIGSTOP for 0.5 s, 1.5 s of simulated time at speed 3, three
/// times the device's link timeout) pauses the device: the host's pings of
/// that time reach it when it runs again, and homing goes on. Before, the
/// device caught up with wall time first and stopped on a link timeout the
/// hardware would not have (`homing: Stopped`, exit 7).
#[test]
fn a_simulator_not_scheduled_for_a_while_pauses_instead_of_losing_the_link() {
    let dir = tmp();
    let frames = sub(dir.path(), "frames");
    let (mut sim, pty) = scanner_sim(&frames, &["--speed", "3"], std::process::Stdio::null());
    let signal = |name: &str| {
        let ok = std::process::Command::new("kill")
            .args([name, &sim.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill {name}");
    };
    let mut home = scanner()
        .args(["home", "--device", &pty])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(600));
    assert!(home.try_wait().unwrap().is_none(), "homing ended before the simulator stopped");
    signal("-STOP");
    std::thread::sleep(Duration::from_millis(500));
    signal("-CONT");
    let out = home.wait_with_output().unwrap();
    sim.kill().unwrap();
    let _ = sim.wait();
    let (stdout, stderr) =
        (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(0), "{stdout}{stderr}");
    assert!(stdout.contains("homing: done"), "{stdout}");
}

/// A noisy link loses a motion's `MotionDone` event now and then: `scanner
/// home` asks the status and ends with the device, where it waited 120 s
/// and failed (exit 7) though homing had completed. In-process simulator
/// (deterministic: simulated time), 1 % of the bytes corrupted, seeds
/// 1–40: every one homes, and some lose the event (11 of 40 when this was
/// written; which ones moves with the link's timing).
#[test]
fn a_lost_end_of_motion_event_is_recovered_from_the_status() {
    let mut recovered = 0;
    for seed in 1..=40 {
        let seed = seed.to_string();
        let (code, out, err) =
            run(&["home", "--device", "sim", "--sim-corrupt", "0.01", "--sim-seed", &seed]);
        assert_eq!(code, Some(0), "seed {seed}: {out}{err}");
        assert!(out.contains("homing: done at"), "seed {seed}: {out}");
        recovered += usize::from(out.contains("its report was lost on the link"));
    }
    assert!(recovered >= 2, "{recovered} of 40 seeds lost the event");
}

/// Commissioning practised on `scanner sim`: a board with the spec's axes
/// on a scanner whose lead screw makes 1.3 % less; the simulator prints
/// where the axes stop, as a ruler on the machine would read, and the
/// measured move corrects the track.
#[test]
fn a_board_to_commission_is_measured_on_scanner_sim_and_corrected() {
    use std::io::BufRead;
    let dir = tmp();
    let built = dir.path().join("built.toml");
    let mut axes = protocol::default_axes();
    let m = "track=100:98.7".parse().unwrap();
    axes[1] = scanner_geometry::correct_axis(&axes[1], m).unwrap();
    std::fs::write(&built, scanner_geometry::axes_to_toml(&axes)).unwrap();
    let spec = dir.path().join("spec.toml");
    std::fs::write(&spec, scanner_geometry::axes_to_toml(&protocol::default_axes())).unwrap();
    let frames = sub(dir.path(), "frames");
    let (built, spec) = (built.display().to_string(), spec.display().to_string());
    let options = ["--speed", "4", "--sim-axes", &built, "--sim-board-axes", &spec];
    let (mut child, pty) = scanner_sim(&frames, &options, std::process::Stdio::piped());
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    // The track's position where the axes next stop, as printed.
    let ruler = || -> f64 {
        loop {
            let line = rx.recv_timeout(Duration::from_secs(60)).expect("the axes stop");
            if let Some(rest) = line.split("track ").nth(1) {
                return rest.split(' ').next().unwrap().parse().unwrap();
            }
        }
    };
    let mut ran = Vec::new();
    for (args, expected) in [
        (vec!["home", "--axes", "track"], 0.0),
        (vec!["move", "--track", "100"], 98.7),
        (vec!["axes", "--correct", "track=100:98.7"], f64::NAN),
        (vec!["home", "--axes", "track"], 0.0),
        (vec!["move", "--track", "100"], 100.0),
    ] {
        let mut all = args.clone();
        all.extend(["--device", &pty]);
        let (code, out, err) = run(&all);
        let at = if expected.is_nan() { f64::NAN } else { ruler() };
        ran.push((args, code, out, err, at, expected));
    }
    child.kill().unwrap();
    let _ = child.wait();
    for (args, code, out, err, at, expected) in ran {
        assert_eq!(code, Some(0), "{args:?}: {out}{err}");
        assert!(expected.is_nan() || (at - expected).abs() < 0.0015, "{args:?}: at {at} mm");
    }
}

#[test]
#[ignore = "needs a scanner on USB with its bulk interface: run with --ignored where one is connected"]
fn usb_bulk_handshake_with_a_connected_scanner() {
    let scanners: Vec<_> = host::discovery::usb_devices()
        .expect("USB devices can be listed")
        .into_iter()
        .filter(|d| d.vendor_interface.is_some())
        .collect();
    let d = scanners.first().expect("a scanner with a USB bulk interface is connected");
    let (code, out, err) = run(&["info", "--device", &format!("usb:{}", d.serial)]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("protocol"), "{out}");
}

#[test]
fn a_bad_geometry_file_exits_3() {
    let dir = tmp();
    let path = sub(dir.path(), "g.toml");
    std::fs::write(&path, "format = 1\n[ellipsoid]\n").unwrap();
    let (code, _, err) =
        run(&["setup", "--device", "sim", "--geometry", &path.display().to_string()]);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("scanner geometry"), "{err}");
}

/// The settle time after each move is the user's (a real build's arm rings
/// for as long as it rings): recorded, kept by a resume, bounded.
#[test]
fn the_settle_time_is_a_scan_option() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let scan = |settle: &str, resume: bool| {
        let mut extra = vec!["--settle-ms", settle];
        if resume {
            extra.push("--resume");
        }
        sim_scan(16, 2, &out, &extra)
    };
    let (code, _, err) = scan("400", false);
    assert_eq!(code, Some(0), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    assert_eq!(m.settings.settle_ms, 400);
    let (code, _, err) = scan("150", true);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("settle 400 ms (the directory's) vs 150 ms"), "{err}");
    let (code, _, err) = scan("60001", true);
    assert_eq!(code, Some(2), "{err}");
}

#[test]
fn verify_reports_missing_and_damaged_frames() {
    let dir = tmp();
    let out = sub(dir.path(), "scan");
    let o = out.display().to_string();
    let (code, _, err) = sim_scan(16, 3, &out, &[]);
    assert_eq!(code, Some(0), "{err}");
    let (code, out_text, _) = run(&["verify", &o]);
    assert_eq!(code, Some(0));
    assert!(out_text.contains("3 of 3 frames intact"), "{out_text}");
    std::fs::write(out.join("frames/mirror-01.exr"), b"not an exr").unwrap();
    let (code, out_text, _) = run(&["verify", &o]);
    assert_eq!(code, Some(3));
    assert!(out_text.contains("damaged: mirror 1"), "{out_text}");
    let (code, out_text, err) = sim_scan(16, 3, &out, &["--resume"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out_text.contains("1 frames taken, 2 kept"), "{out_text}");
    assert_eq!(run(&["verify", &o]).0, Some(0));
}

#[test]
fn a_texture_set_is_scanned_like_a_library_material_and_a_bad_one_exits_3() {
    let dir = tmp();
    let set = sub(dir.path(), "grey-set");
    uniform_set(&set, "grey", 30.0, [0.5; 3], 0.04, 0.6);
    let scan = |material: &str, out: &std::path::Path| {
        run(&[
            "scan",
            "--sim-material",
            material,
            "--sim-bin",
            "16",
            "--mirrors",
            "2",
            "--sample-name",
            "grey",
            "--out",
            &out.display().to_string(),
        ])
    };
    let out = sub(dir.path(), "scan");
    let (code, _, err) = scan(set.to_str().unwrap(), &out);
    assert_eq!(code, Some(0), "{err}");
    let m = host::scan::Manifest::load(&out).unwrap();
    assert!(m.complete && m.frames.len() == 2);
    // The frame sees the grey sample: lit pixels, none clipped.
    let f = host::exrio::read_rgb(&out.join(&m.frames[0].file)).unwrap();
    let lit = f.rgb.iter().filter(|&&v| v > 0.01).count();
    assert!(lit > 1_000, "{lit} lit values");
    assert!(f.rgb.iter().all(|&v| v < 1.0));
    // A broken set: exit 3 naming the file, nothing written.
    std::fs::remove_file(set.join("roughness.exr")).unwrap();
    let bad_out = sub(dir.path(), "bad");
    let (code, _, err) = scan(set.to_str().unwrap(), &bad_out);
    assert_eq!(code, Some(3), "{err}");
    assert!(err.contains("roughness.png: missing"), "{err}");
    assert!(!bad_out.exists());
    let (code, _, err) =
        run(&["demo", "--material", set.to_str().unwrap(), "--out", "/nonexistent/x"]);
    assert_eq!(code, Some(3), "{err}");
    let (code, _, err) = scan("velvet", &bad_out);
    assert_eq!(code, Some(2), "{err}");
}

/// Output into a closed pipe (`scanner geometry | head -1`) ends the
/// program as it ends any Unix tool, by SIGPIPE, not with a panic.
#[cfg(unix)]
#[test]
fn a_closed_pipe_ends_the_program_quietly() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let mut child =
        scanner().arg("geometry").stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    // Closed before the program has started printing.
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    // SIGPIPE = 13; a program that printed everything before the pipe
    // closed (a slow test machine) exits 0.
    assert!(out.status.signal() == Some(13) || out.status.success(), "{:?}: {err}", out.status);
}

/// `scanner demo` simulates the scene a user names: the holder's albedo
/// and the lens in every scan, and how the sample lies (a 1 mm slab on the
/// holder) in the sample's scan only — the targets lie flat in the holder.
/// The build measures the face where the slab puts it. A scene the
/// simulator refuses is refused before the first scan, nothing written.
#[test]
fn the_demo_scans_the_scene_it_is_given() {
    let dir = tmp();
    let out = dir.path().join("demo");
    let (code, said, err) = run(&[
        "demo",
        "--bin",
        "8",
        "--mirrors",
        "12",
        "--material",
        "leather",
        "--sim-holder-albedo",
        "0.04",
        "--sim-sample-height",
        "1",
        "--sim-sample-thickness",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(0), "{said}{err}");
    let simulated = |scan: &str| {
        let m = host::scan::Manifest::load(&out.join(scan)).unwrap();
        m.settings.simulator.unwrap()
    };
    for target in ["checkerboard", "diffuse-white", "glossy-black"] {
        let s = simulated(target);
        assert!(s.contains("holder albedo 0.04") && !s.contains("sample"), "{target}: {s}");
    }
    let s = simulated("leather");
    assert!(
        s.contains("holder albedo 0.04")
            && s.contains("sample's face 1 mm proud of the holder")
            && s.contains("sample 1 mm thick"),
        "{s}"
    );
    // "sample's face measured 0.969 ± 0.032 mm above the holder's plane"
    let measured = said
        .split("sample's face measured ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|h| h.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no height measured: {said}"));
    assert!((measured - 1.0).abs() < 0.1, "measured {measured} mm: {said}");
    assert!(out.join("leather-preview.png").is_file());

    let bad = dir.path().join("bad");
    let (code, said, err) =
        run(&["demo", "--sim-sample-tilt", "40,0", "--out", bad.to_str().unwrap()]);
    assert_eq!(code, Some(2), "{said}{err}");
    assert!(err.contains("a sample tilt of 40° is outside ±10°"), "{err}");
    assert!(!bad.exists());
}
