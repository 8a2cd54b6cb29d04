#!/usr/bin/env bash
# The height signature against the colour signature on a piece of the
# sample's relief in other colours (docs/benchmarks.md, "Enlargement"):
# texture sets A (the sample's piece), B (its albedo faded in places) and C
# (dyed per channel) from scripts/height_signature.py; A's sample scanned
# by `scanner demo` at full resolution; each piece's direct images from
# `hil-sim direct`; `scanner enlarge` by colour and by height, 3 × 3 and
# 5 × 5; and the share of the window's texels mapped to their own place.
#   scripts/height-signature.sh [OUT, default target/height-signature]
# Needs scripts/setup.sh's .venv (numpy, safetensors). 6-10 min here.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/height-signature}
mkdir -p "$out"
cargo build -q --release -p host -p hil-sim
py=.venv/bin/python
"$py" scripts/height_signature.py make "$out"
[ -f "$out/demo/A.material" ] || ./target/release/scanner demo --material "$out/A" --out "$out/demo" > "$out/demo.log"
for piece in A B C; do
    ./target/release/hil-sim direct --material "$out/$piece" --out "$out/direct-$piece" > /dev/null 2>&1
    for signature in colour height; do
        for radius in 1 2; do
            ./target/release/scanner enlarge "$out/demo/A.material" --direct "$out/direct-$piece" \
                --signature "$signature" --radius "$radius" \
                -o "$out/$piece-$signature-r$radius.material" > /dev/null
        done
    done
done
"$py" scripts/height_signature.py score "$out"/[ABC]-*-r[12].material
