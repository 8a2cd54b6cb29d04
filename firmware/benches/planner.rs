//! Planner cost per move on the host (docs/benchmarks.md): plan a whole move
//! into step-generator segments, for the default axes' longest moves and a
//! short one.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use firmware::hal::TICK_HZ;
use firmware::planner::{Profile, SegmentPlanner};

fn plan(steps: u32, v: f64, a: f64) -> u32 {
    let mut planner = SegmentPlanner::new(Profile::trapezoid(steps, 0.0, v, a), TICK_HZ);
    let mut segments = 0;
    while let Some(s) = planner.next_segment() {
        black_box(s);
        segments += 1;
    }
    segments
}

fn planner(c: &mut Criterion) {
    let cases = [
        ("track_full_range_320000_steps", 320_000, 64_000.0, 320_000.0),
        ("disk_half_turn_8000_steps", 8_000, 4_000.0, 8_000.0),
        ("tilt_full_range_18666_steps", 18_666, 5_333.0, 16_000.0),
        ("track_short_1000_steps", 1_000, 64_000.0, 320_000.0),
    ];
    let mut group = c.benchmark_group("plan_move");
    for (name, n, v, a) in cases {
        println!("{name}: {} segments", plan(n, v, a));
        group.bench_function(name, |b| b.iter(|| plan(black_box(n), v, a)));
    }
    group.finish();
}

criterion_group!(benches, planner);
criterion_main!(benches);
