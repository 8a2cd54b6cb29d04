//! The simulated controller board: the firmware's own [`Controller`] with
//! simulated step timers, motors, switches, light and camera trigger, run in
//! simulated time.
//!
//! Time only moves in [`SimDevice::advance_to`]: step interrupts fire at
//! their scheduled ticks, the inputs are sampled every 200 µs as on the real
//! board, and received bytes are handed to the controller at the tick they
//! arrive. The same seed and the same inputs give the same run, byte for byte.

use std::collections::VecDeque;

use firmware::Controller;
use firmware::config::PersistedConfig;
use firmware::hal::{BootInfo, Hardware, Inputs, StorageError, TICKS_PER_MS, TICKS_PER_US};
use firmware::step::StepGenerator;
use protocol::{AXIS_COUNT, Axis, BOARD_SIMULATOR, Capabilities, ResetReason};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::faults::{FaultEvent, FaultPlan, FaultWhen};
use crate::physics::{MotorModel, SimMotor, SimSwitch, SwitchFault};

/// Input sampling period of the board's control loop (5 kHz).
pub const POLL_TICKS: u64 = protocol::INPUT_SAMPLE_US as u64 * TICKS_PER_US;

/// One camera trigger pulse, as it physically happened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TriggerRecord {
    /// Rising edge, device ticks.
    pub rise: u64,
    /// Falling edge, device ticks (`None` while high).
    pub fall: Option<u64>,
    /// Physical axis positions at the rising edge.
    pub positions: [i64; AXIS_COUNT],
    /// Light duty (per mille) at the rising edge.
    pub light_duty: u16,
    /// Light lost per PWM pulse by the light's driver at the rising edge,
    /// ns (0 unless a `slow-light` fault says otherwise).
    pub light_edge_loss_ns: u32,
    /// Whether the camera honoured the trigger (a fault can make it ignore one).
    pub honoured: bool,
}

impl TriggerRecord {
    /// When a camera exposing for the pulse's length `latency` ticks after
    /// its edges (trigger-width mode) integrates: from, and until (`None`:
    /// the pulse is still high). The camera's frames and its strobe both
    /// follow it.
    pub fn exposure_window(&self, latency: u64) -> (u64, Option<u64>) {
        (self.rise + latency, self.fall.map(|fall| fall + latency))
    }
}

/// What physically happened: for tests and benchmarks only. Host code never
/// reads this.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Truth {
    /// Every trigger pulse.
    pub triggers: Vec<TriggerRecord>,
    /// Every change of the light duty: (tick, per mille).
    pub light: Vec<(u64, u16)>,
    /// Boots: (tick, boot id).
    pub boots: Vec<(u64, u32)>,
    /// The board's clock: what happened up to this tick is recorded.
    pub now: u64,
}

/// The simulated hardware behind the controller.
#[derive(Debug)]
pub struct SimHw {
    now: u64,
    steppers: [StepGenerator; AXIS_COUNT],
    armed: [Option<u64>; AXIS_COUNT],
    dir_positive: [bool; AXIS_COUNT],
    drivers_enabled: bool,
    light: u16,
    trigger: bool,
    /// Flash contents (survive resets).
    saved: Option<Vec<u8>>,
    truth: Truth,
    ignore_triggers: u32,
    light_edge_loss_ns: u32,
    positions: [i64; AXIS_COUNT],
}

impl Hardware for SimHw {
    fn with_stepper<R>(&mut self, axis: Axis, f: impl FnOnce(&mut StepGenerator) -> R) -> R {
        f(&mut self.steppers[axis.index()])
    }
    fn set_direction(&mut self, axis: Axis, positive: bool) {
        self.dir_positive[axis.index()] = positive;
    }
    fn arm_step_timer(&mut self, axis: Axis, tick: u64) {
        // A time already past fires at once, as the board's timer does.
        self.armed[axis.index()] = Some(tick.max(self.now));
    }
    fn disarm_step_timer(&mut self, axis: Axis) {
        self.armed[axis.index()] = None;
    }
    fn set_drivers_enabled(&mut self, enabled: bool) {
        self.drivers_enabled = enabled;
    }
    fn set_light(&mut self, duty_permille: u16) {
        if duty_permille != self.light {
            self.truth.light.push((self.now, duty_permille));
        }
        self.light = duty_permille;
    }
    fn set_trigger(&mut self, high: bool) {
        if high && !self.trigger {
            let honoured = self.ignore_triggers == 0;
            self.ignore_triggers = self.ignore_triggers.saturating_sub(1);
            self.truth.triggers.push(TriggerRecord {
                rise: self.now,
                fall: None,
                positions: self.positions,
                light_duty: self.light,
                light_edge_loss_ns: self.light_edge_loss_ns,
                honoured,
            });
        } else if !high
            && self.trigger
            && let Some(last) = self.truth.triggers.last_mut()
        {
            last.fall = Some(self.now);
        }
        self.trigger = high;
    }
    fn save_config(&mut self, blob: &[u8]) -> Result<(), StorageError> {
        self.saved = Some(blob.to_vec());
        Ok(())
    }
}

