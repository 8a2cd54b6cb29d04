//! Random operation of the controller on the [`Rig`], with the safety rules
//! of spec/hardware.md checked at every step the machine makes and after
//! every poll and request.
//!
//! The self-tests drive the controller through the cases someone thought
//! of; this drives it through the ones nobody did: a seeded (or fuzzed)
//! mixture of plausible requests (homing, moves in and out of range, mirror
//! table entries, capture steps, triggers, light, stop, clear, reset, the
//! bootloader), requests decoded from random bytes, line noise, an
//! emergency stop or a driver fault at any moment, home switches that break
//! and mend, axes pushed by hand while unpowered, a host that stops sending,
//! and reboots — with simulated time passing between them, polled at the
//! board's rate.
//!
//! The rules ([`Rule`]): no step while a fault that stops at once is
//! latched; the emergency stop and a driver fault latch within the debounce
//! time and release the drivers; no step of an axis that is not homed
//! outside its homing; a homed axis stays within its soft limits; light off
//! and trigger low while a fault is latched (a failed homing excepted: it
//! stops the axes, not the light); no unpowered axis counted as homed;
//! motion refused while a fault is latched; a reset or the bootloader only
//! once everything has stopped; no trigger pulse longer than the longest
//! exposure, and no step while it is high; the light on only at a level a
//! request asked for, a capture step's only within its light margin of the
//! pulse; a home switch hit far from home latched as a fault; after a
//! reboot, the configuration last saved and the reset's cause latched; an axis stopped within the link
//! timeout and its deceleration once the host falls silent; no wake-up
//! asked for a tick already past; every motion acknowledged ends with
//! exactly one `MotionDone`; no axis steps that no running motion asked to
//! move; a move that completes leaves its axes at its targets; the strobe's
//! report on each pulse agrees with the camera's exposure within a poll; a
//! homing sets the count to the home position at the switch's edge, and a
//! position check reports the count's own error. Any panic of the controller (arithmetic
//! overflow included, in debug builds) fails too.
//!
//! `no_std` and allocation-free like the rest of the test kit: it runs on
//! the PC (`firmware/tests/chaos.rs`), on the Cortex-M4 under QEMU (a
//! short run among the self-tests) and under cargo-fuzz (`fuzz/`), whose
//! bytes are the randomness.

use protocol::{
    AXIS_COUNT, Axis, AxisSet, CaptureStep, DeviceState, Event, FULL_DUTY_PERMILLE, FaultFlags,
    FrameDecoder, LightState, MAX_EXPOSURE_US, MAX_FRAME_LEN, MAX_LIGHT_MARGIN_US, MIN_EXPOSURE_US,
    MirrorPosition, MotionOutcome, MoveMode, PROTOCOL_VERSION, Reply, Request, ResetReason,
    TimedCaptureStep, ToHost, encode_frame,
};

use crate::config::{PERSISTED_MAX_LEN, PersistedConfig};
use crate::controller::{DEBOUNCE_US, LINK_TIMEOUT_MS};
use crate::hal::{TICK_HZ, TICKS_PER_MS, TICKS_PER_US};
use crate::testkit::{CameraStrobe, DEFAULT_SWITCHES, Output, Rig, Switch, Visit, xorshift64star};

/// Where a run's randomness comes from.
pub trait Entropy {
    /// The next random number, `None` once there is no more.
    fn next(&mut self) -> Option<u32>;
}

/// Seeded pseudo-random numbers (xorshift64*): endless.
#[derive(Debug, Clone)]
pub struct Seeded(u64);

impl Seeded {
    /// The sequence of `seed`.
    pub fn new(seed: u64) -> Seeded {
        Seeded(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
}

impl Entropy for Seeded {
    fn next(&mut self) -> Option<u32> {
        Some((xorshift64star(&mut self.0) >> 32) as u32)
    }
}

/// A fuzzer's bytes, four at a time; the run ends with them.
#[derive(Debug, Clone)]
pub struct Bytes<'a>(pub &'a [u8]);

impl Entropy for Bytes<'_> {
    fn next(&mut self) -> Option<u32> {
        if self.0.is_empty() {
            return None;
        }
        let n = self.0.len().min(4);
        let mut b = [0u8; 4];
        b[..n].copy_from_slice(&self.0[..n]);
        self.0 = &self.0[n..];
        Some(u32::from_le_bytes(b))
    }
}

/// What a run does, step by step, for [`run_logged`]'s log: to read the way
/// to a broken rule.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Logged {
    /// A request and its reply.
    Request(Request, Reply),
    /// Bytes through the decoder (noise, a frame, cut or corrupted).
    Bytes(usize),
    /// The inputs after a change: emergency stop, driver fault, switches,
    /// physical positions, keep-alive.
    Inputs {
        /// The emergency stop is open.
        estop: bool,
        /// A driver reports a fault.
        driver_fault: bool,
        /// The home switches.
        switches: [Switch; AXIS_COUNT],
        /// Where the axes physically are.
        physical: [i64; AXIS_COUNT],
        /// The host pings.
        keepalive: bool,
    },
    /// A reboot.
    Reboot(ResetReason),
    /// Simulated time passed, ticks, to this tick.
    Passed(u64, u64),
}

/// A safety rule of the controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rule {
    /// An axis stepped while a fault that stops every axis at once was
    /// latched (any but a link timeout, which decelerates).
    StepWhileFaulted,
    /// The emergency stop or the driver-fault input was asserted longer
    /// than the debounce time and the fault is not latched, or the drivers
    /// are still enabled, or an axis still steps.
    StopInputIgnored,
    /// An axis that is not homed stepped outside its homing.
    UnhomedAxisMoved,
    /// A homed axis left its soft limits.
    SoftLimit,
    /// The light is on or the trigger high while a fault is latched.
    LightWhileFaulted,
    /// Axes are counted as homed while their drivers are released (they
    /// can be pushed by hand).
    HomedWhileUnpowered,
    /// Motion, light or trigger accepted while a fault was latched.
    AcceptedWhileFaulted,
    /// A reset or the bootloader was entered with an axis still moving or
    /// the light or trigger on.
    ResetWhileActive,
    /// The trigger stayed high longer than the longest exposure.
    TriggerStuck,
    /// An axis stepped while the camera's trigger was high: a frame taken
    /// in motion.
    StepDuringExposure,
    /// The light's duty above full.
    LightDuty,
    /// The light on at a level no request asked for (the host's
    /// `SetLight`, put out by a fault or a reboot; or a capture step's), or
    /// a capture step's light on with the trigger low longer than the
    /// step's light margin.
    LightNotAsked,
    /// The home switch of a homed linear axis came on far from home (not
    /// while homing it) and stayed on past the debounce time, and
    /// `UNEXPECTED_HOME_SWITCH` (or `POSITION_LOST`) was not latched: a
    /// crash or a broken switch run on.
    SwitchHitIgnored,
    /// After a reboot, the configuration is not the one the last
    /// acknowledged `SaveConfig` saved (the defaults if none was).
    ConfigNotKept,
    /// After a reboot, a watchdog reset or a flash that failed at boot is
    /// not latched as `WATCHDOG_RESET` / `STORAGE_FAILED` (or one is
    /// latched that did not happen).
    ResetCauseNotLatched,
    /// An axis still stepped after the host had fallen silent for longer
    /// than the link timeout, a poll and the axis' deceleration from its
    /// top speed.
    LinkLossIgnored,
    /// After a poll, the controller asks to be woken at a tick already
    /// past ([`Rig::stale_deadline`]): work it says is due and does not do.
    StaleDeadline,
    /// An acknowledged motion (homing, move, capture step) did not end
    /// with exactly one `MotionDone`, or a motion is running with no axis
    /// moving after a poll (it would never end: the host waits for its
    /// `MotionDone`).
    MotionNotReported,
    /// An axis stepped that no running motion asked to move: not one of a
    /// homing's axes, an axis a `Move` left alone, or any axis with no
    /// motion acknowledged and not yet reported done.
    StepNotAsked,
    /// A move (`Move`, `GoToMirror`, a capture step's) reported
    /// `Completed` with an axis elsewhere than its target (the disk's
    /// modulo a turn), by its `MotionDone` or by the step count.
    MoveOffTarget,
    /// The strobe's report on a pulse (`Exposure`) disagrees with the
    /// camera: a window that ended off by more than a poll from when the
    /// camera exposed, or none for a pulse the camera exposed for within
    /// the configured delay (a frame the host would count as missed).
    ExposureMisread,
    /// A homing ended with the count off the home position at the switch's
    /// edge (`HomingConfig::home_position` is "the position assigned at
    /// the switch edge"): the physical position from the edge the approach
    /// meets, plus the home position, within a step. Checked for homings
    /// undisturbed by a hand or a changed switch.
    HomedOffSwitch,
    /// A position check (`PositionChecked`, at a homed axis' home edge)
    /// reported an error other than the count's (count − physical
    /// position, against the home position at the switch's edge), within
    /// the step between the edge's two sides.
    PositionMisjudged,
}

