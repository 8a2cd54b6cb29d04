//! Fuzz the axis configuration file (docs/axis-config.md), which `scanner
//! axes --set` sends to a device and `scanner geometry --axes` checks a
//! design with: arbitrary text must give a typed error or three
//! configurations that every controller accepts, that write back to the
//! same file, and that the host's unit ↔ step conversion and the design
//! check take without a panic; each axis corrected by measured moves is
//! refused with a reason or accepted, its travel kept in units. Mutated as TOML (`fuzz_support::structured`)
//! as well as bytes.
#![no_main]

use host::geometry::{
    AxisValues, Measured, ScannerGeometry, axes_from_toml, axes_to_toml, check_axes, correct_axis,
};
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
    // Corrected by measured moves: refused with a reason, or a
    // configuration whose travel keeps its units within a step.
    for (commanded, measured) in
        [(100.0, 98.7), (1.0, 4.0), (4.0, 1.0), (1.0, 1e-300), (1e300, 1.0)]
    {
        for axis in protocol::Axis::ALL {
            let was = axes[axis.index()];
            let Ok(now) = correct_axis(&was, Measured { axis, commanded, measured }) else {
                continue;
            };
            let mut corrected = axes;
            corrected[axis.index()] = now;
            if check_axes(&corrected).is_err() || was.continuous {
                continue;
            }
            let unit = |steps: i32, per: f32| steps as f64 / per as f64;
            let (a, b) =
                (unit(was.max_steps, was.steps_per_unit), unit(now.max_steps, now.steps_per_unit));
            assert!((a - b).abs() <= 1.0 / now.steps_per_unit as f64 + 1e-6 * a.abs(), "{a} {b}");
        }
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::toml_file);
