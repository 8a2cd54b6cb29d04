//! A test rig for the controller: mock hardware and an ideal machine (no lost
//! steps, switches at fixed physical positions), driven in simulated time by
//! visiting step-timer events and controller deadlines in time order.
//!
//! `no_std` and allocation-free, so the self-tests run on the Cortex-M4 under
//! QEMU as well as on the PC. `hil-sim` has the full physical simulator; this
//! rig only exists to test the controller's logic.

use heapless::Vec;
use protocol::{
    AXIS_COUNT, Axis, BOARD_SIMULATOR, Capabilities, Event, Frame, PROTOCOL_VERSION, Reply,
    Request, ResetReason,
};

use crate::config::PERSISTED_MAX_LEN;
use crate::controller::Controller;
use crate::hal::{BootInfo, Hardware, Inputs, StorageError, TICKS_PER_MS};
use crate::step::StepGenerator;

/// Output edges and calls recorded by [`MockHw`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Output {
    /// Light duty set (0 = off).
    Light(u64, u16),
    /// Trigger level set.
    Trigger(u64, bool),
}

/// Mock hardware that records what the controller did.
#[derive(Debug, Default)]
pub struct MockHw {
    /// Tick the rig is at (stamped on recorded outputs).
    pub now: u64,
    /// Armed step times per axis.
    pub armed: [Option<u64>; AXIS_COUNT],
    /// DIR lines.
    pub dir_positive: [bool; AXIS_COUNT],
    /// EN lines.
    pub drivers_enabled: bool,
    /// Light duty now.
    pub light: u16,
    /// Trigger level now.
    pub trigger: bool,
    /// Light and trigger changes, in order: the last 64.
    pub outputs: Vec<Output, 64>,
    /// Last saved configuration blob.
    pub saved: Vec<u8, PERSISTED_MAX_LEN>,
    /// Make `save_config` fail.
    pub storage_fails: bool,
    /// The step generators (the interrupt's side).
    pub steppers: [StepGenerator; AXIS_COUNT],
    /// End trigger pulses "in hardware", like the board's one-pulse timer
    /// ([`crate::trigger`]): the fall is at the asked tick, whenever the
    /// controller calls `set_trigger(false)` after it.
    pub hardware_pulse: bool,
    /// The tick at which the running hardware pulse falls.
    pub pulse_falls_at: Option<u64>,
}

impl MockHw {
    /// Record an output change; once [`MockHw::outputs`] is full, the
    /// oldest goes (the camera's strobe reads the last pulse from them).
    fn record(&mut self, output: Output) {
        if self.outputs.is_full() {
            self.outputs.remove(0);
        }
        let _ = self.outputs.push(output);
    }
}

impl Hardware for MockHw {
    fn with_stepper<R>(&mut self, axis: Axis, f: impl FnOnce(&mut StepGenerator) -> R) -> R {
        f(&mut self.steppers[axis.index()])
    }
    fn set_direction(&mut self, axis: Axis, positive: bool) {
        self.dir_positive[axis.index()] = positive;
    }
    fn arm_step_timer(&mut self, axis: Axis, tick: u64) {
        self.armed[axis.index()] = Some(tick);
    }
    fn disarm_step_timer(&mut self, axis: Axis) {
        self.armed[axis.index()] = None;
    }
    fn set_drivers_enabled(&mut self, enabled: bool) {
        self.drivers_enabled = enabled;
    }
    fn set_light(&mut self, duty_permille: u16) {
        if self.light != duty_permille {
            self.record(Output::Light(self.now, duty_permille));
        }
        self.light = duty_permille;
    }
    fn set_trigger(&mut self, high: bool) {
        // A hardware pulse already over fell at its own tick.
        let at = match self.pulse_falls_at.take() {
            Some(fall) if !high && fall <= self.now => fall,
            _ => self.now,
        };
        if self.trigger != high {
            self.record(Output::Trigger(at, high));
        }
        self.trigger = high;
    }
    fn start_trigger_pulse(&mut self, ticks: u64) -> Option<u64> {
        self.set_trigger(true);
        if !self.hardware_pulse {
            return None;
        }
        self.pulse_falls_at = Some(self.now + ticks);
        // As the board: the end estimated a tick late (timer phase).
        Some(self.now + ticks + 1)
    }
    fn save_config(&mut self, blob: &[u8]) -> Result<(), StorageError> {
        if self.storage_fails {
            return Err(StorageError);
        }
        self.saved.clear();
        self.saved.extend_from_slice(blob).map_err(|_| StorageError)
    }
}

