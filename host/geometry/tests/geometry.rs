//! The nominal geometry crate: the shipped file, unit ↔ step conversion,
//! the mirror table.

use protocol::{Axis, AxisConfig};
use scanner_geometry::{
    AxisValues, DEFAULT_GEOMETRY_TOML, GeometryError, ScannerGeometry, StepsError, steps_to_unit,
    unit_to_steps,
};

#[test]
fn shipped_default_geometry_is_the_generated_one() {
    let generated = ScannerGeometry::generate_default();
    assert_eq!(
        DEFAULT_GEOMETRY_TOML,
        generated.to_toml(),
        "regenerate with `cargo run -p scanner-geometry --example write-default-geometry`"
    );
    let parsed = ScannerGeometry::default_scanner();
    assert_eq!(parsed, generated);
    assert_eq!(parsed.mirrors.len(), 40);
}

use firmware::config::{disk_default, tilt_default, track_default};

fn axes() -> [AxisConfig; 3] {
    [disk_default(), track_default(), tilt_default()]
}

#[test]
fn the_continuous_disk_wraps_both_ways() {
    let c = disk_default(); // 16 000 steps per turn
    assert_eq!(unit_to_steps(Axis::Disk, -90.0, &c), Ok(12_000));
    assert_eq!(unit_to_steps(Axis::Disk, 360.0, &c), Ok(0));
    assert_eq!(unit_to_steps(Axis::Disk, 720.0 + 4.5, &c), Ok(200));
    // steps_per_unit is an f32 on the wire (44.444443…).
    assert!((steps_to_unit(-4_000, &c) - 270.0).abs() < 1e-4);
    assert!((steps_to_unit(16_000 + 200, &c) - 4.5).abs() < 1e-5);
}

#[test]
fn a_bounded_axis_refuses_positions_outside_its_travel() {
    let c = track_default(); // 1 600 steps/mm, 0 … 200 mm
    assert_eq!(unit_to_steps(Axis::Track, 30.0, &c), Ok(48_000));
    assert_eq!(
        unit_to_steps(Axis::Track, -1.0, &c),
        Err(StepsError::OutOfRange {
            axis: Axis::Track,
            value: -1.0,
            steps: -1_600,
            min: 0,
            max: 320_000,
            unit: protocol::Unit::Millimetre,
            per_unit: 1600.0
        })
    );
    assert!(matches!(
        unit_to_steps(Axis::Track, f64::NAN, &c),
        Err(StepsError::NotAPosition { axis: Axis::Track, .. })
    ));
    let msg = unit_to_steps(Axis::Track, 250.0, &c).unwrap_err().to_string();
    assert_eq!(
        msg,
        "track: 250.000 mm (400000 steps) is outside its travel 0.00 … 200.00 mm (0 … 320000 steps)"
    );
}

#[test]
fn the_mirror_table_is_the_inverse_kinematics_in_steps() {
    let g = ScannerGeometry::default_scanner();
    let axes = axes();
    let table = g.mirror_table(&axes).unwrap();
    assert_eq!(table.len(), 40);
    for (l, p) in table.iter().enumerate() {
        let back = AxisValues::from_steps(p.steps.map(i64::from), &axes);
        let want = g.mirror_axes(l).unwrap();
        // Within half a step of each axis.
        assert!((back.disk_deg - want.disk_deg).abs() <= 0.5 * 360.0 / 16_000.0, "mirror {l}");
        assert!((back.tilt_deg - want.tilt_deg).abs() <= 0.5 * 360.0 / 96_000.0, "mirror {l}");
    }
    // A track too short for the working position: the error names the mirror.
    let short = [axes[0], AxisConfig { max_steps: 100, ..axes[1] }, axes[2]];
    match g.mirror_table(&short) {
        Err(GeometryError::OutOfTravel(0, StepsError::OutOfRange { axis: Axis::Track, .. })) => {}
        other => panic!("{other:?}"),
    }
}

#[test]
fn unreadable_files_are_typed_errors() {
    let e = ScannerGeometry::load(std::path::Path::new("/nonexistent/g.toml")).unwrap_err();
    assert!(matches!(e, GeometryError::Io { .. }), "{e:?}");
    let e = ScannerGeometry::from_toml("format = 1").unwrap_err();
    assert!(matches!(e, GeometryError::Parse(_)), "{e:?}");
    // A file's errors name it.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mine.toml");
    std::fs::write(&path, "format = 1").unwrap();
    let e = ScannerGeometry::load(&path).unwrap_err();
    assert!(
        matches!(&e, GeometryError::File { source, .. } if matches!(**source, GeometryError::Parse(_))),
        "{e:?}"
    );
    assert!(e.to_string().starts_with(&format!("{}: scanner geometry", path.display())), "{e}");
}

