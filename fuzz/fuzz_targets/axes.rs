//! Fuzz the axis configuration file (docs/axis-config.md), which `scanner
//! axes --set` sends to a device and `scanner geometry --axes` checks a
//! design with: arbitrary text must give a typed error or three
//! configurations that every controller accepts, that write back to the
//! same file, and that the host's unit ↔ step conversion and the design
//! check take without a panic. Mutated as TOML (`fuzz_support::structured`)
//! as well as bytes.
#![no_main]

use host::geometry::{AxisValues, ScannerGeometry, axes_from_toml, axes_to_toml};
use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;

fn design() -> &'static ScannerGeometry {
    static G: OnceLock<ScannerGeometry> = OnceLock::new();
    G.get_or_init(ScannerGeometry::default_scanner)
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(axes) = axes_from_toml(text) else { return };
    for c in &axes {
        assert_eq!(c.problem(), None, "{c:?}");
    }
    // Written and read back: the same configurations, bit for bit.
    assert_eq!(axes_from_toml(&axes_to_toml(&axes)).unwrap(), axes);
    // Positions across and beyond the travel convert or say why not.
    for v in [-1e9, -360.0, -35.0, 0.0, 30.0, 200.0, 361.0, 1e9, f64::NAN] {
        if let Ok(steps) = AxisValues::from_array([v; 3]).to_steps(&axes) {
            let back = AxisValues::from_steps(steps.map(i64::from), &axes);
            assert!(back.to_array().iter().all(|x| x.is_finite()), "{v}: {back:?}");
        }
    }
    let check = design().check_design_on(&axes);
    assert_eq!(check.mirrors.len(), design().mirrors.len());
    for p in &check.problems {
        let _ = p.to_string();
    }
    let _ = design().mirror_table(&axes);
});

fuzz_support::structured_mutator!(fuzz_support::structured::toml_file);
