//! TIM2 (32-bit) as the step timer: a free-running counter at
//! [`TICK_HZ`](firmware::hal::TICK_HZ) extended to 64 bits by counting
//! overflows, and compare channels 1–3 scheduling the next step of the DISK,
//! TRACK and TILT axes. Step pulses come from this hardware timer's compare
//! interrupts, never from software delays.
//!
//! The arming logic is `firmware::timer`, shared with the host tests that
//! run it against a model of TIM2 (rc_w0 flags, compare events between any
//! two register accesses); this file only maps its [`TimerRegs`] onto the
//! registers and keeps `arm`/`disarm` inside a critical section.

use core::sync::atomic::AtomicU32;

use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals;
use firmware::hal::TICK_HZ;
use firmware::timer::{self, TimerRegs};
use protocol::Axis;

static OVERFLOWS: AtomicU32 = AtomicU32::new(0);

/// TIM2's registers.
struct Tim2;

impl TimerRegs for Tim2 {
    fn cnt(&mut self) -> u32 {
        pac::TIM2.cnt().read()
    }
    fn sr(&mut self) -> u32 {
        pac::TIM2.sr().read().0
    }
    fn write_sr(&mut self, value: u32) {
        // rc_w0: a plain write, never a read-modify-write.
        pac::TIM2.sr().write_value(pac::timer::regs::SrGp16(value));
    }
    fn dier(&mut self) -> u32 {
        pac::TIM2.dier().read().0
    }
    fn write_dier(&mut self, value: u32) {
        pac::TIM2.dier().write_value(pac::timer::regs::DierGp16(value));
    }
    fn write_ccr(&mut self, ch: usize, value: u32) {
        pac::TIM2.ccr(ch).write_value(value);
    }
    fn generate(&mut self, ch: usize) {
        pac::TIM2.egr().write(|w| w.set_ccg(ch, true));
    }
}

/// Start TIM2 at `TICK_HZ` from a `timer_clock_hz` kernel clock.
pub fn start(timer_clock_hz: u32) {
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM2>();
    let t = pac::TIM2;
    t.cr1().modify(|w| w.set_cen(false));
    t.psc().write_value((timer_clock_hz / TICK_HZ - 1) as u16);
    t.arr().write_value(u32::MAX);
    t.egr().write(|w| w.set_ug(true));
    t.sr().write_value(pac::timer::regs::SrGp16(0));
    for ch in 0..3 {
        // Frozen output-compare: the channels only raise interrupts.
        t.ccmr_output(ch / 2).modify(|w| w.set_ocm(ch % 2, vals::Ocm::FROZEN));
    }
    t.dier().write_value(pac::timer::regs::DierGp16(timer::UIF));
    t.cr1().modify(|w| w.set_cen(true));
    // SAFETY: the TIM2 handler only touches TIM2, the step pins and the
    // step generators (behind a critical section).
    unsafe { cortex_m::peripheral::NVIC::unmask(pac::Interrupt::TIM2) };
}

/// Ticks since boot.
pub fn now() -> u64 {
    critical_section::with(|_| timer::now(&mut Tim2, &OVERFLOWS))
}

/// Schedule the step of `axis` at `tick`; a time already past fires at once.
pub fn arm(axis: Axis, tick: u64) {
    critical_section::with(|_| timer::arm(&mut Tim2, &OVERFLOWS, axis.index(), tick));
}

/// Cancel the scheduled step of `axis`.
pub fn disarm(axis: Axis) {
    critical_section::with(|_| timer::disarm(&mut Tim2, axis.index()));
}

/// The step interrupt's work on TIM2 (`firmware::timer::on_interrupt`):
/// call with the step block borrowed (inside its critical section).
pub fn on_interrupt(
    generators: &mut [firmware::step::StepGenerator; 3],
    pins: &mut impl timer::StepPins,
) -> [bool; 3] {
    timer::on_interrupt(&mut Tim2, &OVERFLOWS, generators, pins)
}