/// Configuration of a simulated scanner.
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// Seed of every random choice (initial positions, boot ids, faults).
    pub seed: u64,
    /// Motor limits per axis.
    pub motors: [MotorModel; AXIS_COUNT],
    /// Faults to inject.
    pub faults: FaultPlan,
    /// How each axis' home / index sensor is wired: its line high when
    /// actuated (false: low when actuated, the board's default). The
    /// firmware reads them as its `HomeSensors` setting says, so a
    /// mismatch is what a real board with the wrong setting does.
    pub home_active_high: [bool; AXIS_COUNT],
    /// How the drivers' fault line is wired: high on a fault (TMC2209
    /// DIAG, push-pull), or low (false: DRV8825 nFAULT, the board's
    /// default). The firmware reads it as its `BoardConfig` says.
    pub driver_fault_active_high: bool,
    /// The camera's trigger latency, µs: it exposes for the pulse's length
    /// but this long after each of its edges ([`crate::camera::SimCamera::with_trigger_latency`]).
    pub trigger_latency_us: u32,
    /// The camera's "exposure active" strobe, wired to the board's strobe
    /// input: `Some(true)` a push-pull output, high while the camera
    /// exposes (from `trigger_latency_us` after a pulse's rise to as long
    /// after its fall; never for a trigger it ignores); `Some(false)` an
    /// open-collector one, low while exposing; `None` not wired (the
    /// input's pull-up holds it high, and the board does not announce the
    /// input).
    pub strobe_active_high: Option<bool>,
    /// The drives the scanner is built with (steps per unit, travel, where
    /// the switches sit: [`SimSwitch::built_for`]), which the camera's
    /// frames follow too (`SimCamera::with_axes`). Other than the spec's
    /// defaults, the board comes with them saved in its flash, as a
    /// builder who ran `scanner axes --set` would ship it.
    pub axes: [protocol::AxisConfig; AXIS_COUNT],
    /// The axis configuration the board's flash holds when it is not the
    /// drives it is built with (`None`: it holds `axes`): a board still to
    /// be commissioned — `Some(protocol::default_axes())` is one freshly
    /// flashed — or configured wrongly. The firmware moves by it; the
    /// mechanics, the switches and the camera follow `axes`.
    pub flash_axes: Option<[protocol::AxisConfig; AXIS_COUNT]>,
}

impl SimConfig {
    /// Defaults with `seed` and no faults.
    pub fn new(seed: u64) -> SimConfig {
        SimConfig {
            seed,
            motors: Axis::ALL.map(MotorModel::default_for),
            faults: FaultPlan::default(),
            home_active_high: [false; AXIS_COUNT],
            driver_fault_active_high: false,
            trigger_latency_us: 0,
            strobe_active_high: Some(true),
            axes: protocol::default_axes(),
            flash_axes: None,
        }
    }
}

/// The simulated controller board.
#[derive(Debug)]
pub struct SimDevice {
    controller: Controller,
    hw: SimHw,
    motors: [SimMotor; AXIS_COUNT],
    switches: [SimSwitch; AXIS_COUNT],
    /// The drives it is built with (`SimConfig::axes`).
    built: [protocol::AxisConfig; AXIS_COUNT],
    home_active_high: [bool; AXIS_COUNT],
    driver_fault_active_high: bool,
    /// `SimConfig::strobe_active_high`.
    strobe_active_high: Option<bool>,
    /// The camera's trigger latency, ticks.
    trigger_latency: u64,
    estop: bool,
    driver_fault: bool,
    now: u64,
    next_poll: u64,
    rng: ChaCha8Rng,
    faults: FaultPlan,
    /// Bytes the device sent, not yet taken by the link.
    output: VecDeque<u8>,
    boot_count: u32,
    /// In the chip's ROM bootloader (`EnterBootloader`): the firmware is
    /// not running, the protocol gone, until the board is reset.
    in_rom: bool,
    seed: u64,
}