impl Rule {
    /// What the rule says.
    pub const fn describe(self) -> &'static str {
        match self {
            Rule::StepWhileFaulted => "an axis stepped while a stopping fault was latched",
            Rule::StopInputIgnored => {
                "the emergency stop or a driver fault was not acted on within the debounce time"
            }
            Rule::UnhomedAxisMoved => "an axis that is not homed moved outside its homing",
            Rule::SoftLimit => "a homed axis left its soft limits",
            Rule::LightWhileFaulted => "light on or trigger high while a fault was latched",
            Rule::HomedWhileUnpowered => "an axis counted as homed with its drivers released",
            Rule::AcceptedWhileFaulted => "motion, light or trigger accepted while faulted",
            Rule::ResetWhileActive => "reset or bootloader entered with something still running",
            Rule::TriggerStuck => "the trigger stayed high longer than the longest exposure",
            Rule::StepDuringExposure => "an axis stepped while the camera's trigger was high",
            Rule::LightDuty => "light duty above full",
            Rule::LightNotAsked => {
                "the light on unasked, or a capture step's light past its margin"
            }
            Rule::SwitchHitIgnored => "a home switch hit far from home was not acted on",
            Rule::ConfigNotKept => "the configuration after a reboot is not the one last saved",
            Rule::ResetCauseNotLatched => "a watchdog reset or a failing flash not latched at boot",
            Rule::LinkLossIgnored => "an axis went on moving after the host fell silent",
            Rule::StaleDeadline => "after a poll, the controller asked to be woken in the past",
            Rule::MotionNotReported => "a motion did not end with exactly one MotionDone",
            Rule::StepNotAsked => "an axis stepped that no running motion asked to move",
            Rule::MoveOffTarget => "a move completed with an axis off its target",
            Rule::ExposureMisread => "the strobe's report on a pulse disagrees with the camera",
            Rule::HomedOffSwitch => "a homing set the count off the home position at the switch",
            Rule::PositionMisjudged => "a position check reported another error than the count's",
        }
    }
}

/// A broken rule: which, where in the run, and on which axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Violation {
    /// The rule.
    pub rule: Rule,
    /// The action of the run (0-based) after which it broke.
    pub action: usize,
    /// Simulated time, ticks.
    pub tick: u64,
    /// The axis concerned, if one.
    pub axis: Option<Axis>,
    /// The faults latched then.
    pub faults: FaultFlags,
}

impl core::fmt::Display for Violation {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{} (action {}, tick {}", self.rule.describe(), self.action, self.tick)?;
        if let Some(axis) = self.axis {
            write!(f, ", axis {}", axis.name())?;
        }
        write!(f, ", faults {:#06x})", self.faults.0)
    }
}

/// What a run went through: to see that it reached the states the rules
/// are about.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Report {
    /// Actions taken.
    pub actions: usize,
    /// Requests sent (plausible, decoded from random bytes, and framed).
    pub requests: usize,
    /// Requests acknowledged.
    pub acks: usize,
    /// Steps per axis.
    pub steps: [u64; AXIS_COUNT],
    /// Steps made by axes that were homed.
    pub homed_steps: u64,
    /// Homings completed.
    pub homings: usize,
    /// Homings that failed.
    pub homings_failed: usize,
    /// Moves completed.
    pub moves: usize,
    /// Moves (not homings) completed and found at their targets.
    pub on_target: usize,
    /// The strobe's reports checked against the camera (a window or none).
    pub exposures: usize,
    /// Homings whose count was checked against the switch's edge.
    pub homed_at_switch: usize,
    /// Of those, at a sensor wired (and configured) active high.
    pub homed_active_high: usize,
    /// Position checks compared with the count's error.
    pub positions_checked: usize,
    /// Trigger pulses fired.
    pub triggers: usize,
    /// Home switches of homed axes hit far from home (outside homing).
    pub switch_hits: usize,
    /// Configurations saved (`SaveConfig` acknowledged).
    pub saves: usize,
    /// Every fault seen raised.
    pub faults: FaultFlags,
    /// Reboots (reset, bootloader, watchdog).
    pub reboots: usize,
    /// Simulated time, ticks.
    pub ticks: u64,
}

impl Report {
    /// Add `other`'s counts to these.
    pub fn add(&mut self, other: &Report) {
        self.actions += other.actions;
        self.requests += other.requests;
        self.acks += other.acks;
        for (a, b) in self.steps.iter_mut().zip(other.steps) {
            *a += b;
        }
        self.homed_steps += other.homed_steps;
        self.homings += other.homings;
        self.homings_failed += other.homings_failed;
        self.moves += other.moves;
        self.on_target += other.on_target;
        self.exposures += other.exposures;
        self.homed_at_switch += other.homed_at_switch;
        self.homed_active_high += other.homed_active_high;
        self.positions_checked += other.positions_checked;
        self.triggers += other.triggers;
        self.switch_hits += other.switch_hits;
        self.saves += other.saves;
        self.faults = self.faults.union(other.faults);
        self.reboots += other.reboots;
        self.ticks += other.ticks;
    }
}

/// The board's poll period (5 kHz).
const POLL_TICKS: u64 = 200 * TICKS_PER_US;

/// How long after a stop input asserts the controller must have acted: the
/// debounce time and a poll.
const STOP_WITHIN: u64 = DEBOUNCE_US * TICKS_PER_US + POLL_TICKS;

/// What a deceleration may take beyond v_max / a_max: the step already
/// armed and the plan's rounding (10 ms).
const LINK_SLACK: u64 = 10 * TICKS_PER_MS;

/// Every fault but a link timeout stops the axes at once (a link timeout
/// decelerates them).
const fn stops_at_once(f: FaultFlags) -> bool {
    f.0 & !FaultFlags::LINK_TIMEOUT.0 != 0
}

/// Every fault but a failed homing puts the light out.
const fn dark(f: FaultFlags) -> bool {
    f.0 & !FaultFlags::HOMING_FAILED.0 != 0
}

/// Whether `request`, acknowledged, starts a motion (a homing, a move, a
/// capture step's move): one that ends with a `MotionDone`.
const fn starts_motion(request: &Request) -> bool {
    matches!(
        request,
        Request::Home { .. }
            | Request::Move { .. }
            | Request::GoToMirror { .. }
            | Request::CaptureStep(_)
            | Request::TimedCaptureStep(_)
    )
}

/// Run `actions` random actions on a fresh rig (fewer if `entropy` runs
/// out): `Err` names the first rule broken.
pub fn run(entropy: &mut impl Entropy, actions: usize) -> Result<Report, Violation> {
    run_logged(entropy, actions, &mut |_| {})
}

