#!/usr/bin/env bash
# Installs what a fresh machine lacks:
# - the pinned Rust toolchain with rustfmt, clippy, llvm-tools and the
#   thumbv7em-none-eabihf target (all read from rust-toolchain.toml);
# - QEMU's Arm system emulator, which runs the firmware self-tests on a
#   Cortex-M4, and strace, with which a test checks that every rename in a
#   scan directory is followed by a directory fsync (Debian/Ubuntu:
#   apt-get, as root or through sudo).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v rustup >/dev/null 2>&1; then
    echo "rustup is required: https://rustup.rs" >&2
    exit 1
fi
rustup toolchain install >/dev/null
missing=()
command -v qemu-system-arm >/dev/null 2>&1 || missing+=(qemu-system-arm)
command -v strace >/dev/null 2>&1 || missing+=(strace)
if [ "${#missing[@]}" -gt 0 ]; then
    echo "installing ${missing[*]} (firmware Cortex-M4 tests; the fsync test)"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi
