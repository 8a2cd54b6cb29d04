//! Render time of one default frame (4096², woven fabric, mirror 5 lit) and,
//! as the baseline in the same run, of the same frame on a 4× binned sensor
//! (docs/benchmarks.md).
//!
//! The simulator keeps the last exposure's scene (an HDR bracket exposes the
//! same axis positions several times) and, per geometry, the pixels that see
//! the sample. `render_frame_*` times what every new mirror of a scan costs:
//! each iteration starts from a simulator without the scene (the pixels that
//! see the sample are found once, as in a scan). `readout_*` times what a
//! further exposure of the same mirror costs: the sensor model on the kept
//! scene.

use std::time::Duration;

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, Sample};
use hil_sim::optics::{Exposure, OpticalSim};

fn frame(c: &mut Criterion) {
    let mut group = c.benchmark_group("optics");
    group.sample_size(10).measurement_time(Duration::from_secs(20));
    for bin in [1u32, 4] {
        let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(bin);
        let sample = Sample::small(materials::by_name("woven-fabric").unwrap());
        let sim = OpticalSim::as_built(&nominal, sample.clone(), 7);
        let axes = nominal.mirror_axes(5).unwrap();
        let e = Exposure { axes, exposure_s: 0.05, light: 1.0 };
        // Finds the pixels that see the sample; every clone below shares them.
        sim.render(&e);
        let px = nominal.camera.width;
        group.bench_function(format!("render_frame_{px}px"), |b| {
            b.iter_batched(
                || sim.with_sample(sample.clone()),
                |fresh| fresh.render(&e),
                BatchSize::PerIteration,
            )
        });
        group.bench_function(format!("readout_{px}px"), |b| b.iter(|| sim.render(&e)));
    }
    group.finish();
}

criterion_group!(benches, frame);
criterion_main!(benches);
