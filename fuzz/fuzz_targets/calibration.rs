//! Fuzz the calibration file (docs/calibration-format.md), which one
//! calibration run writes and many builds read, perhaps on another
//! machine: arbitrary text must give an error or a calibration, never a
//! panic; and what `scanner regions` and `scanner build` compute from a
//! calibration they accept for the default scanner, before any frame (the
//! region size, the frame windows, each view's resampling filters, the
//! colour calibration's response, the viewers), must not panic and must be
//! finite. Mutated as JSON (`fuzz_support::structured`) as well as bytes.
#![no_main]

use host::build::Calibration;
use host::build::calibrate::view_windows;
use host::build::regions::default_size;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(cal) = Calibration::parse(text) else { return };
    let _ = cal.hash();
    let g = fuzz_support::default_scanner(1);
    if cal.check_geometry(g).is_err() {
        return;
    }
    let size = default_size(&cal);
    assert!((8..=4096).contains(&size), "region size {size}");
    let dims = [g.camera.width as usize, g.camera.height as usize];
    for (v, w) in cal.views.iter().zip(view_windows(&cal.views)) {
        assert!(w[0] < w[2] && w[1] < w[3], "view {}: window {w:?}", v.view);
        let s = v.sampler();
        let viewer = v.viewer_mm(g);
        assert!(viewer.iter().all(|x| x.is_finite()), "view {}: viewer {viewer:?}", v.view);
        for uv in [[0.0, 0.0], [0.5, 0.5], [1.0, 1.0], [0.003, 0.998]] {
            let p = s.frame_point(uv);
            assert!(p.iter().all(|x| x.is_finite()), "view {} at {uv:?}: {p:?}", v.view);
            let _ = s.region_filter(dims, uv);
            assert!(s.region_noise_gain(uv).is_finite());
        }
    }
    for li in 0..cal.lights.len() {
        for vi in 0..cal.views.len() {
            for uv in [[0.0, 0.0], [0.5, 0.5], [1.0, 1.0], [0.3, 0.9]] {
                let r = cal.colour.response(li, vi, uv);
                assert!(r.iter().all(|x| x.is_finite() && *x >= 0.0), "{li}, {vi}: {r:?}");
            }
        }
    }
});

fuzz_support::structured_mutator!(fuzz_support::structured::json_file);
