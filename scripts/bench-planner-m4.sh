#!/usr/bin/env bash
# Planner cost on a Cortex-M4 (soft-float f64), in instructions: QEMU with
# -icount shift=0 (one instruction per ns of virtual time), read through
# SysTick at the mps2-an386 core clock (docs/benchmarks.md).
set -euo pipefail
cd "$(dirname "$0")/../firmware/qemu-tests"
cargo build --release --locked --bin plan_cost -q
qemu-system-arm -cpu cortex-m4 -machine mps2-an386 -nographic \
    -semihosting-config enable=on,target=native -icount shift=0 \
    -kernel target/thumbv7em-none-eabihf/release/plan_cost