/// A home switch at a fixed physical position.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Switch {
    /// No switch (homing must fail).
    Missing,
    /// Actuated at physical positions ≤ `edge` (a limit at the low end).
    Below(i64),
    /// Actuated within `width` steps after `edge`, repeating every `rev`
    /// steps (a disk's index flag).
    Index {
        /// Start of the flag.
        edge: i64,
        /// Flag width.
        width: i64,
        /// Steps per revolution.
        rev: i64,
    },
    /// Always actuated (stuck).
    Stuck,
    /// Actuated at physical positions `lo ..= hi` only: something on the
    /// travel presses its lever there, or its cable shorts where the chain
    /// bends.
    Window(i64, i64),
}

impl Switch {
    fn actuated(self, physical: i64) -> bool {
        match self {
            Switch::Missing => false,
            Switch::Below(edge) => physical <= edge,
            Switch::Index { edge, width, rev } => (physical - edge).rem_euclid(rev) < width,
            Switch::Stuck => true,
            Switch::Window(lo, hi) => (lo..=hi).contains(&physical),
        }
    }
}

/// The home switches where the default axis configurations expect them:
/// the disk's index flag at 0, the track's limit at 0, the tilt's at
/// −9 333 steps (−35°).
pub const DEFAULT_SWITCHES: [Switch; AXIS_COUNT] =
    [Switch::Index { edge: 0, width: 200, rev: 16_000 }, Switch::Below(0), Switch::Below(-9_333)];

/// A camera's "exposure active" strobe output, wired to the rig's input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CameraStrobe {
    /// The camera exposes from this many ticks after the trigger rises to
    /// as long after it falls (an opto-isolated input's delay).
    pub delay: u64,
    /// The line is high while exposing (false: low).
    pub active_high: bool,
    /// The camera ignores its triggers (the line stays inactive).
    pub ignores: bool,
}

/// The controller on an ideal machine.
#[derive(Debug)]
pub struct Rig {
    /// The controller under test.
    pub ctrl: Controller,
    /// Its hardware.
    pub hw: MockHw,
    /// Simulated time, ticks.
    pub now: u64,
    /// Physical position of each axis, steps: integrated from step pulses and
    /// DIR lines, independent of the controller's counter.
    pub physical: [i64; AXIS_COUNT],
    /// Home switch per axis.
    pub switches: [Switch; AXIS_COUNT],
    /// How each switch is wired: its line is high when actuated (false:
    /// low when actuated, the board's default).
    pub switch_active_high: [bool; AXIS_COUNT],
    /// E-stop and driver-fault inputs.
    pub estop: bool,
    /// Driver fault input.
    pub driver_fault: bool,
    /// The camera's strobe, if wired (`None`: the line reads low).
    pub strobe: Option<CameraStrobe>,
    /// Send a `Ping` every 100 ms of simulated time (as a host does).
    pub keepalive: bool,
    /// Also poll every this many ticks, as the board's 5 kHz loop does
    /// (`None`: only at steps, pings and the controller's deadlines).
    pub poll_period: Option<u64>,
    /// Events received, in order.
    pub events: Vec<Event, 64>,
    /// `MotionDone` events received since the boot (all of them, also
    /// when `events` is full).
    pub motion_done: usize,
    /// The last `MotionDone` received since the boot.
    pub last_motion_done: Option<Event>,
    /// Tick of the first and last step of each axis since the last
    /// [`Rig::clear_steps`].
    pub step_span: [Option<(u64, u64)>; AXIS_COUNT],
    seq: u8,
    last_ping: u64,
    last_poll: u64,
    boot: BootInfo,
}

/// What [`Rig::run_until_visiting`] shows its visitor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Visit {
    /// `axis` has just made a step (the machine moved; the controller has
    /// not polled since).
    Stepped(Axis),
    /// The controller has just polled.
    Polled,
}

impl Rig {
    /// A freshly booted controller with default config, handshake done;
    /// switches where the defaults expect them, axes 1000 steps off home.
    pub fn new() -> Rig {
        Self::booted(ResetReason::PowerOn)
    }

    /// A freshly booted controller with the given reset reason.
    pub fn booted(reason: ResetReason) -> Rig {
        Self::with_capabilities(
            reason,
            Capabilities::SIMULATED.union(Capabilities::PERSISTENT_CONFIG),
        )
    }

