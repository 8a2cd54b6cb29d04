//! The controller: request dispatcher, motion and homing, capture sequencer
//! and safety supervisor, in one state machine driven from outside.
//!
//! The caller owns time and hardware: it hands in received bytes
//! ([`Controller::on_bytes`]) and polls with the current tick and an input
//! snapshot ([`Controller::poll`]). The step generators belong to the
//! hardware side (the step interrupt runs them); the controller reaches them
//! only through [`Hardware::with_stepper`], for short pushes and reads, and
//! plans segments outside that. Nothing here blocks, allocates or reads a
//! clock.
//!
//! Safety (spec/hardware.md): emergency stop, driver fault and a home switch
//! hit far from home stop every axis at once, switch the light off and latch a
//! fault; silence from the host for 500 ms while moving decelerates every axis
//! and latches `LINK_TIMEOUT`. Axes halted abruptly lose their homed state.
//! A latched fault refuses motion, light and trigger until `ClearFault`.
//!
//! Lost steps: a stepper has no encoder, so the step count is checked
//! against the switches. Whenever a homed axis crosses its switch's home
//! edge while moving (the edge homing latches: the rising edge moving
//! towards it, the falling edge moving away) the count must be the home
//! position (modulo a turn for the disk's index flag) within
//! [`protocol::POSITION_TOLERANCE_STEPS`]; if not, `POSITION_LOST` is latched
//! and [`Event::PositionChecked`] reports the error. Homing an axis that is
//! homed already is a position check of its own: it returns to the switch's
//! approach side at full speed, latches the edge slowly and reports the
//! count's error before resetting it.

use heapless::Deque;
use protocol::{
    AXIS_COUNT, Axis, AxisSet, AxisStatus, Capabilities, DeviceError, DeviceInfo, DeviceState,
    Direction, Event, FULL_DUTY_PERMILLE, FaultFlags, FirmwareVersion, Frame, FrameDecoder,
    HomingFailure, InputState, LightState, LogLevel, LogText, MAX_EXPOSURE_US,
    MAX_FLUSHED_FRAME_LEN, MAX_LIGHT_MARGIN_US, MAX_MIRRORS, MIN_EXPOSURE_US, MirrorPosition,
    MotionOutcome, MoveMode, PROTOCOL_VERSION, Reply, Request, ResetReason, Status,
    TimedCaptureStep, ToHost, TriggerFired, encode_flushed_frame,
};

use crate::config::{PERSISTED_MAX_LEN, PersistedConfig, is_valid, strobe_is_valid};
use crate::hal::{BootInfo, Hardware, Inputs, TICK_HZ, TICKS_PER_MS, TICKS_PER_US};
use crate::planner::{Phase, Profile, SegmentPlanner};
use crate::step::StepGenerator;
use crate::strobe::StrobeMonitor;

/// The host counts as gone after this much silence while an axis moves.
pub const LINK_TIMEOUT_MS: u64 = 500;
/// An input (emergency stop, driver fault, home switch) counts as changed
/// once it has read the same for this long: 3 samples at the board's
/// 5 kHz, so a one-sample glitch latches nothing. An emergency stop stops
/// every axis at most `DEBOUNCE_US` + one sample period (200 µs) after the
/// input asserts: 600 µs on the board.
pub const DEBOUNCE_US: u64 = 400;

/// The inputs as the controller reads them: debounced, each line read as
/// its polarity says.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Readings {
    /// Per axis: the home / index sensor is actuated.
    home: [bool; AXIS_COUNT],
    /// The emergency stop is open.
    estop: bool,
    /// A driver reports a fault.
    driver_fault: bool,
}

/// One debounced input: the accepted level, and the raw level with when
/// (and at what step count of its axis) it last changed.
#[derive(Debug, Clone, Copy, Default)]
struct Debounced {
    level: bool,
    raw: bool,
    since: u64,
    /// The axis' step count at the first sample of the raw level: where a
    /// switch edge really was (the acceptance comes `DEBOUNCE_US` later).
    position: i32,
}

impl Debounced {
    fn sample(&mut self, raw: bool, now: u64, position: i32) {
        if raw != self.raw {
            self.raw = raw;
            self.since = now;
            self.position = position;
        }
        if self.raw != self.level && now.saturating_sub(self.since) >= DEBOUNCE_US * TICKS_PER_US {
            self.level = self.raw;
        }
    }

    /// The line is read the other way round from now on: what was
    /// sampled and accepted of it means the opposite, at once (no edge).
    fn invert(&mut self) {
        (self.level, self.raw) = (!self.level, !self.raw);
    }

    /// When a pending change will be accepted.
    fn deadline(&self) -> Option<u64> {
        (self.raw != self.level).then_some(self.since + DEBOUNCE_US * TICKS_PER_US)
    }
}
/// Events buffered for the host before the oldest is dropped.
pub const EVENT_QUEUE_LEN: usize = 16;

/// Firmware version reported in the handshake (from Cargo.toml).
pub const FIRMWARE_VERSION: FirmwareVersion = FirmwareVersion {
    major: parse_u8(env!("CARGO_PKG_VERSION_MAJOR")),
    minor: parse_u8(env!("CARGO_PKG_VERSION_MINOR")),
    patch: parse_u8(env!("CARGO_PKG_VERSION_PATCH")),
};

const fn parse_u8(s: &str) -> u8 {
    let b = s.as_bytes();
    let mut i = 0;
    let mut v: u8 = 0;
    while i < b.len() {
        v = v * 10 + (b[i] - b'0');
        i += 1;
    }
    v
}

/// Stage of one axis' homing sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum HomingStage {
    FastApproach,
    /// The switch was hit on the fast approach: braking at `a_max` before
    /// backing off (an instant stop at speed would lose steps).
    Braking,
    BackOff,
    SlowApproach,
    /// A homed axis checks its position: straight to the approach side of
    /// the switch at full speed, then the slow approach.
    Return,
}

/// Whether a homing sequence is a position check, and how it is going.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Check {
    /// Plain homing: the axis was not homed.
    Off,
    /// The axis was homed; it expects the switch where its count says.
    Near,
    /// The switch was not where the count said: searching the full travel.
    Wide,
}

/// What one axis is doing.
#[derive(Debug, Clone)]
struct AxisMotion {
    planner: SegmentPlanner,
    homing: Option<HomingStage>,
}

/// What the controller as a whole is doing.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Activity {
    Idle,
    /// A move (`Move`, `GoToMirror`, or the motion of a capture step).
    Moving {
        axes: AxisSet,
        capture: Option<TimedCaptureStep>,
        stopping: bool,
    },
    Homing {
        axes: AxisSet,
        started: u64,
        stopping: bool,
    },
    Settling {
        step: TimedCaptureStep,
        until: u64,
    },
    /// The light is on, the trigger not yet: a step's light margin.
    Leading {
        step: TimedCaptureStep,
        until: u64,
    },
    /// The trigger is high; after it, the light stays on `trail` ticks.
    Exposing {
        until: u64,
        trail: u64,
    },
}

