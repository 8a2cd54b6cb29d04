//! Scans against the in-process deterministic simulator.

use host::camera::SimCamera;
use host::link::{Device, SimTransport};
use host::scan::{Manifest, Quiet, ScanError, ScanOptions, ScanReport, scan};
use host::simulator::SimSetup;

fn setup(material: &str) -> SimSetup {
    SimSetup { bin: 8, seed: 3, ..SimSetup::new(material) }
}

fn run(s: &SimSetup, opts: &ScanOptions) -> Result<ScanReport, ScanError> {
    let rig = s.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    scan(&mut dev, &mut SimCamera(rig), &s.nominal().unwrap(), opts, &mut Quiet)
}

/// Scans of `mirrors` mirrors on `first`, then on `second`, into two new
/// directories; the second's report.
fn scan_both(
    first: &SimSetup,
    second: &SimSetup,
    mirrors: usize,
) -> (tempfile::TempDir, tempfile::TempDir, ScanReport) {
    let dirs = [tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap()];
    let opts = |d: &tempfile::TempDir| ScanOptions {
        mirrors: Some(mirrors),
        ..ScanOptions::new("m", d.path())
    };
    run(first, &opts(&dirs[0])).unwrap();
    let report = run(second, &opts(&dirs[1])).unwrap();
    let [a, b] = dirs;
    (a, b, report)
}

/// The mean absolute difference of `frame` from `reference`, relative to
/// the reference's mean signal.
fn relative_difference(frame: &[f32], reference: &[f32]) -> f64 {
    let (mut d, mut sum) = (0.0f64, 0.0f64);
    for (a, b) in frame.iter().zip(reference) {
        d += (a - b).abs() as f64;
        sum += b.abs() as f64;
    }
    d / sum.max(1e-12)
}

#[test]
fn a_deterministic_scan_stores_every_frame_and_its_manifest() {
    let s = setup("leather");
    let dir = tempfile::tempdir().unwrap();
    let opts = ScanOptions::new("leather-1", dir.path());
    let report = run(&s, &opts).unwrap();
    assert_eq!(report.captured, 40);
    let m = Manifest::load(dir.path()).unwrap();
    assert!(m.complete);
    assert_eq!(m.frames.len(), 40);
    assert_eq!(m.settings.geometry_sha256, s.nominal().unwrap().hash());
    // Its dark frame, at the scan's exposure, shows a flawless sensor.
    let dark = m.settings.dark.as_ref().expect("a dark frame recorded");
    assert_eq!((dark.exposure_us, dark.defects.len()), (opts.exposure_us, 0));
    for (l, f) in m.frames.iter().enumerate() {
        assert_eq!(f.mirror, l);
        // Trigger 1 is the dark frame.
        assert_eq!(f.trigger_seq as usize, l + 2);
        let bytes = std::fs::read(dir.path().join(&f.file)).unwrap();
        assert_eq!(f.sha256.len(), 64);
        let frame = host::exrio::read_rgb(&dir.path().join(&f.file)).unwrap();
        assert_eq!((frame.width, frame.height), (512, 512));
        assert!(bytes.len() > 1000);
    }
    // Content: each frame is the simulator's rendering of its own mirror
    // (noise-free, at the recorded axes), not a black frame or a
    // neighbour's.
    let optics = hil_sim::optics::OpticalSim::as_built(
        &s.nominal().unwrap(),
        hil_sim::materials::Sample::small(hil_sim::materials::lookup("leather").unwrap()),
        s.seed,
    );
    let expected = |f: &host::scan::FrameRecord| {
        optics.expected(&hil_sim::optics::Exposure {
            axes: hil_sim::geometry::AxisValues::from_array(f.axis_units),
            exposure_s: f.exposure_us as f64 * 1e-6,
            light: 1.0,
        })
    };
    let renders: Vec<_> = m.frames.iter().map(expected).collect();
    for (l, f) in m.frames.iter().enumerate() {
        let frame = host::exrio::read_rgb(&dir.path().join(&f.file)).unwrap();
        let diff = |e: &hil_sim::optics::Frame| relative_difference(&frame.rgb, &e.rgb);
        let own = diff(&renders[l]);
        let neighbour = diff(&renders[(l + 1) % 40]).min(diff(&renders[(l + 39) % 40]));
        assert!(own < 0.03, "mirror {l}: {own:.3} from its own rendering");
        assert!(own < 0.25 * neighbour, "mirror {l}: own {own:.3}, neighbour {neighbour:.3}");
    }
    // The same seed gives the same scan, byte for byte.
    let again = tempfile::tempdir().unwrap();
    run(&s, &ScanOptions::new("leather-1", again.path())).unwrap();
    for f in &m.frames {
        assert_eq!(
            std::fs::read(dir.path().join(&f.file)).unwrap(),
            std::fs::read(again.path().join(&f.file)).unwrap()
        );
    }
}

