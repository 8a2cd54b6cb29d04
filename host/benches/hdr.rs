//! HDR merging with and without the sensor's defects (docs/benchmarks.md,
//! "Sensor defects"): a 2048² frame (a quarter of the default sensor's
//! pixels), three exposures 5× apart, a quarter of the frame lit and
//! highlights clipping the longest. The defect map is looked up for every
//! value no exposure measured: here ≈ 45 % of them (the dark three
//! quarters' noise is the same in every exposure and reads 0 three times
//! in five), more than a real dark frame's ≈ 29 % (0 two times in three,
//! independently). Also the exposures' agreement (`exposure_ratios`) and
//! the check of every frame from the camera.

use std::hint::black_box;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use host::camera::Frame;
use host::defects::{DefectKind, DefectMap, PixelDefect};
use scanner_geometry::ScannerGeometry;

const SIZE: u32 = 2048;

/// Exposure `t` (µs) of a scene lit in its middle quarter, with read noise
/// and clipping as the sensor gives them (a seeded hash, no RNG crate).
fn exposure(t: u32, max: f32) -> Frame {
    let n = (SIZE * SIZE) as usize;
    let rgb = (0..3 * n)
        .map(|i| {
            let p = i / 3;
            let (x, y) = ((p % SIZE as usize) as u32, (p / SIZE as usize) as u32);
            let lit =
                (SIZE / 4..3 * SIZE / 4).contains(&x) && (SIZE / 4..3 * SIZE / 4).contains(&y);
            let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40;
            let noise = (h % 5) as f32 - 2.0; // ± 2 codes
            let signal = if lit { 0.002 * t as f32 * (1.0 + (x % 97) as f32 / 10.0) } else { 0.0 };
            ((signal * max + noise).round().clamp(0.0, max)) / max
        })
        .collect();
    Frame { width: SIZE, height: SIZE, rgb }
}

fn merge(c: &mut Criterion) {
    let sensor = ScannerGeometry::default_scanner().sensor;
    let max = sensor.max_code() as f32;
    let frames: Vec<(Frame, u32)> = [400, 2_000, 10_000].map(|t| (exposure(t, max), t)).into();
    let inputs: Vec<(&Frame, u32)> = frames.iter().map(|(f, t)| (f, *t)).collect();
    // 64 stuck and 64 dead pixels spread over the frame.
    let defects: Vec<PixelDefect> = (0..128u32)
        .map(|k| PixelDefect {
            x: (k * 7919) % SIZE,
            y: (k * 104_729) % SIZE,
            kind: if k % 2 == 0 { DefectKind::Stuck } else { DefectKind::Dead },
        })
        .collect();
    let map = DefectMap::new(&defects, SIZE, SIZE);
    let mut g = c.benchmark_group("hdr merge 2048², 3 exposures");
    g.sample_size(10).measurement_time(Duration::from_secs(8));
    g.bench_function("no defects (baseline)", |b| {
        b.iter(|| host::hdr::merge(black_box(&inputs), &sensor, 0, 10_000, &DefectMap::default()))
    });
    g.bench_function("128 defects", |b| {
        b.iter(|| host::hdr::merge(black_box(&inputs), &sensor, 0, 10_000, &map))
    });
    g.finish();
    // The exposures' agreement the scan records with every merged mirror.
    let mut g = c.benchmark_group("exposure agreement 2048², 3 exposures");
    g.sample_size(20).measurement_time(Duration::from_secs(4));
    g.bench_function("exposure_ratios", |b| {
        b.iter(|| host::hdr::exposure_ratios(black_box(&inputs), &sensor, 0))
    });
    g.finish();
}

/// The check every frame from the camera gets (size, unit, non-finite
/// values) on a default-sensor frame: 4096² × 3 values, all in range.
fn check(c: &mut Criterion) {
    let camera = ScannerGeometry::default_scanner().camera;
    let (w, h) = (camera.width, camera.height);
    let rgb = (0..3 * w as usize * h as usize).map(|i| (i % 4096) as f32 / 4095.0).collect();
    let frame = Frame { width: w, height: h, rgb };
    let mut g = c.benchmark_group("frame check 4096²");
    g.sample_size(20).measurement_time(Duration::from_secs(4));
    g.bench_function("check_frame", |b| {
        b.iter(|| host::camera::check_frame(black_box(&frame), w, h).unwrap())
    });
    g.finish();
}

criterion_group!(benches, merge, check);
criterion_main!(benches);