    /// A freshly booted controller with the given reset reason and capabilities.
    pub fn with_capabilities(reason: ResetReason, capabilities: Capabilities) -> Rig {
        Self::with_boot(reason, capabilities, false)
    }

    /// A rig whose boot found its persistent storage failing.
    pub fn with_storage_failure() -> Rig {
        Self::with_boot(
            ResetReason::PowerOn,
            Capabilities::SIMULATED.union(Capabilities::PERSISTENT_CONFIG),
            true,
        )
    }

    fn with_boot(reason: ResetReason, capabilities: Capabilities, storage_failed: bool) -> Rig {
        let boot = BootInfo {
            boot_id: 0x1234_5678,
            reason,
            device_id: [7; 12],
            board: BOARD_SIMULATOR,
            capabilities,
            storage_failed,
        };
        let mut rig = Rig {
            ctrl: Controller::new(boot, None),
            hw: MockHw::default(),
            now: 0,
            // Disk 90° past its flag, track 50 mm out, tilt 10° above its stop.
            physical: [4_000, 80_000, -9_333 + 2_667],
            switches: DEFAULT_SWITCHES,
            switch_active_high: [false; AXIS_COUNT],
            estop: false,
            driver_fault: false,
            strobe: None,
            keepalive: true,
            poll_period: None,
            events: Vec::new(),
            motion_done: 0,
            last_motion_done: None,
            step_span: [None; AXIS_COUNT],
            seq: 0,
            last_ping: 0,
            last_poll: 0,
            boot,
        };
        rig.poll();
        let _ = rig.request(Request::Hello { host_protocol: PROTOCOL_VERSION });
        rig
    }

    /// The board reset (a `Reset`, the watchdog, back from the bootloader,
    /// power): a new controller with the configuration the board saved,
    /// the pins and timers at their reset state, the machine where it was.
    /// No handshake yet.
    pub fn reboot(&mut self, reason: ResetReason) {
        let boot = BootInfo {
            reason,
            boot_id: self.boot.boot_id.wrapping_add(1),
            // A flash that fails to save fails to count boots as well.
            storage_failed: self.hw.storage_fails,
            ..self.boot
        };
        self.boot = boot;
        let saved = (!self.hw.saved.is_empty()).then_some(&self.hw.saved[..]);
        self.ctrl = Controller::new(boot, saved);
        // What the board is (its flash, its trigger timer) stays; its
        // state goes.
        let saved = core::mem::take(&mut self.hw.saved);
        let (storage_fails, hardware_pulse) = (self.hw.storage_fails, self.hw.hardware_pulse);
        self.hw =
            MockHw { now: self.now, saved, storage_fails, hardware_pulse, ..MockHw::default() };
        self.seq = 0;
        self.motion_done = 0;
        self.last_motion_done = None;
        self.poll();
    }

    /// The controller's position counter of `axis`, steps.
    pub fn position(&self, axis: Axis) -> i32 {
        self.hw.steppers[axis.index()].position()
    }

    /// Status as the controller reports it.
    pub fn status(&mut self) -> protocol::Status {
        self.ctrl.status(&mut self.hw)
    }

    /// Physical position of `axis`.
    pub fn physical(&self, axis: Axis) -> i64 {
        self.physical[axis.index()]
    }

    /// Current input snapshot.
    pub fn inputs(&self) -> Inputs {
        Inputs {
            home_line: Axis::ALL.map(|a| {
                self.switches[a.index()].actuated(self.physical(a))
                    == self.switch_active_high[a.index()]
            }),
            estop: self.estop,
            // The rig's `driver_fault` is "asserted"; the line level
            // follows the configured polarity.
            driver_fault_line: self.driver_fault
                == self.ctrl.config().board.driver_fault_active_high,
            strobe_line: self.strobe.is_some_and(|c| self.camera_exposing(&c) == c.active_high),
        }
    }

    /// Whether the camera `c` exposes now: within its delay of the last
    /// trigger pulse recorded.
    fn camera_exposing(&self, c: &CameraStrobe) -> bool {
        let mut pulse = None;
        for o in &self.hw.outputs {
            match *o {
                Output::Trigger(t, true) => pulse = Some((t, None)),
                Output::Trigger(t, false) => {
                    if let Some((_, fall)) = &mut pulse {
                        *fall = Some(t);
                    }
                }
                Output::Light(..) => {}
            }
        }
        let Some((rise, fall)) = pulse else { return false };
        !c.ignores && self.now >= rise + c.delay && fall.is_none_or(|f| self.now < f + c.delay)
    }