/// [`run`], telling `log` every action.
pub fn run_logged(
    entropy: &mut impl Entropy,
    actions: usize,
    log: &mut dyn FnMut(&Logged),
) -> Result<Report, Violation> {
    let mut chaos = Chaos::new(entropy, log);
    chaos.start()?;
    for action in 0..actions {
        chaos.watch.action = action;
        if chaos.exhausted {
            break;
        }
        chaos.act()?;
        chaos.watch.report.actions += 1;
    }
    chaos.watch.report.ticks = chaos.rig.now;
    Ok(chaos.watch.report)
}

/// The run's state besides the rig.
struct Watch {
    action: usize,
    /// When the emergency stop and the driver fault were asserted.
    estop_since: Option<u64>,
    driver_fault_since: Option<u64>,
    /// When the trigger rose.
    trigger_since: Option<u64>,
    /// Which axes were homed at the last check.
    homed: [bool; AXIS_COUNT],
    /// Per axis: homing since it was last asked for, with no hand on the
    /// axis and its switch unchanged.
    clean: [bool; AXIS_COUNT],
    /// Per axis: when a hand or a changed switch last touched it, and its
    /// count − physical position at the last visit.
    touched: [u64; AXIS_COUNT],
    offset: [i64; AXIS_COUNT],
    /// Events of the rig's list already looked at.
    events_seen: usize,
    /// The light's duty as the host set it on (`None`: set off, put out
    /// by a fault, or not set since the boot).
    set_light: Option<u16>,
    /// The light's duty and margin (ticks) of the last two capture steps
    /// accepted (the last one's light may still trail when the next is).
    step_lights: [Option<(u16, u64)>; 2],
    /// Since when a capture step's light is on with the trigger low, and
    /// at which level (a new step's light, or a new step accepted while
    /// the last one's margin runs on, starts a new margin).
    step_lit_since: Option<(u16, u64)>,
    /// Per axis: whether its switch read on at the last check (by the
    /// polarity configured), and a hit far from home being watched.
    switch_on: [bool; AXIS_COUNT],
    switch_hit: [Hit; AXIS_COUNT],
    /// The configuration the last acknowledged `SaveConfig` saved, encoded
    /// (the defaults' until one is).
    saved: Blob,
    /// When the host last spoke (a request, bytes, or its keep-alive as it
    /// fell silent).
    heard: u64,
    /// Motions (homings, moves, capture steps) acknowledged since the boot.
    motions: usize,
    /// The axes the last motion acknowledged may move, and where a move
    /// must leave them if it completes (`None`: a homing's, or an axis the
    /// move leaves alone).
    asked: AxisSet,
    targets: [Option<i64>; AXIS_COUNT],
    /// `MotionDone` events checked since the boot.
    done_seen: usize,
    /// The last pulses fired since the boot: sequence number, rise (tick),
    /// exposure asked (µs).
    fired: [Option<(u32, u64, u32)>; 4],
    report: Report,
}

/// An encoded configuration.
type Blob = heapless::Vec<u8, PERSISTED_MAX_LEN>;

/// `config` as the controller saves it.
fn blob(config: &PersistedConfig) -> Blob {
    let mut buf = [0u8; PERSISTED_MAX_LEN];
    let bytes = config.encode(&mut buf).map_or(&[][..], |b| &b[..]);
    Blob::from_slice(bytes).unwrap_or_default()
}

/// Where the homing of an axis meets its switch, for the switch as the
/// test kit wires it by default.
#[derive(Debug, Clone, Copy)]
struct Home {
    /// The count there: the home position.
    home_position: i64,
    /// The first actuated position the approach meets (physical).
    edge: i64,
    /// The switch's period (the disk's index flag).
    rev: Option<i64>,
}

impl Home {
    /// For `axis` on `rig`, if its switch is the default one, read the
    /// way it is wired.
    fn of(rig: &Rig, axis: Axis) -> Option<Home> {
        let i = axis.index();
        let c = &rig.ctrl.config().axes[i];
        let wired = rig.switch_active_high[i] == rig.ctrl.config().home.active_high[i];
        if !wired || rig.switches[i] != DEFAULT_SWITCHES[i] {
            return None;
        }
        let positive = c.homing.direction == protocol::Direction::Positive;
        let (edge, rev) = match DEFAULT_SWITCHES[i] {
            Switch::Below(edge) if !positive => (edge, None),
            Switch::Index { edge, width, rev } => {
                (if positive { edge } else { edge + width - 1 }, Some(rev))
            }
            _ => return None, // approached from the side it never leaves
        };
        Some(Home { home_position: c.homing.home_position as i64, edge, rev })
    }

    /// The count's error for `offset` = count − physical position (the
    /// disk's the nearest modulo a turn).
    fn error(&self, offset: i64) -> i64 {
        let e = offset + self.edge - self.home_position;
        self.rev.map_or(e, |rev| {
            let m = e.rem_euclid(rev);
            if m > rev / 2 { m - rev } else { m }
        })
    }
}

/// A home switch hit far from home, outside homing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Hit {
    /// None watched.
    None,
    /// Since this tick, not yet acted on.
    Since(u64),
    /// The fault was latched.
    ActedOn,
}

struct Chaos<'e, E: Entropy> {
    rig: Rig,
    /// Disturbances (random requests, noise, inputs) five times rarer.
    calm: bool,
    entropy: &'e mut E,
    log: &'e mut dyn FnMut(&Logged),
    exhausted: bool,
    /// A request framed on the link but cut short (its number and itself):
    /// the controller's decoder holds it until a delimiter comes.
    cut: Option<(u8, Request)>,
    watch: Watch,
}

impl<'e, E: Entropy> Chaos<'e, E> {
    fn new(entropy: &'e mut E, log: &'e mut dyn FnMut(&Logged)) -> Self {
        let mut rig = Rig::with_capabilities(
            ResetReason::PowerOn,
            protocol::Capabilities::SIMULATED
                .union(protocol::Capabilities::PERSISTENT_CONFIG)
                .union(protocol::Capabilities::EXPOSURE_STROBE)
                .union(protocol::Capabilities::SYSTEM_BOOTLOADER),
        );
        rig.poll_period = Some(POLL_TICKS);
        let watch = Watch {
            action: 0,
            estop_since: None,
            driver_fault_since: None,
            trigger_since: None,
            homed: [false; AXIS_COUNT],
            clean: [false; AXIS_COUNT],
            touched: [0; AXIS_COUNT],
            offset: [0; AXIS_COUNT],
            events_seen: 0,
            set_light: None,
            step_lights: [None; 2],
            step_lit_since: None,
            switch_on: [false; AXIS_COUNT],
            switch_hit: [Hit::None; AXIS_COUNT],
            saved: blob(&PersistedConfig::default()),
            heard: 0,
            motions: 0,
            asked: AxisSet::NONE,
            targets: [None; AXIS_COUNT],
            done_seen: 0,
            fired: [None; 4],
            report: Report::default(),
        };
        Chaos { rig, calm: false, entropy, log, exhausted: false, cut: None, watch }
    }

    /// The rig's own variations, drawn once.
    fn start(&mut self) -> Result<(), Violation> {
        self.calm = self.chance(500);
        self.rig.hw.storage_fails = self.chance(100);
        self.rig.hw.hardware_pulse = self.chance(500);
        // Some rigs' sensors are wired active high (push-pull optical or
        // Hall sensors): the host must say so, and until it does the
        // controller reads them the other way round.
        if self.chance(400) {
            for i in 0..AXIS_COUNT {
                self.rig.switch_active_high[i] = self.chance(500);
            }
            // Mostly its host says so as it first connects, and may save it.
            if self.chance(700) {
                let active_high = self.rig.switch_active_high;
                self.send(Request::SetHomeSensors(protocol::HomeSensors { active_high }))?;
                if self.chance(500) {
                    self.send(Request::SaveConfig)?;
                }
            }
        }
        if self.chance(300) {
            let active_high = self.chance(500);
            // Most cameras expose within 2 ms of their trigger; some (a
            // long readout first) up to the strobe's longest delay.
            let most = if self.chance(700) { 2_000 } else { protocol::MAX_STROBE_DELAY_US };
            let delay = self.below(most) as u64 * TICKS_PER_US;
            self.rig.strobe = Some(CameraStrobe { delay, active_high, ignores: self.chance(200) });
        }
        Ok(())
    }

