//! `scanner check`, a scanner's acceptance run: on the simulated scanner
//! served on a pseudo-terminal (as a real one on its serial port, its
//! camera dropping frames into a folder) it passes once the mirror table
//! is written, and each fault a real build has fails its own check, naming
//! what to do. The same test runs on real hardware when
//! `SCANNER_HIL_DEVICE` names a scanner (ignored otherwise).

mod common;

use std::path::Path;

use common::*;
use hil_sim::{FaultEvent, FaultPlan};

/// `scanner check` on the pty `server` with its camera and geometry in
/// `frames`: (exit code, stdout, stderr).
fn check(server: &hil_sim::PtyServer, frames: &Path) -> (Option<i32>, String, String) {
    check_with(server, frames, &[])
}

/// [`check`] with more arguments.
fn check_with(
    server: &hil_sim::PtyServer,
    frames: &Path,
    extra: &[&str],
) -> (Option<i32>, String, String) {
    let camera = format!("folder:{}", frames.display());
    let geometry = frames.join("geometry.toml").display().to_string();
    let args = [
        "check",
        "--device",
        server.path(),
        "--camera",
        &camera,
        "--geometry",
        &geometry,
        "--homings",
        "2",
        "--frame-timeout",
        "3",
    ];
    let args: Vec<&str> = args.iter().chain(extra).copied().collect();
    let (code, out, err) = run(&args);
    eprintln!("{out}");
    (code, out, err)
}

/// The verdict printed for check `name` ("PASS", "FAIL", "SKIP").
fn verdict<'a>(out: &'a str, name: &str) -> &'a str {
    out.lines()
        .find_map(|l| {
            let (word, rest) = l.split_once(' ')?;
            rest.strip_prefix(name)?.strip_prefix(':').map(|_| word)
        })
        .unwrap_or_else(|| panic!("no line for {name}:\n{out}"))
}

/// Each check's verdict, the checks printed in [`host::check::CHECKS`]'s
/// order.
fn verdicts(out: &str) -> Vec<(&'static str, String)> {
    let printed: Vec<&str> = out
        .lines()
        .filter_map(|l| l.split_once(' ')?.1.split_once(':').map(|(name, _)| name))
        .filter(|name| host::check::CHECKS.contains(name))
        .collect();
    assert_eq!(printed, host::check::CHECKS, "{out}");
    host::check::CHECKS.iter().map(|&n| (n, verdict(out, n).to_string())).collect()
}

fn expect(out: &str, want: [&str; 8]) {
    let got = verdicts(out);
    let want: Vec<(&str, String)> =
        host::check::CHECKS.iter().zip(want).map(|(&n, w)| (n, w.to_string())).collect();
    assert_eq!(got, want, "{out}");
}