    /// Send a request with a fresh sequence number; returns the reply.
    pub fn request(&mut self, request: Request) -> Reply {
        let seq = self.next_seq();
        self.request_seq(seq, request)
    }

    /// The sequence number [`Rig::request`] would give the next request,
    /// taken (for a request framed by hand).
    pub fn next_seq(&mut self) -> u8 {
        self.seq = self.seq.wrapping_add(1);
        self.seq
    }

    /// Send a request with the given sequence number (to test duplicates).
    pub fn request_seq(&mut self, seq: u8, request: Request) -> Reply {
        self.hw.now = self.now;
        let (s, reply) = self.ctrl.handle(Frame { seq, msg: request }, self.now, &mut self.hw);
        debug_assert_eq!(s, seq);
        self.collect();
        reply
    }

    /// Hand `bytes` to the controller as received from the host; its
    /// framed replies go to `tx`.
    pub fn on_bytes(&mut self, bytes: &[u8], tx: &mut impl FnMut(&[u8])) {
        self.hw.now = self.now;
        self.ctrl.on_bytes(bytes, self.now, &mut self.hw, tx);
        self.collect();
    }

    /// Poll the controller at the current time.
    pub fn poll(&mut self) {
        self.hw.now = self.now;
        self.last_poll = self.now;
        let inputs = self.inputs();
        self.ctrl.poll(self.now, &inputs, &mut self.hw);
        self.collect();
    }

    fn collect(&mut self) {
        while let Some(e) = self.ctrl.pop_event() {
            if matches!(e, Event::MotionDone { .. }) {
                self.motion_done += 1;
                self.last_motion_done = Some(e.clone());
            }
            let _ = self.events.push(e);
        }
    }

    /// Forget recorded step ticks.
    pub fn clear_steps(&mut self) {
        self.step_span = [None; AXIS_COUNT];
    }

    /// Run to tick `end`, visiting every step and deadline in time order.
    pub fn run_until(&mut self, end: u64) {
        let ok: Result<(), core::convert::Infallible> = self.run_until_visiting(end, |_, _| Ok(()));
        let Ok(()) = ok;
    }

    /// [`Rig::run_until`], showing `visit` every step and every poll; the
    /// first error `visit` returns stops the run there.
    pub fn run_until_visiting<E>(
        &mut self,
        end: u64,
        mut visit: impl FnMut(&mut Rig, Visit) -> Result<(), E>,
    ) -> Result<(), E> {
        loop {
            let step = Axis::ALL
                .iter()
                .filter_map(|a| self.hw.armed[a.index()].map(|t| (t, *a)))
                .min_by_key(|(t, _)| *t);
            let ping = self.keepalive.then_some(self.last_ping + 100 * TICKS_PER_MS);
            let periodic = self.poll_period.map(|p| self.last_poll + p);
            let deadline = self.ctrl.next_deadline();
            let next = [step.map(|s| s.0), ping, periodic, deadline].into_iter().flatten().min();
            let Some(t) = next.filter(|t| *t <= end) else {
                self.now = self.now.max(end);
                self.poll();
                return visit(self, Visit::Polled);
            };
            self.now = self.now.max(t);
            if let Some((ts, axis)) = step
                && ts == t
            {
                let i = axis.index();
                let first = self.step_span[i].map_or(t, |(first, _)| first);
                self.step_span[i] = Some((first, t));
                self.physical[i] += if self.hw.dir_positive[i] { 1 } else { -1 };
                self.hw.armed[i] = self.hw.steppers[i].step();
                visit(self, Visit::Stepped(axis))?;
            } else if ping == Some(t) {
                self.last_ping = t;
                let _ = self.request(Request::Ping { token: 0 });
            }
            self.poll();
            visit(self, Visit::Polled)?;
        }
    }

    /// Whether the controller, polled at the current tick, asks to be woken
    /// at a tick already past ([`Controller::next_deadline`],
    /// [`Controller::capture_deadline`]): work it says is due and does not
    /// do. [`Rig::run_until`] would turn there without time passing; the
    /// board, for a capture's deadline, without polling its inputs.
    pub fn stale_deadline(&self) -> bool {
        let past = |t: Option<u64>| t.is_some_and(|t| t <= self.now);
        past(self.ctrl.next_deadline()) || past(self.ctrl.capture_deadline())
    }

