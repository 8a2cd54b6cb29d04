#!/usr/bin/env bash
# Instructions per step in the step interrupt, counted under QEMU: traces every
# executed instruction of the `step_cost` program built for 0 and for 10 000
# step interrupts, and divides the difference (docs/benchmarks.md).
set -euo pipefail
cd "$(dirname "$0")/../firmware/qemu-tests"
N=10000
count() {
    STEPS=$1 cargo build --release --locked --bin step_cost -q
    local log
    log=$(mktemp)
    qemu-system-arm -cpu cortex-m4 -machine mps2-an386 -nographic \
        -semihosting-config enable=on,target=native -singlestep \
        -d exec,nochain -D "$log" \
        -kernel target/thumbv7em-none-eabihf/release/step_cost >/dev/null
    grep -c '^Trace' "$log"
    rm -f "$log"
}
base=$(count 0)
full=$(count $N)
awk -v b="$base" -v f="$full" -v n="$N" 'BEGIN {
    per = (f - b) / n
    printf "instructions per step interrupt: %.1f (traced %d vs %d instructions, %d steps)\n", per, f, b, n
}'
