//! TIM5 (32-bit) as the camera trigger's one-pulse timer: channel 2 drives
//! PA1 (AF2) and ends each exposure at its tick in hardware, whatever the
//! tasks are doing. The logic is `firmware::trigger`, shared with the host
//! tests that run it against a model of the timer; this file only maps its
//! [`PulseRegs`] onto TIM5's registers.

use embassy_stm32::pac;
use embassy_stm32::pac::timer::vals;
use firmware::hal::TICK_HZ;
use firmware::trigger::{self, OutputMode, PulseRegs};

/// Channel 2 (0-based 1): PA1.
const CH: usize = 1;

/// TIM5's registers.
struct Tim5;

impl PulseRegs for Tim5 {
    fn cr1(&mut self) -> u32 {
        pac::TIM5.cr1().read().0
    }
    fn write_cr1(&mut self, value: u32) {
        pac::TIM5.cr1().write_value(pac::timer::regs::Cr1Gp16(value));
    }
    fn write_arr(&mut self, value: u32) {
        pac::TIM5.arr().write_value(value);
    }
    fn write_ccr(&mut self, value: u32) {
        pac::TIM5.ccr(CH).write_value(value);
    }
    fn set_mode(&mut self, mode: OutputMode) {
        let ocm = match mode {
            OutputMode::ForceInactive => vals::Ocm::FORCE_INACTIVE,
            OutputMode::ForceActive => vals::Ocm::FORCE_ACTIVE,
            OutputMode::Pwm2 => vals::Ocm::PWM_MODE2,
        };
        pac::TIM5.ccmr_output(CH / 2).modify(|w| w.set_ocm(CH % 2, ocm));
    }
    fn generate_update(&mut self) {
        pac::TIM5.egr().write(|w| w.set_ug(true));
    }
}

/// Start TIM5 at `TICK_HZ` from a `timer_clock_hz` kernel clock, stopped,
/// its channel 2 output enabled and forced low (the pin must already be
/// TIM5_CH2's).
pub fn init(timer_clock_hz: u32) {
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM5>();
    let t = pac::TIM5;
    t.cr1().write_value(pac::timer::regs::Cr1Gp16(trigger::OPM));
    t.psc().write_value((timer_clock_hz / TICK_HZ - 1) as u16);
    t.ccmr_output(CH / 2).modify(|w| {
        w.set_ocpe(CH % 2, false); // CCR without preload
        w.set_ocm(CH % 2, vals::Ocm::FORCE_INACTIVE);
    });
    t.ccer().modify(|w| {
        w.set_ccp(CH, false); // active high
        w.set_cce(CH, true);
    });
    t.egr().write(|w| w.set_ug(true)); // load the prescaler
    t.sr().write_value(pac::timer::regs::SrGp16(0));
}

/// Raise the trigger for `ticks` ticks; the tick by which it has ended.
pub fn start(ticks: u64) -> u64 {
    trigger::start(&mut Tim5, ticks);
    // One tick for the first count, one for TIM5's prescaler phase against
    // TIM2's (the same kernel clock and prescaler, reset apart).
    crate::clock::now() + ticks.min(trigger::MAX_TICKS) + 2
}

/// Lower the trigger now (the end of a pulse already over, or an abort).
pub fn force_low() {
    trigger::force_low(&mut Tim5);
}

/// Hold the trigger high (not used by the controller, which only starts
/// timed pulses; kept so `set_trigger(true)` does what it says).
pub fn force_high() {
    Tim5.write_cr1(trigger::OPM);
    Tim5.set_mode(OutputMode::ForceActive);
}
