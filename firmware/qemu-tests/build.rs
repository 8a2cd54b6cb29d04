//! Put memory.x where the linker finds it (and not in this folder, which
//! the linker searches first): QEMU's mps2-an386 by default,
//! the scanner's STM32F411 with the `black-pill` feature.
use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap());
    let memory: &[u8] = if env::var_os("CARGO_FEATURE_BLACK_PILL").is_some() {
        include_bytes!("memory-black-pill.x")
    } else {
        include_bytes!("memory-mps2.x")
    };
    fs::write(out.join("memory.x"), memory).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory-mps2.x");
    println!("cargo:rerun-if-changed=memory-black-pill.x");
}
