#!/usr/bin/env bash
# The board's firmware as a raw image for the chip's ROM bootloader (USB DFU):
# builds the release ELF and copies it out with the toolchain's own
# llvm-objcopy (rustup component llvm-tools, in rust-toolchain.toml), to
# firmware/board/target/scanner-fw.bin. Then:
#   dfu-util -a 0 -s 0x08000000:leave -D firmware/board/target/scanner-fw.bin
set -euo pipefail
cd "$(dirname "$0")/../firmware/board"
cargo build --release --locked
host=$(rustc -vV | sed -n 's/^host: //p')
objcopy="$(rustc --print sysroot)/lib/rustlib/$host/bin/llvm-objcopy"
"$objcopy" -O binary target/thumbv7em-none-eabihf/release/scanner-fw target/scanner-fw.bin
size=$(stat -c %s target/scanner-fw.bin)
echo "firmware/board/target/scanner-fw.bin: $size bytes, for 0x08000000"
# The image must stay clear of the configuration's sectors 6–7 (0x08040000).
if [ "$size" -gt $((256 * 1024)) ]; then
    echo "larger than the program's 256 KiB: it would erase the saved configuration" >&2
    exit 1
fi
