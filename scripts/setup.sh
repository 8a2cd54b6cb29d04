#!/usr/bin/env bash
# Installs what a fresh machine lacks:
# - the pinned Rust toolchain with rustfmt, clippy, llvm-tools and the
#   thumbv7em-none-eabihf target (all read from rust-toolchain.toml);
# - QEMU's Arm system emulator, which runs the firmware self-tests on a
#   Cortex-M4, and strace, with which a test checks that every rename in a
#   scan directory is followed by a directory fsync, and a C compiler (the
#   linker Rust needs; a test compiles the C API's example with it)
#   (Debian/Ubuntu: apt-get, as root or through sudo);
# - numpy and safetensors in a Python virtual environment, .venv/, for the
#   test that reads material files in Python from their documentation;
# - Node.js and the Khronos glTF validator (tests/gltf/, pinned by its
#   package-lock.json), for the test that validates `scanner export
#   --format gltf`.
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
# The C compiler Rust links with; a test also compiles the C API's example.
command -v cc >/dev/null 2>&1 || missing+=(gcc)
if [ "${#missing[@]}" -gt 0 ]; then
    echo "installing ${missing[*]} (firmware Cortex-M4 tests; the fsync test; the C compiler)"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi

# Python with numpy and safetensors in .venv/, for the test that shades a
# material file from docs/material-format.md alone (host/tests/python.rs,
# tests/python/). Python 3 and its venv module come from apt-get if missing.
if ! python3 -c 'import venv, ensurepip' >/dev/null 2>&1; then
    echo "installing python3 and python3-venv (the material file's Python reader test)"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq python3 python3-venv >/dev/null
fi
if ! .venv/bin/python -c 'import numpy, safetensors' >/dev/null 2>&1; then
    echo "installing numpy and safetensors into .venv (tests/python/requirements.txt)"
    python3 -m venv .venv
    .venv/bin/python -m pip install -q --disable-pip-version-check -r tests/python/requirements.txt
fi

# Node.js and the Khronos glTF validator in tests/gltf/node_modules, for the
# test that validates an exported glTF asset (host/tests/gltf.rs).
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    echo "installing nodejs and npm (the glTF export's validator test)"
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq nodejs npm >/dev/null
fi
if [ ! -f tests/gltf/node_modules/gltf-validator/package.json ]; then
    echo "installing the Khronos glTF validator into tests/gltf (package-lock.json)"
    (cd tests/gltf && npm ci --no-audit --no-fund --silent)
fi
