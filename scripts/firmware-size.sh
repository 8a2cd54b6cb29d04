#!/usr/bin/env bash
# Builds the real firmware ELF (release, thumbv7em-none-eabihf) and fails if
# flash use (.vector_table + .text + .rodata + .data) exceeds 128 KiB or
# static RAM (.data + .bss + .uninit) exceeds 48 KiB. Prints both figures.
set -euo pipefail
cd "$(dirname "$0")/../firmware/board"
cargo build --release --locked
elf=target/thumbv7em-none-eabihf/release/scanner-fw
size_tool=$(find "$(rustc --print sysroot)/lib/rustlib" -name llvm-size -type f | head -n1)
if [ -z "$size_tool" ]; then
    echo "llvm-size not found: the llvm-tools component is missing (scripts/setup.sh installs it)" >&2
    exit 1
fi
read -r flash ram < <("$size_tool" -A "$elf" | awk '
    $1 == ".vector_table" || $1 == ".text" || $1 == ".rodata" { flash += $2 }
    $1 == ".data" { flash += $2; ram += $2 }
    $1 == ".bss" || $1 == ".uninit" { ram += $2 }
    END { print flash, ram }')
awk -v f="$flash" -v r="$ram" 'BEGIN {
    printf "firmware flash use: %d bytes (%.1f KiB of 128 KiB)\n", f, f / 1024
    printf "firmware static RAM: %d bytes (%.1f KiB of 48 KiB)\n", r, r / 1024 }'
fail=0
[ "$flash" -le $((128 * 1024)) ] || { echo "FAIL: flash use over 128 KiB" >&2; fail=1; }
[ "$ram" -le $((48 * 1024)) ] || { echo "FAIL: static RAM over 48 KiB" >&2; fail=1; }
exit $fail
