//! End-to-end scans against the simulator: in-process (deterministic) here.

use std::time::Duration;

use host::camera::SimCamera;
use host::link::{Device, SimTransport};
use host::scan::{Manifest, Quiet, ScanOptions, scan};
use host::simulator::SimSetup;

fn setup(material: &str) -> SimSetup {
    SimSetup { bin: 8, seed: 3, ..SimSetup::new(material) }
}

#[test]
fn a_deterministic_scan_stores_every_frame_and_its_manifest() {
    let s = setup("leather");
    let rig = s.rig().unwrap();
    let geometry = s.nominal().unwrap();
    let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
    let mut cam = SimCamera(rig);
    let dir = tempfile::tempdir().unwrap();
    let mut opts = ScanOptions::new("leather-1", dir.path());
    opts.mirrors = Some(6);
    let t = std::time::Instant::now();
    let report = scan(&mut dev, &mut cam, &geometry, &opts, &mut Quiet).unwrap();
    eprintln!("{report:?} in {:?}", t.elapsed());
    assert_eq!(report.captured, 6);
    let m = Manifest::load(dir.path()).unwrap();
    assert!(m.complete);
    assert_eq!(m.frames.len(), 6);
    let _ = Duration::ZERO;
}