impl SimDevice {
    /// Power on a simulated scanner.
    pub fn new(config: SimConfig) -> SimDevice {
        let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
        // The mechanics are wherever they were left: anywhere in range,
        // off the home switch.
        let start = config.axes.map(|c| {
            let (lo, hi) = if c.continuous {
                (0, c.steps_per_rev.max(1) as i64)
            } else if c.homing.direction == protocol::Direction::Negative {
                (c.homing.home_position as i64 + c.homing.backoff_steps as i64, c.max_steps as i64)
            } else {
                (
                    c.min_steps as i64,
                    c.homing.home_position as i64 - c.homing.backoff_steps as i64 + 1,
                )
            };
            if lo < hi { rng.random_range(lo..hi) } else { lo }
        });
        let motors = [0, 1, 2].map(|i| SimMotor::new(config.motors[i], start[i]));
        let hw = SimHw {
            now: 0,
            steppers: Default::default(),
            armed: [None; AXIS_COUNT],
            dir_positive: [true; AXIS_COUNT],
            drivers_enabled: false,
            light: 0,
            trigger: false,
            saved: Some(config.flash_axes.unwrap_or(config.axes))
                .filter(|axes| *axes != protocol::default_axes())
                .map(|axes| {
                    let factory = PersistedConfig { axes, ..PersistedConfig::default() };
                    let mut buf = [0u8; firmware::config::PERSISTED_MAX_LEN];
                    factory.encode(&mut buf).expect("a configuration fits its blob").to_vec()
                }),
            truth: Truth::default(),
            ignore_triggers: 0,
            light_edge_loss_ns: 0,
            positions: start,
        };
        let strobe = config.strobe_active_high.is_some();
        let boot = Self::boot_info(&mut rng, ResetReason::PowerOn, strobe);
        let mut device = SimDevice {
            controller: Controller::new(boot, hw.saved.as_deref()),
            hw,
            motors,
            switches: Axis::ALL.map(|a| SimSwitch::built_for(a, &config.axes[a.index()])),
            built: config.axes,
            home_active_high: config.home_active_high,
            driver_fault_active_high: config.driver_fault_active_high,
            strobe_active_high: config.strobe_active_high,
            trigger_latency: config.trigger_latency_us as u64 * TICKS_PER_US,
            estop: false,
            driver_fault: false,
            now: 0,
            next_poll: 0,
            rng,
            faults: config.faults,
            output: VecDeque::new(),
            boot_count: 1,
            in_rom: false,
            seed: config.seed,
        };
        device.hw.truth.boots.push((0, boot.boot_id));
        device
    }

    /// A boot's information; `strobe`: the camera's strobe is wired.
    fn boot_info(rng: &mut ChaCha8Rng, reason: ResetReason, strobe: bool) -> BootInfo {
        let capabilities = Capabilities::SIMULATED
            .union(Capabilities::PERSISTENT_CONFIG)
            .union(Capabilities::PWM_LIGHT)
            .union(Capabilities::LOG_EVENTS)
            .union(Capabilities::SYSTEM_BOOTLOADER);
        BootInfo {
            boot_id: rng.random(),
            reason,
            device_id: *b"HILSIM-00001",
            board: BOARD_SIMULATOR,
            capabilities: if strobe {
                capabilities.union(Capabilities::EXPOSURE_STROBE)
            } else {
                capabilities
            },
            storage_failed: false,
        }
    }

    /// Whether the camera exposes now: within its latency of the last
    /// trigger pulse, if it honoured it.
    fn camera_exposing(&self) -> bool {
        let Some(t) = self.hw.truth.triggers.last() else { return false };
        let (start, end) = t.exposure_window(self.trigger_latency);
        t.honoured && self.now >= start && end.is_none_or(|end| self.now < end)
    }

    /// The byte-level noise the plan asks for, seeded from the device seed.
    pub fn link_noise(&self) -> crate::link::LinkNoise {
        crate::link::LinkNoise::new(self.seed, self.faults.corrupt_rate, self.faults.drop_rate)
    }