#[test]
fn resume_takes_again_only_damaged_or_missing_frames() {
    let s = setup("painted-wood");
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("wood", dir.path());
    opts.mirrors = Some(5);
    run(&s, &opts).unwrap();
    let original: Vec<Vec<u8>> = (0..5)
        .map(|l| std::fs::read(dir.path().join(host::scan::frame_file(l))).unwrap())
        .collect();
    // Damage one frame, lose another, leave a temp file behind.
    let f1 = dir.path().join(host::scan::frame_file(1));
    let bytes = std::fs::read(&f1).unwrap();
    std::fs::write(&f1, &bytes[..bytes.len() / 2]).unwrap();
    std::fs::remove_file(dir.path().join(host::scan::frame_file(3))).unwrap();
    std::fs::write(dir.path().join("frames/.tmp-abc"), b"partial").unwrap();
    opts.resume = true;
    let report = run(&s, &opts).unwrap();
    assert_eq!((report.kept, report.captured), (3, 2));
    for (l, bytes) in original.iter().enumerate() {
        assert_eq!(
            &std::fs::read(dir.path().join(host::scan::frame_file(l))).unwrap(),
            bytes,
            "frame {l}"
        );
    }
    assert!(!dir.path().join("frames/.tmp-abc").exists());
    assert!(Manifest::load(dir.path()).unwrap().complete);
}

#[test]
fn a_damaged_manifest_or_another_scan_is_refused_not_overwritten() {
    let s = setup("leather");
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("a", dir.path());
    opts.mirrors = Some(2);
    run(&s, &opts).unwrap();
    opts.resume = true;
    opts.sample_name = "b".into();
    let e = run(&s, &opts).unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    assert!(e.to_string().contains("different scan: sample name \"a\""), "{e}");
    // Damaged, and so is the previous manifest: nothing to recover from.
    let manifest = dir.path().join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    for f in ["manifest.json", "manifest.json.prev"] {
        std::fs::write(dir.path().join(f), &text[..text.len() / 2]).unwrap();
    }
    opts.sample_name = "a".into();
    let e = run(&s, &opts).unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    assert!(e.to_string().contains("not a scan manifest"), "{e}");
    assert_eq!(std::fs::read_to_string(&manifest).unwrap(), text[..text.len() / 2]);
}

#[test]
fn faults_in_the_deterministic_simulator_do_not_change_the_frames() {
    use hil_sim::{FaultEvent, FaultPlan};
    let clean = setup("rough-metal");
    let faulty = SimSetup {
        faults: FaultPlan::none()
            .corrupt(1e-3)
            .after_triggers(3, FaultEvent::Disconnect { duration_ms: 2000 })
            .after_triggers(5, FaultEvent::Reset)
            .after_triggers(7, FaultEvent::IgnoreTriggers(1)),
        ..setup("rough-metal")
    };
    let (a, b, report) = scan_both(&clean, &faulty, 10);
    assert_eq!(report.resets, 1);
    assert!(report.retakes >= 2, "{report:?}");
    for l in 0..10 {
        let f = host::scan::frame_file(l);
        assert!(
            std::fs::read(a.path().join(&f)).unwrap() == std::fs::read(b.path().join(&f)).unwrap(),
            "{f}"
        );
    }
}