    // ----- randomness -----------------------------------------------------------

    fn r(&mut self) -> u32 {
        match self.entropy.next() {
            Some(x) => x,
            None => {
                self.exhausted = true;
                0
            }
        }
    }

    /// 0 … n − 1.
    fn below(&mut self, n: u32) -> u32 {
        if n == 0 { 0 } else { self.r() % n }
    }

    /// True `per_mille` times in a thousand.
    fn chance(&mut self, per_mille: u32) -> bool {
        self.below(1000) < per_mille
    }

    /// lo ..= hi.
    fn between(&mut self, lo: i64, hi: i64) -> i64 {
        if hi <= lo {
            return lo;
        }
        let span = (hi - lo) as u64 + 1;
        let x = ((self.r() as u64) << 32 | self.r() as u64) % span;
        lo + x as i64
    }

    // ----- actions ----------------------------------------------------------------

    fn act(&mut self) -> Result<(), Violation> {
        // A calm run's host has the scanner mostly to itself, and mostly
        // waits for what it started to end.
        let disturbed = !self.calm || self.chance(200);
        let state = self.rig.status().state;
        let busy = !matches!(state, DeviceState::Idle | DeviceState::Faulted);
        match self.below(100) {
            _ if self.calm && busy && self.chance(850) => {}
            k if k < 62 || !disturbed => {
                let request = self.host_request();
                self.send(request)?;
            }
            62..70 => {
                if let Some(request) = self.random_request() {
                    self.send(request)?;
                }
            }
            70..74 => self.line_bytes()?,
            74..80 => self.change_inputs()?,
            80..84 => {
                // Something in a homed linear axis' way.
                let axis = [Axis::Track, Axis::Tilt][self.below(2) as usize];
                if self.rig.ctrl.is_homed(axis) {
                    self.watch.touch(axis.index(), self.rig.now);
                    self.rig.switches[axis.index()] = self.obstacle(axis.index());
                    self.inputs_changed();
                }
            }
            _ => {}
        }
        let dt = match self.below(100) {
            0..20 => 0,
            20..50 => self.below(2 * TICKS_PER_MS as u32) as u64,
            50..85 => self.below(200) as u64 * TICKS_PER_MS,
            _ => self.below(3_000) as u64 * TICKS_PER_MS,
        };
        self.pass(dt)
    }

    /// Send `request` as a host would (a fresh sequence number) and check
    /// the answer.
    fn send(&mut self, request: Request) -> Result<(), Violation> {
        let faulted = self.rig.ctrl.faults();
        let polarity = self.rig.ctrl.config().board.driver_fault_active_high;
        let reply = self.rig.request(request);
        self.tally_events(false)?;
        self.watch.heard = self.rig.now;
        self.line_follows_polarity(polarity);
        (self.log)(&Logged::Request(request, reply));
        self.after_request(&request, faulted, reply)
    }

    fn after_request(
        &mut self,
        request: &Request,
        faulted: FaultFlags,
        reply: Reply,
    ) -> Result<(), Violation> {
        self.watch.report.requests += 1;
        if reply == Reply::Ack {
            self.watch.report.acks += 1;
            let motion = starts_motion(request);
            let gated = motion
                || matches!(
                    request,
                    Request::Trigger { .. }
                        | Request::SaveConfig
                        | Request::SetLight(LightState { on: true, .. })
                );
            if gated && !faulted.is_empty() {
                return Err(self.violation(Rule::AcceptedWhileFaulted, None));
            }
            self.watch.light_asked(request);
            if motion {
                self.watch.motion_asked(request, &self.rig);
            }
            if matches!(request, Request::SetHomeSensors(_)) {
                // A switch read the other way round from now on.
                self.watch.touched = [self.rig.now; AXIS_COUNT];
            }
            if *request == Request::SaveConfig {
                self.watch.saved = blob(self.rig.ctrl.config());
                self.watch.report.saves += 1;
            }
        }
        self.check_state()?;
        self.reboot_if_asked()?;
        if reply == Reply::Error(protocol::DeviceError::NoHandshake) {
            // A host handshakes after the device's reset.
            self.send(Request::Hello { host_protocol: PROTOCOL_VERSION })?;
        }
        Ok(())
    }

    /// What a host does next: clear a fault, home, scan, or anything else.
    fn host_request(&mut self) -> Request {
        let homed = Axis::ALL.iter().all(|a| self.rig.ctrl.is_homed(*a));
        let idle = self.rig.status().state == DeviceState::Idle;
        if !self.rig.ctrl.faults().is_empty() && self.chance(500) {
            Request::ClearFault
        } else if !homed && self.chance(400) {
            Request::Home { axes: AxisSet::ALL }
        } else if let Some(strobe) = self.strobe_setup() {
            strobe
        } else if homed && idle && self.chance(400) {
            self.scan_request()
        } else {
            self.plausible_request()
        }
    }

    /// A host whose camera's strobe is wired sets the board up to watch it
    /// (enabled, the camera's polarity, a delay limit beyond the camera's
    /// mostly), now and then while it does not.
    fn strobe_setup(&mut self) -> Option<Request> {
        let camera = self.rig.strobe?;
        let config = self.rig.ctrl.config().strobe;
        if (config.enabled && config.active_high == camera.active_high) || !self.chance(300) {
            return None;
        }
        let delay_us = camera.delay / TICKS_PER_US;
        let max = protocol::MAX_STROBE_DELAY_US as i64;
        let max_delay_us = if self.chance(900) {
            self.between(delay_us as i64 + 500, max)
        } else {
            self.between(0, max)
        };
        Some(Request::SetStrobe(protocol::StrobeConfig {
            enabled: true,
            active_high: camera.active_high,
            max_delay_us: max_delay_us.min(max) as u32,
        }))
    }

    /// A scan's next request: a capture step at a mirror of the table (at
    /// settings a scan uses, the strobe's and a light margin's included),
    /// or a mirror's position set within the travel if the table has none.
    fn scan_request(&mut self) -> Request {
        let set = self.rig.ctrl.config().mirrors.iter().filter(|m| m.is_some()).count();
        if set == 0 || self.chance(50) {
            let axes = self.rig.ctrl.config().axes;
            let steps = core::array::from_fn(|i| {
                self.between(axes[i].min_steps as i64, axes[i].max_steps as i64) as i32
            });
            let mirror = self.below(6) as u8;
            return Request::SetMirror { mirror, position: MirrorPosition { steps } };
        }
        let nth = self.below(set as u32) as usize;
        let mirrors = self.rig.ctrl.config().mirrors.iter().enumerate();
        let mirror = mirrors.filter(|(_, m)| m.is_some()).nth(nth);
        let mirror = mirror.map_or(0, |(i, _)| i as u8);
        let step = CaptureStep {
            mirror,
            settle_ms: self.below(200) as u16,
            exposure_us: self.between(MIN_EXPOSURE_US as i64, 60_000) as u32,
            light_duty_permille: self.between(1, FULL_DUTY_PERMILLE as i64) as u16,
        };
        if self.chance(300) {
            Request::CaptureStep(step)
        } else {
            let light_margin_us = self.below(MAX_LIGHT_MARGIN_US as u32 + 1) as u16;
            Request::TimedCaptureStep(TimedCaptureStep { step, light_margin_us })
        }
    }