    /// Device time, ticks of [`firmware::hal::TICK_HZ`].
    pub fn now(&self) -> u64 {
        self.now
    }

    /// What physically happened (tests only).
    pub fn truth(&self) -> &Truth {
        &self.hw.truth
    }

    /// Where the axes physically are, in degrees and mm: what a ruler or a
    /// protractor on the machine reads (tests, and `scanner sim`'s
    /// stand-in for measuring a move).
    pub fn physical_axes(&self) -> scanner_geometry::AxisValues {
        crate::camera::axis_values(Axis::ALL.map(|a| self.physical_position(a)), &self.built)
    }

    /// Physical position of `axis` (tests only).
    pub fn physical_position(&self, axis: Axis) -> i64 {
        self.motors[axis.index()].position()
    }

    /// Steps lost by `axis` so far (tests only).
    pub fn lost_steps(&self, axis: Axis) -> u64 {
        self.motors[axis.index()].lost_steps()
    }

    /// Light duty now (tests only).
    pub fn light(&self) -> u16 {
        self.hw.light
    }

    /// Times the device has booted.
    pub fn boot_count(&self) -> u32 {
        self.boot_count
    }

    /// Mutable access to a switch (tests inject faults directly too).
    pub fn switch_mut(&mut self, axis: Axis) -> &mut SimSwitch {
        &mut self.switches[axis.index()]
    }

    /// Set the emergency-stop input.
    pub fn set_estop(&mut self, asserted: bool) {
        self.estop = asserted;
    }

    /// Set the driver-fault input.
    pub fn set_driver_fault(&mut self, asserted: bool) {
        self.driver_fault = asserted;
    }

    /// The faults the board's controller has latched.
    pub fn faults(&self) -> protocol::FaultFlags {
        self.controller.faults()
    }

    /// Whether the board sits in its ROM bootloader (`EnterBootloader`; a
    /// reset brings the firmware back, as flashing over DFU ends).
    pub fn in_bootloader(&self) -> bool {
        self.in_rom
    }

    /// Bytes from the host arrive now (the ROM bootloader does not speak
    /// the protocol: they are lost).
    pub fn receive(&mut self, bytes: &[u8]) {
        if self.in_rom {
            return;
        }
        let SimDevice { controller, hw, output, now, .. } = self;
        hw.now = *now;
        controller.on_bytes(bytes, *now, hw, &mut |frame: &[u8]| output.extend(frame));
        self.after_controller();
    }

    /// Take the bytes the device has sent.
    pub fn take_output(&mut self) -> Vec<u8> {
        self.output.drain(..).collect()
    }

    /// Whether the device has bytes to send.
    pub fn has_output(&self) -> bool {
        !self.output.is_empty()
    }

    /// Run the board until tick `end`.
    pub fn advance_to(&mut self, end: u64) {
        loop {
            let step = (0..AXIS_COUNT)
                .filter_map(|i| self.hw.armed[i].map(|t| (t, i)))
                .min_by_key(|&(t, i)| (t, i));
            let fault = self.faults.next_at(self.trigger_count());
            let mut next = self.next_poll;
            if let Some((t, _)) = step {
                next = next.min(t);
            }
            // The board wakes when a capture's timed work is due
            // (firmware/board: the control task's timer), so the pulse lasts
            // what was asked.
            let exposure_end = self.controller.capture_deadline();
            if let Some(t) = exposure_end {
                next = next.min(t);
            }
            if let Some(FaultWhen::AtTick(t)) = fault {
                next = next.min(t);
            }
            if next > end {
                self.now = end;
                self.hw.truth.now = end;
                return;
            }
            self.now = next;
            self.hw.now = next;
            self.hw.truth.now = next;
            match step {
                Some((t, i)) if t == next => self.step_interrupt(i),
                _ if next == self.next_poll => {
                    self.poll();
                    self.next_poll += POLL_TICKS;
                }
                _ if exposure_end == Some(next) => {
                    self.controller.capture_due(next, &mut self.hw);
                    self.after_controller();
                }
                _ => {}
            }
            self.apply_due_faults();
        }
    }

    fn trigger_count(&self) -> u32 {
        self.hw.truth.triggers.len() as u32
    }

    fn step_interrupt(&mut self, i: usize) {
        let positive = self.hw.dir_positive[i];
        if self.hw.drivers_enabled {
            self.motors[i].pulse(self.now, positive);
            self.hw.positions[i] = self.motors[i].position();
        }
        self.hw.armed[i] = self.hw.steppers[i].step();
    }