/// The controller. See the module docs.
#[derive(Debug)]
pub struct Controller {
    boot: BootInfo,
    config: PersistedConfig,
    motion: [Option<AxisMotion>; AXIS_COUNT],
    homed: [bool; AXIS_COUNT],
    check: [Check; AXIS_COUNT],
    /// Homing: where the switch was hit at speed (braking runs past it).
    hit: [Option<i32>; AXIS_COUNT],
    activity: Activity,
    faults: FaultFlags,
    light: LightState,
    trigger_seq: u32,
    last_trigger: Option<TriggerFired>,
    /// When the light, left on after a pulse for its step's margin, goes
    /// back to its idle state.
    light_trail: Option<u64>,
    handshake: bool,
    last_request: Option<(u8, Reply)>,
    last_rx: u64,
    now: u64,
    /// The debounced inputs as of the last poll.
    prev_inputs: Readings,
    /// Debouncers: home switch per axis, emergency stop, driver fault.
    debounce: [Debounced; AXIS_COUNT + 2],
    events: Deque<Event, EVENT_QUEUE_LEN>,
    event_seq: u8,
    decoder: FrameDecoder<Request>,
    reset_requested: bool,
    bootloader_requested: bool,
    /// Step-queue underruns (planner fell behind); diagnostics only.
    underruns: u32,
    /// The camera's exposure strobe, watched after each pulse while
    /// `config.strobe` says so.
    strobe: StrobeMonitor,
}

impl Controller {
    /// A controller after boot, with the persisted configuration blob if one
    /// was read from storage (invalid or missing → defaults).
    pub fn new(boot: BootInfo, persisted: Option<&[u8]>) -> Controller {
        let config = persisted.and_then(PersistedConfig::decode).unwrap_or_default();
        let mut c = Controller {
            boot,
            config,
            motion: Default::default(),
            homed: [false; AXIS_COUNT],
            check: [Check::Off; AXIS_COUNT],
            hit: [None; AXIS_COUNT],
            activity: Activity::Idle,
            faults: FaultFlags::NONE,
            light: LightState { on: false, duty_permille: FULL_DUTY_PERMILLE },
            trigger_seq: 0,
            last_trigger: None,
            light_trail: None,
            handshake: false,
            last_request: None,
            last_rx: 0,
            now: 0,
            prev_inputs: Readings::default(),
            debounce: Default::default(),
            events: Deque::new(),
            event_seq: 0,
            decoder: FrameDecoder::new(),
            reset_requested: false,
            bootloader_requested: false,
            underruns: 0,
            strobe: StrobeMonitor::default(),
        };
        c.emit(Event::Boot { boot_id: boot.boot_id, reason: boot.reason });
        if boot.reason == ResetReason::Watchdog {
            c.faults = FaultFlags::WATCHDOG_RESET;
        }
        if boot.storage_failed {
            c.faults = c.faults.union(FaultFlags::STORAGE_FAILED);
        }
        if !c.faults.is_empty() {
            c.emit(Event::FaultRaised { faults: c.faults, axis: None });
        }
        c
    }

    // ----- accessors used by the board, the simulator and tests -------------

    /// Whether `axis` has been homed.
    pub fn is_homed(&self, axis: Axis) -> bool {
        self.homed[axis.index()]
    }
    /// The axes a running homing moves (also while it stops short).
    pub fn homing_axes(&self) -> AxisSet {
        match self.activity {
            Activity::Homing { axes, .. } => axes,
            _ => AxisSet::NONE,
        }
    }
    /// Whether a homing or a move (a capture step's included) is running,
    /// also while it stops short: it ends with [`Event::MotionDone`].
    pub fn in_motion(&self) -> bool {
        matches!(self.activity, Activity::Moving { .. } | Activity::Homing { .. })
    }
    /// Latched faults.
    pub fn faults(&self) -> FaultFlags {
        self.faults
    }
    /// The configuration in force.
    pub fn config(&self) -> &PersistedConfig {
        &self.config
    }
    /// Whether a `Reset` request asks the caller to reboot (after sending
    /// the pending reply).
    pub fn reset_requested(&self) -> bool {
        self.reset_requested
    }
    /// Whether an `EnterBootloader` request asks the caller to reset into
    /// the chip's ROM bootloader (after sending the pending reply;
    /// [`crate::bootloader`]).
    pub fn bootloader_requested(&self) -> bool {
        self.bootloader_requested
    }
    /// Step-queue underruns since boot.
    pub fn underruns(&self) -> u32 {
        self.underruns
    }
    /// Whether any axis has steps scheduled or planned.
    pub fn is_moving(&self) -> bool {
        self.motion.iter().any(Option::is_some)
    }
    /// The earliest tick at which [`poll`](Self::poll) has timed work to do
    /// (settle or exposure end, homing or link timeout), if any.
    pub fn next_deadline(&self) -> Option<u64> {
        let timed = match self.activity {
            Activity::Settling { until, .. }
            | Activity::Leading { until, .. }
            | Activity::Exposing { until, .. } => Some(until),
            // The timeout of each axis still searching (as `poll_homing`
            // checks it): none for an axis homed already, none while the
            // homing stops short.
            Activity::Homing { started, axes, stopping: false } => axes
                .iter()
                .filter(|a| self.motion[a.index()].as_ref().is_some_and(|m| m.homing.is_some()))
                .map(|a| {
                    started + self.config.axes[a.index()].homing.timeout_ms as u64 * TICKS_PER_MS
                })
                .min(),
            _ => None,
        };
        let link = (self.is_moving() && !self.faults.contains(FaultFlags::LINK_TIMEOUT))
            .then_some(self.last_rx + LINK_TIMEOUT_MS * TICKS_PER_MS + 1);
        let inputs = self.debounce.iter().filter_map(Debounced::deadline).min();
        [timed, link, inputs, self.light_trail].into_iter().flatten().min()
    }

    // ----- link ------------------------------------------------------------

    /// Feed bytes received from the host; every reply frame is handed to `tx`.
    /// Corrupted frames are dropped silently (the host retransmits).
    pub fn on_bytes(
        &mut self,
        chunk: &[u8],
        now: u64,
        hw: &mut impl Hardware,
        tx: &mut impl FnMut(&[u8]),
    ) {
        let mut rest = chunk;
        while !rest.is_empty() {
            let mut feed = self.decoder.feed(rest);
            let frame = feed.next();
            rest = feed.remaining();
            if let Some(Ok(frame)) = frame {
                let (seq, reply) = self.handle(frame, now, hw);
                send(tx, seq, &ToHost::Reply(reply));
            }
        }
    }