#[test]
fn check_passes_on_a_sound_scanner_once_its_mirror_table_is_written() {
    let dir = tmp();
    let frames = sub(dir.path(), "camera");
    let server = serve(&setup("leather", FaultPlan::none()), &frames);
    // A scanner fresh from flashing: no mirror table.
    let (code, out, err) = check(&server, &frames);
    assert_eq!(code, Some(10), "{out}{err}");
    expect(&out, ["PASS", "PASS", "PASS", "PASS", "PASS", "FAIL", "FAIL", "SKIP"]);
    assert!(out.contains("the device's table is empty, the geometry has 40 mirrors"), "{out}");
    assert!(out.contains("`scanner setup --geometry` writes"), "{out}");
    assert!(err.contains("failed: mirror table, mirrors"), "{err}");
    let geometry = frames.join("geometry.toml").display().to_string();
    let (code, _, err) = run(&["setup", "--device", server.path(), "--geometry", &geometry]);
    assert_eq!(code, Some(0), "{err}");
    // Its camera's exposure strobe wired and watched: checked too.
    let (code, _, err) = run(&["config", "--device", server.path(), "--strobe", "active-high"]);
    assert_eq!(code, Some(0), "{err}");
    let report = sub(dir.path(), "check.json");
    let junit = sub(dir.path(), "check.xml");
    let (code, out, err) = check_with(
        &server,
        &frames,
        &["--report", report.to_str().unwrap(), "--junit", junit.to_str().unwrap()],
    );
    assert_eq!(code, Some(0), "{out}{err}");
    // The same run as JUnit XML, for a CI system: a test case a check.
    let x = junit_report(&junit);
    assert_eq!((x.tests, x.failures, x.errors), (8, 0, 0));
    let suite = &x.test_suites[0];
    let props: Vec<(&str, &str)> =
        suite.properties.iter().map(|p| (p.name.as_str(), p.value.as_str())).collect();
    assert!(props.contains(&("protocol", "1.5")), "{props:?}");
    let cases: Vec<&str> = suite.test_cases.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(cases, host::check::CHECKS);
    let homing = &suite.test_cases[4];
    assert!(matches!(homing.status, quick_junit::TestCaseStatus::Success { .. }));
    assert!(homing.system_out.as_ref().unwrap().as_str().starts_with("count at the switch"));
    assert!(homing.time.unwrap() > std::time::Duration::ZERO);
    // The rig's record: every check, as printed.
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!((r["format"].as_str(), r["version"].as_u64()), (Some("scanner-check"), Some(1)));
    assert_eq!((r["passed"].as_u64(), r["failed"].as_u64()), (Some(8), Some(0)), "{r}");
    let names: Vec<&str> =
        r["checks"].as_array().unwrap().iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, host::check::CHECKS);
    assert!(r["checks"].as_array().unwrap().iter().all(|c| c["verdict"] == "pass"), "{r}");
    assert_eq!(r["device"]["protocol"], "1.5");
    assert!(out.contains("ms after the trigger, as long as the pulse"), "{out}");
    assert!(out.contains("camera strobe over 4 exposures: 0."), "{out}");
    expect(&out, ["PASS"; 8]);
    assert!(out.contains("8 checks: 8 passed, 0 failed, 0 skipped"), "{out}");
    assert!(out.contains("count at the switch after 2 homings"), "{out}");
    assert!(out.contains("mirrors 0–39 visited"), "{out}");
    assert!(out.contains("a 50.0 ms frame with the light off, 512×512"), "{out}");
    // A leather sample: its views alike, so where the beam went is not told.
    assert!(out.contains("the sample's views lit: mirror 0 at "), "{out}");
    assert!(out.contains(", mirror 17 at ") && out.contains(", mirror 24 at "), "{out}");
    assert!(out.contains(", mirror 39 at "), "the outermost mirror too: {out}");
    assert!(out.contains("(views alike: which mirror the beam lit is not told"), "{out}");
    // A rig that says its target is glossy: the leather's alike views fail.
    let (code, out, err) = check_with(&server, &frames, &["--glossy"]);
    assert_eq!(code, Some(10), "{out}{err}");
    expect(&out, ["PASS", "PASS", "PASS", "PASS", "PASS", "PASS", "PASS", "FAIL"]);
    assert!(
        out.contains(
            "FAIL capture: mirror 0 (views at 6.4 %), mirror 17 (views at 4.4 %), mirror 24 \
             (views at 4.4 %): no highlight, the views alike, though --glossy says the target is \
             glossy"
        ),
        "{out}"
    );
}

