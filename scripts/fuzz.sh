#!/usr/bin/env bash
# Fuzz the controller's safety rules under random operation
# (firmware::chaos), the host's device link and capture against a hostile
# device (host::hostile), the material reader, the query/answer file readers, the protocol
# decoder, the OpenEXR frame decoder, the PNG and TIFF frame files, the texture maps' OpenEXR reader, the
# scanner geometry file, the axis configuration file, the calibration file, the scan manifest, the
# direct images' manifest, finding a piece's corners in a photograph, the NPF
# model file and the BRDF measurement CSV (read and fitted) with cargo-fuzz.
#   scripts/fuzz.sh [SECONDS per target, default 300]
# Needs the nightly toolchain (rustup toolchain install nightly) and
# cargo-fuzz (cargo install cargo-fuzz); libFuzzer is built with the system
# C++ compiler. Not part of the test command: a long run, not a check.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-300}
mkdir -p fuzz/corpus/decoder fuzz/corpus/controller fuzz/corpus/device_link fuzz/corpus/capture
# Start from valid files, so the fuzzer gets past the container checks
# (fuzz/corpus/material, queries, frame, frame_file, texture_map, geometry, axes, calibration,
# manifest, direct, corners, measurements and npf_model).
cargo run -q --release -p host --example fuzz_seeds -- fuzz/corpus
for target in material queries decoder frame frame_file texture_map geometry axes calibration manifest \
    direct corners npf_model measurements controller device_link capture; do
    # The exr crate's flat-layer reader decodes on a thread pool of its own
    # per file, whose jobs still hold blocks when the process exits: leak
    # detection at exit would report those, so it is off for that target.
    leaks=1
    [ "$target" = texture_map ] && leaks=0
    # The text files' numbers: NaN, infinities, the edges of the ranges.
    # Their targets mutate them as documents too (fuzz/src/structured.rs),
    # whose repeated lists are kept within 256 KiB (8 × a calibration), and
    # a count-driven hang is a timeout of 10 s.
    extra=(-max_len=1048576)
    case "$target" in
    geometry | axes | calibration | manifest | direct | npf_model | measurements)
        extra=(-max_len=262144 -timeout=10 -dict=dicts/numbers.dict)
        ;;
    device_link | capture)
        extra=(-max_len=16384)
        ;;
    controller)
        # Four bytes a random number, a few numbers an action: up to ≈ 500
        # actions a run.
        extra=(-max_len=16384)
        ;;
    esac
    (cd fuzz && cargo +nightly fuzz run --release "$target" "corpus/$target" -- \
        -max_total_time="$seconds" -rss_limit_mb=4096 -detect_leaks=$leaks "${extra[@]}")
done