    fn poll(&mut self) {
        if self.in_rom {
            return;
        }
        let mut home_line = [false; AXIS_COUNT];
        for (i, h) in home_line.iter_mut().enumerate() {
            let actuated = self.switches[i].sample(self.motors[i].position(), &mut self.rng);
            *h = actuated == self.home_active_high[i];
        }
        // `driver_fault` is "asserted"; the line level follows the drivers'
        // wiring, whatever the firmware is set to read.
        let inputs = Inputs {
            home_line,
            estop: self.estop,
            driver_fault_line: self.driver_fault == self.driver_fault_active_high,
            strobe_line: self.strobe_active_high.is_none_or(|high| self.camera_exposing() == high),
        };
        self.controller.poll(self.now, &inputs, &mut self.hw);
        self.after_controller();
    }

    fn after_controller(&mut self) {
        let SimDevice { controller, output, .. } = self;
        controller.drain_events(&mut |frame: &[u8]| output.extend(frame));
        if self.controller.reset_requested() {
            self.reset(ResetReason::Software);
        } else if self.controller.bootloader_requested() {
            // The board resets into the ROM: outputs as at reset, nothing
            // more from the firmware (its Ack is already out).
            self.outputs_at_reset();
            self.in_rom = true;
        }
    }

    /// The board's outputs as a reset leaves them: no steps, drivers
    /// disabled, light and trigger off.
    fn outputs_at_reset(&mut self) {
        self.hw.steppers = Default::default();
        self.hw.armed = [None; AXIS_COUNT];
        self.hw.drivers_enabled = false;
        self.hw.set_light(0);
        self.hw.set_trigger(false);
    }

    /// Reset the board: a new boot id, homing lost, config reloaded from the
    /// simulated flash; the mechanics stay where they are.
    pub fn reset(&mut self, reason: ResetReason) {
        self.in_rom = false;
        let boot = Self::boot_info(&mut self.rng, reason, self.strobe_active_high.is_some());
        self.outputs_at_reset();
        self.controller = Controller::new(boot, self.hw.saved.as_deref());
        self.boot_count += 1;
        self.hw.truth.boots.push((self.now, boot.boot_id));
        let SimDevice { controller, output, .. } = self;
        controller.drain_events(&mut |frame: &[u8]| output.extend(frame));
    }

    fn apply_due_faults(&mut self) {
        while let Some(event) = self.faults.take_due(self.now, self.trigger_count()) {
            match event {
                FaultEvent::Reset => self.reset(ResetReason::Watchdog),
                FaultEvent::LoseSteps { axis, steps } => {
                    self.motors[axis.index()].inject_lost_steps(steps)
                }
                FaultEvent::Switch { axis, fault } => self.switches[axis.index()].fault = fault,
                FaultEvent::DriverFault(on) => self.driver_fault = on,
                FaultEvent::EmergencyStop(on) => self.estop = on,
                FaultEvent::IgnoreTriggers(n) => self.hw.ignore_triggers += n,
                FaultEvent::SlowLight { edge_ns } => self.hw.light_edge_loss_ns = edge_ns,
                // Link faults are applied by the link.
                FaultEvent::Disconnect { .. } => self.faults.push_link_event(self.now, event),
            }
        }
    }

    /// Add a fault to the plan (e.g. one due now).
    pub fn schedule(&mut self, spec: crate::faults::FaultSpec) {
        let plan = std::mem::take(&mut self.faults);
        self.faults = plan.with(spec.when, spec.event);
    }

    /// Link-level faults that became due (the link applies them).
    pub fn take_link_faults(&mut self) -> Vec<(u64, FaultEvent)> {
        self.faults.take_link_events()
    }

    /// The configuration as the device would save it.
    pub fn saved_config(&self) -> Option<PersistedConfig> {
        self.hw.saved.as_deref().and_then(PersistedConfig::decode)
    }

    /// Milliseconds of device time.
    pub fn now_ms(&self) -> f64 {
        self.now as f64 / TICKS_PER_MS as f64
    }

    /// Whether an axis' switch is mechanically stuck (for diagnostics).
    pub fn switch_fault(&self, axis: Axis) -> SwitchFault {
        self.switches[axis.index()].fault
    }
}