    /// A request a host (or a person at `scanner move`) might send: mostly
    /// sensible, some out of range.
    fn plausible_request(&mut self) -> Request {
        let axes = self.rig.ctrl.config().axes;
        match self.below(100) {
            0..6 => Request::Home { axes: AxisSet::ALL },
            6..8 => Request::Home { axes: AxisSet(self.below(8) as u8) },
            8..22 => {
                let mut targets = [None; AXIS_COUNT];
                for (i, t) in targets.iter_mut().enumerate() {
                    if self.chance(700) {
                        *t = Some(self.target(i));
                    }
                }
                Request::Move { mode: MoveMode::Absolute, targets }
            }
            22..28 => {
                let mut targets = [None; AXIS_COUNT];
                for t in targets.iter_mut() {
                    if self.chance(600) {
                        *t = Some(self.between(-3_000, 3_000) as i32);
                    }
                }
                Request::Move { mode: MoveMode::Relative, targets }
            }
            28..35 => {
                let mirror = self.below(6) as u8;
                let steps = core::array::from_fn(|i| self.target(i));
                Request::SetMirror { mirror, position: MirrorPosition { steps } }
            }
            35..36 => Request::SetMirrorCount { count: self.below(8) as u8 },
            36..44 => Request::GoToMirror { mirror: self.below(7) as u8 },
            44..62 => {
                let step = CaptureStep {
                    mirror: self.below(7) as u8,
                    settle_ms: self.below(300) as u16,
                    exposure_us: self.between(MIN_EXPOSURE_US as i64 - 10, 120_000) as u32,
                    light_duty_permille: self.between(0, FULL_DUTY_PERMILLE as i64 + 5) as u16,
                };
                let light_margin_us = self.below(MAX_LIGHT_MARGIN_US as u32 + 100) as u16;
                if self.chance(500) {
                    Request::CaptureStep(step)
                } else {
                    Request::TimedCaptureStep(TimedCaptureStep { step, light_margin_us })
                }
            }
            62..66 => Request::Trigger {
                exposure_us: self.between(MIN_EXPOSURE_US as i64 - 10, 150_000) as u32,
            },
            66..71 => Request::SetLight(LightState {
                on: self.chance(600),
                duty_permille: self.between(0, FULL_DUTY_PERMILLE as i64 + 5) as u16,
            }),
            71..77 => Request::Stop,
            77..87 => Request::ClearFault,
            87..88 => Request::EmergencyStop,
            88..91 => Request::GetStatus,
            91..93 => Request::SaveConfig,
            93..95 => {
                let axis = Axis::from_index(self.below(AXIS_COUNT as u32) as usize);
                let axis = axis.unwrap_or(Axis::Track);
                let mut config = axes[axis.index()];
                config.v_max = (config.v_max as i64 * self.between(50, 200) / 100) as u32;
                config.a_max = (config.a_max as i64 * self.between(50, 200) / 100) as u32;
                if !config.continuous && self.chance(300) {
                    config.max_steps =
                        (config.max_steps as i64 * self.between(80, 110) / 100) as i32;
                }
                Request::SetAxisConfig { axis, config }
            }
            95 if self.chance(500) => Request::Reset,
            96 if self.chance(500) => Request::EnterBootloader,
            97 => {
                // Mostly the wiring's own polarity, sometimes one sensor
                // the wrong way round.
                let mut home = protocol::HomeSensors { active_high: self.rig.switch_active_high };
                if self.chance(300) {
                    let i = self.below(AXIS_COUNT as u32) as usize;
                    home.active_high[i] = !home.active_high[i];
                }
                Request::SetHomeSensors(home)
            }
            98 => Request::SetBoardConfig(protocol::BoardConfig {
                driver_fault_active_high: self.chance(200),
            }),
            99 if self.chance(500) => Request::SetStrobe(protocol::StrobeConfig {
                enabled: self.chance(700),
                active_high: self.chance(500),
                max_delay_us: self.between(0, protocol::MAX_STROBE_DELAY_US as i64 + 10) as u32,
            }),
            _ => Request::Hello { host_protocol: PROTOCOL_VERSION },
        }
    }

