//! The firmware core's self-test suite on a Cortex-M4F, under QEMU's
//! `mps2-an386` machine, reporting through semihosting:
//! `cargo run --release` here prints one line per test and "N passed, N failed",
//! and exits non-zero if any test failed.
#![no_std]
#![no_main]

mod common;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};

#[entry]
fn main() -> ! {
    hprintln!("running {} firmware self-tests on a Cortex-M4", firmware::selftest::TESTS.len());
    let (passed, failed) = firmware::selftest::run_all(|name, result| match result {
        Ok(()) => hprintln!("test {} ... ok", name),
        Err(why) => hprintln!("test {} ... FAILED: {}", name, why),
    });
    hprintln!("{} passed, {} failed", passed, failed);
    debug::exit(if failed == 0 { debug::EXIT_SUCCESS } else { debug::EXIT_FAILURE });
    #[allow(clippy::empty_loop)]
    loop {}
}