    /// Run until no axis moves and nothing is timed, at most `max_ms`.
    /// Returns whether the controller went idle.
    pub fn run_until_idle(&mut self, max_ms: u64) -> bool {
        let end = self.now + max_ms * TICKS_PER_MS;
        while self.now < end {
            let idle = !self.ctrl.is_moving()
                && self.hw.armed.iter().all(Option::is_none)
                && self.ctrl.next_deadline().is_none();
            if idle {
                return true;
            }
            self.run_until((self.now + 10 * TICKS_PER_MS).min(end));
        }
        false
    }

    /// Home every axis and run until done; whether all axes are homed.
    pub fn home_all(&mut self) -> bool {
        if self.request(Request::Home { axes: protocol::AxisSet::ALL }) != Reply::Ack {
            return false;
        }
        self.run_until_idle(60_000);
        Axis::ALL.iter().all(|a| self.ctrl.is_homed(*a))
    }
}

impl Default for Rig {
    fn default() -> Self {
        Self::new()
    }
}

// ----- a model of TIM2 ---------------------------------------------------------------

/// TIM2 as the step timer sees it, with the real semantics: a free-running
/// 32-bit counter; a compare flag set when the counter *equals* CCRx (whether
/// or not its interrupt is enabled); UIF at every wrap; rc_w0 status flags;
/// EGR.CCxG. The counter runs on by a random number of ticks (0 …
/// `max_step`) at **every register access**, so compare events and
/// overflows land at every point of the code under test. Time is kept in a
/// shared [`Cell`](core::cell::Cell) so that a model STEP pin can read it.
#[derive(Debug)]
pub struct Tim2Model<'a> {
    /// Ticks since the model's epoch (the counter is its low 32 bits).
    pub clock: &'a core::cell::Cell<u64>,
    sr: u32,
    dier: u32,
    ccr: [u32; 3],
    rng: u64,
    /// Largest advance per register access, ticks.
    pub max_step: u64,
}

impl<'a> Tim2Model<'a> {
    /// A model at `clock`'s time, counter running, flags clear, UIE set.
    pub fn new(clock: &'a core::cell::Cell<u64>, seed: u64, max_step: u64) -> Tim2Model<'a> {
        Tim2Model { clock, sr: 0, dier: crate::timer::UIF, ccr: [0; 3], rng: seed | 1, max_step }
    }

    /// Ticks since the epoch.
    pub fn time(&self) -> u64 {
        self.clock.get()
    }

    /// A pseudo-random number.
    pub fn random(&mut self) -> u64 {
        xorshift64star(&mut self.rng)
    }

    /// Let `dt` ticks pass: compare matches and wraps on the way set flags.
    pub fn advance(&mut self, dt: u64) {
        if dt == 0 {
            return;
        }
        let time = self.time();
        for ch in 0..3 {
            // A tick t in (time, time + dt] with t mod 2^32 == CCR?
            let first = (self.ccr[ch] as u64).wrapping_sub(time + 1) & 0xFFFF_FFFF;
            if first < dt {
                self.sr |= crate::timer::ccif(ch);
            }
        }
        if (time >> 32) != ((time + dt) >> 32) {
            self.sr |= crate::timer::UIF;
        }
        self.clock.set(time + dt);
    }

    fn bus(&mut self) {
        let dt = self.random() % (self.max_step + 1);
        self.advance(dt);
    }
}

impl crate::timer::TimerRegs for Tim2Model<'_> {
    fn cnt(&mut self) -> u32 {
        self.bus();
        self.time() as u32
    }
    fn sr(&mut self) -> u32 {
        self.bus();
        self.sr
    }
    fn write_sr(&mut self, value: u32) {
        self.bus();
        self.sr &= value; // rc_w0
    }
    fn dier(&mut self) -> u32 {
        self.bus();
        self.dier
    }
    fn write_dier(&mut self, value: u32) {
        self.bus();
        self.dier = value;
    }
    fn write_ccr(&mut self, ch: usize, value: u32) {
        self.bus();
        self.ccr[ch] = value;
    }
    fn generate(&mut self, ch: usize) {
        self.bus();
        self.sr |= crate::timer::ccif(ch);
    }
}

