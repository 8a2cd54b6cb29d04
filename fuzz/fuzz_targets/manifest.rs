//! Fuzz the scan manifest (docs/scan-format.md), which `scanner verify`,
//! `calibrate`, `regions`, `build` and `scan --resume` read from a scan
//! directory: arbitrary bytes must give an error or a scan, never a panic
//! or a hang; a scan the builder opens names an exposure for every frame.
//! The scanner is the default one with its sensor binned 64×, as the seeds'
//! simulated scans (`fuzz_seeds`). No frame file exists: every one is missing.
//! Mutated as JSON (`fuzz_support::structured`) as well as bytes.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use host::build::scanread::ScanFrames;
use libfuzzer_sys::fuzz_target;

/// A scan directory of this process's own.
fn dir() -> &'static PathBuf {
    static D: OnceLock<PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("manifest-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let dir = dir();
    std::fs::write(dir.join("manifest.json"), data).unwrap();
    if let Ok(v) = host::scan::verify(dir) {
        assert_eq!(v.intact, 0, "no frame file exists");
    }
    let Ok(scan) = ScanFrames::open(dir, fuzz_support::default_scanner(64)) else { return };
    for l in scan.lights() {
        let _ = scan.exposure_s(l);
        let exposures = scan.exposures_us(l).unwrap();
        assert!(!exposures.is_empty(), "mirror {l}");
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::json_file);