    /// A position for axis `i`: anywhere in its travel, at its ends or
    /// home, near where it is, or a little outside the travel.
    fn target(&mut self, i: usize) -> i32 {
        let c = self.rig.ctrl.config().axes[i];
        let (lo, hi) = (c.min_steps as i64, c.max_steps as i64);
        let margin = (hi - lo) / 20 + 1;
        let here = self.rig.hw.steppers[i].position() as i64;
        let x = match self.below(10) {
            0 => self.between(lo - margin, hi + margin),
            1 => [lo, hi, c.homing.home_position as i64][self.below(3) as usize],
            2..6 => here + self.between(-margin, margin),
            _ => self.between(lo, hi),
        };
        x.clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    /// A request decoded from random bytes: any variant, any field values
    /// the wire format allows.
    fn random_request(&mut self) -> Option<Request> {
        let mut buf = [0u8; 32];
        buf[0] = self.below(32) as u8;
        for b in buf[1..].iter_mut() {
            *b = if self.chance(500) { self.below(4) as u8 } else { self.r() as u8 };
        }
        postcard::from_bytes::<Request>(&buf).ok()
    }

    /// Bytes on the link: noise, or a request framed (whole or cut, perhaps
    /// corrupted), through the controller's decoder. A frame cut short
    /// before its delimiter is taken when later bytes bring one: its answer
    /// comes then.
    fn line_bytes(&mut self) -> Result<(), Violation> {
        let mut bytes = [0u8; MAX_FRAME_LEN];
        // The request framed whole, if one, and the one cut short.
        let (mut whole, mut cut) = (None, None);
        let n = if self.chance(500) {
            let n = self.below(64) as usize;
            for b in bytes[..n].iter_mut() {
                *b = if self.chance(200) { 0 } else { self.r() as u8 };
            }
            n
        } else {
            let r = self.plausible_request();
            // Numbered as a host numbers its requests: the last request's
            // number again would be a retransmission of it (answered again,
            // not executed).
            let seq = self.rig.next_seq();
            let n = encode_frame(seq, &r, &mut bytes).unwrap_or(0);
            let corrupted = self.chance(200) && n > 0;
            if corrupted {
                let at = self.below(n as u32) as usize;
                bytes[at] ^= 1 << self.below(8);
            }
            let sent = if self.chance(100) { self.below(n as u32 + 1) as usize } else { n };
            match (corrupted, sent == n) {
                (true, _) => {}
                (false, true) => whole = Some((seq, r)),
                (false, false) => cut = Some((seq, r)),
            }
            sent
        };
        (self.log)(&Logged::Bytes(n));
        // A delimiter ends what an earlier cut left in the decoder.
        let earlier = if bytes[..n].contains(&0) { self.cut.take() } else { None };
        let faulted = self.rig.ctrl.faults();
        let polarity = self.rig.ctrl.config().board.driver_fault_active_high;
        let mut out: heapless::Vec<u8, { 2 * MAX_FRAME_LEN }> = heapless::Vec::new();
        self.rig.on_bytes(&bytes[..n], &mut |b: &[u8]| {
            let _ = out.extend_from_slice(b);
        });
        self.tally_events(false)?;
        self.watch.heard = self.rig.now;
        let mut answered: heapless::Vec<(Request, Reply), 2> = heapless::Vec::new();
        for frame in FrameDecoder::<ToHost>::new().feed(&out).flatten() {
            let ToHost::Reply(reply) = frame.msg else { continue };
            let asked = [earlier, whole].into_iter().flatten().find(|(s, _)| *s == frame.seq);
            if let Some((_, request)) = asked {
                let _ = answered.push((request, reply));
            }
        }
        self.line_follows_polarity(polarity);
        self.cut = self.cut.or(cut);
        if answered.is_empty() {
            self.check_state()?;
            return self.reboot_if_asked();
        }
        let reboots = self.watch.report.reboots;
        for (request, reply) in answered {
            if self.watch.report.reboots != reboots {
                break; // the rest went to the controller before
            }
            (self.log)(&Logged::Request(request, reply));
            self.after_request(&request, faulted, reply)?;
        }
        Ok(())
    }

    /// The world changes: the emergency stop, a driver fault, a home
    /// switch breaking, closing where it should not, or mended, an unpowered axis pushed by hand or a
    /// powered one skipping steps, the host falling silent or back, the
    /// board's watchdog (and its flash failing).
    fn change_inputs(&mut self) -> Result<(), Violation> {
        match self.below(100) {
            0..25 => self.rig.estop = !self.rig.estop && self.chance(300),
            25..40 => self.rig.driver_fault = !self.rig.driver_fault && self.chance(300),
            40..55 => {
                let i = self.below(AXIS_COUNT as u32) as usize;
                self.watch.touch(i, self.rig.now);
                self.rig.switches[i] = match self.below(10) {
                    0 => Switch::Missing,
                    1 => Switch::Stuck,
                    2 => self.obstacle(i),
                    _ => DEFAULT_SWITCHES[i],
                };
            }
            55..75 => {
                // Unpowered, an axis can be pushed by hand; powered, a
                // stalled motor skips steps.
                let i = self.below(AXIS_COUNT as u32) as usize;
                self.watch.touch(i, self.rig.now);
                self.rig.physical[i] += self.between(-6_000, 6_000);
            }
            // A calm run's host stays alive.
            75..97 => {
                if self.rig.keepalive {
                    self.watch.heard = self.rig.now;
                }
                self.rig.keepalive = self.calm || !self.rig.keepalive || self.chance(800);
            }
            _ => {
                // The watchdog bites; the flash may have failed meanwhile.
                self.rig.hw.storage_fails ^= self.chance(300);
                self.rig.reboot(ResetReason::Watchdog);
                self.rebooted(ResetReason::Watchdog)?;
            }
        }
        self.inputs_changed();
        Ok(())
    }

    /// A home switch that closes somewhere on the travel of axis `i`
    /// (something there presses its lever, or its cable shorts where the
    /// chain bends), perhaps where the axis is.
    fn obstacle(&mut self, i: usize) -> Switch {
        let c = self.rig.ctrl.config().axes[i];
        let lo = if self.chance(300) {
            self.rig.physical[i] - self.between(0, 1_000)
        } else {
            self.between(c.min_steps as i64, c.max_steps as i64)
        };
        Switch::Window(lo, lo + self.between(50, 3_000))
    }

    /// Log the inputs after a change, and note when a stop input asserted.
    fn inputs_changed(&mut self) {
        let rig = &self.rig;
        (self.log)(&Logged::Inputs {
            estop: rig.estop,
            driver_fault: rig.driver_fault,
            switches: rig.switches,
            physical: rig.physical,
            keepalive: rig.keepalive,
        });
        let now = self.rig.now;
        self.watch.estop_since = self.rig.estop.then(|| self.watch.estop_since.unwrap_or(now));
        self.watch.driver_fault_since =
            self.rig.driver_fault.then(|| self.watch.driver_fault_since.unwrap_or(now));
    }

    /// Let `dt` ticks pass, checking every step and poll.
    fn pass(&mut self, dt: u64) -> Result<(), Violation> {
        let end = self.rig.now + dt;
        let watch = &mut self.watch;
        let result = self.rig.run_until_visiting(end, |rig, visit| watch.visit(rig, visit));
        (self.log)(&Logged::Passed(dt, self.rig.now));
        result?;
        self.tally_events(true)?;
        self.reboot_if_asked()
    }

    /// Count the events received and clear them; `check`: check the
    /// strobe's reports (not those a request's own handling sent: a
    /// `SetStrobe` ends the watch of a pulse where it is).
    fn tally_events(&mut self, check: bool) -> Result<(), Violation> {
        for e in self.rig.events.iter() {
            match *e {
                Event::Exposure { trigger_seq, window } if check => {
                    self.watch.exposure(&self.rig, trigger_seq, window)?;
                }
                Event::MotionDone { outcome: MotionOutcome::Completed, .. } => {
                    self.watch.report.moves += 1
                }
                Event::MotionDone { outcome: MotionOutcome::HomingFailed(..), .. } => {
                    self.watch.report.homings_failed += 1
                }
                Event::TriggerFired(f) => {
                    self.watch.report.triggers += 1;
                    // Its rise: the last one recorded in its microsecond.
                    let rise = self.rig.hw.outputs.iter().rev().find_map(|o| match *o {
                        Output::Trigger(t, true) if t / TICKS_PER_US == f.timestamp_us => Some(t),
                        _ => None,
                    });
                    if let Some(rise) = rise {
                        let fired = &mut self.watch.fired;
                        fired.rotate_left(1);
                        fired[3] = Some((f.trigger_seq, rise, f.exposure_us));
                    }
                }
                Event::FaultRaised { faults, .. } => {
                    self.watch.report.faults = self.watch.report.faults.union(faults)
                }
                _ => {}
            }
        }
        self.rig.events.clear();
        self.watch.events_seen = 0;
        Ok(())
    }

    /// After a `Reset` or `EnterBootloader`, the board resets once the
    /// reply is out: check that everything stopped first.
    fn reboot_if_asked(&mut self) -> Result<(), Violation> {
        let reset = self.rig.ctrl.reset_requested();
        let bootloader = self.rig.ctrl.bootloader_requested();
        if !(reset || bootloader) {
            return Ok(());
        }
        let hw = &self.rig.hw;
        let moving = self.rig.ctrl.is_moving() || hw.armed.iter().any(Option::is_some);
        if moving || (bootloader && (hw.light != 0 || hw.trigger)) {
            return Err(self.violation(Rule::ResetWhileActive, None));
        }
        self.tally_events(true)?;
        let reason = if reset { ResetReason::Software } else { ResetReason::PowerOn };
        self.rig.reboot(reason);
        self.rebooted(reason)?;
        self.send(Request::Hello { host_protocol: PROTOCOL_VERSION })
    }

    /// The rig's driver-fault line follows the configured polarity (its
    /// fault is "asserted", whatever the level): a changed polarity changes
    /// the line, and the controller has its debounce time from now.
    fn line_follows_polarity(&mut self, before: bool) {
        if self.rig.ctrl.config().board.driver_fault_active_high != before {
            let now = self.rig.now;
            self.watch.driver_fault_since = self.watch.driver_fault_since.map(|_| now);
        }
    }

    /// A new controller: what the old one saw of the inputs is gone; what
    /// was saved is its configuration.
    fn rebooted(&mut self, reason: ResetReason) -> Result<(), Violation> {
        (self.log)(&Logged::Reboot(reason));
        self.watch.report.reboots += 1;
        self.cut = None;
        let now = self.rig.now;
        let w = &mut self.watch;
        w.trigger_since = None;
        (w.set_light, w.step_lights, w.step_lit_since) = (None, [None; 2], None);
        w.switch_hit = [Hit::None; AXIS_COUNT];
        (w.motions, w.done_seen, w.fired) = (0, 0, [None; 4]);
        w.clean = [false; AXIS_COUNT];
        w.estop_since = w.estop_since.map(|_| now);
        w.driver_fault_since = w.driver_fault_since.map(|_| now);
        let faults = self.rig.ctrl.faults();
        let watchdog = reason == ResetReason::Watchdog;
        let storage = self.rig.hw.storage_fails;
        if blob(self.rig.ctrl.config()) != self.watch.saved {
            return Err(self.violation(Rule::ConfigNotKept, None));
        }
        if faults.contains(FaultFlags::WATCHDOG_RESET) != watchdog
            || faults.contains(FaultFlags::STORAGE_FAILED) != storage
        {
            return Err(self.violation(Rule::ResetCauseNotLatched, None));
        }
        Ok(())
    }

    fn check_state(&mut self) -> Result<(), Violation> {
        self.watch.state(&self.rig)
    }

    fn violation(&self, rule: Rule, axis: Option<Axis>) -> Violation {
        self.watch.violation(&self.rig, rule, axis)
    }
}

/// Position `p` of an axis configured as `c`: the disk's within its turn.
fn within_turn(c: &protocol::AxisConfig, p: i64) -> i64 {
    if c.continuous { p.rem_euclid(c.steps_per_rev.max(1) as i64) } else { p }
}

impl Watch {
    /// A hand or a switch changed axis `i` at `now`: a homing running is
    /// no longer the switch's alone.
    fn touch(&mut self, i: usize, now: u64) {
        (self.clean[i], self.touched[i]) = (false, now);
    }

