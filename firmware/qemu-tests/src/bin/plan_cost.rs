//! Planner cost on the Cortex-M4 (soft-float f64), counted in instructions
//! under QEMU with `-icount shift=0` (virtual time = 1 ns per instruction),
//! read through SysTick running at the mps2-an386 core clock (25 MHz, i.e.
//! one tick per 40 instructions). `scripts/bench-planner-m4.sh` runs it.
#![no_std]
#![no_main]

#[path = "../common.rs"]
mod common;

use cortex_m::peripheral::syst::SystClkSource;
use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use firmware::hal::TICK_HZ;
use firmware::planner::{Profile, SegmentPlanner};

/// mps2-an386 core clock.
const CORE_HZ: u64 = 25_000_000;

#[entry]
fn main() -> ! {
    let mut core = cortex_m::Peripherals::take().unwrap();
    core.SYST.set_clock_source(SystClkSource::Core);
    core.SYST.set_reload(0x00FF_FFFF);
    core.SYST.clear_current();
    core.SYST.enable_counter();
    let cases = [
        ("track 320000 steps", 320_000u32, 64_000.0, 320_000.0),
        ("disk 8000 steps", 8_000, 4_000.0, 8_000.0),
        ("tilt 18666 steps", 18_666, 5_333.0, 16_000.0),
    ];
    for (name, n, v, a) in cases {
        let start = cortex_m::peripheral::SYST::get_current();
        let mut planner = SegmentPlanner::new(Profile::trapezoid(n, 0.0, v, a), TICK_HZ);
        let mut segments = 0u32;
        while let Some(s) = planner.next_segment() {
            core::hint::black_box(s);
            segments += 1;
        }
        let end = cortex_m::peripheral::SYST::get_current();
        let ticks = (start.wrapping_sub(end) & 0x00FF_FFFF) as u64;
        let instructions = ticks * 1_000_000_000 / CORE_HZ;
        hprintln!(
            "{}: {} segments, {} instructions, {} per segment",
            name,
            segments,
            instructions,
            instructions / segments as u64
        );
    }
    debug::exit(debug::EXIT_SUCCESS);
    #[allow(clippy::empty_loop)]
    loop {}
}
