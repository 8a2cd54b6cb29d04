//! The firmware core's self-test suite on a Cortex-M4F, under QEMU's
//! `mps2-an386` machine, reporting through semihosting:
//! `cargo run --release` here prints one line per test, the stack it used
//! and "N passed, N failed", and exits non-zero if any test failed or the
//! stack outgrew what the scanner's board has. With the `black-pill`
//! feature it is linked for the board itself, and `probe-rs run --chip
//! STM32F411CEUx` runs it there (README, "Self-tests on the board").
#![no_std]
#![no_main]

mod common;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};

#[entry]
fn main() -> ! {
    stack::paint();
    hprintln!("running {} firmware self-tests on a Cortex-M4", firmware::selftest::TESTS.len());
    let (passed, mut failed) = firmware::selftest::run_all(|name, result| match result {
        Ok(()) => hprintln!("test {} ... ok", name),
        Err(why) => hprintln!("test {} ... FAILED: {}", name, why),
    });
    // The suite must also run on the scanner's board, with its 128 KiB.
    let used = stack::used();
    let budget = stack::BOARD_STACK_BYTES;
    if used > budget {
        hprintln!("stack: {} bytes used, more than the board's {} allow: FAILED", used, budget);
        failed += 1;
    } else {
        hprintln!("stack: {} bytes used (the board allows {})", used, budget);
    }
    hprintln!("{} passed, {} failed", passed, failed);
    debug::exit(if failed == 0 { debug::EXIT_SUCCESS } else { debug::EXIT_FAILURE });
    #[allow(clippy::empty_loop)]
    loop {}
}

/// How deep the stack went: the free RAM below the stack is painted with a
/// pattern at the start, and the deepest word no longer holding it marks
/// the most the stack used. The scanner's board has 128 KiB of RAM, where
/// QEMU's machine has 4 MiB: [`BOARD_STACK_BYTES`] is what the self-tests
/// may use so that they run on the board too (`black-pill` feature).
pub mod stack {
    use core::ptr::{addr_of, read_volatile, write_volatile};

    /// What the board leaves the stack: 128 KiB of RAM less 8 KiB for the
    /// program's statics and a margin.
    pub const BOARD_STACK_BYTES: usize = 120 * 1024;

    const PAINT: u32 = 0x5CA7_57AC;
    /// Left unpainted below the stack pointer at painting: the painter's
    /// own frame.
    const MARGIN: usize = 256;

    unsafe extern "C" {
        static _stack_start: u32;
        static __sheap: u32;
    }

    fn bounds() -> (usize, usize) {
        // Only the symbols' addresses are taken (cortex-m-rt's linker
        // script defines both: the top of the stack, the end of the
        // statics).
        (addr_of!(__sheap) as usize, addr_of!(_stack_start) as usize)
    }

    /// Paint the free RAM between the statics and the stack in use.
    pub fn paint() {
        let (bottom, _) = bounds();
        let sp = cortex_m::register::msp::read() as usize;
        let mut p = bottom;
        while p + 4 <= sp - MARGIN {
            // SAFETY: RAM between the statics' end and below the live
            // stack: no object lives there.
            unsafe { write_volatile(p as *mut u32, PAINT) };
            p += 4;
        }
    }

    /// The most bytes the stack has used since [`paint`].
    pub fn used() -> usize {
        let (bottom, top) = bounds();
        let mut p = bottom;
        // SAFETY: reads of the RAM painted above.
        while p < top && unsafe { read_volatile(p as *const u32) } == PAINT {
            p += 4;
        }
        top - p
    }
}
