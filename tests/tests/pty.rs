//! End-to-end: the `scanner` program against the simulated scanner served on
//! a pseudo-terminal, its camera dropping frames into a folder.

mod common;

use std::path::Path;
use std::process::Stdio;
use std::time::{Duration, Instant};

use common::*;
use hil_sim::{FaultEvent, FaultPlan};
use host::scan::Manifest;

const MIRRORS: usize = 8;
/// The kill test needs a longer scan.
const KILL_MIRRORS: usize = 12;

#[test]
fn a_scan_over_the_pty_stores_every_frame_and_matches_the_in_process_scan() {
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let out = sub(dir.path(), "scan");
    let s = setup("painted-wood", FaultPlan::none());
    let server = serve(&s, &frames_dir);
    let t = Instant::now();
    let result =
        scanner().args(scan_args(server.path(), &frames_dir, &out, MIRRORS)).output().unwrap();
    eprintln!("pty scan: {:?}\n{}", t.elapsed(), String::from_utf8_lossy(&result.stdout));
    assert!(result.status.success(), "{}", String::from_utf8_lossy(&result.stderr));
    let m = Manifest::load(&out).unwrap();
    assert!(m.complete);
    assert_eq!(m.frames.len(), MIRRORS);
    for (l, f) in m.frames.iter().enumerate() {
        assert_eq!(f.mirror, l);
        assert_eq!((f.width, f.height), (512, 512));
        assert_eq!(f.exposure_us, 50_000);
        let frame = host::exrio::read_rgb(&out.join(&f.file)).unwrap();
        assert!(frame.rgb.iter().any(|&v| v > 0.02), "mirror {l} lit");
    }
    // The same scanner simulated in-process and deterministic: same frames.
    assert_same_frames_as_in_process(&s, &out, &sub(dir.path(), "in-process"));
    drop(server);
}

/// Assert the scan in `out` stored the frames, byte for byte, that the same
/// scanner simulated in-process (and deterministic) gives; that scan goes to
/// `reference`.
fn assert_same_frames_as_in_process(s: &host::simulator::SimSetup, out: &Path, reference: &Path) {
    let rig = s.rig().unwrap();
    let mut dev =
        host::link::Device::connect(Box::new(host::link::SimTransport(rig.clone()))).unwrap();
    let mut opts = host::scan::ScanOptions::new("e2e", reference);
    opts.mirrors = Some(MIRRORS);
    host::scan::scan(
        &mut dev,
        &mut host::camera::SimCamera(rig),
        &s.nominal().unwrap(),
        &opts,
        &mut host::scan::Quiet,
    )
    .unwrap();
    let a = frames(out);
    let b = frames(reference);
    assert_eq!(a.len(), b.len());
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert!(x == y, "{name}: pty and in-process frames differ");
    }
}

#[test]
fn sixteen_bit_tiff_frames_give_the_same_scan_and_a_wrong_convention_is_named() {
    use hil_sim::camera::FrameFiles;
    use scanner_geometry::IntegerCodes;
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let s = setup("leather", FaultPlan::none());
    // A capture program that writes 16-bit TIFFs of 12-bit codes × 16.
    let server = serve_files(&s, &frames_dir, FrameFiles::Tiff(IntegerCodes::Shifted));
    // Read as the codes themselves, the first frame that shows it stops the
    // scan and names the option: the dark frame when a thousand of its
    // values are non-zero, else mirror 0, far above 4095.
    let wrong = sub(dir.path(), "wrong");
    let r =
        scanner().args(scan_args(server.path(), &frames_dir, &wrong, MIRRORS)).output().unwrap();
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(3), "{err}");
    assert!(err.contains("frame-") && err.contains(".tiff: "), "{err}");
    assert!(err.contains("the capture program shifts its codes left (× 16)"), "{err}");
    assert!(err.contains("scan with --camera-codes shifted"), "{err}");
    assert!(Manifest::load(&wrong).map_or(true, |m| m.frames.is_empty()), "nothing stored");
    // Nor can a resume read them another way than the scan began with.
    let mut resume = scan_args(server.path(), &frames_dir, &wrong, MIRRORS);
    resume.extend(["--camera-codes".into(), "shifted".into(), "--resume".into()]);
    let r = scanner().args(&resume).output().unwrap();
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(3), "{err}");
    assert!(err.contains("camera codes native (the directory's) vs shifted (this run's)"), "{err}");
    // Read as shifted: the frames the in-process scanner gives, byte for byte.
    let out = sub(dir.path(), "scan");
    let mut args = scan_args(server.path(), &frames_dir, &out, MIRRORS);
    args.extend(["--camera-codes".into(), "shifted".into()]);
    let r = scanner().args(&args).output().unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(
        std::fs::read_dir(&frames_dir)
            .unwrap()
            .flatten()
            .any(|e| e.file_name().to_string_lossy().ends_with(".tiff")),
        "the camera wrote TIFFs"
    );
    drop(server);
    assert_same_frames_as_in_process(&s, &out, &sub(dir.path(), "in-process"));
}