/// With a glossy black target on the holder the capture check sees each
/// beam's highlight where the lit mirror's reflection faces; a disk whose
/// home position is a quarter turn off (the flag mounted elsewhere than the
/// board's configuration says) lights another mirror of the same ring —
/// every view still lit, the table still the geometry's — and fails it.
#[test]
fn a_glossy_target_tells_which_mirror_the_beam_lit() {
    let dir = tmp();
    for (name, quarter_turn_off) in [("sound", false), ("disk-off", true)] {
        let frames = sub(dir.path(), name);
        let mut s = setup("glossy-black", FaultPlan::none());
        if quarter_turn_off {
            let mut board = protocol::default_axes();
            board[0].homing.home_position += (board[0].steps_per_rev / 4) as i32;
            s.board_axes = Some(board);
        }
        let server = serve(&s, &frames);
        let geometry = frames.join("geometry.toml").display().to_string();
        let (code, _, err) = run(&["setup", "--device", server.path(), "--geometry", &geometry]);
        assert_eq!(code, Some(0), "{err}");
        if !quarter_turn_off {
            let (code, out, err) = check(&server, &frames);
            assert_eq!(code, Some(0), "{out}{err}");
            expect(&out, ["PASS"; 8]);
            assert!(
                out.contains(
                    "a glossy target's highlight where each beam's reflection faces: mirror 0 in \
                     view 2, mirror 17 in view 23, mirror 24 in view 18; mirror 39: a reflection \
                     that faces no view, so the glossy target shows nothing there"
                ),
                "{out}"
            );
            // Every mirror that faces a view: the first ring's across the
            // holder (0 ↔ 2, 1 ↔ 3), the third ring's half a turn on.
            let (code, out, err) = check_with(&server, &frames, &["--capture-all", "--glossy"]);
            assert_eq!(code, Some(0), "{out}{err}");
            let faced = (0..4)
                .map(|l| (l, (l + 2) % 4))
                .chain((13..25).map(|l| (l, (l - 13 + 6) % 12 + 13)));
            let seen: Vec<String> = faced.map(|(l, v)| format!("mirror {l} in view {v}")).collect();
            assert!(
                out.contains(&format!(
                    "a glossy target's highlight where each beam's reflection faces: {}",
                    seen.join(", ")
                )),
                "{out}"
            );
            continue;
        }
        let (code, out, err) = check(&server, &frames);
        assert_eq!(code, Some(10), "{out}{err}");
        expect(&out, ["PASS", "PASS", "PASS", "PASS", "PASS", "PASS", "PASS", "FAIL"]);
        // Mirror 0 (azimuth 0°) lit mirror 1 or 3 (±90°) instead, whose
        // reflections face views 3 and 1.
        let line = out.lines().find(|l| l.starts_with("FAIL capture")).unwrap();
        assert!(
            line.contains("mirror 0: the highlight shows in view 3, where mirror 1's light is reflected, not in view 2")
                || line.contains("mirror 0: the highlight shows in view 1, where mirror 3's light is reflected, not in view 2"),
            "{line}"
        );
        assert!(line.contains("mirror 17: the highlight shows in view"), "{line}");
        assert!(
            line.contains(
                "the beam lit another mirror than the table's — the axes' home positions or \
                 steps per unit (`scanner move --mirror N`"
            ),
            "{line}"
        );
        assert!(err.contains("failed: capture"), "{err}");
    }
}

#[test]
fn a_camera_that_misses_its_trigger_and_a_slipping_motor_fail_their_checks() {
    let dir = tmp();
    let frames = sub(dir.path(), "camera");
    // The camera misses the first trigger (the camera check's); after it
    // the track loses 800 steps (during the homing check's first cycle).
    let faults = FaultPlan::none()
        .after_triggers(0, FaultEvent::IgnoreTriggers(1))
        .after_triggers(1, FaultEvent::LoseSteps { axis: protocol::Axis::Track, steps: 800 });
    let server = serve(&setup("leather", faults), &frames);
    let geometry = frames.join("geometry.toml").display().to_string();
    let (code, _, err) = run(&["setup", "--device", server.path(), "--geometry", &geometry]);
    assert_eq!(code, Some(0), "{err}");
    // Homed already: the steps are lost on the homing check's way out.
    let (code, _, err) = run(&["home", "--device", server.path()]);
    assert_eq!(code, Some(0), "{err}");
    let (code, out, err) = check(&server, &frames);
    assert_eq!(code, Some(10), "{out}{err}");
    expect(&out, ["PASS", "PASS", "PASS", "FAIL", "FAIL", "PASS", "SKIP", "SKIP"]);
    assert!(
        out.contains("FAIL camera: a bare trigger with the light off: camera: no frame"),
        "{out}"
    );
    assert!(out.contains("track lost steps"), "{out}");
    assert!(out.contains("SKIP mirrors: needs homing"), "{out}");
    assert!(err.contains("failed: camera, homing"), "{err}");
}