    /// Send queued events through `tx`.
    pub fn drain_events(&mut self, tx: &mut impl FnMut(&[u8])) {
        while let Some(event) = self.events.pop_front() {
            send(tx, self.event_seq, &ToHost::Event(event));
            self.event_seq = self.event_seq.wrapping_add(1);
        }
    }

    /// Take the next queued event without encoding it.
    pub fn pop_event(&mut self) -> Option<Event> {
        let e = self.events.pop_front();
        if e.is_some() {
            self.event_seq = self.event_seq.wrapping_add(1);
        }
        e
    }

    /// Execute one decoded request (at most once per sequence number) and
    /// return the reply with its sequence number.
    pub fn handle(
        &mut self,
        frame: Frame<Request>,
        now: u64,
        hw: &mut impl Hardware,
    ) -> (u8, Reply) {
        self.now = now;
        self.last_rx = now;
        if !matches!(frame.msg, Request::Hello { .. })
            && let Some((seq, reply)) = self.last_request
            && seq == frame.seq
        {
            return (seq, reply);
        }
        let reply = match self.execute(frame.msg, hw) {
            Ok(reply) => reply,
            Err(e) => Reply::Error(e),
        };
        self.last_request = Some((frame.seq, reply));
        (frame.seq, reply)
    }

    fn execute(&mut self, request: Request, hw: &mut impl Hardware) -> Result<Reply, DeviceError> {
        if let Request::Hello { host_protocol } = request {
            self.last_request = None;
            self.handshake = PROTOCOL_VERSION.is_compatible_with(host_protocol);
            if !self.handshake {
                return Err(DeviceError::UnsupportedVersion(PROTOCOL_VERSION));
            }
            return Ok(Reply::Info(self.info()));
        }
        if !self.handshake {
            return Err(DeviceError::NoHandshake);
        }
        match request {
            Request::Hello { .. } => unreachable!("handled above"),
            Request::Ping { token } => Ok(Reply::Pong { token }),
            Request::GetStatus => Ok(Reply::Status(self.status(hw))),
            Request::Home { axes } => self.start_homing(axes, hw).map(|_| Reply::Ack),
            Request::Move { mode, targets } => {
                self.ensure_can_move()?;
                let targets = self.resolve_targets(mode, targets, hw)?;
                self.start_move(targets, None, hw)?;
                Ok(Reply::Ack)
            }
            Request::GoToMirror { mirror } => {
                self.ensure_can_move()?;
                let position = self.mirror(mirror)?;
                let targets =
                    self.resolve_targets(MoveMode::Absolute, position.steps.map(Some), hw)?;
                self.start_move(targets, None, hw)?;
                Ok(Reply::Ack)
            }
            Request::GetMirror { mirror } => {
                if mirror as usize >= MAX_MIRRORS {
                    return Err(DeviceError::OutOfRange);
                }
                let position = self.config.mirrors.get(mirror as usize).copied().flatten();
                Ok(Reply::Mirror { mirror, position })
            }
            Request::SetMirror { mirror, position } => {
                let i = mirror as usize;
                if i >= MAX_MIRRORS {
                    return Err(DeviceError::OutOfRange);
                }
                for axis in Axis::ALL {
                    self.check_limits(axis, position.steps[axis.index()])?;
                }
                while self.config.mirrors.len() <= i {
                    // Cannot fail: i < MAX_MIRRORS = capacity.
                    let _ = self.config.mirrors.push(None);
                }
                self.config.mirrors[i] = Some(position);
                Ok(Reply::Ack)
            }
            Request::SetMirrorCount { count } => {
                if count as usize > MAX_MIRRORS {
                    return Err(DeviceError::OutOfRange);
                }
                self.config.mirrors.truncate(count as usize);
                while self.config.mirrors.len() < count as usize {
                    let _ = self.config.mirrors.push(None);
                }
                Ok(Reply::Ack)
            }
            Request::SetLight(state) => {
                self.ensure_no_fault()?;
                if state.duty_permille > FULL_DUTY_PERMILLE {
                    return Err(DeviceError::OutOfRange);
                }
                if matches!(
                    self.activity,
                    Activity::Exposing { .. }
                        | Activity::Settling { .. }
                        | Activity::Leading { .. }
                ) {
                    return Err(DeviceError::Busy);
                }
                self.light = state;
                self.restore_light(hw);
                Ok(Reply::Ack)
            }
            Request::Trigger { exposure_us } => {
                self.ensure_no_fault()?;
                check_exposure(exposure_us)?;
                if self.activity != Activity::Idle {
                    return Err(DeviceError::Busy);
                }
                // A bare trigger (a dark frame) sees the light as set, not
                // a capture step's margin.
                if self.light_trail.is_some() {
                    self.restore_light(hw);
                }
                self.fire_trigger(exposure_us, None, 0, hw);
                Ok(Reply::Ack)
            }
            Request::CaptureStep(step) => {
                self.capture_step(TimedCaptureStep { step, light_margin_us: 0 }, hw)
            }
            Request::TimedCaptureStep(timed) => self.capture_step(timed, hw),
            Request::Stop => {
                self.controlled_stop(hw);
                Ok(Reply::Ack)
            }
            Request::EmergencyStop => {
                self.raise_fault(FaultFlags::EMERGENCY_STOP, None, hw);
                self.de_energise(hw);
                Ok(Reply::Ack)
            }
            Request::ClearFault => {
                // The drivers are disabled (EN released) since the fault: a
                // TMC2209 clears its fault while disabled, so the fault
                // input reads clear by the time the host asks again. The
                // next move enables them.
                let inputs = self.prev_inputs;
                if inputs.estop || inputs.driver_fault {
                    self.de_energise(hw);
                    return Err(DeviceError::FaultLatched);
                }
                self.faults = FaultFlags::NONE;
                Ok(Reply::Ack)
            }
            Request::GetAxisConfig { axis } => {
                Ok(Reply::AxisConfig { axis, config: self.config.axes[axis.index()] })
            }
            Request::SetAxisConfig { axis, config } => {
                if self.activity != Activity::Idle {
                    return Err(DeviceError::Busy);
                }
                if !is_valid(&config) {
                    return Err(DeviceError::BadRequest);
                }
                self.config.axes[axis.index()] = config;
                self.homed[axis.index()] = false;
                Ok(Reply::Ack)
            }
            Request::SaveConfig => {
                if !self.boot.capabilities.contains(Capabilities::PERSISTENT_CONFIG) {
                    return Err(DeviceError::Unsupported);
                }
                // A flash erase stalls instruction fetch on the single-bank
                // F411 and with it the step interrupt: only when nothing
                // moves, and like motion, not while a fault is latched.
                self.ensure_can_move()?;
                let mut buf = [0u8; PERSISTED_MAX_LEN];
                let blob = self.config.encode(&mut buf).ok_or(DeviceError::Storage)?;
                hw.save_config(blob).map_err(|_| DeviceError::Storage)?;
                Ok(Reply::Ack)
            }
            Request::GetBoardConfig => Ok(Reply::BoardConfig(self.config.board)),
            Request::SetBoardConfig(board) => {
                if self.activity != Activity::Idle {
                    return Err(DeviceError::Busy);
                }
                if board.driver_fault_active_high != self.config.board.driver_fault_active_high {
                    // As for the home sensors: the same line now means the
                    // opposite, at once. A fault latched only because the
                    // line was read the wrong way round can be cleared
                    // straight away; a line that now reads a fault latches
                    // one at the next poll.
                    self.debounce[AXIS_COUNT + 1].invert();
                    self.prev_inputs.driver_fault = !self.prev_inputs.driver_fault;
                }
                self.config.board = board;
                Ok(Reply::Ack)
            }
            Request::GetHomeSensors => Ok(Reply::HomeSensors(self.config.home)),
            Request::GetInputs => Ok(Reply::Inputs(self.input_state())),
            Request::SetHomeSensors(home) => {
                if self.activity != Activity::Idle {
                    return Err(DeviceError::Busy);
                }
                for axis in Axis::ALL {
                    let i = axis.index();
                    if home.active_high[i] != self.config.home.active_high[i] {
                        // The same line now means the opposite: so does
                        // what was read of it, at once (no edge), and the
                        // axis' home is no longer known.
                        self.debounce[i].invert();
                        self.prev_inputs.home[i] = !self.prev_inputs.home[i];
                        self.homed[i] = false;
                    }
                }
                self.config.home = home;
                Ok(Reply::Ack)
            }
            Request::GetLastTrigger => Ok(Reply::Trigger(self.last_trigger)),
            Request::GetStrobe => Ok(Reply::Strobe(self.config.strobe)),
            Request::SetStrobe(strobe) => {
                if self.activity != Activity::Idle {
                    return Err(DeviceError::Busy);
                }
                if !strobe_is_valid(&strobe) {
                    return Err(DeviceError::OutOfRange);
                }
                if strobe.enabled && !self.boot.capabilities.contains(Capabilities::EXPOSURE_STROBE)
                {
                    return Err(DeviceError::Unsupported);
                }
                // The last pulse's watch ends by the setting it began with.
                if let Some(e) = self.strobe.finish(self.now) {
                    self.emit(e);
                }
                self.config.strobe = strobe;
                Ok(Reply::Ack)
            }
            Request::Reset => {
                self.halt_all(hw);
                self.reset_requested = true;
                Ok(Reply::Ack)
            }
            Request::EnterBootloader => {
                if !self.boot.capabilities.contains(Capabilities::SYSTEM_BOOTLOADER) {
                    return Err(DeviceError::Unsupported);
                }
                // Everything off now: the ROM leaves the pins floating.
                self.halt_all(hw);
                self.light.on = false;
                self.restore_light(hw);
                hw.set_trigger(false);
                self.activity = Activity::Idle;
                self.bootloader_requested = true;
                Ok(Reply::Ack)
            }
        }
    }