/// Drives other than the spec's: a 4 mm lead screw (800 steps/mm), a disk
/// of 32 000 steps a turn homed turning down, a 60:1 tilt worm homed at
/// its top (+35°).
fn other_drives() -> [protocol::AxisConfig; 3] {
    let [mut disk, mut track, mut tilt] = protocol::default_axes();
    disk.steps_per_unit = 32_000.0 / 360.0;
    (disk.steps_per_rev, disk.max_steps) = (32_000, 31_999);
    disk.homing.direction = protocol::Direction::Negative;
    disk.homing.max_travel_steps = 35_200;
    track.steps_per_unit = 800.0;
    track.max_steps = 160_000;
    track.homing.backoff_steps = 1_600;
    tilt.steps_per_unit = 192_000.0 / 360.0;
    (tilt.min_steps, tilt.max_steps) = (-18_667, 18_667);
    tilt.homing.direction = protocol::Direction::Positive;
    tilt.homing.home_position = 18_667;
    (tilt.homing.backoff_steps, tilt.homing.max_travel_steps) = (1_066, 40_000);
    let axes = [disk, track, tilt];
    scanner_geometry::check_axes(&axes).unwrap();
    axes
}

#[test]
fn a_scanner_built_with_other_drives_takes_the_same_frames() {
    let spec = setup("rough-metal");
    let other = SimSetup { axes: other_drives(), ..setup("rough-metal") };
    let (a, b, _) = scan_both(&spec, &other, 12);
    // The board came with its drives saved; the host read them, wrote the
    // mirror table in their steps and recorded every frame's axes in units.
    let rig = other.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig))).unwrap();
    assert_eq!(host::scan::axis_configs(&mut dev).unwrap(), other_drives());
    let (ma, mb) = (Manifest::load(a.path()).unwrap(), Manifest::load(b.path()).unwrap());
    let mut worst = 0.0f64;
    for (fa, fb) in ma.frames.iter().zip(&mb.frames) {
        // Each axis within a step of the coarser drive.
        for (k, step) in [1.0 / 44.4, 1.0 / 800.0, 1.0 / 266.6].into_iter().enumerate() {
            let d = (fa.axis_units[k] - fb.axis_units[k]).abs();
            let d = if k == 0 { d.min(360.0 - d) } else { d };
            assert!(
                d <= step,
                "mirror {}: {:?} against {:?}",
                fa.mirror,
                fa.axis_units,
                fb.axis_units
            );
        }
        // The frames alike but for where a step falls: mean absolute
        // difference relative to the mean signal.
        let fa = host::exrio::read_rgb(&a.path().join(&fa.file)).unwrap();
        let fb = host::exrio::read_rgb(&b.path().join(&fb.file)).unwrap();
        worst = worst.max(relative_difference(&fb.rgb, &fa.rgb));
    }
    eprintln!("largest mean relative difference: {worst:.4}");
    assert!(worst < 0.01, "{worst}");
}

/// The device's mirror table.
fn device_table(dev: &mut Device) -> Vec<Option<protocol::MirrorPosition>> {
    host::scan::mirror_entries(dev).unwrap()
}

