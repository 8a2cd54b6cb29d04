//! Request round trips per second: over the simulator's pty (a real serial
//! link through the kernel, the device run in real time) against the
//! in-process deterministic link as the baseline measured in the same run;
//! and a whole deterministic scan on the 4×-binned sensor
//! (docs/benchmarks.md).

use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use host::camera::SimCamera;
use host::link::{Device, SerialTransport, SimTransport};
use host::scan::{Quiet, ScanOptions, scan};
use host::simulator::SimSetup;
use protocol::Request;

fn round_trips(c: &mut Criterion) {
    let setup = SimSetup { bin: 8, ..SimSetup::new("leather") };
    let frames = tempfile::tempdir().unwrap();
    let server =
        setup.serve(1.0, frames.path().to_path_buf(), hil_sim::camera::FrameFiles::Exr).unwrap();
    let mut pty = Device::connect(Box::new(SerialTransport::open(server.path()).unwrap())).unwrap();
    let mut sim = Device::connect(Box::new(SimTransport(setup.rig().unwrap()))).unwrap();
    let mut group = c.benchmark_group("link");
    group.throughput(Throughput::Elements(1));
    group.measurement_time(Duration::from_secs(10));
    group.bench_function("ping_round_trip_pty", |b| {
        b.iter(|| pty.request(Request::Ping { token: 7 }).unwrap())
    });
    group.bench_function("ping_round_trip_in_process", |b| {
        b.iter(|| sim.request(Request::Ping { token: 7 }).unwrap())
    });
    group.bench_function("status_round_trip_pty", |b| b.iter(|| pty.status().unwrap()));
    group.finish();
    drop(server);
}

fn deterministic_scan(c: &mut Criterion) {
    let setup = SimSetup { bin: 4, ..SimSetup::new("woven-fabric") };
    let mut group = c.benchmark_group("scan");
    group.sample_size(10).measurement_time(Duration::from_secs(30));
    group.bench_function("deterministic_40_mirrors_1024px", |b| {
        b.iter(|| {
            let dir = tempfile::tempdir().unwrap();
            let rig = setup.rig().unwrap();
            let mut dev = Device::connect(Box::new(SimTransport(rig.clone()))).unwrap();
            scan(
                &mut dev,
                &mut SimCamera(rig),
                &setup.nominal().unwrap(),
                &ScanOptions::new("b", dir.path()),
                &mut Quiet,
            )
            .unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, round_trips, deterministic_scan);
criterion_main!(benches);
