//! Wall-clock of a deterministic 40-mirror capture, homing included, and the
//! device time it simulates (docs/benchmarks.md).

#[path = "../tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::{Client, capture_all, load_mirror_table};
use criterion::{Criterion, criterion_group, criterion_main};
use hil_sim::SimConfig;

/// One full session; returns the device time it took, seconds.
fn scan() -> f64 {
    let mut c = Client::new(SimConfig::new(7));
    c.home_all();
    load_mirror_table(&mut c);
    capture_all(&mut c, 40);
    c.now_ticks() as f64 / firmware::hal::TICK_HZ as f64
}

fn capture(c: &mut Criterion) {
    let device_s = scan();
    println!("simulated device time of one homing + 40-mirror capture: {device_s:.1} s");
    let mut group = c.benchmark_group("hil_sim");
    group.sample_size(10).measurement_time(Duration::from_secs(10));
    group.bench_function("home_and_capture_40_mirrors", |b| b.iter(scan));
    group.finish();
}

criterion_group!(benches, capture);
criterion_main!(benches);