#[test]
fn faults_on_the_way_do_not_change_a_single_frame() {
    let dir = tmp();
    let clean_out = sub(dir.path(), "clean");
    let faulty_out = sub(dir.path(), "faulty");
    let clean_frames = sub(dir.path(), "camera-clean");
    let faulty_frames = sub(dir.path(), "camera-faulty");
    let clean = serve(&setup("leather", FaultPlan::none()), &clean_frames);
    let r = scanner()
        .args(scan_args(clean.path(), &clean_frames, &clean_out, MIRRORS))
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    drop(clean);

    let faults = FaultPlan::none()
        .corrupt(1e-3)
        .after_triggers(2, FaultEvent::Disconnect { duration_ms: 1500 })
        .after_triggers(4, FaultEvent::Reset)
        .after_triggers(6, FaultEvent::IgnoreTriggers(1));
    let faulty = serve(&setup("leather", faults), &faulty_frames);
    let r = scanner()
        .args(scan_args(faulty.path(), &faulty_frames, &faulty_out, MIRRORS))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&r.stdout);
    eprintln!("{stdout}\n{}", String::from_utf8_lossy(&r.stderr));
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    assert!(stdout.contains("1 resets survived"), "the reset was seen: {stdout}");
    // The disconnect and the reset each unplugged the board (a USB port):
    // the host reopened its port after each.
    let reconnects = stdout
        .split(", ")
        .find_map(|s| s.trim().strip_suffix(" reconnects"))
        .and_then(|n| n.rsplit(' ').next()?.parse::<u32>().ok());
    assert!(reconnects.is_some_and(|n| n >= 2), "{reconnects:?}: {stdout}");
    assert!(stdout.contains("retransmissions"), "the noise was seen: {stdout}");
    drop(faulty);
    assert_same_scan(&clean_out, &faulty_out);
}

#[test]
fn resume_after_sigkill_at_six_moments_gives_the_uninterrupted_scan() {
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let reference = sub(dir.path(), "reference");
    let resumed = sub(dir.path(), "resumed");
    let s = setup("rough-metal", FaultPlan::none());
    let server = serve(&s, &frames_dir);
    let t = Instant::now();
    let r = scanner()
        .args(scan_args(server.path(), &frames_dir, &reference, KILL_MIRRORS))
        .output()
        .unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    let whole = t.elapsed();
    eprintln!("uninterrupted scan: {whole:?}");
    // Kill moments spread over a run: during start-up, moves, exposures
    // and writes (each resumed run goes on from where the last stopped).
    let moments = [150u64, 500, 900, 1300, 1000, 700].map(Duration::from_millis);
    let mut interrupted = 0;
    let mut args = scan_args(server.path(), &frames_dir, &resumed, KILL_MIRRORS);
    args.push("--resume".into());
    for (k, after) in moments.iter().enumerate() {
        let done_before = resumed.join("manifest.json").exists()
            && Manifest::load(&resumed).is_ok_and(|m| m.complete);
        let mut child =
            scanner().args(&args).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
        std::thread::sleep(*after);
        // SIGKILL: no chance to clean up.
        let _ = child.kill();
        let _ = child.wait();
        // Nothing partial is ever visible under its final name.
        if resumed.join("manifest.json").exists() {
            let m = Manifest::load(&resumed).unwrap_or_else(|e| panic!("kill {k}: manifest: {e}"));
            for f in &m.frames {
                host::exrio::read_rgb(&resumed.join(&f.file))
                    .unwrap_or_else(|e| panic!("kill {k}: {}: {e}", f.file));
            }
            eprintln!("kill {k} after {after:?}: {} frames stored", m.frames.len());
            if !done_before && !m.complete {
                interrupted += 1;
            }
        } else {
            interrupted += 1;
        }
        for entry in std::fs::read_dir(resumed.join("frames")).into_iter().flatten().flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if !name.starts_with(".tmp-") {
                host::exrio::read_rgb(&entry.path())
                    .unwrap_or_else(|e| panic!("kill {k}: {name}: {e}"));
            }
        }
    }
    assert!(interrupted >= 5, "only {interrupted} kills hit an unfinished scan");
    let r = scanner().args(&args).output().unwrap();
    assert!(r.status.success(), "{}", String::from_utf8_lossy(&r.stderr));
    drop(server);
    assert_same_scan(&reference, &resumed);
    let _ = Duration::ZERO;
}

