//! The pin map of the default controller: an STM32F411CEU6 "Black Pill"
//! driving three STEP/DIR drivers (TMC2209 or DRV8825 class). Change pins
//! here and nowhere else; the README's wiring table mirrors this file.
//!
//! | signal | pin | notes |
//! |---|---|---|
//! | DISK STEP / DIR | PB12 / PB13 | |
//! | TRACK STEP / DIR | PB14 / PB15 | |
//! | TILT STEP / DIR | PA8 / PA9 | |
//! | drivers EN (all) | PA10 | active low |
//! | DISK index flag | PB3 | pull-up; active low (default) or high: `HomeSensors` |
//! | TRACK home switch | PB4 | pull-up; active low (default) or high: `HomeSensors` |
//! | TILT home switch | PB5 | pull-up; active low (default) or high: `HomeSensors` |
//! | emergency stop | PB8 | NC contact to GND, pull-up: open (or a cut wire) = stop |
//! | driver fault | PB9 | pull-up; active low (DRV8825 nFAULT, default) or high (TMC2209 DIAG): `BoardConfig` |
//! | camera trigger | PA1 | TIM5 CH2 one-pulse (`pulse.rs`), active high, to the opto-isolator |
//! | camera exposure strobe | PA2 | pull-up; active low (open collector, default) or high: `StrobeConfig`, watched only when enabled |
//! | light PWM | PB6 | TIM4 CH1, 20 kHz, active high |
//! | USB D− / D+ | PA11 / PA12 | CDC-ACM |
//! | (reserved: status LED) | PC13 | not configured by this firmware |
//! | SWD | PA13 / PA14 | debug probe |

use embassy_stm32::gpio::{Input, Level, Output, Pull, Speed};
use embassy_stm32::peripherals::{TIM4, TIM5};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::Ch2;
use embassy_stm32::timer::simple_pwm::{PwmPin, SimplePwm};
use embassy_stm32::{Peri, peripherals as p};
use firmware::hal::Inputs;

/// Shortest STEP high time, ns: 1 µs (TMC2209 needs 100 ns; set 1 900 for
/// the DRV8825's 1.9 µs). Converted to core cycles from the clock tree.
pub const STEP_PULSE_NS: u32 = 1_000;

/// STEP and DIR lines per axis, EN shared.
pub struct Motors {
    /// STEP lines, indexed by axis.
    pub step: [Output<'static>; 3],
    /// DIR lines, indexed by axis.
    pub dir: [Output<'static>; 3],
    /// Drivers' EN (active low).
    pub enable_n: Output<'static>,
}

/// Switches, E-stop, driver fault and camera strobe inputs.
pub struct Sensors {
    home: [Input<'static>; 3],
    estop: Input<'static>,
    driver_fault: Input<'static>,
    strobe: Input<'static>,
}

impl Sensors {
    /// Sample every input.
    pub fn read(&self) -> Inputs {
        Inputs {
            home_line: [self.home[0].is_high(), self.home[1].is_high(), self.home[2].is_high()],
            estop: self.estop.is_high(),
            driver_fault_line: self.driver_fault.is_high(),
            strobe_line: self.strobe.is_high(),
        }
    }
}

/// Camera trigger and light.
pub struct Camera {
    /// Trigger output (active high): PA1 as TIM5 CH2, driven by `pulse.rs`.
    /// Held, never read: dropping it would disconnect the pin from TIM5.
    #[allow(dead_code)]
    pub trigger: PwmPin<'static, TIM5, Ch2>,
    /// Light PWM (TIM4 CH1).
    pub light: SimplePwm<'static, TIM4>,
}

/// The pins the board uses, taken from the peripherals.
#[allow(clippy::too_many_arguments)]
pub struct Pins {
    pub pb12: Peri<'static, p::PB12>,
    pub pb13: Peri<'static, p::PB13>,
    pub pb14: Peri<'static, p::PB14>,
    pub pb15: Peri<'static, p::PB15>,
    pub pa8: Peri<'static, p::PA8>,
    pub pa9: Peri<'static, p::PA9>,
    pub pa10: Peri<'static, p::PA10>,
    pub pb3: Peri<'static, p::PB3>,
    pub pb4: Peri<'static, p::PB4>,
    pub pb5: Peri<'static, p::PB5>,
    pub pb8: Peri<'static, p::PB8>,
    pub pb9: Peri<'static, p::PB9>,
    pub pa1: Peri<'static, p::PA1>,
    pub pa2: Peri<'static, p::PA2>,
    pub pb6: Peri<'static, p::PB6>,
    pub tim4: Peri<'static, p::TIM4>,
    /// Owned so nothing else takes the trigger's timer.
    pub tim5: Peri<'static, p::TIM5>,
}

/// Configure every pin.
pub fn init(pins: Pins) -> (Motors, Sensors, Camera) {
    let out = |pin: Peri<'static, embassy_stm32::gpio::AnyPin>| {
        Output::new(pin, Level::Low, Speed::VeryHigh)
    };
    let motors = Motors {
        step: [out(pins.pb12.into()), out(pins.pb14.into()), out(pins.pa8.into())],
        dir: [out(pins.pb13.into()), out(pins.pb15.into()), out(pins.pa9.into())],
        enable_n: Output::new(pins.pa10, Level::High, Speed::Low),
    };
    let sensors = Sensors {
        home: [
            Input::new(pins.pb3, Pull::Up),
            Input::new(pins.pb4, Pull::Up),
            Input::new(pins.pb5, Pull::Up),
        ],
        estop: Input::new(pins.pb8, Pull::Up),
        driver_fault: Input::new(pins.pb9, Pull::Up),
        strobe: Input::new(pins.pa2, Pull::Up),
    };
    let mut light = SimplePwm::new(
        pins.tim4,
        Some(PwmPin::new(pins.pb6, embassy_stm32::gpio::OutputType::PushPull)),
        None,
        None,
        None,
        Hertz(protocol::LIGHT_PWM_HZ),
        Default::default(),
    );
    light.ch1().set_duty_cycle_fully_off();
    light.ch1().enable();
    // TIM5 first, its output forced low, then the pin handed to it (a
    // high-impedance input from reset until here, as before).
    let _ = pins.tim5;
    crate::pulse::init(embassy_stm32::rcc::frequency::<TIM5>().0);
    let trigger = PwmPin::new(pins.pa1, embassy_stm32::gpio::OutputType::PushPull);
    let camera = Camera { trigger, light };
    (motors, sensors, camera)
}