/// New drives keep the mirror table's axis positions: each entry within a
/// step of what `setup` writes for the design on them; entries the new
/// travel cannot reach are unset, the others kept.
#[test]
fn new_drives_carry_the_mirror_table_to_their_steps() {
    use host::scan::{axis_configs, set_axis_configs};
    let s = setup("leather");
    let geometry = s.nominal().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(s.rig().unwrap()))).unwrap();
    let spec = axis_configs(&mut dev).unwrap();
    host::scan::prepare(&mut dev, &geometry, &mut Quiet).unwrap();
    let before = device_table(&mut dev);
    assert_eq!(before.len(), 40);

    // Not while an axis moves: refused before anything is touched.
    let half_turn = [Some(8_000), None, None];
    let go = protocol::Request::Move { mode: protocol::MoveMode::Relative, targets: half_turn };
    dev.command(go).unwrap();
    let other = other_drives();
    let e = set_axis_configs(&mut dev, &spec, &other).unwrap_err();
    assert!(e.to_string().contains("busy"), "{e}");
    assert_eq!((axis_configs(&mut dev).unwrap(), device_table(&mut dev)), (spec, before.clone()));
    host::scan::wait_idle(&mut dev, std::time::Duration::from_secs(10)).unwrap();

    let set = set_axis_configs(&mut dev, &spec, &other).unwrap();
    assert_eq!(set.changed, protocol::Axis::ALL.to_vec());
    assert_eq!((set.mirrors, set.unreachable.len()), (40, 0));
    assert!(set.saved && set.mirrors_moved == 40, "{set:?}");
    let exact = geometry.mirror_table(&other).unwrap();
    for (l, (got, want)) in device_table(&mut dev).iter().zip(&exact).enumerate() {
        let got = got.expect("set").steps;
        // Within the old drive's half step, in the new drive's steps.
        for (k, limit) in [1usize, 2, 1].into_iter().enumerate() {
            let d = (got[k] - want.steps[k]).abs();
            let d = if k == 0 { d.min(32_000 - d) } else { d };
            assert!(d <= limit as i32, "mirror {l}: {got:?} against {:?}", want.steps);
        }
    }
    // `setup` on the new drives has at most those steps left to write.
    assert!(host::scan::setup(&mut dev, &geometry).unwrap().written < 40);

    // Back: every entry where it was.
    let set = set_axis_configs(&mut dev, &other, &spec).unwrap();
    assert!(set.unreachable.is_empty(), "{set:?}");
    host::scan::setup(&mut dev, &geometry).unwrap();
    let before = device_table(&mut dev);
    // A tilt that stops at 5.63°: the outer ring's 6.404° is out of it.
    let mut short = spec;
    short[2].max_steps = 1500;
    let set = set_axis_configs(&mut dev, &spec, &short).unwrap();
    assert_eq!((set.changed.clone(), set.mirrors_moved), (vec![protocol::Axis::Tilt], 0));
    let unreachable: Vec<usize> = set.unreachable.iter().map(|(l, _)| *l).collect();
    let now = device_table(&mut dev);
    assert_eq!(now.len(), 40, "the count stays");
    for (l, (now, was)) in now.iter().zip(&before).enumerate() {
        let want = if unreachable.contains(&l) { None } else { *was };
        assert_eq!(*now, want, "mirror {l}");
    }
    assert!(unreachable.contains(&39), "{unreachable:?}");
    assert!(set.unreachable[0].1.to_string().contains("outside its travel"), "{set:?}");
    // The device refuses to go to an unset entry.
    let e = dev.request(protocol::Request::GoToMirror { mirror: 39 });
    assert!(
        matches!(
            e,
            Err(host::link::LinkError::Refused { error: protocol::DeviceError::MirrorNotSet, .. })
        ),
        "{e:?}"
    );
}

