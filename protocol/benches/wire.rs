//! Wire size and throughput of the protocol (docs/benchmarks.md).
//!
//! Prints the bytes on the wire of a capture-step request and a status reply,
//! then measures encode + frame + decode of status frames, one core.

#[path = "../tests/common/mod.rs"]
mod common;

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use protocol::*;

fn wire(c: &mut Criterion) {
    let capture = common::Example::ToDevice(common::capture_step()).encode(200);
    let status = common::Example::ToHost(common::status()).encode(200);
    println!("wire bytes: capture-step request {} (target ≤ 16)", capture.len());
    println!("wire bytes: status reply {} (target ≤ 64)", status.len());
    println!("max frame: request {} / to-host {}", Request::MAX_FRAME_LEN, ToHost::MAX_FRAME_LEN);

    let ToHost::Reply(Reply::Status(st)) = common::status() else { unreachable!() };
    let msg = ToHost::Reply(Reply::Status(st));

    let mut group = c.benchmark_group("status");
    group.throughput(Throughput::Elements(1));
    group.bench_function("encode_frame", |b| {
        let mut buf = [0u8; MAX_FRAME_LEN];
        b.iter(|| encode_frame(black_box(7), black_box(&msg), &mut buf).unwrap())
    });
    group.bench_function("decode_stream", |b| {
        let mut decoder = FrameDecoder::<ToHost>::new();
        b.iter(|| decoder.feed(black_box(&status)).next().unwrap().unwrap())
    });
    group.bench_function("encode_frame_decode", |b| {
        let mut buf = [0u8; MAX_FRAME_LEN];
        let mut decoder = FrameDecoder::<ToHost>::new();
        b.iter(|| {
            let n = encode_frame(black_box(7), black_box(&msg), &mut buf).unwrap();
            decoder.feed(&buf[..n]).next().unwrap().unwrap()
        })
    });
    group.finish();

    let mut group = c.benchmark_group("capture_step");
    group.throughput(Throughput::Elements(1));
    let req = common::capture_step();
    group.bench_function("encode_frame_decode", |b| {
        let mut buf = [0u8; MAX_FRAME_LEN];
        let mut decoder = FrameDecoder::<Request>::new();
        b.iter(|| {
            let n = encode_frame(black_box(12), black_box(&req), &mut buf).unwrap();
            decoder.feed(&buf[..n]).next().unwrap().unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, wire);
criterion_main!(benches);
