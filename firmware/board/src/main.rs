//! Scanner controller firmware for the STM32F411CEU6.
//!
//! This file only initialises the chip, binds interrupts and spawns tasks; all
//! behaviour lives in the `firmware` library ([`firmware::Controller`]).
//!
//! - TIM2 compare interrupts run each axis' step generator (`clock.rs`). The
//!   generators and STEP pins are the only state the interrupt shares, in
//!   [`STEP`]; the controller plans outside that lock, so planning (soft
//!   f64 on the M4) never delays a step.
//! - TIM5 ends each camera trigger pulse in hardware (`pulse.rs`, one-pulse
//!   mode on PA1), so an exposure lasts exactly the ticks asked for.
//! - The control task polls the inputs every 200 µs (5 kHz) and the
//!   controller's timers, feeds the watchdog and queues outgoing frames;
//!   it also wakes when a running exposure has ended, to turn the light
//!   back and report without waiting for the next poll.
//! - The USB task serves CDC-ACM; received bytes go straight to the
//!   controller, replies and events go back through a pipe.
#![no_std]
#![no_main]

mod board;
mod clock;
mod pulse;
mod storage;

use core::cell::RefCell;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use critical_section::Mutex;
use defmt::{info, unwrap, warn};
use embassy_executor::Spawner;
use embassy_futures::join::join4;
use embassy_futures::select::{Either, select};
use embassy_stm32::flash::Flash;
use embassy_stm32::gpio::Output;
use embassy_stm32::peripherals::USB_OTG_FS;
use embassy_stm32::time::Hertz;
use embassy_stm32::usb::{self, Driver};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{Config, bind_interrupts, interrupt, pac};
use embassy_sync::blocking_mutex::ThreadModeMutex;
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::pipe::Pipe;
use embassy_time::{Duration, Ticker, Timer};
use embassy_usb::class::cdc_acm::CdcAcmClass;
use embassy_usb::driver::{Endpoint, EndpointIn, EndpointOut};
use firmware::Controller;
use firmware::config::PERSISTED_MAX_LEN;
use firmware::hal::{BootInfo, Hardware, StorageError};
use firmware::step::StepGenerator;
use protocol::{Axis, BOARD_STM32F411_BLACKPILL, Capabilities, ResetReason};
use static_cell::StaticCell;
use {defmt_rtt as _, panic_probe as _};

bind_interrupts!(struct Irqs {
    OTG_FS => usb::InterruptHandler<USB_OTG_FS>;
});

/// The controller and the hardware it drives. Only thread-mode tasks touch
/// it (they never preempt each other), so it needs no critical section.
struct Machine {
    controller: Controller,
    hw: BoardHw,
}

static MACHINE: ThreadModeMutex<RefCell<Option<Machine>>> =
    ThreadModeMutex::new(RefCell::new(None));

