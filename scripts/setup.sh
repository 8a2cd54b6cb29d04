#!/usr/bin/env bash
# Installs what a fresh machine lacks:
# - the pinned Rust toolchain with rustfmt, clippy, llvm-tools and the
#   thumbv7em-none-eabihf target (all read from rust-toolchain.toml);
# - QEMU's Arm system emulator, which runs the firmware self-tests on a
#   Cortex-M4 (Debian/Ubuntu: apt-get, as root or through sudo).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v rustup >/dev/null 2>&1; then
    echo "rustup is required: https://rustup.rs" >&2
    exit 1
fi
rustup toolchain install >/dev/null
if ! command -v qemu-system-arm >/dev/null 2>&1; then
    echo "installing qemu-system-arm (for the firmware's Cortex-M4 tests)"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq qemu-system-arm >/dev/null
fi
