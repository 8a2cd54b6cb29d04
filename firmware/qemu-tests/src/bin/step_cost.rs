//! Step-interrupt cost, counted in instructions under QEMU
//! (`scripts/bench-step-isr.sh`): runs the board's TIM2 handler work
//! `STEPS` times — critical section, borrow of the shared step block, and
//! `firmware::timer::on_interrupt` itself (take_due with its flag clears,
//! the STEP pin raise, the step generator's `step()`, `arm` with its CCR,
//! SR and DIER writes and `now`) — on a generator cruising at 64 000
//! steps/s, over volatile memory standing in for TIM2's registers and the
//! GPIO BSRR (the pulse-width wait and the pin lowering are time and two
//! stores, not counted). The script traces two builds (STEPS = 0 and
//! STEPS = 10000) and divides the difference.
#![no_std]
#![no_main]

#[path = "../common.rs"]
mod common;

use core::cell::RefCell;
use core::ptr::{addr_of, addr_of_mut, read_volatile, write_volatile};
use core::sync::atomic::AtomicU32;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use critical_section::Mutex;
use firmware::hal::TICK_HZ;
use firmware::step::{ONE_TICK, Segment, StepGenerator};
use firmware::timer::{self, StepPins, TimerRegs};
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
static OVERFLOWS: AtomicU32 = AtomicU32::new(0);

/// Stand-ins for TIM2's CNT, SR, DIER, CCR1–3 and the GPIO BSRR register.
static mut CNT: u32 = 0;
static mut SR: u32 = 0;
static mut DIER: u32 = 0;
static mut CCR: [u32; 3] = [0; 3];
static mut BSRR: u32 = 0;

/// TIM2 as volatile memory: each access one load or store, as on the chip.
/// The counter advances by one compare interval per read and the due
/// channel's flag is set again by `main`, so every interrupt finds work.
struct FakeTim2;

// SAFETY (all accesses): single-threaded benchmark; volatile stands in
// for MMIO.
impl TimerRegs for FakeTim2 {
    fn cnt(&mut self) -> u32 {
        unsafe { read_volatile(addr_of!(CNT)) }
    }
    fn sr(&mut self) -> u32 {
        unsafe { read_volatile(addr_of!(SR)) }
    }
    fn write_sr(&mut self, value: u32) {
        unsafe { write_volatile(addr_of_mut!(SR), read_volatile(addr_of!(SR)) & value) };
    }
    fn dier(&mut self) -> u32 {
        unsafe { read_volatile(addr_of!(DIER)) }
    }
    fn write_dier(&mut self, value: u32) {
        unsafe { write_volatile(addr_of_mut!(DIER), value) };
    }
    fn write_ccr(&mut self, ch: usize, value: u32) {
        unsafe { write_volatile(addr_of_mut!(CCR[ch]), value) };
    }
    fn generate(&mut self, ch: usize) {
        unsafe { write_volatile(addr_of_mut!(SR), read_volatile(addr_of!(SR)) | timer::ccif(ch)) };
    }
}

struct Pins;

impl StepPins for Pins {
    fn raise(&mut self, ch: usize) {
        unsafe { write_volatile(addr_of_mut!(BSRR), 1 << ch) };
    }
}

/// The board's TIM2 handler work for what is due (without the pulse-width
/// wait and the lowering store).
#[inline(never)]
fn isr() -> [bool; 3] {
    critical_section::with(|cs| {
        let mut step = STEP.borrow_ref_mut(cs);
        let Some(generators) = step.as_mut() else { return [false; 3] };
        timer::on_interrupt(&mut FakeTim2, &OVERFLOWS, generators, &mut Pins)
    })
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
    let ch = Axis::Track.index();
    // SAFETY: single-threaded benchmark.
    unsafe { write_volatile(addr_of_mut!(DIER), timer::UIF | timer::ccif(ch)) };
    for k in 0..STEPS {
        // The compare event: the counter at the armed tick, the flag set.
        unsafe {
            write_volatile(addr_of_mut!(CNT), (k as u64 * 188) as u32);
            write_volatile(addr_of_mut!(SR), timer::ccif(ch));
        }
        core::hint::black_box(isr());
    }
    hprintln!("ran {} step interrupts", STEPS);
    debug::exit(debug::EXIT_SUCCESS);
    #[allow(clippy::empty_loop)]
    loop {}
}