/// What the step interrupt owns: the step generators and the STEP lines.
struct StepBlock {
    generators: [StepGenerator; 3],
    pins: [Output<'static>; 3],
}

static STEP: Mutex<RefCell<Option<StepBlock>>> = Mutex::new(RefCell::new(None));

/// The STEP pins for the step interrupt's work.
struct StepLines<'a>(&'a mut [Output<'static>; 3]);

impl firmware::timer::StepPins for StepLines<'_> {
    fn raise(&mut self, ch: usize) {
        self.0[ch].set_high();
    }
}

/// Frames for the host, written by whoever holds the machine, read by USB.
static TX: Pipe<CriticalSectionRawMutex, { firmware::hal::USB_TX_QUEUE }> = Pipe::new();

/// Whether the host last spoke on the vendor-class bulk interface (else on
/// the CDC-ACM one): replies and events go where the host is listening.
static VENDOR_ACTIVE: AtomicBool = AtomicBool::new(false);

/// Whether the host has sent anything since boot, on either interface.
static HOST_SPOKE: AtomicBool = AtomicBool::new(false);

/// How long a packet may wait for the host to read it before it is dropped
/// (the host retransmits; a host that switched interfaces must not stall
/// the other one).
const TX_TIMEOUT: Duration = Duration::from_millis(firmware::hal::USB_TX_TIMEOUT_MS);

fn send(frame: &[u8]) {
    // Whole frames only, across the ring's end too; one that does not fit
    // is dropped (the host recovers replies by retransmitting, events by
    // status / GetLastTrigger).
    if !firmware::usb::queue_whole(&TX, frame) {
        warn!("{} bytes for the host dropped: the queue is full", frame.len());
    }
}

struct BoardHw {
    dir: [Output<'static>; 3],
    enable_n: Output<'static>,
    camera: board::Camera,
    store: storage::Store,
}

impl Hardware for BoardHw {
    fn with_stepper<R>(&mut self, axis: Axis, f: impl FnOnce(&mut StepGenerator) -> R) -> R {
        critical_section::with(|cs| {
            let mut step = STEP.borrow_ref_mut(cs);
            let block = step.as_mut().expect("step block installed before the controller runs");
            f(&mut block.generators[axis.index()])
        })
    }
    fn set_direction(&mut self, axis: Axis, positive: bool) {
        self.dir[axis.index()].set_level(positive.into());
    }
    fn arm_step_timer(&mut self, axis: Axis, tick: u64) {
        clock::arm(axis, tick);
    }
    fn disarm_step_timer(&mut self, axis: Axis) {
        clock::disarm(axis);
    }
    fn set_drivers_enabled(&mut self, enabled: bool) {
        self.enable_n.set_level((!enabled).into());
    }
    fn set_light(&mut self, duty_permille: u16) {
        let mut ch = self.camera.light.ch1();
        ch.set_duty_cycle_fraction(duty_permille.min(1000) as u32, 1000);
    }
    fn set_trigger(&mut self, high: bool) {
        if high { pulse::force_high() } else { pulse::force_low() }
    }
    fn start_trigger_pulse(&mut self, ticks: u64) -> Option<u64> {
        Some(pulse::start(ticks))
    }
    fn save_config(&mut self, blob: &[u8]) -> Result<(), StorageError> {
        self.store.save_config(blob)
    }
}

/// The boot counter in RAM (see `main`): in `.uninit`, not zeroed at reset.
#[unsafe(link_section = ".uninit.RAM_BOOTS")]
static mut RAM_BOOTS: core::mem::MaybeUninit<u32> = core::mem::MaybeUninit::uninit();

/// The ROM bootloader's request across the reset
/// ([`firmware::bootloader`]): in `.uninit`, not zeroed at reset.
#[unsafe(link_section = ".uninit.RAM_BOOTLOADER")]
static mut RAM_BOOTLOADER: core::mem::MaybeUninit<u32> = core::mem::MaybeUninit::uninit();

/// The core's view of the RCC, SYSCFG and SCB registers, for
/// [`firmware::bootloader::map_system_memory`].
struct Mmio;

impl firmware::bootloader::Registers for Mmio {
    fn modify(&mut self, address: u32, clear: u32, set: u32) {
        let register = address as *mut u32;
        // SAFETY: the addresses are the STM32F4's RCC_APB2ENR,
        // SYSCFG_MEMRMP and the core's VTOR, written before anything else
        // runs.
        unsafe { register.write_volatile((register.read_volatile() & !clear) | set) }
    }
}

/// If the host asked for it before the reset that started this boot, leave
/// for the ROM bootloader (USB DFU) — first, before any clock or
/// peripheral is touched, as the ROM expects the chip.
fn enter_bootloader_if_asked() {
    // SAFETY: read and written once, here, before anything else runs.
    let asked = unsafe {
        let mark = core::ptr::addr_of_mut!(RAM_BOOTLOADER).cast::<u32>();
        let mut value = core::ptr::read_volatile(mark);
        let asked = firmware::bootloader::take_request(&mut value);
        core::ptr::write_volatile(mark, value);
        asked
    };
    if asked {
        firmware::bootloader::map_system_memory(&mut Mmio);
        // SAFETY: the system memory holds the ROM's vector table; nothing
        // of the firmware runs after this.
        unsafe { cortex_m::asm::bootload(firmware::bootloader::SYSTEM_MEMORY as *const u32) }
    }
}

/// Leave a mark for the next boot to go to the ROM bootloader, and reset.
fn reset_into_bootloader() -> ! {
    // SAFETY: a plain store to the RAM word only this and
    // `enter_bootloader_if_asked` touch.
    unsafe {
        let mark = core::ptr::addr_of_mut!(RAM_BOOTLOADER).cast::<u32>();
        core::ptr::write_volatile(mark, firmware::bootloader::REQUEST_MARK);
    }
    cortex_m::peripheral::SCB::sys_reset()
}

/// Independent watchdog period, µs at the nominal 32 kHz LSI.
const WATCHDOG_US: u32 = 8_000_000;

/// STEP high time in core cycles, from the clock tree at start-up
/// ([`board::STEP_PULSE_NS`] at HCLK).
static STEP_PULSE_CYCLES: AtomicU32 = AtomicU32::new(u32::MAX);

/// The step interrupt (the highest priority: USB and the time driver
/// cannot delay a step). Raises the STEP line of every due axis and
/// advances its generator under a short critical section, holds the pulse
/// with interrupts enabled, then lowers the lines.
#[interrupt]
fn TIM2() {
    let raised = critical_section::with(|cs| {
        let mut step = STEP.borrow_ref_mut(cs);
        let Some(block) = step.as_mut() else { return [false; 3] };
        let StepBlock { generators, pins } = block;
        clock::on_interrupt(generators, &mut StepLines(pins))
    });
    if !raised.iter().any(|r| *r) {
        return;
    }
    let start = cortex_m::peripheral::DWT::cycle_count();
    let width = STEP_PULSE_CYCLES.load(Ordering::Relaxed);
    while cortex_m::peripheral::DWT::cycle_count().wrapping_sub(start) < width {}
    critical_section::with(|cs| {
        if let Some(block) = STEP.borrow_ref_mut(cs).as_mut() {
            for axis in Axis::ALL.into_iter().filter(|a| raised[a.index()]) {
                block.pins[axis.index()].set_low();
            }
        }
    });
}

fn reset_reason() -> ResetReason {
    let csr = pac::RCC.csr().read();
    let reason = if csr.wdgrstf() || csr.wwdgrstf() {
        ResetReason::Watchdog
    } else if csr.sftrstf() {
        ResetReason::Software
    } else if csr.porrstf() || csr.borrstf() {
        ResetReason::PowerOn
    } else if csr.padrstf() {
        ResetReason::Pin
    } else {
        ResetReason::Other
    };
    pac::RCC.csr().modify(|w| w.set_rmvf(true));
    reason
}

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    enter_bootloader_if_asked();
    // 25 MHz HSE → PLL 96 MHz SYSCLK and exactly 48 MHz for USB.
    let mut config = Config::default();
    {
        use embassy_stm32::rcc::*;
        config.rcc.hse = Some(Hse { freq: Hertz(25_000_000), mode: HseMode::Oscillator });
        config.rcc.pll_src = PllSource::HSE;
        config.rcc.pll = Some(Pll {
            prediv: PllPreDiv::DIV25,
            mul: PllMul::MUL192,
            divp: Some(PllPDiv::DIV2),
            divq: Some(PllQDiv::DIV4),
            divr: None,
        });
        config.rcc.ahb_pre = AHBPrescaler::DIV1;
        config.rcc.apb1_pre = APBPrescaler::DIV2;
        config.rcc.apb2_pre = APBPrescaler::DIV1;
        config.rcc.sys = Sysclk::PLL1_P;
        config.rcc.mux.clk48sel = mux::Clk48sel::PLL1_Q;
    }
    let p = embassy_stm32::init(config);
    let clocks = *embassy_stm32::rcc::clocks(&p.RCC);
    let reason = reset_reason();
    info!("scanner firmware {} booting ({})", env!("CARGO_PKG_VERSION"), reason);

