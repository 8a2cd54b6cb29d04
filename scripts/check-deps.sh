#!/usr/bin/env bash
# Crate boundaries (docs/architecture.md): what a library may not pull in.
# - the host library without its default features: no simulator, no CLI crates;
# - the nominal geometry crate: nothing of the simulator, serial/USB or the CLI;
# - the renderer-facing shading crate and its C API: no simulator, serial/USB, image decoding, CLI or builder crates.
set -euo pipefail
cd "$(dirname "$0")/.."

forbid() { # package, cargo-tree flags, forbidden crates...
    local pkg=$1 flags=$2
    shift 2
    # shellcheck disable=SC2086
    local tree
    tree=$(cargo tree --locked -p "$pkg" $flags -e normal,build --prefix none --format '{p}')
    local bad=0
    for crate in "$@"; do
        if grep -qE "^$crate v" <<<"$tree"; then
            echo "error: $pkg ($flags) depends on $crate" >&2
            bad=1
        fi
    done
    [ "$bad" -eq 0 ] && echo "$pkg ${flags:-(default features)}: none of $*"
    return "$bad"
}

forbid host "--no-default-features" hil-sim firmware clap clap_complete clap_mangen quick-junit indicatif tracing-subscriber anyhow plotters ctrlc
forbid scanner-geometry "" hil-sim firmware clap indicatif serialport nusb exr image rand
forbid scanner-shading "" hil-sim firmware clap indicatif tracing-subscriber anyhow serialport nusb exr image spade rayon
forbid scanner-shading-c "" hil-sim firmware host clap indicatif tracing-subscriber anyhow serialport nusb exr image spade rayon
