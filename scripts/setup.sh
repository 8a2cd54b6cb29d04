#!/usr/bin/env bash
# Installs what a fresh machine lacks: the pinned toolchain with its components
# and the thumbv7em-none-eabihf target (all read from rust-toolchain.toml).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v rustup >/dev/null 2>&1; then
    echo "rustup is required: https://rustup.rs" >&2
    exit 1
fi
rustup toolchain install >/dev/null
