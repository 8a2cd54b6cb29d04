#!/usr/bin/env bash
# Fuzz the material reader, the query/answer file readers, the protocol
# decoder, the OpenEXR frame decoder and the texture maps' OpenEXR reader
# with cargo-fuzz.
#   scripts/fuzz.sh [SECONDS per target, default 300]
# Needs the nightly toolchain (rustup toolchain install nightly) and
# cargo-fuzz (cargo install cargo-fuzz); libFuzzer is built with the system
# C++ compiler. Not part of the test command: a long run, not a check.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-300}
mkdir -p fuzz/corpus/decoder
# Start from valid files, so the fuzzer gets past the container checks
# (fuzz/corpus/material, fuzz/corpus/queries).
cargo run -q --release -p host --example fuzz_seeds -- fuzz/corpus
for target in material queries decoder frame texture_map; do
    (cd fuzz && cargo +nightly fuzz run --release "$target" "corpus/$target" -- \
        -max_total_time="$seconds" -rss_limit_mb=4096 -max_len=1048576)
done