    /// Note the motion an acknowledged `request` starts: the axes it may
    /// move and, for a move, where it must leave them.
    fn motion_asked(&mut self, request: &Request, rig: &Rig) {
        self.motions += 1;
        let config = rig.ctrl.config();
        let mirror = |m: u8| {
            let position = config.mirrors.get(m as usize).copied().flatten();
            (AxisSet::ALL, position.map_or([None; AXIS_COUNT], |p| p.steps.map(Some)))
        };
        let (mode, (asked, targets)) = match *request {
            Request::Home { axes } => {
                for axis in axes.iter() {
                    self.clean[axis.index()] = true;
                }
                (MoveMode::Absolute, (axes, [None; AXIS_COUNT]))
            }
            Request::Move { mode, targets } => {
                let axes = Axis::ALL.into_iter().filter(|a| targets[a.index()].is_some());
                (mode, (axes.fold(AxisSet::NONE, AxisSet::with), targets))
            }
            Request::GoToMirror { mirror: m } => (MoveMode::Absolute, mirror(m)),
            Request::CaptureStep(step) => (MoveMode::Absolute, mirror(step.mirror)),
            Request::TimedCaptureStep(t) => (MoveMode::Absolute, mirror(t.step.mirror)),
            _ => (MoveMode::Absolute, (AxisSet::NONE, [None; AXIS_COUNT])),
        };
        self.asked = asked;
        self.targets = core::array::from_fn(|i| {
            let t = targets[i]? as i64;
            let end = match mode {
                MoveMode::Absolute => t,
                MoveMode::Relative => rig.hw.steppers[i].position() as i64 + t,
            };
            Some(within_turn(&config.axes[i], end))
        });
    }

    /// [`Rule::HomedOffSwitch`] on `axis`, homed since the last check.
    fn homed_at(&mut self, rig: &Rig, axis: Axis) -> Result<(), Violation> {
        let Some(home) = Home::of(rig, axis).filter(|_| self.clean[axis.index()]) else {
            return Ok(());
        };
        self.report.homed_at_switch += 1;
        self.report.homed_active_high += usize::from(rig.switch_active_high[axis.index()]);
        if home.error(rig.position(axis) as i64 - rig.physical(axis)).abs() > 1 {
            return Err(self.violation(rig, Rule::HomedOffSwitch, Some(axis)));
        }
        Ok(())
    }

    /// [`Rule::PositionMisjudged`] on the `PositionChecked` events since
    /// the last visit, against the counts' offsets then.
    fn positions_checked(&mut self, rig: &Rig) -> Result<(), Violation> {
        let new = rig.events.get(self.events_seen..).unwrap_or_default();
        self.events_seen = rig.events.len();
        for e in new {
            let Event::PositionChecked { axis, error_steps } = *e else { continue };
            let i = axis.index();
            // A hand or a switch changed within the debounce time: the
            // offset before this visit may not be the one at the edge.
            let settled = rig.now > self.touched[i] + STOP_WITHIN + POLL_TICKS;
            let Some(home) = Home::of(rig, axis).filter(|_| settled) else { continue };
            self.report.positions_checked += 1;
            // The edge met the other way is a step further on.
            if (error_steps as i64 - home.error(self.offset[i])).abs() > 1 + 1 {
                return Err(self.violation(rig, Rule::PositionMisjudged, Some(axis)));
            }
        }
        Ok(())
    }

    /// [`Rule::MoveOffTarget`] on a `MotionDone` not yet checked.
    fn motion_done(&mut self, rig: &Rig) -> Result<(), Violation> {
        if rig.motion_done == self.done_seen {
            return Ok(());
        }
        self.done_seen = rig.motion_done;
        let Some(Event::MotionDone { outcome: MotionOutcome::Completed, positions, .. }) =
            rig.last_motion_done
        else {
            return Ok(());
        };
        for axis in Axis::ALL {
            let i = axis.index();
            let at = |p: i32| within_turn(&rig.ctrl.config().axes[i], p as i64);
            if let Some(target) = self.targets[i]
                && (at(positions[i]) != target || at(rig.position(axis)) != target)
            {
                return Err(self.violation(rig, Rule::MoveOffTarget, Some(axis)));
            }
        }
        self.report.on_target += usize::from(self.targets.iter().any(Option::is_some));
        Ok(())
    }

    /// [`Rule::ExposureMisread`] on the strobe's report of pulse `seq`,
    /// against the rig's camera (its line read through the configured
    /// polarity, sampled at every poll: each edge seen within a poll).
    fn exposure(
        &mut self,
        rig: &Rig,
        seq: u32,
        window: Option<protocol::StrobeWindow>,
    ) -> Result<(), Violation> {
        let config = rig.ctrl.config().strobe;
        let Some(camera) = rig
            .strobe
            .filter(|c| !c.ignores && config.enabled && config.active_high == c.active_high)
        else {
            return Ok(());
        };
        // The pulse's edges and the next pulse's rise, from the outputs.
        let Some(fired) = self.fired.iter().flatten().find(|f| f.0 == seq) else {
            return Ok(());
        };
        let rise = fired.1;
        let edges = rig.hw.outputs.iter().filter_map(|o| match *o {
            Output::Trigger(t, high) if t >= rise => Some((t, high)),
            _ => None,
        });
        let mut edges = edges.skip_while(|e| *e != (rise, true)).skip(1);
        let Some((fall, false)) = edges.next() else {
            return Ok(()); // not recorded (or still high)
        };
        let next_rise = edges.find(|e| e.1).map(|e| e.0);
        let (d, length) = (camera.delay, fall - rise);
        let ticks = |us: u32| us as u64 * TICKS_PER_US;
        let near = |measured: u64, truth: u64| {
            measured + TICKS_PER_US >= truth && measured <= truth + POLL_TICKS + TICKS_PER_US
        };
        self.report.exposures += 1;
        match window {
            Some(w) if w.ended => {
                // Seen from the first poll in the window to the first after.
                let length_ok = ticks(w.length_us) + POLL_TICKS + TICKS_PER_US >= length
                    && ticks(w.length_us) <= length + POLL_TICKS + TICKS_PER_US;
                if !near(ticks(w.delay_us), d) || !length_ok {
                    return Err(self.violation(rig, Rule::ExposureMisread, None));
                }
            }
            Some(_) => {}
            None => {
                // Visible: exposing for two polls or more, rising well
                // before the watch gives up, and not cut by the next pulse.
                let asked = ticks(fired.2);
                let gives_up = asked + ticks(config.max_delay_us);
                let visible = length >= 2 * POLL_TICKS
                    && d + 2 * POLL_TICKS <= gives_up
                    && next_rise.is_none_or(|n| n > rise + d + 2 * POLL_TICKS);
                if visible {
                    return Err(self.violation(rig, Rule::ExposureMisread, None));
                }
            }
        }
        Ok(())
    }

    /// Note the light an acknowledged `request` asks for.
    fn light_asked(&mut self, request: &Request) {
        let step = match *request {
            Request::SetLight(LightState { on, duty_permille }) => {
                self.set_light = on.then_some(duty_permille);
                return;
            }
            Request::CaptureStep(step) => (step.light_duty_permille, 0),
            Request::TimedCaptureStep(t) => {
                (t.step.light_duty_permille, t.light_margin_us as u64 * TICKS_PER_US)
            }
            _ => return,
        };
        self.step_lights = [self.step_lights[1], Some(step)];
        self.step_lit_since = None;
    }