/// A model of the trigger's one-pulse timer ([`crate::trigger`]): a
/// 32-bit up-counter of prescaled ticks with CR1.CEN/OPM, ARR, one
/// output-compare channel and its output level, on a shared clock that
/// also advances by a random 0 … `max_step` ticks at every register access
/// (the code runs while the counter counts). Records the output's edges.
#[derive(Debug)]
pub struct PulseTimerModel<'a> {
    /// Ticks since the model's epoch.
    pub clock: &'a core::cell::Cell<u64>,
    cr1: u32,
    cnt: u32,
    arr: u32,
    ccr: u32,
    mode: crate::trigger::OutputMode,
    high: bool,
    /// The output's edges: (tick, level).
    pub edges: Vec<(u64, bool), 64>,
    rng: u64,
    /// Largest advance per register access, ticks.
    pub max_step: u64,
}

impl<'a> PulseTimerModel<'a> {
    /// A stopped timer, output forced low.
    pub fn new(clock: &'a core::cell::Cell<u64>, seed: u64, max_step: u64) -> PulseTimerModel<'a> {
        PulseTimerModel {
            clock,
            cr1: 0,
            cnt: 0,
            arr: u32::MAX,
            ccr: 0,
            mode: crate::trigger::OutputMode::ForceInactive,
            high: false,
            edges: Vec::new(),
            rng: seed | 1,
            max_step,
        }
    }

    /// Whether the output is high now.
    pub fn is_high(&self) -> bool {
        self.high
    }

    /// The output level the mode and counter give.
    fn level(&self) -> bool {
        use crate::trigger::OutputMode::*;
        match self.mode {
            ForceInactive => false,
            ForceActive => true,
            Pwm2 => self.cnt >= self.ccr,
        }
    }

    fn set_level(&mut self, at: u64) {
        let high = self.level();
        if high != self.high {
            self.high = high;
            let _ = self.edges.push((at, high));
        }
    }

    /// Let `dt` ticks pass.
    pub fn advance(&mut self, mut dt: u64) {
        let mut t = self.clock.get();
        while dt > 0 && self.cr1 & crate::trigger::CEN != 0 {
            if self.cnt < self.arr {
                // Count up to ARR; the output may rise on the way (at CNT = CCR).
                let step = dt.min((self.arr - self.cnt) as u64);
                let (from, to) = (self.cnt as u64, self.cnt as u64 + step);
                let ccr = self.ccr as u64;
                if from < ccr && ccr <= to {
                    self.cnt = self.ccr;
                    self.set_level(t + (ccr - from));
                }
                self.cnt = to as u32;
                self.set_level(t + step);
                t += step;
                dt -= step;
            } else {
                // The tick after ARR: the update, which stops a one-pulse counter.
                t += 1;
                dt -= 1;
                self.cnt = 0;
                if self.cr1 & crate::trigger::OPM != 0 {
                    self.cr1 &= !crate::trigger::CEN;
                }
                self.set_level(t);
            }
        }
        self.clock.set(t + dt);
    }

    fn bus(&mut self) {
        let dt = xorshift64star(&mut self.rng) % (self.max_step + 1);
        self.advance(dt);
    }
}

impl crate::trigger::PulseRegs for PulseTimerModel<'_> {
    fn cr1(&mut self) -> u32 {
        self.bus();
        self.cr1
    }
    fn write_cr1(&mut self, value: u32) {
        self.bus();
        self.cr1 = value;
    }
    fn write_arr(&mut self, value: u32) {
        self.bus();
        self.arr = value;
    }
    fn write_ccr(&mut self, value: u32) {
        self.bus();
        self.ccr = value;
        self.set_level(self.clock.get());
    }
    fn set_mode(&mut self, mode: crate::trigger::OutputMode) {
        self.bus();
        self.mode = mode;
        self.set_level(self.clock.get());
    }
    fn generate_update(&mut self) {
        self.bus();
        self.cnt = 0;
        self.set_level(self.clock.get());
    }
}

/// The next number of a xorshift64* sequence (`state` ≠ 0): the models'
/// and the tests' seeded randomness.
pub fn xorshift64star(state: &mut u64) -> u64 {
    *state ^= *state >> 12;
    *state ^= *state << 25;
    *state ^= *state >> 27;
    state.wrapping_mul(0x2545_F491_4F6C_DD1D)
}

/// STEP lines on the model's clock: when each was raised last.
#[derive(Debug)]
pub struct ModelPins<'a> {
    /// The model's clock.
    pub clock: &'a core::cell::Cell<u64>,
    /// Tick of the last rising edge per channel.
    pub raised: [Option<u64>; 3],
}

impl crate::timer::StepPins for ModelPins<'_> {
    fn raise(&mut self, ch: usize) {
        self.raised[ch] = Some(self.clock.get());
    }
}