    fn info(&self) -> DeviceInfo {
        DeviceInfo {
            protocol: PROTOCOL_VERSION,
            firmware: FIRMWARE_VERSION,
            board: self.boot.board,
            device_id: self.boot.device_id,
            capabilities: self.boot.capabilities,
            mirror_count: self.config.mirrors.len() as u8,
            boot_id: self.boot.boot_id,
        }
    }

    /// Axis positions, steps.
    fn positions(&self, hw: &mut impl Hardware) -> [i32; AXIS_COUNT] {
        Axis::ALL.map(|a| hw.with_stepper(a, |s| s.position()))
    }

    /// A status snapshot.
    pub fn status(&self, hw: &mut impl Hardware) -> Status {
        let positions = self.positions(hw);
        let axes = Axis::ALL.map(|axis| {
            let i = axis.index();
            let steps = positions[i];
            AxisStatus {
                position_steps: steps,
                position_units: steps as f32 / self.config.axes[i].steps_per_unit,
                moving: self.motion[i].is_some(),
                homed: self.homed[i],
            }
        });
        let state = if !self.faults.is_empty() {
            DeviceState::Faulted
        } else {
            match self.activity {
                Activity::Idle => DeviceState::Idle,
                Activity::Homing { .. } => DeviceState::Homing,
                Activity::Moving { capture: None, .. } => DeviceState::Moving,
                _ => DeviceState::Capturing,
            }
        };
        Status {
            axes,
            light: self.light,
            faults: self.faults,
            state,
            trigger_seq: self.trigger_seq,
            uptime_ms: (self.now / TICKS_PER_MS) as u32,
        }
    }

    // ----- validation --------------------------------------------------------

    fn ensure_no_fault(&self) -> Result<(), DeviceError> {
        if self.faults.is_empty() { Ok(()) } else { Err(DeviceError::FaultLatched) }
    }

    /// Start a capture step: the move to its mirror, then settle, light,
    /// trigger.
    fn capture_step(
        &mut self,
        timed: TimedCaptureStep,
        hw: &mut impl Hardware,
    ) -> Result<Reply, DeviceError> {
        self.ensure_can_move()?;
        let step = timed.step;
        check_exposure(step.exposure_us)?;
        if step.light_duty_permille == 0
            || step.light_duty_permille > FULL_DUTY_PERMILLE
            || timed.light_margin_us > MAX_LIGHT_MARGIN_US
        {
            return Err(DeviceError::OutOfRange);
        }
        let position = self.mirror(step.mirror)?;
        let targets = self.resolve_targets(MoveMode::Absolute, position.steps.map(Some), hw)?;
        self.start_move(targets, Some(timed), hw)?;
        Ok(Reply::Ack)
    }

    fn ensure_can_move(&self) -> Result<(), DeviceError> {
        self.ensure_no_fault()?;
        if self.activity != Activity::Idle {
            return Err(DeviceError::Busy);
        }
        Ok(())
    }

    fn mirror(&self, mirror: u8) -> Result<MirrorPosition, DeviceError> {
        if mirror as usize >= MAX_MIRRORS {
            return Err(DeviceError::OutOfRange);
        }
        self.config.mirrors.get(mirror as usize).copied().flatten().ok_or(DeviceError::MirrorNotSet)
    }

    fn check_limits(&self, axis: Axis, target: i32) -> Result<(), DeviceError> {
        let c = &self.config.axes[axis.index()];
        let ok = if c.continuous {
            (0..c.steps_per_rev as i64).contains(&(target as i64))
        } else {
            (c.min_steps..=c.max_steps).contains(&target)
        };
        if ok { Ok(()) } else { Err(DeviceError::OutOfRange) }
    }