    /// [`Rule::SwitchHitIgnored`]: a homed linear axis' switch that came on
    /// far from home (outside its homing) latches a fault within the
    /// debounce time and a poll.
    fn switches(&mut self, rig: &Rig) -> Result<(), Violation> {
        let lines = rig.inputs().home_line;
        let faults = rig.ctrl.faults();
        let acted_on = faults.contains(FaultFlags::UNEXPECTED_HOME_SWITCH)
            || faults.contains(FaultFlags::POSITION_LOST);
        for axis in Axis::ALL {
            let i = axis.index();
            let on = lines[i] == rig.ctrl.config().home.active_high[i];
            let rose = on && !self.switch_on[i];
            self.switch_on[i] = on;
            let watched = on
                && rig.ctrl.is_homed(axis)
                && !rig.ctrl.config().axes[i].continuous
                && !rig.ctrl.homing_axes().contains(axis);
            self.switch_hit[i] = match self.switch_hit[i] {
                _ if !watched => Hit::None,
                Hit::None if rose && rig.ctrl.far_from_home(axis, rig.position(axis)) => {
                    self.report.switch_hits += 1;
                    Hit::Since(rig.now)
                }
                Hit::Since(_) if acted_on => Hit::ActedOn,
                Hit::Since(t) if rig.now > t + STOP_WITHIN => {
                    return Err(self.violation(rig, Rule::SwitchHitIgnored, Some(axis)));
                }
                hit => hit,
            };
        }
        Ok(())
    }

    /// [`Rule::LightNotAsked`] on the light as it is.
    fn light(&mut self, rig: &Rig) -> Result<(), Violation> {
        if dark(rig.ctrl.faults()) {
            self.set_light = None;
        }
        let level = rig.hw.light;
        if level == 0 || Some(level) == self.set_light {
            self.step_lit_since = None;
            return Ok(());
        }
        let margin = self.step_lights.iter().flatten().filter(|(d, _)| *d == level).map(|s| s.1);
        let Some(margin) = margin.max() else {
            return Err(self.violation(rig, Rule::LightNotAsked, None));
        };
        if rig.hw.trigger {
            self.step_lit_since = None;
            return Ok(());
        }
        let since = match self.step_lit_since {
            Some((lit, since)) if lit == level => since,
            _ => rig.now,
        };
        self.step_lit_since = Some((level, since));
        if rig.now > since + margin + POLL_TICKS {
            return Err(self.violation(rig, Rule::LightNotAsked, None));
        }
        Ok(())
    }

    fn violation(&self, rig: &Rig, rule: Rule, axis: Option<Axis>) -> Violation {
        Violation { rule, action: self.action, tick: rig.now, axis, faults: rig.ctrl.faults() }
    }

    fn visit(&mut self, rig: &mut Rig, visit: Visit) -> Result<(), Violation> {
        self.positions_checked(rig)?;
        for axis in Axis::ALL {
            self.offset[axis.index()] = rig.position(axis) as i64 - rig.physical(axis);
        }
        match visit {
            Visit::Stepped(axis) => self.step(rig, axis),
            Visit::Polled if rig.stale_deadline() => {
                Err(self.violation(rig, Rule::StaleDeadline, None))
            }
            Visit::Polled if rig.ctrl.in_motion() && !rig.ctrl.is_moving() => {
                Err(self.violation(rig, Rule::MotionNotReported, None))
            }
            Visit::Polled => self.state(rig),
        }
    }

    /// `axis` has just stepped (the controller has not polled since).
    fn step(&mut self, rig: &Rig, axis: Axis) -> Result<(), Violation> {
        let i = axis.index();
        self.report.steps[i] += 1;
        let faults = rig.ctrl.faults();
        if stops_at_once(faults) {
            return Err(self.violation(rig, Rule::StepWhileFaulted, Some(axis)));
        }
        if rig.hw.trigger {
            return Err(self.violation(rig, Rule::StepDuringExposure, Some(axis)));
        }
        let late = |since: Option<u64>| since.is_some_and(|t| rig.now > t + STOP_WITHIN);
        if late(self.estop_since) || late(self.driver_fault_since) {
            return Err(self.violation(rig, Rule::StopInputIgnored, Some(axis)));
        }
        let config = &rig.ctrl.config().axes[i];
        let stop = config.v_max as u64 * TICK_HZ as u64 / config.a_max.max(1) as u64;
        let timeout = LINK_TIMEOUT_MS * TICKS_PER_MS + POLL_TICKS;
        if !rig.keepalive && rig.now > self.heard + timeout + stop + LINK_SLACK {
            return Err(self.violation(rig, Rule::LinkLossIgnored, Some(axis)));
        }
        if rig.ctrl.is_homed(axis) {
            self.report.homed_steps += 1;
            let c = &rig.ctrl.config().axes[i];
            if !c.continuous && !(c.min_steps..=c.max_steps).contains(&rig.position(axis)) {
                return Err(self.violation(rig, Rule::SoftLimit, Some(axis)));
            }
        } else if !rig.ctrl.homing_axes().contains(axis) {
            return Err(self.violation(rig, Rule::UnhomedAxisMoved, Some(axis)));
        }
        if self.motions <= rig.motion_done || !self.asked.contains(axis) {
            return Err(self.violation(rig, Rule::StepNotAsked, Some(axis)));
        }
        Ok(())
    }

    /// The rules on the controller's state, after a poll or a request.
    fn state(&mut self, rig: &Rig) -> Result<(), Violation> {
        let faults = rig.ctrl.faults();
        let hw = &rig.hw;
        for axis in Axis::ALL {
            let homed = rig.ctrl.is_homed(axis);
            if homed && !self.homed[axis.index()] {
                self.report.homings += 1;
                self.homed_at(rig, axis)?;
            }
            self.homed[axis.index()] = homed;
        }
        if hw.light > FULL_DUTY_PERMILLE {
            return Err(self.violation(rig, Rule::LightDuty, None));
        }
        if dark(faults) && (hw.light != 0 || hw.trigger) {
            return Err(self.violation(rig, Rule::LightWhileFaulted, None));
        }
        self.light(rig)?;
        self.switches(rig)?;
        // One `MotionDone` per motion acknowledged, once it has ended (a
        // reset or the bootloader ends it without: the device goes away).
        let running = usize::from(rig.ctrl.in_motion());
        let leaving = rig.ctrl.reset_requested() || rig.ctrl.bootloader_requested();
        if rig.motion_done + running != self.motions && !leaving {
            return Err(self.violation(rig, Rule::MotionNotReported, None));
        }
        self.motion_done(rig)?;
        if !hw.drivers_enabled
            && let Some(axis) = Axis::ALL.into_iter().find(|a| rig.ctrl.is_homed(*a))
        {
            return Err(self.violation(rig, Rule::HomedWhileUnpowered, Some(axis)));
        }
        let late = |since: Option<u64>| since.is_some_and(|t| rig.now > t + STOP_WITHIN);
        let stopped = |flag: FaultFlags| {
            faults.contains(flag) && !hw.drivers_enabled && hw.armed.iter().all(Option::is_none)
        };
        if (late(self.estop_since) && !stopped(FaultFlags::EMERGENCY_STOP))
            || (late(self.driver_fault_since) && !stopped(FaultFlags::DRIVER_FAULT))
        {
            return Err(self.violation(rig, Rule::StopInputIgnored, None));
        }
        match (hw.trigger, self.trigger_since) {
            (true, None) => self.trigger_since = Some(rig.now),
            (false, Some(_)) => self.trigger_since = None,
            (true, Some(t)) => {
                let longest = (MAX_EXPOSURE_US as u64 + 2 * MAX_LIGHT_MARGIN_US as u64)
                    * TICKS_PER_US
                    + POLL_TICKS;
                if rig.now > t + longest {
                    return Err(self.violation(rig, Rule::TriggerStuck, None));
                }
            }
            (false, None) => {}
        }
        Ok(())
    }
}
