#!/usr/bin/env bash
# The project's test command (README, "Tests"). CI (.ci/run) runs exactly this.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh

step() { printf '\n==> %s\n' "$*"; }

step "format"
cargo fmt --all -- --check
step "clippy"
cargo clippy --workspace --all-targets --locked -- -D warnings
step "tests"
cargo test --workspace --locked
step "no_std build of protocol for thumbv7em-none-eabihf"
cargo build -p protocol --target thumbv7em-none-eabihf --release --locked
cargo build -p protocol --target thumbv7em-none-eabihf --release --locked --features defmt