#[test]
fn without_resume_an_existing_scan_is_not_touched() {
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let out = sub(dir.path(), "scan");
    let server = serve(&setup("leather", FaultPlan::none()), &frames_dir);
    let r = scanner().args(scan_args(server.path(), &frames_dir, &out, 2)).output().unwrap();
    assert!(r.status.success());
    let before = frames(&out);
    let r = scanner().args(scan_args(server.path(), &frames_dir, &out, 2)).output().unwrap();
    assert_eq!(r.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&r.stderr).contains("--resume"));
    assert_eq!(frames(&out), before);
}

/// Run `scanner ARGS --device PATH`: (exit code, stdout, stderr).
fn on_device(path: &str, args: &[&str]) -> (Option<i32>, String, String) {
    let r = scanner().args(args).args(["--device", path]).output().unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    (r.status.code(), text(&r.stdout), text(&r.stderr))
}

/// Drivers whose fault line is active high (TMC2209 DIAG) on a board set
/// active low: the idle line reads as a fault from power-on, which no
/// `scanner clear` clears and no setting could be saved under. Setting the
/// polarity rescues it: set, cleared and saved in one command.
#[test]
fn drivers_that_signal_faults_the_other_way_are_rescued_by_setting_the_polarity() {
    let dir = tmp();
    let mut s = setup("leather", FaultPlan::none());
    s.driver_fault_active_high = true;
    let server = serve(&s, &sub(dir.path(), "camera"));
    let run = |args: &[&str]| on_device(server.path(), args);
    let (_, out, _) = run(&["status"]);
    assert!(out.contains("driver fault"), "{out}");
    let (code, _, err) = run(&["home"]);
    assert_eq!(code, Some(7), "{err}");
    let (code, _, err) = run(&["clear"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(
        err.contains("the driver fault line is still low, read active low as a fault")
            && err.contains("`scanner config --driver-fault active-high`"),
        "{err}"
    );
    // Another setting is still refused while it is latched…
    let (code, _, err) = run(&["config", "--home-sensor", "track=active-high"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("nothing changed"), "{err}");
    // …and setting the polarity the wrong way again changes nothing.
    let (code, _, err) = run(&["config", "--driver-fault", "active-low"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(
        err.contains("the driver fault line is low, a fault read active low")
            && err.contains("nothing changed"),
        "{err}"
    );
    let (code, out, err) = run(&["config", "--driver-fault", "active-high"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("cleared: driver fault (its line reads no fault read active high)"),
        "{out}"
    );
    assert!(out.contains("saved to the device's flash"), "{out}");
    assert!(out.contains("driver fault line: active high (TMC2209 DIAG)"), "{out}");
    let (_, out, _) = run(&["inputs"]);
    assert!(out.contains("driver fault        line low  → no fault (read active high)"), "{out}");
    let (code, out, err) = run(&["home"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("homing: done"), "{out}");
    drop(server);
}

#[test]
fn a_home_sensor_wired_active_high_fails_homing_until_configured_so() {
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    let mut s = setup("leather", FaultPlan::none());
    // The track's sensor is a push-pull one: high when actuated.
    s.home_active_high = [false, true, false];
    let server = serve(&s, &frames_dir);
    let run = |args: &[&str]| on_device(server.path(), args);
    let (code, out, err) = run(&["config"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("home sensors: disk active low, track active low, tilt active low"),
        "{out}"
    );
    // Far from its switch, the track's sensor holds its line low: read
    // active low, that is "actuated" — what `scanner inputs` shows.
    let (code, out, err) = run(&["inputs", "--watch", "0.3"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("track home switch   line low  → ACTUATED (read active low)"), "{out}");
    assert!(
        out.contains("disk  index flag    line high → not actuated (read active low)"),
        "{out}"
    );
    assert!(out.contains("emergency stop      closed (run)"), "{out}");
    assert!(out.contains("driver fault        line high → no fault (read active low)"), "{out}");
    assert!(out.contains("watching …"), "{out}");
    // Read active low, it seems pressed wherever the track is but home.
    let (code, _, err) = run(&["home"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("track failed: its switch stayed pressed after backing off"), "{err}");
    assert!(err.contains("--home-sensor track=active-high"), "{err}");
    let (code, _, err) = run(&["home"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("fault latched") && err.contains("`scanner clear` clears it"), "{err}");
    // The device saves nothing while a fault is latched: nothing changes.
    let (code, _, err) = run(&["config", "--home-sensor", "track=active-high"]);
    assert_eq!(code, Some(7), "{err}");
    assert!(err.contains("homing failed latched") && err.contains("nothing changed"), "{err}");
    let (_, out, _) = run(&["config"]);
    assert!(out.contains("track active low"), "{out}");
    let (code, out, err) = run(&["clear"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("cleared: homing failed"), "{out}");
    let (code, _, err) = run(&["config", "--home-sensor", "track=up"]);
    assert_eq!(code, Some(2), "{err}");
    let (code, out, err) = run(&["config", "--home-sensor", "track=active-high"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("track must be homed again"), "{out}");
    assert!(out.contains("saved to the device's flash"), "{out}");
    assert!(out.contains("disk active low, track active high, tilt active low"), "{out}");
    let (_, out, _) = run(&["inputs"]);
    assert!(
        out.contains("track home switch   line low  → not actuated (read active high)"),
        "{out}"
    );
    let (code, out, err) = run(&["home"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("homing: done at [0, 0, -9333] steps"), "{out}");
    drop(server);
}

/// A camera whose "exposure active" strobe is wired to the board, 1 ms
/// late on its trigger: once `scanner config --strobe` has the board watch
/// it, a scan whose light follows the pulse alone is stopped at its first
/// frame with the light margin that covers the camera; with that margin it
/// completes, and a trigger the camera misses is taken again on the
/// strobe's word (no frame timeout). A board without the input refuses to
/// watch one.
#[test]
fn a_watched_exposure_strobe_catches_a_late_camera_and_a_missed_trigger() {
    let dir = tmp();
    let frames_dir = sub(dir.path(), "camera");
    // Trigger 1 is the first scan's dark frame, 2 its mirror 0; 5 and 6
    // the second scan's, 7 the third's dark frame.
    let faults = FaultPlan::none()
        .after_triggers(1, FaultEvent::IgnoreTriggers(1))
        .after_triggers(6, FaultEvent::IgnoreTriggers(1));
    let mut s = setup("leather", faults);
    s.trigger_latency_us = 1_000;
    let server = serve(&s, &frames_dir);
    let run = |args: &[&str]| on_device(server.path(), args);
    let (code, out, err) = run(&["config"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("camera exposure strobe: not watched"), "{out}");
    let (code, out, err) = run(&["config", "--strobe", "active-high"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("saved") && out.contains("strobe: watched, active high"), "{out}");
    // The miss is known from the strobe, not from a frame that does not
    // come (that would say "no frame within 3s").
    let scan = |out: &Path, extra: &[&str]| {
        let args = scan_args(server.path(), &frames_dir, out, 2);
        let r = scanner().args(&args).args(extra).output().unwrap();
        let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
        (r.status.code(), text(&r.stdout), text(&r.stderr))
    };
    let (code, out, err) = scan(&sub(dir.path(), "mended"), &["--light-margin-us", "1500"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains("missed its trigger (its exposure strobe did not rise); taking it again"),
        "{out}\n{err}"
    );
    let m = Manifest::load(&sub(dir.path(), "mended")).unwrap();
    assert!(m.complete && m.frames.len() == 2);
    // Each frame records its exposure as the strobe showed it, and the
    // scan sums them up: the camera 1 ms late, each edge seen up to one
    // 200 µs input sample late.
    for f in &m.frames {
        let e = f.strobe.unwrap_or_else(|| panic!("mirror {}: no strobe recorded", f.mirror));
        assert!((1_000..1_200).contains(&e.delay_us), "{e:?}");
        assert!(e.length_us.abs_diff(f.exposure_us) < 200, "{e:?}");
    }
    assert!(out.contains("camera strobe over 2 exposures: 1."), "{out}");
    assert!(out.contains("the light 1.5 ms"), "{out}");
    // The light on during the pulse alone: the camera's last ms is dark.
    let (code, _, err) = scan(&sub(dir.path(), "late"), &[]);
    assert_eq!(code, Some(3), "{err}");
    assert!(
        err.contains("mirror 0: the camera exposed until 51.")
            && err.contains("give --light-margin-us 1")
            && err.contains("or more"),
        "{err}"
    );
    let suggested: u32 = err
        .split("give --light-margin-us ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap();
    assert!((1_000..=1_200).contains(&suggested), "{suggested}: {err}");
    // A dark frame the camera misses is taken again on the strobe's word
    // too (its latency does not matter with the light off).
    let (code, out, err) = scan(&sub(dir.path(), "dark"), &["--light-margin-us", "1500"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        err.contains(
            "dark frame: camera: missed its trigger (its exposure strobe did not rise); taking \
             it again"
        ),
        "{out}\n{err}"
    );
    let m = Manifest::load(&sub(dir.path(), "dark")).unwrap();
    assert!(m.complete, "{out}");
    // The retaken dark frame records its exposure as the strobe showed it.
    let dark = m.settings.dark.expect("a dark frame recorded");
    let e = dark.strobe.expect("the dark frame's strobe window recorded");
    assert!((1_000..1_200).contains(&e.delay_us), "{e:?}");
    assert!(e.length_us.abs_diff(dark.exposure_us) < 200, "{e:?}");
    drop(server);
    // A board the strobe is not wired to (and that says so).
    let mut s = setup("leather", FaultPlan::none());
    s.strobe_active_high = None;
    let server = serve(&s, &sub(dir.path(), "camera-2"));
    let (code, _, err) = on_device(server.path(), &["config", "--strobe", "active-low"]);
    assert_eq!(code, Some(6), "{err}");
    assert!(err.contains("this board has no exposure strobe input"), "{err}");
    let (code, out, _) = on_device(server.path(), &["config"]);
    assert_eq!(code, Some(0));
    assert!(out.contains("camera exposure strobe: no input on this board"), "{out}");
}

/// `scanner bootloader`: the controller accepts, stops and falls silent
/// (its chip's ROM bootloader does not speak the protocol), and the
/// command says how to flash it; until the board is reset nothing answers.
#[test]
fn the_bootloader_command_leaves_the_firmware_and_says_how_to_flash() {
    let dir = tmp();
    let server = serve(&setup("leather", FaultPlan::none()), &sub(dir.path(), "camera"));
    let (code, out, err) = on_device(server.path(), &["info"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("exposure strobe input, log events, simulated, ROM bootloader on command)"),
        "{out}"
    );
    let (code, out, err) = on_device(server.path(), &["bootloader"]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("left its firmware for the chip's ROM bootloader (USB DFU)"), "{out}");
    assert!(
        out.contains("dfu-util -a 0 -s 0x08000000:leave -D firmware/board/target/scanner-fw.bin"),
        "{out}"
    );
    // The port is gone, as a USB board's is while its ROM runs (DFU).
    assert!(std::fs::symlink_metadata(server.path()).is_err(), "the port went away");
    let (code, _, err) = on_device(server.path(), &["info"]);
    assert_eq!(code, Some(5), "the ROM does not answer: {err}");
}
