//! Fuzz the scanner geometry file (docs/scanner-geometry.md), the one file
//! every command takes (`--geometry`): arbitrary text must give a typed
//! error or a geometry, never a panic; and what the host computes from a
//! geometry it accepted, before any frame (the inverse kinematics, the
//! device's mirror table, the sample's views in the frame, the windows
//! calibration searches, the metering's spans, `scanner geometry`'s
//! check of the design), must not panic either and
//! must be finite where it is given. Mutated as TOML
//! (`fuzz_support::structured`) as well as bytes.
#![no_main]

use host::build::locate::{nominal_homography, search_window};
use host::geometry::MAX_MAGNITUDE;
use host::geometry::ScannerGeometry;
use libfuzzer_sys::fuzz_target;

/// Asserts that every number under `v` (`key` its dotted path) is finite
/// and within ±MAX_MAGNITUDE.
fn assert_finite(v: &toml::Value, key: &str) {
    match v {
        toml::Value::Float(x) => assert!(x.abs() <= MAX_MAGNITUDE, "{key} = {x}"),
        toml::Value::Integer(i) => assert!(i.unsigned_abs() as f64 <= MAX_MAGNITUDE, "{key} = {i}"),
        toml::Value::Array(a) => a.iter().for_each(|x| assert_finite(x, key)),
        toml::Value::Table(t) => {
            t.iter().for_each(|(k, x)| assert_finite(x, &format!("{key}.{k}")))
        }
        _ => {}
    }
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(g) = ScannerGeometry::from_toml(text) else { return };
    let _ = g.hash();
    // docs/scanner-geometry.md: every number of a geometry accepted is
    // finite and within ±MAX_MAGNITUDE, its defaults included.
    let written: toml::Value = toml::from_str(&g.to_toml()).unwrap();
    assert_finite(&written, "");
    let configs = [
        firmware::config::disk_default(),
        firmware::config::track_default(),
        firmware::config::tilt_default(),
    ];
    let _ = g.mirror_table(&configs);
    let [w, h] = [g.camera.width, g.camera.height];
    for l in 0..g.mirrors.len() {
        if let Ok(axes) = g.mirror_axes(l) {
            assert!(axes.to_array().iter().all(|x| x.is_finite()), "mirror {l}: {axes:?}");
        }
        if let Ok(d) = g.light_direction(l) {
            assert!(d.is_finite(), "light {l}: {d:?}");
        }
        if let Some(d) = g.mirror_direction(l) {
            assert!(d.is_finite(), "mirror {l}: {d:?}");
        }
        for uv in [[0.0, 0.0], [0.5, 0.5], [1.0, 1.0]] {
            if let Some(p) = g.view_point(l, uv) {
                assert!(p.iter().all(|x| x.is_finite()), "view {l} at {uv:?}: {p:?}");
            }
        }
        let _ = g.sample_image_corners(l);
        if let Some(hm) = nominal_homography(&g, l) {
            let _ = hm.window(4.0);
            let _ = hm.inverse();
        }
        if let Some(r) = search_window(&g, l) {
            assert!(r[0] <= r[2] && r[1] <= r[3], "view {l}: window {r:?}");
        }
    }
    // `scanner geometry`'s check of the design: a figure per mirror, every
    // problem said.
    let check = g.check_design();
    assert_eq!(check.mirrors.len(), g.mirrors.len());
    for p in &check.problems {
        let _ = p.to_string();
    }
    let _ = host::exposure::sample_spans(&g, w, h);
    for (x, y) in [(0.0, 0.0), (w as f64 / 2.0, h as f64 / 2.0), (w as f64, h as f64)] {
        let r = g.camera.ray(x, y);
        let far = host::geometry::DVec3::from(g.camera.position_mm) + r * 100.0;
        if let Some(p) = g.camera.project(far) {
            assert!(p.iter().all(|x| x.is_finite()), "ray through ({x}, {y}): {p:?}");
        }
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::toml_file);