#[test]
fn an_open_emergency_stop_fails_the_faults_check_and_nothing_moves() {
    let dir = tmp();
    let frames = sub(dir.path(), "camera");
    let faults =
        FaultPlan::none().with(hil_sim::FaultWhen::AtTick(0), FaultEvent::EmergencyStop(true));
    let server = serve(&setup("leather", faults), &frames);
    // A report that could not be written is refused before anything runs.
    let (code, out, err) = check_with(&server, &frames, &["--report", "/dev/null"]);
    assert_eq!(code, Some(4), "{out}{err}");
    assert!(!out.contains("PASS"), "{out}");
    let junit = sub(dir.path(), "check.xml");
    let (code, out, err) = check_with(&server, &frames, &["--junit", junit.to_str().unwrap()]);
    assert_eq!(code, Some(10), "{out}{err}");
    expect(&out, ["PASS", "FAIL", "SKIP", "SKIP", "SKIP", "FAIL", "SKIP", "SKIP"]);
    assert!(out.contains("the emergency stop is open"), "{out}");
    assert!(out.contains("SKIP homing: needs faults"), "{out}");
    // Written for a failed run too: failures and skips as JUnit has them.
    let x = junit_report(&junit);
    assert_eq!((x.tests, x.failures, x.errors), (8, 2, 0));
    let faults = &x.test_suites[0].test_cases[1];
    match &faults.status {
        quick_junit::TestCaseStatus::NonSuccess { kind, message, .. } => {
            assert_eq!(*kind, quick_junit::NonSuccessKind::Failure);
            assert!(message.as_ref().unwrap().as_str().contains("the emergency stop is open"));
        }
        other => panic!("{other:?}"),
    }
    let homing = &x.test_suites[0].test_cases[4];
    match &homing.status {
        quick_junit::TestCaseStatus::Skipped { message, .. } => {
            assert_eq!(message.as_ref().unwrap().as_str(), "needs faults")
        }
        other => panic!("{other:?}"),
    }
    // One file for both records is refused before anything moves.
    let (code, _, err) = check_with(&server, &frames, &["--report", "same", "--junit", "same"]);
    assert_eq!(code, Some(2), "{err}");
}

/// `scanner check --junit`'s file, read back.
fn junit_report(path: &Path) -> quick_junit::Report {
    let xml = std::fs::read_to_string(path).unwrap();
    assert!(xml.starts_with("<?xml"), "{xml}");
    quick_junit::Report::deserialize_from_str(&xml).unwrap_or_else(|e| panic!("{e}: {xml}"))
}

/// The same acceptance on a real scanner: `SCANNER_HIL_DEVICE` (a port or
/// serial number), `SCANNER_HIL_CAMERA` (`folder:DIR`, its capture program
/// writing there, a sample on the holder) and, for a scanner not built to
/// the default design, `SCANNER_HIL_GEOMETRY`.
#[test]
#[ignore = "needs a scanner: set SCANNER_HIL_DEVICE and SCANNER_HIL_CAMERA, run with --ignored"]
fn a_connected_scanner_passes_every_check() {
    let device = std::env::var("SCANNER_HIL_DEVICE")
        .expect("SCANNER_HIL_DEVICE names the scanner (a port such as /dev/ttyACM0, or a serial)");
    let camera = std::env::var("SCANNER_HIL_CAMERA")
        .expect("SCANNER_HIL_CAMERA names its camera (folder:DIR)");
    let mut args = vec!["check", "--device", &device, "--camera", &camera];
    let geometry = std::env::var("SCANNER_HIL_GEOMETRY").ok();
    if let Some(g) = &geometry {
        args.extend(["--geometry", g]);
    }
    let (code, out, err) = run(&args);
    eprintln!("{out}");
    assert_eq!(code, Some(0), "{out}{err}");
    expect(&out, ["PASS"; 8]);
}

/// A board that resets in the middle (a brown-out, the watchdog) fails the
/// check it happened in, naming the reset; what comes after is skipped.
#[test]
fn a_board_that_resets_during_the_check_stops_it_there() {
    let dir = tmp();
    let frames = sub(dir.path(), "camera");
    // Right after the camera check's trigger.
    let faults = FaultPlan::none().after_triggers(1, FaultEvent::Reset);
    let server = serve(&setup("leather", faults), &frames);
    let (code, out, err) = check(&server, &frames);
    assert_eq!(code, Some(10), "{out}{err}");
    let v = verdicts(&out);
    assert_eq!(
        &v[..3],
        &[("link", "PASS".into()), ("faults", "PASS".into()), ("light", "PASS".into())]
    );
    let failed: Vec<_> = v.iter().filter(|(_, w)| w == "FAIL").map(|(n, _)| *n).collect();
    assert_eq!(failed.len(), 1, "{out}");
    let after = v.iter().skip_while(|(n, _)| *n != failed[0]).skip(1);
    assert!(after.clone().all(|(_, w)| w == "SKIP"), "{out}");
    assert!(out.contains("the board reset (boot id "), "{out}");
    assert!(out.contains("during this check: a watchdog reset or a brown-out"), "{out}");
    assert!(out.contains("SKIP capture: after the board reset"), "{out}");
}
