//! Render time of one default frame (4096², woven fabric, mirror 5 lit) and,
//! as the baseline in the same run, of the same frame on a 4× binned sensor
//! (docs/benchmarks.md).

use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use hil_sim::geometry::ScannerGeometry;
use hil_sim::materials::{self, Sample};
use hil_sim::optics::{Exposure, OpticalSim};

fn frame(c: &mut Criterion) {
    let mut group = c.benchmark_group("optics");
    group.sample_size(10).measurement_time(Duration::from_secs(20));
    for bin in [1u32, 4] {
        let nominal = ScannerGeometry::default_scanner().with_sensor_scaled(bin);
        let sim = OpticalSim::as_built(
            &nominal,
            Sample::small(materials::by_name("woven-fabric").unwrap()),
            7,
        );
        let axes = nominal.mirror_axes(5).unwrap();
        let e = Exposure { axes, exposure_s: 0.05, light: 1.0 };
        let name = format!("render_frame_{}px", nominal.camera.width);
        group.bench_function(name, |b| b.iter(|| sim.render(&e)));
    }
    group.finish();
}

criterion_group!(benches, frame);
criterion_main!(benches);