    let mut core = unwrap!(cortex_m::Peripherals::take());
    core.DCB.enable_trace();
    core.DWT.enable_cycle_counter();

    // Flash work first (a sector erase may take 4 s), then the watchdog.
    let mut store = storage::Store::new(Flash::new_blocking(p.FLASH));
    let (boot_count, storage_failed) = match store.next_boot_count() {
        Ok(n) => (n, false),
        Err(n) => {
            warn!("cannot store the boot counter: flash storage failed");
            (n, true)
        }
    };
    let device_id = embassy_stm32::uid::uid();
    // The boot id changes every boot even if the flash counter cannot be
    // stored: a RAM counter outside the zeroed sections survives a warm
    // reset (+1 per boot) and is arbitrary after power-up.
    // SAFETY: read and written once, here, before anything else runs.
    let ram_boots = unsafe {
        let boots = core::ptr::addr_of_mut!(RAM_BOOTS).cast::<u32>();
        let n = core::ptr::read_volatile(boots).wrapping_add(1);
        core::ptr::write_volatile(boots, n);
        n
    };
    let mut blob = [0u8; PERSISTED_MAX_LEN];
    let saved = store.load_config(&mut blob).map(|n| &blob[..n]);
    // 8 s nominal (LSI 32 kHz): at least 5.4 s at the fastest LSI (47 kHz),
    // over a 4 s worst-case sector erase (`SaveConfig`); at most 15 s at
    // the slowest (17 kHz). A hung thread mode stops stepping by itself: the
    // step queues run dry within milliseconds.
    let mut watchdog = IndependentWatchdog::new(p.IWDG, WATCHDOG_US);
    watchdog.unleash();
    let boot = BootInfo {
        boot_id: firmware::hal::boot_id(&device_id, boot_count, ram_boots),
        reason,
        device_id,
        board: BOARD_STM32F411_BLACKPILL,
        capabilities: Capabilities::PERSISTENT_CONFIG
            .union(Capabilities::PWM_LIGHT)
            .union(Capabilities::LOG_EVENTS)
            // PA2 is the strobe input; `SetStrobe` says whether a camera's
            // strobe is wired to it.
            .union(Capabilities::EXPOSURE_STROBE)
            .union(Capabilities::SYSTEM_BOOTLOADER),
        storage_failed,
    };
    let controller = Controller::new(boot, saved);

