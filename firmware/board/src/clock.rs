//! TIM2 (32-bit) as the step timer: a free-running counter at
//! [`TICK_HZ`](firmware::hal::TICK_HZ) extended to 64 bits by counting
//! overflows, and compare channels 1–3 scheduling the next step of the DISK,
//! TRACK and TILT axes. Step pulses come from this hardware timer's compare
//! interrupts, never from software delays.

use core::sync::atomic::{AtomicU32, Ordering};

use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals;
use firmware::hal::TICK_HZ;
use protocol::Axis;

static OVERFLOWS: AtomicU32 = AtomicU32::new(0);

fn tim() -> pac::timer::TimGp32 {
    pac::TIM2
}

/// Start TIM2 at `TICK_HZ` from a `timer_clock_hz` kernel clock.
pub fn start(timer_clock_hz: u32) {
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM2>();
    let t = tim();
    t.cr1().modify(|w| w.set_cen(false));
    t.psc().write_value((timer_clock_hz / TICK_HZ - 1) as u16);
    t.arr().write_value(u32::MAX);
    t.egr().write(|w| w.set_ug(true));
    t.sr().write_value(pac::timer::regs::SrGp16(0));
    for ch in 0..3 {
        // Frozen output-compare: the channels only raise interrupts.
        t.ccmr_output(ch / 2).modify(|w| w.set_ocm(ch % 2, vals::Ocm::FROZEN));
    }
    t.dier().modify(|w| w.set_uie(true));
    t.cr1().modify(|w| w.set_cen(true));
    // SAFETY: the TIM2 handler below only touches TIM2, the step pins and the
    // controller behind a critical section.
    unsafe { cortex_m::peripheral::NVIC::unmask(pac::Interrupt::TIM2) };
}

/// Ticks since boot. Call with interrupts enabled or inside a critical section.
pub fn now() -> u64 {
    critical_section::with(|_| {
        let t = tim();
        let mut hi = OVERFLOWS.load(Ordering::Relaxed);
        let lo = t.cnt().read();
        // An overflow that happened but is not yet counted by the handler.
        if t.sr().read().uif() && lo < 0x8000_0000 {
            hi += 1;
        }
        ((hi as u64) << 32) | lo as u64
    })
}

/// Schedule the step of `axis` at `tick`; a time already past fires at once.
pub fn arm(axis: Axis, tick: u64) {
    let t = tim();
    let ch = axis.index();
    t.ccr(ch).write_value(tick as u32);
    t.dier().modify(|w| w.set_ccie(ch, true));
    if tick <= now() {
        t.egr().write(|w| w.set_ccg(ch, true));
    }
}

/// Cancel the scheduled step of `axis`.
pub fn disarm(axis: Axis) {
    let t = tim();
    t.dier().modify(|w| w.set_ccie(axis.index(), false));
    t.sr().modify(|w| w.set_ccif(axis.index(), false));
}

/// Pending compare events (and overflow bookkeeping), for the handler.
pub fn take_due() -> [bool; 3] {
    let t = tim();
    let sr = t.sr().read();
    let dier = t.dier().read();
    if sr.uif() {
        t.sr().modify(|w| w.set_uif(false));
        OVERFLOWS.fetch_add(1, Ordering::Relaxed);
    }
    let mut due = [false; 3];
    for (ch, d) in due.iter_mut().enumerate() {
        if sr.ccif(ch) && dier.ccie(ch) {
            t.sr().modify(|w| w.set_ccif(ch, false));
            *d = true;
        }
    }
    due
}