    /// Per-axis signed step deltas for a move request.
    fn resolve_targets(
        &self,
        mode: MoveMode,
        targets: [Option<i32>; AXIS_COUNT],
        hw: &mut impl Hardware,
    ) -> Result<[i32; AXIS_COUNT], DeviceError> {
        let positions = self.positions(hw);
        if targets.iter().all(Option::is_none) {
            return Err(DeviceError::BadRequest);
        }
        let mut deltas = [0i32; AXIS_COUNT];
        for axis in Axis::ALL {
            let Some(t) = targets[axis.index()] else { continue };
            if !self.homed[axis.index()] {
                return Err(DeviceError::NotHomed);
            }
            let c = &self.config.axes[axis.index()];
            let pos = positions[axis.index()] as i64;
            let delta = match (mode, c.continuous) {
                (MoveMode::Absolute, false) => {
                    self.check_limits(axis, t)?;
                    t as i64 - pos
                }
                (MoveMode::Relative, false) => {
                    let target = pos + t as i64;
                    let target = i32::try_from(target).map_err(|_| DeviceError::OutOfRange)?;
                    self.check_limits(axis, target)?;
                    t as i64
                }
                (MoveMode::Absolute, true) => {
                    // Shortest way round to the target angle.
                    self.check_limits(axis, t)?;
                    let rev = c.steps_per_rev as i64;
                    let d = (t as i64 - pos).rem_euclid(rev);
                    if d > rev / 2 { d - rev } else { d }
                }
                (MoveMode::Relative, true) => t as i64,
            };
            deltas[axis.index()] = i32::try_from(delta).map_err(|_| DeviceError::OutOfRange)?;
        }
        Ok(deltas)
    }

    // ----- motion -------------------------------------------------------------

    fn start_move(
        &mut self,
        deltas: [i32; AXIS_COUNT],
        capture: Option<TimedCaptureStep>,
        hw: &mut impl Hardware,
    ) -> Result<(), DeviceError> {
        let mut axes = AxisSet::NONE;
        for axis in Axis::ALL {
            let delta = deltas[axis.index()];
            if delta != 0 {
                let c = self.config.axes[axis.index()];
                let profile =
                    Profile::trapezoid(delta.unsigned_abs(), 0.0, c.v_max as f64, c.a_max as f64);
                self.start_axis(axis, profile, delta.signum(), None, hw);
                axes = axes.with(axis);
            }
        }
        self.activity = Activity::Moving { axes, capture, stopping: false };
        if axes.is_empty() {
            // Already there: complete at the next poll.
            self.finish_motion(MotionOutcome::Completed, hw);
        }
        Ok(())
    }

    fn start_axis(
        &mut self,
        axis: Axis,
        profile: Profile,
        direction: i32,
        homing: Option<HomingStage>,
        hw: &mut impl Hardware,
    ) {
        let i = axis.index();
        let mut planner = SegmentPlanner::new(profile, TICK_HZ);
        hw.with_stepper(axis, StepGenerator::halt);
        fill_queue(&mut planner, axis, hw);
        hw.set_drivers_enabled(true);
        hw.set_direction(axis, direction > 0);
        let now = self.now;
        if let Some(first) = hw.with_stepper(axis, |s| s.start(now, direction)) {
            hw.arm_step_timer(axis, first);
        }
        self.motion[i] = Some(AxisMotion { planner, homing });
    }

    /// Decelerate every moving axis to rest; abort homing and capture.
    fn controlled_stop(&mut self, hw: &mut impl Hardware) {
        match &mut self.activity {
            Activity::Moving { stopping, .. } | Activity::Homing { stopping, .. } => {
                *stopping = true
            }
            Activity::Settling { .. } | Activity::Leading { .. } | Activity::Exposing { .. } => {
                self.end_exposure(0, hw);
                self.activity = Activity::Idle;
                return;
            }
            Activity::Idle => {}
        }
        for axis in Axis::ALL {
            self.decelerate_axis(axis, hw);
            if let Some(motion) = &mut self.motion[axis.index()] {
                motion.homing = None;
            }
        }
    }

    fn decelerate_axis(&mut self, axis: Axis, hw: &mut impl Hardware) {
        let i = axis.index();
        let Some(motion) = &mut self.motion[i] else { return };
        let decel = self.config.axes[i].a_max as f64;
        let profile = *motion.planner.profile();
        let planned = motion.planner.planned();
        // Cut the plan after the step already armed in the timer, unless the
        // move is ramping down already (as fast as allowed). More steps
        // scheduled than planned: the armed step is the one a cut kept of
        // the plan before, and this plan is a stop already.
        let cut = hw.with_stepper(axis, |s| {
            if !s.is_running() {
                return None;
            }
            let pending = planned.checked_sub(s.scheduled_steps())? + 1;
            if profile.phase(pending as f64) == Phase::Decelerate {
                return None;
            }
            s.truncate_after_pending();
            Some(pending)
        });
        if let Some(pending) = cut {
            let v = profile.velocity_at(pending as f64);
            motion.planner = SegmentPlanner::new(Profile::stop(v, decel), TICK_HZ);
            fill_queue(&mut motion.planner, axis, hw);
        }
    }

    /// Stop every axis at once (no ramp): an axis stopped while stepping may
    /// have lost steps, so it loses its homed state.
    fn halt_all(&mut self, hw: &mut impl Hardware) {
        for axis in Axis::ALL {
            let i = axis.index();
            if self.motion[i].take().is_some() {
                hw.with_stepper(axis, StepGenerator::halt);
                hw.disarm_step_timer(axis);
                self.homed[i] = false;
            }
        }
    }

    fn finish_motion(&mut self, outcome: MotionOutcome, hw: &mut impl Hardware) {
        let axes = match self.activity {
            Activity::Moving { axes, .. } | Activity::Homing { axes, .. } => axes,
            _ => AxisSet::NONE,
        };
        let capture = match self.activity {
            Activity::Moving { capture, stopping: false, .. } => capture,
            _ => None,
        };
        let positions = self.positions(hw);
        self.emit(Event::MotionDone { axes, outcome, positions });
        self.activity = match (capture, outcome) {
            (Some(step), MotionOutcome::Completed) => Activity::Settling {
                step,
                until: self.now + step.step.settle_ms as u64 * TICKS_PER_MS,
            },
            _ => Activity::Idle,
        };
    }

    // ----- homing -------------------------------------------------------------

