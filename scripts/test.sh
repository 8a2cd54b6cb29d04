#!/usr/bin/env bash
# The project's test command (README, "Tests"). CI (.ci/run) runs exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh

step() { printf '\n==> %s\n' "$*"; }

step "format"
cargo fmt --all -- --check
(cd firmware/board && cargo fmt -- --check)
(cd firmware/qemu-tests && cargo fmt -- --check)
step "clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings
(cd firmware/board && cargo clippy --release --locked -- -D warnings)
(cd firmware/qemu-tests && cargo clippy --release --locked --bins -- -D warnings)
step "crate boundaries"
scripts/check-deps.sh
cargo check -p host --lib --no-default-features --locked
cargo check -p host --bin scanner --no-default-features --features cli --locked
step "tests"
cargo test --workspace --locked
step "vendored exr's PIZ decoder (host/vendor/exr/PATCHES.md)"
(cd host/vendor/exr && CARGO_TARGET_DIR=../../../target/vendor-exr cargo test --release --locked --lib compression::piz)
step "no_std build of protocol for thumbv7em-none-eabihf"
cargo build -p protocol --target thumbv7em-none-eabihf --release --locked
cargo build -p protocol --target thumbv7em-none-eabihf --release --locked --features defmt
step "firmware core self-tests linked for the board (STM32F411, feature black-pill)"
(cd firmware/qemu-tests && cargo build --release --locked --features black-pill --bin firmware-qemu-tests)
step "firmware core self-tests on a Cortex-M4 (QEMU mps2-an386)"
(cd firmware/qemu-tests && cargo run --release --locked)
step "firmware ELF size (release, STM32F411)"
scripts/firmware-size.sh
