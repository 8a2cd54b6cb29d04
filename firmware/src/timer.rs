//! The step timer's arming logic, over a small register interface: the
//! board implements [`TimerRegs`] on TIM2 (`firmware/board/src/clock.rs`),
//! the tests on a model of TIM2 with the real semantics
//! ([`crate::testkit::Tim2Model`]).
//!
//! TIM2 is a free-running 32-bit up-counter at [`TICK_HZ`](crate::hal::TICK_HZ)
//! (it wraps every 358 s), extended to 64 bits by counting update
//! (overflow) events; compare channels 1–3 schedule the next step of the
//! DISK, TRACK and TILT axes. What the hardware does, and what the code
//! below relies on:
//!
//! - A compare flag CCxIF is set when the counter *equals* CCRx — whether or
//!   not its interrupt is enabled, so after a long idle the flag of a
//!   channel is stale (the counter passed the old CCR). Writing a CCR the
//!   counter has already passed sets nothing: the event must be generated
//!   (EGR.CCxG).
//! - The status flags are **rc_w0**: writing 0 clears a flag, writing 1
//!   leaves it. A read-modify-write (`modify`) writes back 0 for a flag that
//!   was set between the read and the write and loses that event. Flags are
//!   cleared here by writing the complement of the one flag.
//! - The counter runs on while the code runs: a compare event or an
//!   overflow can happen between any two register accesses.
//!
//! Concurrency contract: [`arm`] and [`disarm`] run with the step interrupt
//! masked (inside a critical section in thread mode, or in the step
//! interrupt itself); [`take_due`] and [`arm`] run in the step interrupt;
//! [`now`] runs in either.

use core::sync::atomic::{AtomicU32, Ordering};

use crate::step::StepGenerator;

/// TIMx_SR.UIF / TIMx_DIER.UIE.
pub const UIF: u32 = 1 << 0;

/// TIMx_SR.CCxIF / TIMx_DIER.CCxIE of compare channel `ch` (0-based: the
/// hardware's channel `ch + 1`).
pub const fn ccif(ch: usize) -> u32 {
    1 << (ch + 1)
}

/// The registers of a general-purpose 32-bit timer that the step timer
/// uses (bit layouts as in the STM32 reference manual).
pub trait TimerRegs {
    /// TIMx_CNT.
    fn cnt(&mut self) -> u32;
    /// TIMx_SR.
    fn sr(&mut self) -> u32;
    /// Write TIMx_SR (rc_w0: a 0 bit clears its flag, a 1 bit leaves it).
    fn write_sr(&mut self, value: u32);
    /// TIMx_DIER.
    fn dier(&mut self) -> u32;
    /// Write TIMx_DIER.
    fn write_dier(&mut self, value: u32);
    /// Write TIMx_CCRx of channel `ch` (0-based).
    fn write_ccr(&mut self, ch: usize, value: u32);
    /// Write TIMx_EGR.CCxG of channel `ch`: sets its CCxIF now.
    fn generate(&mut self, ch: usize);
}

/// Ticks since start: the overflow count and the counter, with an overflow
/// that happened but is not yet counted by [`take_due`] (UIF still set)
/// added. Call with the step interrupt masked or from it.
pub fn now(r: &mut impl TimerRegs, overflows: &AtomicU32) -> u64 {
    let mut hi = overflows.load(Ordering::Relaxed) as u64;
    let lo = r.cnt();
    // UIF set: an overflow not yet counted. It belongs to this reading if
    // the counter has wrapped to a small value (read after the overflow);
    // a large value was read before it.
    if r.sr() & UIF != 0 && lo < 0x8000_0000 {
        hi += 1;
    }
    (hi << 32) | lo as u64
}

/// Schedule the step of channel `ch` at `tick`; a tick already past fires
/// at once. Call with the step interrupt masked or from it.
pub fn arm(r: &mut impl TimerRegs, overflows: &AtomicU32, ch: usize, tick: u64) {
    r.write_ccr(ch, tick as u32);
    // A stale flag (the counter passed the old CCR while idle) would fire
    // the step at once: clear it, and only it.
    r.write_sr(!ccif(ch));
    let dier = r.dier();
    r.write_dier(dier | ccif(ch));
    // Passed already (possibly while the flag was being cleared): generate
    // the event. If the counter matched after the clear as well, the flag
    // is simply set twice: one event.
    if tick <= now(r, overflows) {
        r.generate(ch);
    }
}

/// Cancel the scheduled step of channel `ch`. Call with the step interrupt
/// masked or from it.
pub fn disarm(r: &mut impl TimerRegs, ch: usize) {
    let dier = r.dier();
    r.write_dier(dier & !ccif(ch));
    r.write_sr(!ccif(ch));
}

/// In the step interrupt: count an overflow, and return the channels whose
/// step is due (their flags cleared, each alone).
pub fn take_due(r: &mut impl TimerRegs, overflows: &AtomicU32) -> [bool; 3] {
    let sr = r.sr();
    let dier = r.dier();
    if sr & UIF != 0 {
        r.write_sr(!UIF);
        overflows.fetch_add(1, Ordering::Relaxed);
    }
    let mut due = [false; 3];
    for (ch, d) in due.iter_mut().enumerate() {
        if sr & dier & ccif(ch) != 0 {
            r.write_sr(!ccif(ch));
            *d = true;
        }
    }
    due
}

/// Whether the step interrupt is pending: an enabled flag is set.
pub fn pending(r: &mut impl TimerRegs) -> bool {
    let sr = r.sr();
    let dier = r.dier();
    sr & dier & (UIF | ccif(0) | ccif(1) | ccif(2)) != 0
}

/// The STEP outputs as the step interrupt drives them.
pub trait StepPins {
    /// Raise the STEP line of channel `ch` (the caller lowers it after the
    /// pulse width).
    fn raise(&mut self, ch: usize);
}

/// **The step interrupt's work**, as the board runs it (with the step block
/// borrowed): count an overflow, and for every due channel raise its STEP
/// line, account for the step and arm the next one (or disarm at the end).
/// Returns the channels raised (a due channel whose generator was halted
/// meanwhile is disarmed, not pulsed). Holding the pulse and lowering the
/// lines are the caller's (they are time, not work).
pub fn on_interrupt(
    r: &mut impl TimerRegs,
    overflows: &AtomicU32,
    generators: &mut [StepGenerator; 3],
    pins: &mut impl StepPins,
) -> [bool; 3] {
    let mut due = take_due(r, overflows);
    for (ch, generator) in generators.iter_mut().enumerate() {
        if !due[ch] {
            continue;
        }
        // Halted between its compare event and this interrupt (thread mode
        // halts the generator, then disarms the timer): no pulse, or the
        // motor would make a step the count does not know.
        if generator.next_step_tick().is_none() {
            disarm(r, ch);
            due[ch] = false;
            continue;
        }
        pins.raise(ch);
        match generator.step() {
            Some(next) => arm(r, overflows, ch, next),
            None => disarm(r, ch),
        }
    }
    due
}