/// The simulator's link, cut for good after a number of writes.
struct Cut {
    inner: SimTransport,
    writes_left: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

impl host::link::Transport for Cut {
    fn write_all(&mut self, bytes: &[u8]) -> Result<(), host::link::TransportError> {
        use std::sync::atomic::Ordering;
        let left = self.writes_left.load(Ordering::SeqCst);
        if left == 0 {
            return Err(host::link::TransportError::Disconnected("cut".into()));
        }
        self.writes_left.store(left - 1, Ordering::SeqCst);
        self.inner.write_all(bytes)
    }
    fn read(
        &mut self,
        out: &mut Vec<u8>,
        timeout: std::time::Duration,
    ) -> Result<usize, host::link::TransportError> {
        self.inner.read(out, timeout)
    }
    fn sleep(&mut self, d: std::time::Duration) {
        self.inner.sleep(d)
    }
    fn now(&self) -> std::time::Duration {
        self.inner.now()
    }
    fn reconnect(&mut self) -> Result<(), host::link::TransportError> {
        Err(host::link::TransportError::Open("cut".into()))
    }
    fn describe(&self) -> String {
        "a link that is cut".into()
    }
}

/// A link lost anywhere in a change of drives leaves mirror-table entries
/// unset, never in the steps of the other configuration.
#[test]
fn a_change_of_drives_cut_short_leaves_no_entry_in_the_other_steps() {
    use host::scan::{axis_configs, set_axis_configs};
    use std::sync::atomic::{AtomicUsize, Ordering};
    let s = setup("leather");
    let geometry = s.nominal().unwrap();
    let spec = protocol::default_axes();
    let (old, new) =
        (geometry.mirror_table(&spec).unwrap(), geometry.mirror_table(&other_drives()));
    // Carried entries are within a step of the exact table (the test above).
    let near = |a: &[i32; 3], b: &[i32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 2);
    let mut cuts = 0;
    for budget in 0.. {
        let rig = s.rig().unwrap();
        let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
        host::scan::setup(&mut dev, &geometry).unwrap();
        let writes_left = std::sync::Arc::new(AtomicUsize::new(usize::MAX));
        let cut = Cut { inner: SimTransport(rig.clone()), writes_left: writes_left.clone() };
        let mut dev = Device::connect(Box::new(cut)).unwrap();
        writes_left.store(budget, Ordering::SeqCst);
        let done = set_axis_configs(&mut dev, &spec, &other_drives()).is_ok();
        drop(dev);
        let mut dev = Device::connect(Box::new(SimTransport(rig))).unwrap();
        let axes = axis_configs(&mut dev).unwrap();
        for (l, entry) in device_table(&mut dev).iter().enumerate() {
            let Some(p) = entry else { continue };
            let right = if axes == spec {
                p.steps == old[l].steps
            } else {
                axes == other_drives() && near(&p.steps, &new.as_ref().unwrap()[l].steps)
            };
            assert!(right, "cut after {budget} writes: mirror {l} at {:?} under {axes:?}", p.steps);
        }
        if done {
            break;
        }
        cuts += 1;
    }
    // GetMirror × 40, the count, 3 axes, 40 entries, the count, the save.
    assert!(cuts > 80, "{cuts}");
}

/// Commissioning against the simulator's truth: a board still configured
/// with the spec's drives, on a scanner built with others (a disk belt,
/// a lead screw and a tilt worm each a few per cent off), moves too short
/// or too far; each axis corrected by one measured move then moves as far
/// as it is told, within a step.
#[test]
fn a_board_corrected_by_measured_moves_moves_as_far_as_it_is_told() {
    use host::scan::{axis_configs, prepare, set_axis_configs, wait_idle};
    use protocol::{Axis, MoveMode, Request};
    use scanner_geometry::{Measured, correct_axis, offset_to_steps};
    let spec = protocol::default_axes();
    // Moves of these lengths go these lengths on the machine built.
    let (told, went) = ([180.0, 100.0, 40.0], [177.5, 98.7, 42.0]);
    let built: [protocol::AxisConfig; 3] = std::array::from_fn(|i| {
        let m = Measured { axis: Axis::ALL[i], commanded: told[i], measured: went[i] };
        correct_axis(&spec[i], m).unwrap()
    });
    let s = SimSetup { axes: built, board_axes: Some(spec), ..setup("leather") };
    let geometry = s.nominal().unwrap();
    let rig = s.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    assert_eq!(axis_configs(&mut dev).unwrap(), spec, "the board is not commissioned yet");
    // One relative move of `by` on `axis` from −10 (or 10°), as measured on
    // the machine.
    let measure = |dev: &mut Device, axis: Axis, by: f64| -> f64 {
        let config = axis_configs(dev).unwrap()[axis.index()];
        let mut go = |mode, value: f64| {
            let mut targets = [None; 3];
            targets[axis.index()] = Some(offset_to_steps(axis, value, &config).unwrap());
            dev.command(Request::Move { mode, targets }).unwrap();
            wait_idle(dev, std::time::Duration::from_secs(120)).unwrap();
        };
        go(MoveMode::Absolute, if axis == Axis::Tilt { -10.0 } else { 10.0 });
        let at = || rig.with_device(|d| d.physical_axes()).to_array()[axis.index()];
        let before = at();
        go(MoveMode::Relative, by);
        let moved = at() - before;
        if axis == Axis::Disk { moved.rem_euclid(360.0) } else { moved }
    };
    prepare(&mut dev, &geometry, &mut Quiet).unwrap();
    let mut corrected = spec;
    for axis in Axis::ALL {
        let i = axis.index();
        let moved = measure(&mut dev, axis, told[i]);
        assert!((moved - went[i]).abs() < 0.01, "{axis:?}: {moved}");
        let m = Measured { axis, commanded: told[i], measured: moved };
        corrected[i] = correct_axis(&spec[i], m).unwrap();
    }
    let set = set_axis_configs(&mut dev, &spec, &corrected).unwrap();
    assert_eq!((set.changed.len(), set.mirrors_moved), (3, 40));
    // The table written for the wrong drives, carried over, now sends the
    // axes where the design puts each mirror (within a step of each drive).
    dev.command(Request::Home { axes: protocol::AxisSet::ALL }).unwrap();
    wait_idle(&mut dev, std::time::Duration::from_secs(120)).unwrap();
    for mirror in [0u8, 17, 39] {
        dev.command(Request::GoToMirror { mirror }).unwrap();
        wait_idle(&mut dev, std::time::Duration::from_secs(120)).unwrap();
        let at = rig.with_device(|d| d.physical_axes()).to_array();
        let want = geometry.mirror_axes(mirror as usize).unwrap().to_array();
        for (k, c) in built.iter().enumerate() {
            let d = (at[k] - want[k]).abs();
            let d = if k == 0 { d.min(360.0 - d) } else { d };
            assert!(d <= 1.5 / c.steps_per_unit as f64, "mirror {mirror}: {at:?} for {want:?}");
        }
    }
    prepare(&mut dev, &geometry, &mut Quiet).unwrap();
    for axis in Axis::ALL {
        let i = axis.index();
        let per = corrected[i].steps_per_unit as f64;
        assert!((per / built[i].steps_per_unit as f64 - 1.0).abs() < 1e-4, "{axis:?}: {per}");
        let moved = measure(&mut dev, axis, told[i]);
        assert!((moved - told[i]).abs() <= 1.0 / per, "{axis:?}: told {}, moved {moved}", told[i]);
    }
}

/// `scanner home --repeat`'s check: the spec's drives keep their steps;
/// steps lost on the way out are measured at the switch, as many as the
/// simulator's motor lost; a speed beyond the motor's pull-out is found.
#[test]
fn repeated_homing_measures_the_steps_a_drive_loses() {
    use host::scan::homing_repeatability;
    use protocol::{Axis, AxisSet};
    let s = setup("leather");
    let rig = s.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let mut seen = Vec::new();
    let cycles = homing_repeatability(&mut dev, AxisSet::ALL, 2, &mut |c, r| {
        seen.push((c, r.clone()));
    })
    .unwrap();
    assert_eq!(seen.len(), 2);
    for c in &cycles {
        for (k, e) in c.error_steps.iter().enumerate() {
            let e = e.expect("measured");
            assert!(e.abs() <= protocol::POSITION_TOLERANCE_STEPS, "axis {k}: {e}");
        }
        assert_eq!(c.went_to[1], Some(288_000), "the track 90 % of the way out");
    }
    // 400 track pulses lost on the next move out.
    rig.with_device(|d| {
        let when = hil_sim::FaultWhen::AtTick(d.now() + 1);
        let event = hil_sim::FaultEvent::LoseSteps { axis: Axis::Track, steps: 400 };
        d.schedule(hil_sim::FaultSpec { when, event });
    });
    let track = AxisSet::single(Axis::Track);
    let lost = homing_repeatability(&mut dev, track, 1, &mut |_, _| {}).unwrap();
    // Caught as the track leaves its switch, at speed: within the
    // firmware's tolerance of the switch edge.
    let error = lost[0].error_steps[1].unwrap();
    assert!((error - 400).abs() <= protocol::POSITION_TOLERANCE_STEPS, "{error}");
    assert_eq!(lost[0].error_steps[0], None, "the disk was not homed again");

    // A track told to run beyond its motor's pull-out (80 000 steps/s):
    // it stalls on the way out (280 170 pulses lost) and on the homing's
    // own return at full speed (276 970 the other way); the switch measures
    // the net, 3 200 steps, beyond tolerance.
    let mut fast = protocol::default_axes();
    fast[1].v_max = 100_000;
    let s = SimSetup { axes: fast, ..setup("leather") };
    let rig = s.rig().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let cycles = homing_repeatability(&mut dev, track, 1, &mut |_, _| {}).unwrap();
    let error = cycles[0].error_steps[1].unwrap();
    assert!(error.abs() > protocol::POSITION_TOLERANCE_STEPS, "{error}");
    assert!(rig.with_device(|d| d.lost_steps(Axis::Track)) > 0);
}

/// A host killed mid-move leaves the device moving; 500 ms of silence
/// latch `link-timeout` and the device *decelerates* (status: faulted,
/// still moving). The next scan clears the fault and must wait for the
/// stop before its first capture step — not act on the status it read
/// before clearing (the device answered "busy" then).
#[test]
fn a_scan_after_a_link_timeout_waits_for_the_decelerating_axes() {
    use protocol::{MoveMode, Request};
    let s = setup("leather");
    let rig = s.rig().unwrap();
    let nominal = s.nominal().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    host::scan::prepare(&mut dev, &nominal, &mut Quiet).unwrap();
    // Half a disk turn, then the host goes silent.
    dev.command(Request::Move { mode: MoveMode::Relative, targets: [Some(8_000), None, None] })
        .unwrap();
    rig.sleep(std::time::Duration::from_millis(700));
    let status = dev.status().unwrap();
    assert!(status.faults.contains(protocol::FaultFlags::LINK_TIMEOUT), "{status:?}");
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("leather", dir.path());
    opts.mirrors = Some(2);
    scan(&mut dev, &mut SimCamera(rig), &nominal, &opts, &mut Quiet).unwrap();
}

/// A scan of 20 mirrors with `faults` (the `--sim-fault` syntax), into a
/// fresh directory.
fn faulty_scan(faults: &[&str]) -> (tempfile::TempDir, Result<ScanReport, ScanError>) {
    let mut plan = hil_sim::FaultPlan::none();
    for f in faults {
        let spec: hil_sim::FaultSpec = f.parse().unwrap();
        plan = plan.with(spec.when, spec.event);
    }
    let s = SimSetup { faults: plan, ..setup("rough-metal") };
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("m", dir.path());
    opts.mirrors = Some(20);
    let result = run(&s, &opts);
    (dir, result)
}

#[test]
fn lost_steps_on_any_axis_are_found_and_their_frames_taken_again() {
    let (clean, report) = faulty_scan(&[]);
    assert_eq!(report.unwrap().retakes, 0);
    let m = Manifest::load(clean.path()).unwrap();
    assert!(m.checks.iter().all(|c| c.passed) && m.checks.len() == 2, "{:?}", m.checks);
    // Each axis slips while the scan runs: caught at the disk's index flag
    // as it passes, or by the position check after the frame.
    for (fault, axis, lost) in [
        ("lose-steps:disk:400@ms=18000", 0, 400),
        ("lose-steps:disk:40@ms=18000", 0, 40),
        ("lose-steps:track:400@ms=24000", 1, 400),
        ("lose-steps:track:6000@ms=24000", 1, 6000),
        ("lose-steps:tilt:300@ms=24000", 2, 300),
    ] {
        let (dir, report) = faulty_scan(&[fault]);
        let report = report.unwrap_or_else(|e| panic!("{fault}: {e}"));
        assert!(report.retakes > 0, "{fault}: {report:?}");
        let m = Manifest::load(dir.path()).unwrap();
        assert!(m.complete && m.frames.iter().all(|f| f.verified), "{fault}");
        let failed: Vec<_> = m.checks.iter().filter(|c| !c.passed).collect();
        assert_eq!(failed.len(), 1, "{fault}: {:?}", m.checks);
        let error = failed[0].error_steps[axis].unwrap_or_else(|| panic!("{fault}: {failed:?}"));
        assert!((error.abs() - lost).abs() <= 8, "{fault}: measured {error}");
        assert!(!failed[0].mirrors.is_empty());
        for l in 0..20 {
            let f = host::scan::frame_file(l);
            assert!(
                std::fs::read(clean.path().join(&f)).unwrap()
                    == std::fs::read(dir.path().join(&f)).unwrap(),
                "{fault}: {f} differs from the clean scan"
            );
        }
    }
}

#[test]
fn a_motor_that_keeps_slipping_ends_the_scan_with_exit_7() {
    // A slip in every batch of ten frames, retakes included.
    let (dir, result) = faulty_scan(&[
        "lose-steps:track:800@trigger=3",
        "lose-steps:track:800@trigger=13",
        "lose-steps:track:800@trigger=23",
        "lose-steps:track:800@trigger=33",
    ]);
    let e = result.unwrap_err();
    assert_eq!(e.exit_code(), 7, "{e}");
    assert!(e.to_string().contains("steps lost at 3 position checks in a row"), "{e}");
    let m = Manifest::load(dir.path()).unwrap();
    assert!(!m.complete);
    assert_eq!(m.checks.iter().filter(|c| !c.passed).count(), 3, "{:?}", m.checks);
    assert!(m.frames.iter().all(|f| !f.verified), "nothing unverified counts as good");
}

/// A camera whose capture program writes its frames in ADC codes (0…4095)
/// instead of code / top code.
struct CodesCamera(SimCamera);

impl host::camera::Camera for CodesCamera {
    fn arm(&mut self) -> Result<(), host::camera::CameraError> {
        self.0.arm()
    }
    fn wait_frame(
        &mut self,
        timeout: std::time::Duration,
    ) -> Result<host::camera::Frame, host::camera::CameraError> {
        let mut f = self.0.wait_frame(timeout)?;
        f.rgb.iter_mut().for_each(|v| *v *= 4095.0);
        Ok(f)
    }
    fn describe(&self) -> String {
        "a camera writing ADC codes".into()
    }
}

#[test]
fn frames_of_another_unit_or_size_stop_the_scan_at_the_first_mirror() {
    let s = setup("leather");
    let rig = s.rig().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("leather", dir.path());
    opts.mirrors = Some(4);
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let e =
        scan(&mut dev, &mut CodesCamera(SimCamera(rig)), &s.nominal().unwrap(), &opts, &mut Quiet)
            .unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    let said = e.to_string();
    assert!(said.starts_with("mirror 0: camera: "), "{said}");
    // The largest value is an ADC code of the simulator's 12-bit camera.
    let top: f64 = said
        .split("up to ")
        .nth(1)
        .and_then(|t| t.split(':').next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("{said}"));
    assert!(said.contains("values above full scale") && (2.0..=4095.0).contains(&top), "{said}");
    assert!(said.contains("not ADC codes"), "{said}");
    let m = Manifest::load(dir.path()).unwrap();
    assert!(m.frames.is_empty() && !m.complete, "nothing stored: {:?}", m.frames.len());
    // A camera set to another resolution than the geometry's (here: the
    // geometry of the unbinned 4096² sensor, frames binned to 512²).
    let rig = s.rig().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let opts = ScanOptions { mirrors: Some(4), ..ScanOptions::new("leather", dir.path()) };
    let full = SimSetup { bin: 1, ..s.clone() }.nominal().unwrap();
    assert_eq!(full.camera.width, 4096);
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let e = scan(&mut dev, &mut SimCamera(rig), &full, &opts, &mut Quiet).unwrap_err();
    assert_eq!(e.exit_code(), 3, "{e}");
    assert!(
        e.to_string().contains("a frame of 512×512 px; the geometry's camera has 4096×4096 px"),
        "{e}"
    );
}