    let (motors, sensors, camera) = board::init(board::Pins {
        pb12: p.PB12,
        pb13: p.PB13,
        pb14: p.PB14,
        pb15: p.PB15,
        pa8: p.PA8,
        pa9: p.PA9,
        pa10: p.PA10,
        pb3: p.PB3,
        pb4: p.PB4,
        pb5: p.PB5,
        pb8: p.PB8,
        pb9: p.PB9,
        pa1: p.PA1,
        pa2: p.PA2,
        pb6: p.PB6,
        tim4: p.TIM4,
        tim5: p.TIM5,
    });
    let board::Motors { step, dir, enable_n } = motors;
    critical_section::with(|cs| {
        STEP.borrow(cs).replace(Some(StepBlock { generators: Default::default(), pins: step }));
    });
    MACHINE
        .borrow()
        .replace(Some(Machine { controller, hw: BoardHw { dir, enable_n, camera, store } }));
    // The step timer from its kernel clock (APB1 at 48 MHz: its timers run
    // at 96 MHz), the pulse width from the core clock, as configured above.
    let core_hz = unwrap!(clocks.hclk1.to_hertz()).0;
    STEP_PULSE_CYCLES.store(
        (core_hz as u64 * board::STEP_PULSE_NS as u64).div_ceil(1_000_000_000) as u32,
        Ordering::Relaxed,
    );
    clock::start(embassy_stm32::rcc::frequency::<embassy_stm32::peripherals::TIM2>().0);
    // TIM2 above everything else (every other interrupt is at the default
    // P0 until here: USB, the time driver's TIM3).
    {
        use embassy_stm32::interrupt::{InterruptExt, Priority};
        interrupt::OTG_FS.set_priority(Priority::P2);
        interrupt::TIM3.set_priority(Priority::P2);
        interrupt::TIM2.set_priority(Priority::P0);
    }

    // USB: CDC-ACM and a vendor-class bulk interface carrying the same
    // framed protocol, with MS OS 2.0 descriptors for WinUSB — the shared
    // `firmware::usb` device (descriptors tested on the host). The F411's
    // OTG_FS has 4 IN and 4 OUT endpoints and 320 FIFO words (≈ 112 used);
    // EP_OUT holds the 3 × 64-byte OUT packets.
    static EP_OUT: StaticCell<[u8; 256]> = StaticCell::new();
    let mut usb_config = usb::Config::default();
    usb_config.vbus_detection = false;
    let driver =
        Driver::new_fs(p.USB_OTG_FS, Irqs, p.PA12, p.PA11, EP_OUT.init([0; 256]), usb_config);
    static USB_BUFFERS: StaticCell<firmware::usb::UsbBuffers<'static>> = StaticCell::new();
    let firmware::usb::UsbParts { device: usb, cdc: class, vendor_out, vendor_in } =
        firmware::usb::build(
            driver,
            embassy_stm32::uid::uid_hex(),
            USB_BUFFERS.init(Default::default()),
        );
    spawner.spawn(unwrap!(usb_task(usb, class, vendor_out, vendor_in)));

