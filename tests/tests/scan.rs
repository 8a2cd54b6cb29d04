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
    for (l, f) in m.frames.iter().enumerate() {
        assert_eq!(f.mirror, l);
        assert_eq!(f.trigger_seq as usize, l + 1);
        let bytes = std::fs::read(dir.path().join(&f.file)).unwrap();
        assert_eq!(f.sha256.len(), 64);
        let frame = host::exrio::read_rgb(&dir.path().join(&f.file)).unwrap();
        assert_eq!((frame.width, frame.height), (512, 512));
        assert!(bytes.len() > 1000);
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
    assert!(e.to_string().contains("different scan"), "{e}");
    let manifest = dir.path().join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, &text[..text.len() / 2]).unwrap();
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
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let mut oa = ScanOptions::new("m", a.path());
    oa.mirrors = Some(10);
    let mut ob = ScanOptions::new("m", b.path());
    ob.mirrors = Some(10);
    run(&clean, &oa).unwrap();
    let report = run(&faulty, &ob).unwrap();
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