#[test]
fn lens_distortion_round_trips_and_must_map_the_image_one_to_one() {
    use scanner_geometry::{radial_distort, radial_undistort};
    for k in [[-0.05, 0.0], [0.08, -0.02], [-0.2, 0.05], [0.0, 0.0]] {
        for n in [[0.0, 0.0], [0.1, -0.05], [-0.3, 0.2], [0.37, 0.37]] {
            let d = radial_distort(k, n);
            let back = radial_undistort(k, d);
            assert!(
                (back[0] - n[0]).abs() < 1e-12 && (back[1] - n[1]).abs() < 1e-12,
                "{k:?} {n:?}"
            );
        }
    }
    // A ray and its projection agree through the lens.
    let mut g = ScannerGeometry::default_scanner();
    g.camera.distortion = [-0.05, 0.01];
    let p = g.camera.position_mm;
    let ray = g.camera.ray(300.5, 3900.5);
    let x = g.camera.project(scanner_geometry::DVec3::from(p) + ray * 1000.0).unwrap();
    assert!((x[0] - 300.5).abs() < 1e-6 && (x[1] - 3900.5).abs() < 1e-6, "{x:?}");
    // The hash of a pinhole geometry does not change with the new key.
    let text = ScannerGeometry::default_scanner().to_toml();
    assert!(!text.contains("distortion"), "absent when zero");
    assert!(ScannerGeometry::from_toml(&g.to_toml()).is_ok());
    // One that folds the image over is refused.
    g.camera.distortion = [-2.0, 0.0];
    let err = ScannerGeometry::from_toml(&g.to_toml()).unwrap_err().to_string();
    assert!(err.contains("does not map the image one to one"), "{err}");
}

/// Every float of a geometry file (its key as the error names it: dotted,
/// arrays indexed) — the file's numbers are all floats but the camera's size,
/// the sensor's bits and the format.
fn float_keys(v: &toml::Value, key: &str, out: &mut Vec<String>) {
    match v {
        toml::Value::Float(_) => out.push(key.to_string()),
        toml::Value::Table(t) => {
            for (k, x) in t {
                let child = if key.is_empty() { k.clone() } else { format!("{key}.{k}") };
                float_keys(x, &child, out);
            }
        }
        toml::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                float_keys(x, &format!("{key}[{i}]"), out);
            }
        }
        _ => {}
    }
}

/// The value at `key` (as [`float_keys`] writes it) under `v`.
fn at<'a>(v: &'a mut toml::Value, key: &str) -> &'a mut toml::Value {
    key.split('.').fold(v, |v, part| {
        let (name, index) = match part.split_once('[') {
            Some((n, i)) => (n, Some(i.trim_end_matches(']').parse::<usize>().unwrap())),
            None => (part, None),
        };
        let v = &mut v.as_table_mut().unwrap()[name];
        match index {
            Some(i) => &mut v.as_array_mut().unwrap()[i],
            None => v,
        }
    })
}

/// TOML writes `nan` and `inf`: no number of a geometry file may be either,
/// nor so large that the kinematics' products overflow. Each is refused by
/// its key, whichever number it is; the largest allowed keep the projections
/// finite.
#[test]
fn every_number_must_be_finite_and_within_range() {
    let base: toml::Value = toml::from_str(DEFAULT_GEOMETRY_TOML).unwrap();
    let mut keys = Vec::new();
    float_keys(&base, "", &mut keys);
    assert!(keys.len() > 40 * 8, "{} keys", keys.len());
    assert!(keys.contains(&"mirror[39].center_mm[2]".to_string()), "{keys:?}");
    for key in &keys {
        for x in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 2e9, -1e300] {
            let mut v = base.clone();
            *at(&mut v, key) = toml::Value::Float(x);
            let err = ScannerGeometry::from_toml(&toml::to_string(&v).unwrap()).unwrap_err();
            assert!(
                matches!(err, GeometryError::Invalid(_))
                    && err.to_string().contains(&format!("{key} = ")),
                "{key} = {x}: {err}"
            );
        }
    }
    // At the limit, a camera or a mirror far away still projects finitely.
    for key in ["camera.position_mm[0]", "camera.up[1]", "mirror[0].center_mm[2]"] {
        for x in [scanner_geometry::MAX_MAGNITUDE, -scanner_geometry::MAX_MAGNITUDE] {
            let mut v = base.clone();
            *at(&mut v, key) = toml::Value::Float(x);
            let Ok(g) = ScannerGeometry::from_toml(&toml::to_string(&v).unwrap()) else {
                continue;
            };
            for l in 0..g.mirrors.len() {
                if let Some(p) = g.view_point(l, [0.5, 0.5]) {
                    assert!(p.iter().all(|c| c.is_finite()), "{key} = {x}: view {l} at {p:?}");
                }
            }
        }
    }
}

/// A mirror at the sample, or behind it, has no direction from it: refused
/// when the file is read, naming the mirror (the geometry fuzz target found
/// a centre of 5e-324 mm giving NaN view and light directions).
#[test]
fn a_mirror_that_cannot_face_the_sample_is_refused() {
    for centre in [[5e-324, 0.0, 0.0], [0.0, 0.0, -10.0], [60.0, 0.0, 150.0]] {
        let mut g = ScannerGeometry::default_scanner();
        g.mirrors[19].center_mm = centre;
        let e = ScannerGeometry::from_toml(&g.to_toml()).unwrap_err();
        assert!(matches!(e, GeometryError::Invalid(_)), "{centre:?}: {e:?}");
        assert!(e.to_string().contains("mirror 19: centre"), "{e}");
    }
}