    // Control loop: inputs at 5 kHz, the controller's timers, the watchdog;
    // and a capture's timed work when it is due, not at the next poll: the
    // trigger's rise after a step's light margin, the end of a running
    // exposure when TIM5 has ended its pulse (the tick `start_trigger_pulse`
    // reported; the light goes back and the next capture step starts without
    // up to 200 µs more), the light's return after its margin. An exposure
    // the USB task starts is seen at the next poll, before it ends:
    // exposures are at least `MIN_EXPOSURE_US` (1 ms) > 200 µs.
    let mut ticker = Ticker::every(Duration::from_micros(protocol::INPUT_SAMPLE_US as u64));
    loop {
        let due = MACHINE.borrow().borrow().as_ref().and_then(|m| m.controller.capture_deadline());
        if let Some(end) = due {
            let wait_us = end.saturating_sub(clock::now()).div_ceil(firmware::hal::TICKS_PER_US);
            if let Either::Second(()) = select(ticker.next(), Timer::after_micros(wait_us)).await {
                let mut machine = MACHINE.borrow().borrow_mut();
                if let Some(m) = machine.as_mut() {
                    m.controller.capture_due(clock::now(), &mut m.hw);
                    m.controller.drain_events(&mut send);
                }
                // Not due yet (woken early): the next turn waits again.
                continue;
            }
        } else {
            ticker.next().await;
        }
        let inputs = sensors.read();
        let (reset, bootloader) = {
            let mut machine = MACHINE.borrow().borrow_mut();
            let Some(m) = machine.as_mut() else { continue };
            m.controller.poll(clock::now(), &inputs, &mut m.hw);
            m.controller.drain_events(&mut send);
            (m.controller.reset_requested(), m.controller.bootloader_requested())
        };
        watchdog.pet();
        if (reset || bootloader) && TX.is_empty() {
            embassy_time::Timer::after_millis(firmware::hal::RESET_AFTER_REPLY_MS).await;
            if bootloader {
                warn!("the host asked for the ROM bootloader (USB DFU)");
                reset_into_bootloader();
            }
            warn!("reset requested by the host");
            cortex_m::peripheral::SCB::sys_reset();
        }
    }
}

type UsbDriver = Driver<'static, USB_OTG_FS>;
type VendorOut = <UsbDriver as embassy_usb::driver::Driver<'static>>::EndpointOut;
type VendorIn = <UsbDriver as embassy_usb::driver::Driver<'static>>::EndpointIn;

/// Bytes from the host, on either interface, to the controller.
fn received(bytes: &[u8]) {
    let mut machine = MACHINE.borrow().borrow_mut();
    if let Some(m) = machine.as_mut() {
        m.controller.on_bytes(bytes, clock::now(), &mut m.hw, &mut send);
    }
}

#[embassy_executor::task]
async fn usb_task(
    mut usb: embassy_usb::UsbDevice<'static, UsbDriver>,
    class: CdcAcmClass<'static, UsbDriver>,
    mut vendor_out: VendorOut,
    mut vendor_in: VendorIn,
) {
    let (mut sender, mut receiver) = class.split();
    let cdc_rx = async {
        let mut packet = [0u8; 64];
        loop {
            receiver.wait_connection().await;
            info!("host connected (CDC-ACM)");
            while let Ok(n) = receiver.read_packet(&mut packet).await {
                VENDOR_ACTIVE.store(false, Ordering::Relaxed);
                HOST_SPOKE.store(true, Ordering::Relaxed);
                received(&packet[..n]);
            }
            info!("host disconnected (CDC-ACM)");
        }
    };
    let vendor_rx = async {
        let mut packet = [0u8; 64];
        loop {
            vendor_out.wait_enabled().await;
            info!("vendor interface enabled");
            while let Ok(n) = vendor_out.read(&mut packet).await {
                VENDOR_ACTIVE.store(true, Ordering::Relaxed);
                HOST_SPOKE.store(true, Ordering::Relaxed);
                received(&packet[..n]);
            }
            info!("vendor interface disabled");
        }
    };
    let tx = async {
        let mut buf = [0u8; firmware::hal::USB_TX_PACKET];
        loop {
            let n = TX.read(&mut buf).await;
            // Nothing follows: a full-size last packet must be closed by a
            // zero-length one to end the transfer.
            let last = TX.is_empty();
            // Until the host has spoken on one interface (the Boot event,
            // events after a reset), everything goes to both.
            let (to_vendor, to_cdc) = firmware::hal::usb_destinations(
                HOST_SPOKE.load(Ordering::Relaxed),
                VENDOR_ACTIVE.load(Ordering::Relaxed),
            );
            let mut delivered = false;
            if to_vendor {
                let sent = embassy_time::with_timeout(
                    TX_TIMEOUT,
                    vendor_in.write_transfer(&buf[..n], last),
                )
                .await;
                delivered |= matches!(sent, Ok(Ok(())));
            }
            if to_cdc {
                let sent = embassy_time::with_timeout(TX_TIMEOUT, async {
                    sender.wait_connection().await;
                    sender.write_packet(&buf[..n]).await?;
                    if last && n == buf.len() {
                        sender.write_packet(&[]).await?;
                    }
                    Ok::<(), embassy_usb::driver::EndpointError>(())
                })
                .await;
                delivered |= matches!(sent, Ok(Ok(())));
            }
            if !delivered {
                warn!("{} bytes not read by the host: dropped", n);
            }
        }
    };
    join4(usb.run(), cdc_rx, vendor_rx, tx).await;
}
