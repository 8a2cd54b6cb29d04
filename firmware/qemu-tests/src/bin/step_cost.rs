//! Step-interrupt cost, counted in instructions under QEMU
//! (`scripts/bench-step-isr.sh`): runs the body of the board's TIM2 handler
//! `STEPS` times — critical section, borrow of the shared step block, the
//! step generator's `step()`, the compare-register write and the STEP pin
//! writes — on a generator cruising at 64 000 steps/s. The script traces
//! two builds (STEPS = 0 and STEPS = 10000) and divides the difference.
#![no_std]
#![no_main]

#[path = "../common.rs"]
mod common;

use core::cell::RefCell;
use core::ptr::{addr_of_mut, write_volatile};

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use critical_section::Mutex;
use firmware::hal::TICK_HZ;
use firmware::step::{ONE_TICK, Segment, StepGenerator};
use protocol::Axis;

const STEPS: u32 = match option_env!("STEPS") {
    Some(s) => parse(s),
    None => 10_000,
};

const fn parse(s: &str) -> u32 {
    let b = s.as_bytes();
    let (mut i, mut v) = (0, 0u32);
    while i < b.len() {
        v = v * 10 + (b[i] - b'0') as u32;
        i += 1;
    }
    v
}

static STEP: Mutex<RefCell<Option<[StepGenerator; 3]>>> = Mutex::new(RefCell::new(None));
/// Stand-ins for TIM2 CCRx and the GPIO BSRR register.
static mut CCR: [u32; 3] = [0; 3];
static mut BSRR: u32 = 0;

/// The board's TIM2 handler body for one due axis (without the pulse-width
/// wait, which is time, not instructions).
#[inline(never)]
fn isr(due: [bool; 3]) {
    critical_section::with(|cs| {
        let mut step = STEP.borrow_ref_mut(cs);
        let Some(generators) = step.as_mut() else { return };
        for axis in Axis::ALL {
            if !due[axis.index()] {
                continue;
            }
            // SAFETY: single-threaded benchmark; volatile stands in for MMIO.
            unsafe { write_volatile(addr_of_mut!(BSRR), 1 << axis.index()) };
            let next = generators[axis.index()].step().unwrap_or(0);
            unsafe { write_volatile(addr_of_mut!(CCR[axis.index()]), next as u32) };
            unsafe { write_volatile(addr_of_mut!(BSRR), 1 << (16 + axis.index())) };
        }
    });
}

#[entry]
fn main() -> ! {
    // TRACK cruising at 64 000 steps/s: a segment as the planner makes them.
    let mut generators: [StepGenerator; 3] = Default::default();
    let track = &mut generators[Axis::Track.index()];
    let interval = (TICK_HZ as u64 * ONE_TICK) / 64_000;
    let _ = track.push(Segment { count: 1 << 20, interval, add: 0 });
    let _ = track.start(0, 1);
    critical_section::with(|cs| STEP.borrow(cs).replace(Some(generators)));
    for _ in 0..STEPS {
        isr(core::hint::black_box([false, true, false]));
    }
    hprintln!("ran {} step interrupts", STEPS);
    debug::exit(debug::EXIT_SUCCESS);
    #[allow(clippy::empty_loop)]
    loop {}
}