    fn start_homing(&mut self, axes: AxisSet, hw: &mut impl Hardware) -> Result<(), DeviceError> {
        if !axes.is_valid() || axes.is_empty() {
            return Err(DeviceError::BadRequest);
        }
        self.ensure_can_move()?;
        self.activity = Activity::Homing { axes, started: self.now, stopping: false };
        for axis in axes.iter() {
            let i = axis.index();
            self.check[i] = if self.homed[i] { Check::Near } else { Check::Off };
            self.hit[i] = None;
            self.homed[i] = false;
            let stage = if self.prev_inputs.home[i] {
                HomingStage::BackOff
            } else if self.check[i] == Check::Near {
                HomingStage::Return
            } else {
                HomingStage::FastApproach
            };
            self.start_homing_stage(axis, stage, hw);
        }
        Ok(())
    }

    /// Counted position minus home, steps (for a continuous axis the
    /// nearest value modulo a turn).
    fn position_error(&self, axis: Axis, position: i32) -> i32 {
        let c = &self.config.axes[axis.index()];
        let d = position as i64 - c.homing.home_position as i64;
        let d = if c.continuous {
            let rev = c.steps_per_rev as i64;
            let m = d.rem_euclid(rev);
            if m > rev / 2 { m - rev } else { m }
        } else {
            d
        };
        d.clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    fn start_homing_stage(&mut self, axis: Axis, stage: HomingStage, hw: &mut impl Hardware) {
        let c = self.config.axes[axis.index()];
        let h = c.homing;
        let toward = if h.direction == Direction::Positive { 1 } else { -1 };
        // Back off by the braking distance past the switch as well.
        let overshoot = match self.hit[axis.index()] {
            Some(hit) => hw.with_stepper(axis, |s| s.position().abs_diff(hit)),
            None => 0,
        };
        let (steps, speed, direction) = match stage {
            HomingStage::FastApproach | HomingStage::Braking => {
                (h.max_travel_steps, h.fast_speed, toward)
            }
            HomingStage::BackOff => {
                (h.backoff_steps.saturating_add(overshoot), h.fast_speed, -toward)
            }
            HomingStage::SlowApproach => {
                (h.backoff_steps.saturating_mul(2).saturating_add(overshoot), h.slow_speed, toward)
            }
            HomingStage::Return => {
                // To the back-off distance on the approach side of where
                // the count says the switch is.
                // A continuous axis goes round the approach way unless it is
                // between that point and home already: never across its
                // index flag.
                let position = hw.with_stepper(axis, |s| s.position());
                let ahead = toward as i64 * self.position_error(axis, position) as i64;
                let back = h.backoff_steps as i64;
                let forward = if c.continuous && !(-back..0).contains(&ahead) {
                    (-back - ahead).rem_euclid(c.steps_per_rev as i64)
                } else {
                    -back - ahead
                };
                let delta = toward as i64 * forward;
                if delta == 0 || delta.unsigned_abs() > u32::MAX as u64 {
                    return self.start_homing_stage(axis, HomingStage::SlowApproach, hw);
                }
                (delta.unsigned_abs() as u32, c.v_max, delta.signum() as i32)
            }
        };
        let profile = Profile::trapezoid(steps, 0.0, speed as f64, c.a_max as f64);
        self.start_axis(axis, profile, direction, Some(stage), hw);
    }

    /// Advance the homing sequences after inputs changed or moves ended.
    fn poll_homing(&mut self, inputs: &Readings, hw: &mut impl Hardware) {
        let Activity::Homing { axes, started, stopping } = self.activity else { return };
        if stopping {
            return;
        }
        for axis in axes.iter() {
            let i = axis.index();
            let Some(motion) = &self.motion[i] else { continue };
            let Some(stage) = motion.homing else { continue };
            let h = self.config.axes[i].homing;
            if self.now.saturating_sub(started) >= h.timeout_ms as u64 * TICKS_PER_MS {
                self.homing_failed(axis, HomingFailure::Timeout, hw);
                return;
            }
            let switch = inputs.home[i];
            let finished = motion.planner.is_done() && hw.with_stepper(axis, |s| s.is_idle());
            match stage {
                HomingStage::FastApproach | HomingStage::Return if switch => {
                    self.hit[i] = Some(self.edge_position(axis));
                    self.decelerate_axis(axis, hw);
                    if let Some(m) = &mut self.motion[i] {
                        m.homing = Some(HomingStage::Braking);
                    }
                }
                HomingStage::Braking if finished => {
                    self.start_homing_stage(axis, HomingStage::BackOff, hw);
                }
                HomingStage::Return if finished => {
                    self.start_homing_stage(axis, HomingStage::SlowApproach, hw);
                }
                HomingStage::SlowApproach if switch => {
                    self.stop_axis_now(axis, hw);
                    // The edge was where the switch first read pressed; the
                    // axis has gone on a little since (the debounce time).
                    let edge = self.edge_position(axis);
                    if self.check[i] != Check::Off {
                        let error_steps = self.position_error(axis, edge);
                        self.emit(Event::PositionChecked { axis, error_steps });
                    }
                    hw.with_stepper(axis, |s| {
                        let past = s.position().wrapping_sub(edge);
                        s.set_position(h.home_position.wrapping_add(past))
                    });
                    self.homed[i] = true;
                }
                HomingStage::SlowApproach if finished && self.check[i] == Check::Near => {
                    // The switch is not where the count said: search for
                    // it; the count goes on, so the error is still measured.
                    self.check[i] = Check::Wide;
                    self.start_homing_stage(axis, HomingStage::FastApproach, hw);
                }
                HomingStage::FastApproach | HomingStage::SlowApproach if finished => {
                    self.homing_failed(axis, HomingFailure::SwitchNotFound, hw);
                    return;
                }
                HomingStage::BackOff if finished => {
                    if switch {
                        self.homing_failed(axis, HomingFailure::SwitchStuck, hw);
                        return;
                    }
                    self.start_homing_stage(axis, HomingStage::SlowApproach, hw);
                }
                _ => {}
            }
        }
        if axes.iter().all(|a| self.homed[a.index()]) {
            self.finish_motion(MotionOutcome::Completed, hw);
        }
    }

    fn stop_axis_now(&mut self, axis: Axis, hw: &mut impl Hardware) {
        hw.with_stepper(axis, StepGenerator::halt);
        hw.disarm_step_timer(axis);
        self.motion[axis.index()] = None;
    }

    fn homing_failed(&mut self, axis: Axis, why: HomingFailure, hw: &mut impl Hardware) {
        self.halt_all(hw);
        self.faults = self.faults.union(FaultFlags::HOMING_FAILED);
        self.finish_motion(MotionOutcome::HomingFailed(axis, why), hw);
        self.emit(Event::FaultRaised { faults: self.faults, axis: Some(axis) });
    }

    // ----- capture ------------------------------------------------------------

    /// Raise the trigger for `exposure_us`; the light (if on for a step)
    /// stays on `trail` ticks after the pulse.
    fn fire_trigger(
        &mut self,
        exposure_us: u32,
        mirror: Option<u8>,
        trail: u64,
        hw: &mut impl Hardware,
    ) {
        self.trigger_seq = self.trigger_seq.wrapping_add(1);
        let ticks = exposure_us as u64 * TICKS_PER_US;
        // A pulse the hardware ends: the light stays on until it has.
        let ended = hw.start_trigger_pulse(ticks).unwrap_or(0);
        let fired = TriggerFired {
            trigger_seq: self.trigger_seq,
            timestamp_us: self.now / TICKS_PER_US,
            exposure_us,
            mirror,
        };
        self.last_trigger = Some(fired);
        if self.config.strobe.enabled
            && let Some(last) = self.strobe.start(self.trigger_seq, self.now, ticks)
        {
            self.emit(last);
        }
        self.emit(Event::TriggerFired(fired));
        self.activity = Activity::Exposing { until: (self.now + ticks).max(ended), trail };
    }

    /// Trigger low; the light back to its idle state now, or `trail` ticks
    /// from now.
    fn end_exposure(&mut self, trail: u64, hw: &mut impl Hardware) {
        hw.set_trigger(false);
        if trail > 0 {
            self.light_trail = Some(self.now + trail);
        } else {
            self.restore_light(hw);
        }
    }

    /// The light as the host last set it (any margin's trail is over).
    fn restore_light(&mut self, hw: &mut impl Hardware) {
        self.light_trail = None;
        hw.set_light(if self.light.on { self.light.duty_permille } else { 0 });
    }

    // ----- safety -------------------------------------------------------------

    /// Latch `fault`, stop everything at once, light and trigger off.
    fn raise_fault(&mut self, fault: FaultFlags, axis: Option<Axis>, hw: &mut impl Hardware) {
        let new = !self.faults.contains(fault);
        self.faults = self.faults.union(fault);
        let was_moving = self.is_moving();
        self.halt_all(hw);
        self.light.on = false;
        self.restore_light(hw);
        hw.set_trigger(false);
        if was_moving || matches!(self.activity, Activity::Moving { .. } | Activity::Homing { .. })
        {
            self.finish_motion(MotionOutcome::Aborted, hw);
        }
        self.activity = Activity::Idle;
        if new {
            self.emit(Event::FaultRaised { faults: self.faults, axis });
        }
    }

    fn check_safety(&mut self, inputs: &Readings, hw: &mut impl Hardware) {
        if inputs.estop {
            self.raise_fault(FaultFlags::EMERGENCY_STOP, None, hw);
        }
        if inputs.driver_fault {
            self.raise_fault(FaultFlags::DRIVER_FAULT, None, hw);
        }
        if inputs.estop || inputs.driver_fault {
            self.de_energise(hw);
        }
        for axis in Axis::ALL {
            let i = axis.index();
            let rising = inputs.home[i] && !self.prev_inputs.home[i];
            let falling = !inputs.home[i] && self.prev_inputs.home[i];
            let homing = self.motion[i].as_ref().is_some_and(|m| m.homing.is_some());
            if !self.homed[i] || homing || !(rising || falling) {
                continue;
            }
            let c = &self.config.axes[i];
            let continuous = c.continuous;
            let toward = if c.homing.direction == Direction::Positive { 1 } else { -1 };
            let position = self.edge_position(axis);
            let direction = hw.with_stepper(axis, |s| s.direction());
            // A limit switch far from home is a crash or a broken switch,
            // not a count to correct: a person must look. (The disk's index
            // flag is passed every turn; only its home edge is checked.)
            if rising && !continuous && self.far_from_home(axis, position) {
                self.raise_fault(FaultFlags::UNEXPECTED_HOME_SWITCH, Some(axis), hw);
                continue;
            }
            let moving = self.motion[i].is_some();
            let home_edge = (rising && direction == toward) || (falling && direction == -toward);
            if moving && home_edge {
                let error_steps = self.position_error(axis, position);
                if error_steps.unsigned_abs() > protocol::POSITION_TOLERANCE_STEPS as u32 {
                    self.emit(Event::PositionChecked { axis, error_steps });
                    self.raise_fault(FaultFlags::POSITION_LOST, Some(axis), hw);
                }
            }
        }
        let silent = self.now.saturating_sub(self.last_rx) > LINK_TIMEOUT_MS * TICKS_PER_MS;
        if silent && self.is_moving() && !self.faults.contains(FaultFlags::LINK_TIMEOUT) {
            // Decelerate rather than halt: no steps are lost, homing is kept.
            self.faults = self.faults.union(FaultFlags::LINK_TIMEOUT);
            self.light.on = false;
            self.restore_light(hw);
            hw.set_trigger(false);
            self.controlled_stop(hw);
            self.emit(Event::FaultRaised { faults: self.faults, axis: None });
        }
    }

    /// The inputs as last sampled: each line's level (from what its
    /// debouncer last saw, read back through the polarity) and the
    /// debounced reading.
    fn input_state(&self) -> InputState {
        let home = &self.config.home.active_high;
        let fault = &self.debounce[AXIS_COUNT + 1];
        InputState {
            home_line_high: core::array::from_fn(|i| self.debounce[i].raw == home[i]),
            home_actuated: self.prev_inputs.home,
            estop_open: self.prev_inputs.estop,
            driver_fault_line_high: fault.raw == self.config.board.driver_fault_active_high,
            driver_fault: self.prev_inputs.driver_fault,
        }
    }

    /// Debounce the raw inputs (see [`DEBOUNCE_US`]).
    fn debounced(&mut self, raw: &Inputs, hw: &mut impl Hardware) -> Readings {
        let now = self.now;
        for axis in Axis::ALL {
            let i = axis.index();
            let position = hw.with_stepper(axis, |s| s.position());
            let actuated = raw.home_line[i] == self.config.home.active_high[i];
            self.debounce[i].sample(actuated, now, position);
        }
        self.debounce[AXIS_COUNT].sample(raw.estop, now, 0);
        let fault = raw.driver_fault_line == self.config.board.driver_fault_active_high;
        self.debounce[AXIS_COUNT + 1].sample(fault, now, 0);
        Readings {
            home: core::array::from_fn(|i| self.debounce[i].level),
            estop: self.debounce[AXIS_COUNT].level,
            driver_fault: self.debounce[AXIS_COUNT + 1].level,
        }
    }

    /// The step count of `axis` where its switch last changed (the first
    /// sample of the level now accepted).
    fn edge_position(&self, axis: Axis) -> i32 {
        self.debounce[axis.index()].position
    }

    /// Release the drivers (EN off): an emergency stop or a driver fault
    /// leaves no motor energised. Unpowered axes may be moved by hand, so
    /// none stays homed.
    fn de_energise(&mut self, hw: &mut impl Hardware) {
        hw.set_drivers_enabled(false);
        self.homed = [false; AXIS_COUNT];
    }

    /// Whether the switch of `axis` is far (more than the back-off distance)
    /// from where homing found it: it cannot legitimately be hit here.
    pub fn far_from_home(&self, axis: Axis, position: i32) -> bool {
        let backoff = self.config.axes[axis.index()].homing.backoff_steps;
        self.position_error(axis, position).unsigned_abs() > backoff
    }

    // ----- the poll loop ------------------------------------------------------

    /// Advance every state machine to tick `now` with the current inputs.
    /// Call it often (the board: every 200 µs and after every interrupt that
    /// ends a move; the simulator: after every event).
    pub fn poll(&mut self, now: u64, raw: &Inputs, hw: &mut impl Hardware) {
        self.now = now;
        let inputs = &self.debounced(raw, hw);
        let strobe = raw.strobe_line == self.config.strobe.active_high;
        let max_delay = self.config.strobe.max_delay_us as u64 * TICKS_PER_US;
        if let Some(e) = self.strobe.sample(now, strobe, max_delay) {
            self.emit(e);
        }
        self.check_safety(inputs, hw);
        self.poll_homing(inputs, hw);
        self.prev_inputs = *inputs;
        self.refill(hw);
        self.poll_motion_end(hw);
        if let Activity::Settling { step, until } = self.activity
            && now >= until
        {
            if self.faults.is_empty() {
                // The last step's light margin, if still running, is over.
                self.light_trail = None;
                hw.set_light(step.step.light_duty_permille);
                let margin = step.light_margin_us as u64 * TICKS_PER_US;
                self.activity = Activity::Leading { step, until: now + margin };
            } else {
                self.activity = Activity::Idle;
            }
        }
        self.capture_due(now, hw);
    }

    /// The tick at which the running capture has timed work, if any: the
    /// trigger's rise after a step's light margin, the exposure's end (the
    /// asked exposure after the trigger rose, or where the hardware reported
    /// its pulse over ([`Hardware::start_trigger_pulse`]) if later), the
    /// light's return after its margin. The board and the simulator wake
    /// there and call [`Self::capture_due`] instead of waiting for the next
    /// 200 µs poll. Where the controller ends the pulse itself (the
    /// simulator), this makes it last the exposure asked for, not up to a
    /// poll period more (3.2 instead of 3.09 ms: 3.5 % more light than the
    /// host counts on); where the board's timer ends it, the light goes
    /// back and the next step starts at once.
    pub fn capture_deadline(&self) -> Option<u64> {
        let stage = match self.activity {
            Activity::Leading { until, .. } | Activity::Exposing { until, .. } => Some(until),
            _ => None,
        };
        match (stage, self.light_trail) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Do the capture's timed work due at `now` ([`Self::capture_deadline`]):
    /// raise the trigger after the light margin, end the pulse (trigger
    /// low, the light back to its idle state now or after the margin),
    /// return the light. Inputs are not sampled: [`Self::poll`] does that.
    pub fn capture_due(&mut self, now: u64, hw: &mut impl Hardware) {
        self.now = now;
        if self.light_trail.is_some_and(|t| now >= t) {
            self.restore_light(hw);
        }
        match self.activity {
            Activity::Leading { step, until } if now >= until => {
                let trail = step.light_margin_us as u64 * TICKS_PER_US;
                self.fire_trigger(step.step.exposure_us, Some(step.step.mirror), trail, hw);
            }
            Activity::Exposing { until, trail } if now >= until => {
                self.end_exposure(trail, hw);
                self.activity = Activity::Idle;
            }
            _ => {}
        }
    }

    /// Keep every step queue topped up; restart an axis whose queue ran dry.
    fn refill(&mut self, hw: &mut impl Hardware) {
        for axis in Axis::ALL {
            let i = axis.index();
            let Some(motion) = &mut self.motion[i] else { continue };
            fill_queue(&mut motion.planner, axis, hw);
            // If the interrupt ran the queue dry before this refill, the
            // planner fell behind: resume from now.
            let now = self.now;
            if let Some(first) = hw.with_stepper(axis, |s| s.resume(now)) {
                self.underruns += 1;
                hw.arm_step_timer(axis, first);
            }
        }
    }

    fn poll_motion_end(&mut self, hw: &mut impl Hardware) {
        for axis in Axis::ALL {
            let i = axis.index();
            let planned =
                self.motion[i].as_ref().is_some_and(|m| m.homing.is_none() && m.planner.is_done());
            if planned && hw.with_stepper(axis, |s| s.is_idle()) {
                self.motion[i] = None;
                let c = &self.config.axes[i];
                if c.continuous {
                    let rev = c.steps_per_rev as i32;
                    hw.with_stepper(axis, |s| s.set_position(s.position().rem_euclid(rev)));
                }
            }
        }
        if self.is_moving() {
            return;
        }
        match self.activity {
            Activity::Moving { stopping, .. } => {
                let outcome =
                    if stopping { MotionOutcome::Stopped } else { MotionOutcome::Completed };
                self.finish_motion(outcome, hw);
            }
            Activity::Homing { stopping: true, .. } => {
                self.finish_motion(MotionOutcome::Stopped, hw);
            }
            _ => {}
        }
    }

    // ----- events ---------------------------------------------------------------

    fn emit(&mut self, event: Event) {
        if self.events.is_full() {
            self.events.pop_front();
        }
        let _ = self.events.push_back(event);
    }

    /// Queue a log line for the host.
    pub fn log(&mut self, level: LogLevel, text: &str) {
        self.emit(Event::Log { level, text: LogText::truncated(text) });
    }
}

/// Plan segments (outside any lock) and push them into the step queue of
/// `axis` until it is full. Only the interrupt pops, so the free places seen
/// first stay free.
fn fill_queue(planner: &mut SegmentPlanner, axis: Axis, hw: &mut impl Hardware) {
    let free = hw.with_stepper(axis, |s| s.free());
    for _ in 0..free {
        let Some(segment) = planner.next_segment() else { break };
        hw.with_stepper(axis, |s| {
            let _ = s.push(segment);
        });
    }
}

fn check_exposure(exposure_us: u32) -> Result<(), DeviceError> {
    if (MIN_EXPOSURE_US..=MAX_EXPOSURE_US).contains(&exposure_us) {
        Ok(())
    } else {
        Err(DeviceError::OutOfRange)
    }
}

/// Hand one frame to `tx`, after a delimiter (docs/protocol.md §2): a frame
/// whose delimiter line noise hid costs only itself, not the one after it.
fn send(tx: &mut impl FnMut(&[u8]), seq: u8, msg: &ToHost) {
    let mut buf = [0u8; MAX_FLUSHED_FRAME_LEN];
    if let Ok(n) = encode_flushed_frame(seq, msg, &mut buf) {
        tx(&buf[..n]);
    }
}
