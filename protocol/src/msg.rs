//! The message table: every request the host sends and every reply or event the
//! device sends, plus the plain data types they carry.
//!
//! postcard is not self-describing, so this module *is* the wire schema: enum
//! variants are encoded as their declaration index (a varint), so **variants are
//! only ever appended**, never reordered or removed, within one protocol major
//! version. `docs/protocol.md` lists the indices and the encoding of every field.
//!
//! Positions and speeds travel in integer **steps** (exact, no rounding on the
//! device); the axis configuration carries the steps-per-unit factor so the host
//! can convert to millimetres or degrees.

use postcard::experimental::max_size::MaxSize;
use serde::{Deserialize, Serialize};

/// Derives shared by every wire type (kept in one place so no type forgets one).
macro_rules! wire_type {
    ($(#[$meta:meta])* $vis:vis $kind:ident $name:ident $($body:tt)*) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, MaxSize)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        #[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
        $vis $kind $name $($body)*
    };
}

/// Number of motor axes on the scanner.
pub const AXIS_COUNT: usize = 3;

/// Most mirror-table entries a device can hold (the default scanner uses 40).
pub const MAX_MIRRORS: usize = 64;

/// Longest log line a device sends, in bytes of UTF-8.
pub const LOG_TEXT_CAPACITY: usize = 48;

wire_type! {
    /// A protocol version. Peers with different `major` refuse to talk; `minor`
    /// only adds messages or variants at the end of a table.
    #[derive(Eq, Hash)]
    pub struct ProtocolVersion {
        /// Incompatible changes bump this.
        pub major: u8,
        /// Compatible additions bump this.
        pub minor: u8,
    }
}

impl ProtocolVersion {
    /// Whether a peer speaking `other` can talk to one speaking `self`.
    pub const fn is_compatible_with(self, other: ProtocolVersion) -> bool {
        self.major == other.major
    }
}

impl core::fmt::Display for ProtocolVersion {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{}.{}", self.major, self.minor)
    }
}

wire_type! {
    /// Firmware semantic version.
    #[derive(Eq, Hash)]
    pub struct FirmwareVersion {
        /// Major.
        pub major: u8,
        /// Minor.
        pub minor: u8,
        /// Patch.
        pub patch: u8,
    }
}

impl core::fmt::Display for FirmwareVersion {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "{}.{}.{}", self.major, self.minor, self.patch)
    }
}

wire_type! {
    /// One of the scanner's three motor axes (spec/hardware.md, "Axes").
    #[derive(Eq, Hash, PartialOrd, Ord)]
    pub enum Axis {
        /// Rotation of the source disk; continuous, homes on its index flag.
        Disk,
        /// Radial position of the source on the disk.
        Track,
        /// Tilt of the fold mirror.
        Tilt,
    }
}

impl Axis {
    /// All axes, in wire order.
    pub const ALL: [Axis; AXIS_COUNT] = [Axis::Disk, Axis::Track, Axis::Tilt];

    /// Index of this axis in per-axis arrays.
    pub const fn index(self) -> usize {
        self as usize
    }

    /// The axis at `index`, if any.
    pub const fn from_index(index: usize) -> Option<Axis> {
        match index {
            0 => Some(Axis::Disk),
            1 => Some(Axis::Track),
            2 => Some(Axis::Tilt),
            _ => None,
        }
    }

    /// Lower-case name, as used by the CLI and the docs.
    pub const fn name(self) -> &'static str {
        match self {
            Axis::Disk => "disk",
            Axis::Track => "track",
            Axis::Tilt => "tilt",
        }
    }
}

wire_type! {
    /// A set of axes as a bit mask: bit *n* is `Axis::from_index(n)`.
    /// Bits 3..=7 are invalid and make the device answer `BadRequest`.
    #[derive(Eq, Hash, Default)]
    pub struct AxisSet(pub u8);
}

impl AxisSet {
    /// No axis.
    pub const NONE: AxisSet = AxisSet(0);
    /// Every axis.
    pub const ALL: AxisSet = AxisSet(0b111);

    /// The set holding only `axis`.
    pub const fn single(axis: Axis) -> AxisSet {
        AxisSet(1 << axis as u8)
    }
    /// Whether `axis` is in the set.
    pub const fn contains(self, axis: Axis) -> bool {
        self.0 & (1 << axis as u8) != 0
    }
    /// The set with `axis` added.
    pub const fn with(self, axis: Axis) -> AxisSet {
        AxisSet(self.0 | (1 << axis as u8))
    }
    /// Whether only bits of real axes are set.
    pub const fn is_valid(self) -> bool {
        self.0 & !Self::ALL.0 == 0
    }
    /// Whether the set is empty.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
    /// The axes in the set, in wire order.
    pub fn iter(self) -> impl Iterator<Item = Axis> {
        Axis::ALL.into_iter().filter(move |a| self.contains(*a))
    }
}

wire_type! {
    /// Physical unit of an axis position.
    #[derive(Eq, Hash)]
    pub enum Unit {
        /// Degrees (rotary axes).
        Degree,
        /// Millimetres (linear axes).
        Millimetre,
    }
}

wire_type! {
    /// Direction of travel.
    #[derive(Eq, Hash)]
    pub enum Direction {
        /// Towards decreasing step counts.
        Negative,
        /// Towards increasing step counts.
        Positive,
    }
}

wire_type! {
    /// How an axis finds its home: fast approach to the switch, back off, slow
    /// approach; the position at the slow-approach edge becomes `home_position`.
    #[derive(Eq, Hash)]
    pub struct HomingConfig {
        /// Direction of the approach to the switch.
        pub direction: Direction,
        /// Fast-approach speed, steps/s.
        pub fast_speed: u32,
        /// Slow-approach speed, steps/s.
        pub slow_speed: u32,
        /// Back-off distance after the fast approach, steps.
        pub backoff_steps: u32,
        /// Longest travel searched before homing fails (`SwitchNotFound`), steps.
        pub max_travel_steps: u32,
        /// Time limit for the whole homing sequence, ms.
        pub timeout_ms: u32,
        /// Position (steps) assigned at the switch edge.
        pub home_position: i32,
    }
}

wire_type! {
    /// Per-axis configuration: kinematics, limits and homing.
    pub struct AxisConfig {
        /// Unit of `steps_per_unit`.
        pub unit: Unit,
        /// Steps per unit (e.g. 1600 steps/mm); used only to report units.
        pub steps_per_unit: f32,
        /// Soft limit, lowest allowed position, steps (ignored when `continuous`).
        pub min_steps: i32,
        /// Soft limit, highest allowed position, steps (ignored when `continuous`).
        pub max_steps: i32,
        /// Continuous rotation: no soft limits, positions wrap at `steps_per_rev`.
        pub continuous: bool,
        /// Steps per full revolution (continuous axes), 0 otherwise.
        pub steps_per_rev: u32,
        /// Maximum speed, steps/s.
        pub v_max: u32,
        /// Maximum acceleration, steps/s².
        pub a_max: u32,
        /// Homing parameters.
        pub homing: HomingConfig,
    }
}

// The default axes (spec/hardware.md, "Axes"): what the firmware runs
// until a configuration is saved, and the travel `scanner geometry`
// checks a design against.

/// DISK: 200 × 16 µsteps × 5:1 belt = 16 000 steps/rev; 90 °/s; 180 °/s².
pub const fn disk_default() -> AxisConfig {
    AxisConfig {
        unit: Unit::Degree,
        steps_per_unit: 16_000.0 / 360.0,
        min_steps: 0,
        max_steps: 15_999,
        continuous: true,
        steps_per_rev: 16_000,
        v_max: 4_000,
        a_max: 8_000,
        homing: HomingConfig {
            direction: Direction::Positive,
            fast_speed: 1_000,
            slow_speed: 100,
            backoff_steps: 400,
            max_travel_steps: 17_600,
            timeout_ms: 30_000,
            home_position: 0,
        },
    }
}

/// TRACK: 2 mm lead, 16 µsteps → 1 600 steps/mm; 0 … 200 mm; 40 mm/s; 200 mm/s².
pub const fn track_default() -> AxisConfig {
    AxisConfig {
        unit: Unit::Millimetre,
        steps_per_unit: 1_600.0,
        min_steps: 0,
        max_steps: 320_000,
        continuous: false,
        steps_per_rev: 0,
        v_max: 64_000,
        a_max: 320_000,
        homing: HomingConfig {
            direction: Direction::Negative,
            fast_speed: 16_000,
            slow_speed: 1_600,
            backoff_steps: 3_200,
            max_travel_steps: 336_000,
            timeout_ms: 40_000,
            home_position: 0,
        },
    }
}

/// TILT: 200 × 16 × 30:1 worm = 96 000 steps/rev; −35° … +35°; 20 °/s; 60 °/s².
pub const fn tilt_default() -> AxisConfig {
    AxisConfig {
        unit: Unit::Degree,
        steps_per_unit: 96_000.0 / 360.0,
        min_steps: -9_333,
        max_steps: 9_333,
        continuous: false,
        steps_per_rev: 0,
        v_max: 5_333,
        a_max: 16_000,
        homing: HomingConfig {
            direction: Direction::Negative,
            fast_speed: 2_667,
            slow_speed: 267,
            backoff_steps: 533,
            max_travel_steps: 20_000,
            timeout_ms: 30_000,
            home_position: -9_333,
        },
    }
}

/// Slowest speed a controller's step generator times (its fixed-point
/// interval limit is 2^40 ticks; this keeps a wide margin), steps/s; also
/// the least acceleration, steps/s².
pub const MIN_AXIS_SPEED: u32 = 10;
/// Fastest step rate a controller accepts per axis, steps/s.
pub const MAX_AXIS_SPEED: u32 = 100_000;

/// Why a controller refuses an [`AxisConfig`] ([`AxisConfig::problem`]):
/// `SetAxisConfig` answers `BadRequest` to any of these.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AxisConfigProblem {
    /// `steps_per_unit` is not a finite positive number.
    StepsPerUnit,
    /// `v_max` is outside [`MIN_AXIS_SPEED`] … [`MAX_AXIS_SPEED`].
    MaxSpeed,
    /// `a_max` is below [`MIN_AXIS_SPEED`].
    MaxAcceleration,
    /// `homing.fast_speed` is outside the speed range or above `v_max`.
    FastSpeed,
    /// `homing.slow_speed` is outside the speed range or above `fast_speed`.
    SlowSpeed,
    /// `homing.backoff_steps` is 0.
    Backoff,
    /// `homing.max_travel_steps` is not beyond `backoff_steps`.
    MaxTravel,
    /// `homing.timeout_ms` is 0.
    Timeout,
    /// A continuous axis' `steps_per_rev` is 0 or beyond `i32::MAX`.
    StepsPerRev,
    /// A limited axis' `min_steps` is not below `max_steps`.
    Limits,
}

impl core::fmt::Display for AxisConfigProblem {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let (lo, hi) = (MIN_AXIS_SPEED, MAX_AXIS_SPEED);
        match self {
            Self::StepsPerUnit => write!(f, "steps_per_unit must be a finite number above 0"),
            Self::MaxSpeed => write!(f, "v_max must be {lo} … {hi} steps/s"),
            Self::MaxAcceleration => write!(f, "a_max must be at least {lo} steps/s²"),
            Self::FastSpeed => {
                write!(f, "homing.fast_speed must be {lo} … {hi} steps/s and at most v_max")
            }
            Self::SlowSpeed => write!(
                f,
                "homing.slow_speed must be {lo} … {hi} steps/s and at most homing.fast_speed"
            ),
            Self::Backoff => write!(f, "homing.backoff_steps must be above 0"),
            Self::MaxTravel => {
                write!(f, "homing.max_travel_steps must be above homing.backoff_steps")
            }
            Self::Timeout => write!(f, "homing.timeout_ms must be above 0"),
            Self::StepsPerRev => {
                write!(f, "a continuous axis' steps_per_rev must be 1 … {}", i32::MAX)
            }
            Self::Limits => write!(f, "min_steps must be below max_steps"),
        }
    }
}

impl AxisConfig {
    /// The first reason a controller cannot execute this configuration,
    /// if any (the one rule the firmware applies to `SetAxisConfig` and to
    /// a saved configuration, and the host to a file before sending it).
    pub fn problem(&self) -> Option<AxisConfigProblem> {
        let speed_ok = |v: u32| (MIN_AXIS_SPEED..=MAX_AXIS_SPEED).contains(&v);
        let h = &self.homing;
        let problem = if !(self.steps_per_unit.is_finite() && self.steps_per_unit > 0.0) {
            AxisConfigProblem::StepsPerUnit
        } else if !speed_ok(self.v_max) {
            AxisConfigProblem::MaxSpeed
        } else if self.a_max < MIN_AXIS_SPEED {
            AxisConfigProblem::MaxAcceleration
        } else if !speed_ok(h.fast_speed) || h.fast_speed > self.v_max {
            AxisConfigProblem::FastSpeed
        } else if !speed_ok(h.slow_speed) || h.slow_speed > h.fast_speed {
            AxisConfigProblem::SlowSpeed
        } else if h.backoff_steps == 0 {
            AxisConfigProblem::Backoff
        } else if h.max_travel_steps <= h.backoff_steps {
            AxisConfigProblem::MaxTravel
        } else if h.timeout_ms == 0 {
            AxisConfigProblem::Timeout
        } else if self.continuous && !(1..=i32::MAX as u32).contains(&self.steps_per_rev) {
            AxisConfigProblem::StepsPerRev
        } else if !self.continuous && self.min_steps >= self.max_steps {
            AxisConfigProblem::Limits
        } else {
            return None;
        };
        Some(problem)
    }
}

/// The three defaults, indexed by axis.
pub const fn default_axes() -> [AxisConfig; AXIS_COUNT] {
    [disk_default(), track_default(), tilt_default()]
}

wire_type! {
    /// Position of every axis that aims the beam at one mirror, in steps.
    #[derive(Eq, Hash)]
    pub struct MirrorPosition {
        /// Target per axis, indexed by [`Axis::index`].
        pub steps: [i32; AXIS_COUNT],
    }
}

wire_type! {
    /// Absolute targets or relative offsets.
    #[derive(Eq, Hash)]
    pub enum MoveMode {
        /// Targets are positions.
        Absolute,
        /// Targets are offsets from the current position.
        Relative,
    }
}

wire_type! {
    /// Light output state.
    #[derive(Eq, Hash, Default)]
    pub struct LightState {
        /// Whether the light is on.
        pub on: bool,
        /// PWM duty in per mille (0..=1000) used while on.
        pub duty_permille: u16,
    }
}

wire_type! {
    /// One capture step, executed by the device as a unit: go to `mirror` →
    /// settle → light on → trigger pulse of `exposure_us` → light off →
    /// [`Event::TriggerFired`].
    #[derive(Eq, Hash)]
    pub struct CaptureStep {
        /// Mirror-table index.
        pub mirror: u8,
        /// Settling time after the move, ms.
        pub settle_ms: u16,
        /// Trigger pulse / exposure length, µs (1 ms ..= 2 s).
        pub exposure_us: u32,
        /// Light duty while exposing, per mille (1..=1000).
        pub light_duty_permille: u16,
    }
}

wire_type! {
    /// A capture step whose light goes on `light_margin_us` before the
    /// trigger rises and off as long after it falls (since 1.3): for a
    /// camera that exposes later than its trigger's edges (an
    /// opto-isolated input's delay) or a light that takes time to come
    /// up. The exposure is still the pulse; the light covers it.
    #[derive(Eq, Hash)]
    pub struct TimedCaptureStep {
        /// The step.
        pub step: CaptureStep,
        /// Light before and after the pulse, µs (0 ..= [`MAX_LIGHT_MARGIN_US`]).
        pub light_margin_us: u16,
    }
}

/// Longest light margin of a [`TimedCaptureStep`], µs.
pub const MAX_LIGHT_MARGIN_US: u16 = 10_000;

/// Default settle time of a capture step (spec/hardware.md).
pub const DEFAULT_SETTLE_MS: u16 = 150;
/// Default exposure of a capture step (spec/hardware.md).
pub const DEFAULT_EXPOSURE_US: u32 = 50_000;
/// Shortest allowed exposure.
pub const MIN_EXPOSURE_US: u32 = 1_000;
/// Longest allowed exposure.
pub const MAX_EXPOSURE_US: u32 = 2_000_000;
/// Full light duty.
pub const FULL_DUTY_PERMILLE: u16 = 1000;
/// The light's PWM frequency on the board, Hz: a duty of d ‰ lights
/// d/1000 of every 50 µs period.
pub const LIGHT_PWM_HZ: u32 = 20_000;

wire_type! {
    /// Latched fault flags (bit mask). A set flag stops all motion and switches
    /// the light off; it stays set until [`Request::ClearFault`].
    #[derive(Eq, Hash, Default)]
    pub struct FaultFlags(pub u16);
}

impl FaultFlags {
    /// No fault.
    pub const NONE: FaultFlags = FaultFlags(0);
    /// Emergency-stop input asserted or [`Request::EmergencyStop`] received.
    pub const EMERGENCY_STOP: FaultFlags = FaultFlags(1 << 0);
    /// A stepper driver reported a fault.
    pub const DRIVER_FAULT: FaultFlags = FaultFlags(1 << 1);
    /// A home switch was hit outside homing.
    pub const UNEXPECTED_HOME_SWITCH: FaultFlags = FaultFlags(1 << 2);
    /// No message from the host for 500 ms while moving.
    pub const LINK_TIMEOUT: FaultFlags = FaultFlags(1 << 3);
    /// The last reset was caused by the hardware watchdog.
    pub const WATCHDOG_RESET: FaultFlags = FaultFlags(1 << 4);
    /// Homing of an axis failed (switch not found, timeout, stuck switch).
    pub const HOMING_FAILED: FaultFlags = FaultFlags(1 << 5);
    /// An axis' step count disagreed with its home or index switch by more
    /// than [`POSITION_TOLERANCE_STEPS`](crate::POSITION_TOLERANCE_STEPS)
    /// while it moved (steps were lost): the axis is no longer homed, and
    /// [`Event::PositionChecked`] says by how much.
    pub const POSITION_LOST: FaultFlags = FaultFlags(1 << 6);
    /// The device could not write its flash at boot (the boot counter): its
    /// saved configuration may not persist either. Motion is refused until
    /// `ClearFault`, so that the host notices.
    pub const STORAGE_FAILED: FaultFlags = FaultFlags(1 << 7);

    /// Whether no flag is set.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
    /// Whether every flag of `other` is set.
    pub const fn contains(self, other: FaultFlags) -> bool {
        self.0 & other.0 == other.0 && other.0 != 0
    }
    /// Union.
    pub const fn union(self, other: FaultFlags) -> FaultFlags {
        FaultFlags(self.0 | other.0)
    }
    /// Names of the set flags in words, for messages.
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        const NAMES: [&str; 8] = [
            "emergency stop",
            "driver fault",
            "home switch hit far from home",
            "link timeout",
            "watchdog reset",
            "homing failed",
            "position lost (steps lost)",
            "flash storage failed",
        ];
        set_bit_names(self.0, &NAMES)
    }
}

/// The names of the bits set in `mask`, bit 0 first: `names[bit]` (a bit
/// beyond `names` is left out).
fn set_bit_names(
    mask: u16,
    names: &'static [&'static str],
) -> impl Iterator<Item = &'static str> + use<> {
    names.iter().enumerate().filter(move |(bit, _)| mask & (1 << bit) != 0).map(|(_, n)| *n)
}

wire_type! {
    /// Device capabilities (bit mask).
    #[derive(Eq, Hash, Default)]
    pub struct Capabilities(pub u16);
}

impl Capabilities {
    /// Mirror table and axis configs persist in flash ([`Request::SaveConfig`]).
    pub const PERSISTENT_CONFIG: Capabilities = Capabilities(1 << 0);
    /// Light output is PWM-dimmable.
    pub const PWM_LIGHT: Capabilities = Capabilities(1 << 1);
    /// Camera "exposure active" strobe input is wired.
    pub const EXPOSURE_STROBE: Capabilities = Capabilities(1 << 2);
    /// A vendor-class USB bulk interface is offered beside CDC-ACM.
    pub const USB_BULK: Capabilities = Capabilities(1 << 3);
    /// The device sends [`Event::Log`] lines.
    pub const LOG_EVENTS: Capabilities = Capabilities(1 << 4);
    /// The device is a simulator.
    pub const SIMULATED: Capabilities = Capabilities(1 << 5);
    /// [`Request::EnterBootloader`] resets it into the chip's ROM
    /// bootloader (USB DFU) (since 1.5).
    pub const SYSTEM_BOOTLOADER: Capabilities = Capabilities(1 << 6);

    /// Whether every capability of `other` is present.
    pub const fn contains(self, other: Capabilities) -> bool {
        self.0 & other.0 == other.0
    }
    /// Union.
    pub const fn union(self, other: Capabilities) -> Capabilities {
        Capabilities(self.0 | other.0)
    }
    /// Names of the set capabilities in words, for messages (a bit this
    /// version does not know is left out).
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        const NAMES: [&str; 7] = [
            "persistent config",
            "PWM light",
            "exposure strobe input",
            "USB bulk interface",
            "log events",
            "simulated",
            "ROM bootloader on command",
        ];
        set_bit_names(self.0, &NAMES)
    }
}

wire_type! {
    /// Answer to [`Request::Hello`]: who the device is.
    #[derive(Eq, Hash)]
    pub struct DeviceInfo {
        /// Protocol version the device speaks.
        pub protocol: ProtocolVersion,
        /// Firmware version.
        pub firmware: FirmwareVersion,
        /// Board identifier ([`BOARD_STM32F411_BLACKPILL`], [`BOARD_SIMULATOR`], …).
        pub board: u16,
        /// Unique device id (the STM32's 96-bit UID).
        pub device_id: [u8; 12],
        /// Capabilities.
        pub capabilities: Capabilities,
        /// Entries in the mirror table.
        pub mirror_count: u8,
        /// An id that changes at every boot (the board: a CRC of its chip id and
        /// its flash and RAM boot counters): a change means the device was reset.
        pub boot_id: u32,
    }
}

/// [`DeviceInfo::board`] of the default STM32F411CEU6 "Black Pill" controller.
pub const BOARD_STM32F411_BLACKPILL: u16 = 0x0411;
/// [`DeviceInfo::board`] of the hil-sim simulated scanner.
pub const BOARD_SIMULATOR: u16 = 0x5100;

wire_type! {
    /// What the device is doing.
    #[derive(Eq, Hash, Default)]
    pub enum DeviceState {
        /// Ready for a command.
        #[default]
        Idle,
        /// Homing one or more axes.
        Homing,
        /// Executing a move.
        Moving,
        /// Executing a capture step or a trigger pulse.
        Capturing,
        /// A fault is latched; only status, info, stop and clear are accepted.
        Faulted,
    }
}

wire_type! {
    /// State of one axis.
    pub struct AxisStatus {
        /// Commanded position, steps.
        pub position_steps: i32,
        /// Same position in the axis' unit.
        pub position_units: f32,
        /// Whether the axis is moving.
        pub moving: bool,
        /// Whether the axis has been homed since boot.
        pub homed: bool,
    }
}

wire_type! {
    /// Answer to [`Request::GetStatus`].
    pub struct Status {
        /// Per axis, indexed by [`Axis::index`].
        pub axes: [AxisStatus; AXIS_COUNT],
        /// Light output.
        pub light: LightState,
        /// Latched faults.
        pub faults: FaultFlags,
        /// Activity.
        pub state: DeviceState,
        /// Sequence number of the last trigger fired (0: none since boot).
        pub trigger_seq: u32,
        /// Milliseconds since boot (wraps after 49 days).
        pub uptime_ms: u32,
    }
}

wire_type! {
    /// A camera trigger pulse that was fired.
    #[derive(Eq, Hash)]
    pub struct TriggerFired {
        /// Trigger sequence number, 1 for the first trigger after boot.
        pub trigger_seq: u32,
        /// Device time at the rising edge, µs since boot.
        pub timestamp_us: u64,
        /// Pulse length, µs.
        pub exposure_us: u32,
        /// Mirror of the capture step that fired it (`None` for a bare trigger).
        pub mirror: Option<u8>,
    }
}

wire_type! {
    /// Why homing failed.
    #[derive(Eq, Hash)]
    pub enum HomingFailure {
        /// The switch was not reached within `max_travel_steps`.
        SwitchNotFound,
        /// The switch did not release during the back-off (stuck switch).
        SwitchStuck,
        /// The sequence exceeded `timeout_ms`.
        Timeout,
    }
}

wire_type! {
    /// How a motion ended.
    #[derive(Eq, Hash)]
    pub enum MotionOutcome {
        /// Reached its targets / homed.
        Completed,
        /// Stopped by [`Request::Stop`] before reaching its targets.
        Stopped,
        /// Aborted by a fault.
        Aborted,
        /// Homing failed on the axis.
        HomingFailed(Axis, HomingFailure),
    }
}

impl core::fmt::Display for HomingFailure {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            HomingFailure::SwitchNotFound => "its switch was not found within its travel",
            HomingFailure::SwitchStuck => "its switch stayed pressed after backing off",
            HomingFailure::Timeout => "it took longer than its homing timeout",
        })
    }
}

impl core::fmt::Display for MotionOutcome {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            MotionOutcome::Completed => f.write_str("completed"),
            MotionOutcome::Stopped => f.write_str("stopped"),
            MotionOutcome::Aborted => f.write_str("aborted by a fault"),
            MotionOutcome::HomingFailed(axis, why) => {
                write!(f, "failed on the {} axis: {why}", axis.name())
            }
        }
    }
}

wire_type! {
    /// Why the device booted.
    #[derive(Eq, Hash)]
    pub enum ResetReason {
        /// Power on or brown-out.
        PowerOn,
        /// Reset pin or debugger.
        Pin,
        /// [`Request::Reset`] or other software reset.
        Software,
        /// The independent watchdog expired.
        Watchdog,
        /// Unknown.
        Other,
    }
}

wire_type! {
    /// Severity of a log line.
    #[derive(Eq, Hash)]
    pub enum LogLevel {
        /// Diagnostic detail.
        Debug,
        /// Normal operation.
        Info,
        /// Something unusual that the device handled.
        Warn,
        /// Something that failed.
        Error,
    }
}

/// A log line of at most [`LOG_TEXT_CAPACITY`] bytes.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[serde(transparent)]
pub struct LogText(pub heapless::String<LOG_TEXT_CAPACITY>);

impl LogText {
    /// `text`, cut at a character boundary to fit.
    pub fn truncated(text: &str) -> LogText {
        let mut end = text.len().min(LOG_TEXT_CAPACITY);
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        let mut s = heapless::String::new();
        // Cannot fail: `end` bytes fit by construction.
        let _ = s.push_str(&text[..end]);
        LogText(s)
    }
    /// The text.
    pub fn as_str(&self) -> &str {
        self.0.as_str()
    }
}

impl MaxSize for LogText {
    // varint length prefix (1 byte below 128) + the bytes.
    const POSTCARD_MAX_SIZE: usize = 1 + LOG_TEXT_CAPACITY;
}

#[cfg(feature = "arbitrary")]
impl<'a> arbitrary::Arbitrary<'a> for LogText {
    fn arbitrary(u: &mut arbitrary::Unstructured<'a>) -> arbitrary::Result<Self> {
        let s: &str = u.arbitrary()?;
        Ok(LogText::truncated(s))
    }
}

/// Every error the device can answer a request with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, MaxSize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
#[non_exhaustive]
pub enum DeviceError {
    /// Motion requested on an axis that has not been homed.
    NotHomed,
    /// A target, index or parameter is outside its allowed range.
    OutOfRange,
    /// Another motion, homing or capture is in progress.
    Busy,
    /// A fault is latched; clear it first.
    FaultLatched,
    /// The request is malformed (invalid axis set, inconsistent config…).
    BadRequest,
    /// The host's protocol major differs; carries the device's version.
    UnsupportedVersion(ProtocolVersion),
    /// No mirror-table entry at that index.
    MirrorNotSet,
    /// Persistent storage failed.
    Storage,
    /// The device lacks the capability this request needs.
    Unsupported,
    /// [`Request::Hello`] has not been exchanged on this link yet.
    NoHandshake,
}

impl core::fmt::Display for DeviceError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            DeviceError::NotHomed => f.write_str("axis not homed"),
            DeviceError::OutOfRange => f.write_str("value out of range"),
            DeviceError::Busy => f.write_str("device busy"),
            DeviceError::FaultLatched => f.write_str("fault latched; clear it first"),
            DeviceError::BadRequest => f.write_str("malformed request"),
            DeviceError::UnsupportedVersion(v) => {
                write!(f, "unsupported protocol version (device speaks {v})")
            }
            DeviceError::MirrorNotSet => f.write_str("mirror table entry not set"),
            DeviceError::Storage => f.write_str("persistent storage failed"),
            DeviceError::Unsupported => f.write_str("not supported by this device"),
            DeviceError::NoHandshake => f.write_str("no handshake yet"),
        }
    }
}

impl core::error::Error for DeviceError {}

wire_type! {
    /// A request from the host. The device answers every request with exactly
    /// one [`Reply`] carrying the request's sequence number.
    pub enum Request {
        /// Handshake: the host's protocol version. Answer: [`Reply::Info`] or
        /// `Error(UnsupportedVersion)`. Also resets duplicate detection.
        Hello {
            /// Version the host speaks.
            host_protocol: ProtocolVersion,
        },
        /// Heartbeat. Answer: [`Reply::Pong`] with the same token.
        Ping {
            /// Echoed back.
            token: u32,
        },
        /// Answer: [`Reply::Status`].
        GetStatus,
        /// Home the axes in the set (concurrently). Answer: `Ack`, then
        /// [`Event::MotionDone`].
        Home {
            /// Axes to home.
            axes: AxisSet,
        },
        /// Move one or several axes concurrently; `None` leaves an axis alone.
        /// Answer: `Ack`, then [`Event::MotionDone`].
        Move {
            /// Absolute or relative.
            mode: MoveMode,
            /// Per-axis target in steps, indexed by [`Axis::index`].
            targets: [Option<i32>; AXIS_COUNT],
        },
        /// Move all axes to a mirror-table entry. Answer: `Ack`, then
        /// [`Event::MotionDone`].
        GoToMirror {
            /// Mirror-table index.
            mirror: u8,
        },
        /// Answer: [`Reply::Mirror`].
        GetMirror {
            /// Mirror-table index.
            mirror: u8,
        },
        /// Store a mirror-table entry (RAM; [`Request::SaveConfig`] persists).
        SetMirror {
            /// Mirror-table index (< [`MAX_MIRRORS`]).
            mirror: u8,
            /// Axis positions that aim the beam at it.
            position: MirrorPosition,
        },
        /// Set how many mirror-table entries are in use (≤ [`MAX_MIRRORS`]).
        SetMirrorCount {
            /// Entries in use.
            count: u8,
        },
        /// Switch the light.
        SetLight(LightState),
        /// Fire one camera trigger pulse. Answer: `Ack`, then
        /// [`Event::TriggerFired`].
        Trigger {
            /// Pulse length, µs.
            exposure_us: u32,
        },
        /// One capture step. Answer: `Ack`, then [`Event::MotionDone`] and
        /// [`Event::TriggerFired`].
        CaptureStep(CaptureStep),
        /// Decelerate every axis to a stop and abort a capture step.
        Stop,
        /// Stop immediately, light off, latch `EMERGENCY_STOP`.
        EmergencyStop,
        /// Clear latched faults (refused with `FaultLatched` while an input
        /// still asserts one).
        ClearFault,
        /// Answer: [`Reply::AxisConfig`].
        GetAxisConfig {
            /// Which axis.
            axis: Axis,
        },
        /// Replace an axis' configuration (only while idle; clears its homed flag).
        SetAxisConfig {
            /// Which axis.
            axis: Axis,
            /// The new configuration.
            config: AxisConfig,
        },
        /// Persist axis configs and the mirror table to flash.
        SaveConfig,
        /// Answer: [`Reply::Trigger`] with the last trigger event (recovers a
        /// lost [`Event::TriggerFired`]).
        GetLastTrigger,
        /// Reset the device. Answer: `Ack`, then a new [`Event::Boot`].
        Reset,
        /// Answer: [`Reply::BoardConfig`] (since 1.1).
        GetBoardConfig,
        /// Set the board's wiring options (persisted by `SaveConfig`);
        /// refused while busy (since 1.1).
        SetBoardConfig(BoardConfig),
        /// Answer: [`Reply::HomeSensors`] (since 1.2).
        GetHomeSensors,
        /// Set which level of each home / index sensor means actuated
        /// (persisted by `SaveConfig`); refused while busy; an axis whose
        /// polarity changes is no longer homed (since 1.2).
        SetHomeSensors(HomeSensors),
        /// Answer: [`Reply::Inputs`], the inputs as last sampled: for wiring
        /// a board up (since 1.2).
        GetInputs,
        /// A capture step with the light on around its pulse (since 1.3).
        /// Answer: like [`Request::CaptureStep`].
        TimedCaptureStep(TimedCaptureStep),
        /// Answer: [`Reply::Strobe`], how the camera's exposure strobe is
        /// watched (since 1.4).
        GetStrobe,
        /// Watch the camera's "exposure active" strobe (persisted by
        /// `SaveConfig`); refused while busy, `Unsupported` to enable on a
        /// board without [`Capabilities::EXPOSURE_STROBE`], `OutOfRange` for
        /// a `max_delay_us` beyond [`MAX_STROBE_DELAY_US`] (since 1.4).
        SetStrobe(StrobeConfig),
        /// Leave the firmware for the chip's ROM bootloader (USB DFU), to
        /// be flashed over USB without a probe: motion stops and the light
        /// goes off, the device answers `Ack` and then resets into it;
        /// `Unsupported` on a board without
        /// [`Capabilities::SYSTEM_BOOTLOADER`] (since 1.5).
        EnterBootloader,
    }
}

wire_type! {
    /// How the camera's "exposure active" strobe is wired and watched
    /// (since 1.4). While enabled, every trigger pulse is followed by an
    /// [`Event::Exposure`] saying whether, when and how long the camera
    /// exposed.
    #[derive(Eq, Hash, Default)]
    pub struct StrobeConfig {
        /// Watch the strobe input (off by default: it is optional wiring).
        pub enabled: bool,
        /// The line is high while the camera exposes (a push-pull output)
        /// rather than low (an open-collector output against the board's
        /// pull-up).
        pub active_high: bool,
        /// How far the strobe may lag the pulse, µs (1 ..=
        /// [`MAX_STROBE_DELAY_US`]): a strobe not yet risen this long
        /// after the pulse's end means the camera missed the trigger; one
        /// not yet fallen this long after the pulse's end plus the
        /// strobe's delay is reported as not ended.
        pub max_delay_us: u32,
    }
}

/// Longest [`StrobeConfig::max_delay_us`], µs.
pub const MAX_STROBE_DELAY_US: u32 = 100_000;

/// A default strobe delay bound: 10 ms, beyond any camera's trigger latency.
pub const DEFAULT_STROBE_DELAY_US: u32 = 10_000;

wire_type! {
    /// When the camera's strobe said it exposed, relative to a trigger's
    /// rise (since 1.4). Read at the controller's input sampling period
    /// ([`INPUT_SAMPLE_US`](crate::INPUT_SAMPLE_US)): each edge is placed
    /// up to one period after it happened.
    #[derive(Eq, Hash)]
    pub struct StrobeWindow {
        /// From the trigger's rise to the strobe's, µs.
        pub delay_us: u32,
        /// How long the strobe was active, µs.
        pub length_us: u32,
        /// The strobe went inactive again. `false`: it was still active
        /// `max_delay_us` after the pulse's end plus its own delay (stuck,
        /// or a camera exposing longer than its pulse), `length_us` is up
        /// to then.
        pub ended: bool,
    }
}

wire_type! {
    /// How the board is wired, where drivers differ (persisted with the
    /// axis configurations).
    #[derive(Eq, Default)]
    pub struct BoardConfig {
        /// The driver-fault input is active high (TMC2209 DIAG, push-pull)
        /// rather than active low (DRV8825 nFAULT, open drain; the default).
        pub driver_fault_active_high: bool,
    }
}

wire_type! {
    /// How each axis' home / index sensor signals (persisted with the axis
    /// configurations; since 1.2).
    #[derive(Eq, Default)]
    pub struct HomeSensors {
        /// Per axis (disk, track, tilt): the sensor's output is high when
        /// actuated (a push-pull optical or Hall sensor) rather than low (a
        /// switch or open-collector sensor to ground against the board's
        /// pull-up; the default).
        pub active_high: [bool; AXIS_COUNT],
    }
}

wire_type! {
    /// The board's inputs as last sampled: each line's electrical level and
    /// what the controller makes of it (since 1.2).
    #[derive(Eq, Default)]
    pub struct InputState {
        /// Per axis: the home / index sensor's line is high.
        pub home_line_high: [bool; AXIS_COUNT],
        /// Per axis: the sensor counts as actuated (its line read as
        /// [`HomeSensors`] says, debounced).
        pub home_actuated: [bool; AXIS_COUNT],
        /// The emergency-stop input is open: stop (debounced).
        pub estop_open: bool,
        /// The drivers' fault line is high.
        pub driver_fault_line_high: bool,
        /// A driver reports a fault (the line read as [`BoardConfig`] says,
        /// debounced).
        pub driver_fault: bool,
    }
}

impl Request {
    /// The variant's name, for messages and logs.
    pub const fn name(&self) -> &'static str {
        match self {
            Request::Hello { .. } => "Hello",
            Request::Ping { .. } => "Ping",
            Request::GetStatus => "GetStatus",
            Request::Home { .. } => "Home",
            Request::Move { .. } => "Move",
            Request::GoToMirror { .. } => "GoToMirror",
            Request::GetMirror { .. } => "GetMirror",
            Request::SetMirror { .. } => "SetMirror",
            Request::SetMirrorCount { .. } => "SetMirrorCount",
            Request::SetLight(_) => "SetLight",
            Request::Trigger { .. } => "Trigger",
            Request::CaptureStep(_) => "CaptureStep",
            Request::Stop => "Stop",
            Request::EmergencyStop => "EmergencyStop",
            Request::ClearFault => "ClearFault",
            Request::GetAxisConfig { .. } => "GetAxisConfig",
            Request::SetAxisConfig { .. } => "SetAxisConfig",
            Request::SaveConfig => "SaveConfig",
            Request::GetLastTrigger => "GetLastTrigger",
            Request::Reset => "Reset",
            Request::GetBoardConfig => "GetBoardConfig",
            Request::SetBoardConfig(_) => "SetBoardConfig",
            Request::GetHomeSensors => "GetHomeSensors",
            Request::SetHomeSensors(_) => "SetHomeSensors",
            Request::GetInputs => "GetInputs",
            Request::TimedCaptureStep(_) => "TimedCaptureStep",
            Request::GetStrobe => "GetStrobe",
            Request::SetStrobe(_) => "SetStrobe",
            Request::EnterBootloader => "EnterBootloader",
        }
    }
}

wire_type! {
    /// The answer to one request (same sequence number as the request).
    pub enum Reply {
        /// Accepted / done.
        Ack,
        /// Refused.
        Error(DeviceError),
        /// Handshake answer.
        Info(DeviceInfo),
        /// Status snapshot.
        Status(Status),
        /// A mirror-table entry (`None`: not set).
        Mirror {
            /// Index.
            mirror: u8,
            /// Entry.
            position: Option<MirrorPosition>,
        },
        /// An axis configuration.
        AxisConfig {
            /// Which axis.
            axis: Axis,
            /// Its configuration.
            config: AxisConfig,
        },
        /// Heartbeat answer.
        Pong {
            /// The request's token.
            token: u32,
        },
        /// The last trigger (`None`: none since boot).
        Trigger(Option<TriggerFired>),
        /// The board's wiring options (since 1.1).
        BoardConfig(BoardConfig),
        /// The home / index sensors' polarity (since 1.2).
        HomeSensors(HomeSensors),
        /// The inputs as last sampled (since 1.2).
        Inputs(InputState),
        /// How the camera's exposure strobe is watched (since 1.4).
        Strobe(StrobeConfig),
    }
}

/// An unsolicited message from the device. Events carry their own sequence
/// number (counting from 0 at boot), so the host can see a gap.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, MaxSize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum Event {
    /// Sent once after every boot.
    Boot {
        /// Changes at every boot (see `DeviceInfo::boot_id`).
        boot_id: u32,
        /// Why it booted.
        reason: ResetReason,
    },
    /// A move, homing or the motion part of a capture step ended.
    MotionDone {
        /// Axes that were moving.
        axes: AxisSet,
        /// How it ended.
        outcome: MotionOutcome,
        /// Positions at the end, steps.
        positions: [i32; AXIS_COUNT],
    },
    /// A camera trigger pulse started.
    TriggerFired(TriggerFired),
    /// A fault was latched.
    FaultRaised {
        /// All latched faults, including the new one.
        faults: FaultFlags,
        /// Axis concerned, if any.
        axis: Option<Axis>,
    },
    /// A log line.
    Log {
        /// Severity.
        level: LogLevel,
        /// Text.
        text: LogText,
    },
    /// An axis' step count was compared with its home or index switch:
    /// when homing an axis that was homed already (a position check), and
    /// when a moving axis crosses its switch's home edge with an error
    /// beyond [`POSITION_TOLERANCE_STEPS`](crate::POSITION_TOLERANCE_STEPS)
    /// (then with [`FaultFlags::POSITION_LOST`]).
    PositionChecked {
        /// The axis.
        axis: Axis,
        /// Counted position minus the switch's home position, steps (for a
        /// continuous axis the nearest value modulo a turn). Positive: the
        /// axis counted more steps than it made in the positive direction.
        error_steps: i32,
    },
    /// What the camera's exposure strobe showed of a trigger pulse, while
    /// the strobe is watched ([`StrobeConfig`]; since 1.4). Sent when the
    /// strobe goes inactive, or when it is overdue: not active
    /// `max_delay_us` after the pulse's end (`window: None`: the camera did
    /// not expose), or still active `max_delay_us` after the pulse's end
    /// plus its delay. A new pulse before then ends the watch of the last
    /// one at once.
    Exposure {
        /// The pulse's [`TriggerFired::trigger_seq`].
        trigger_seq: u32,
        /// When the camera exposed (`None`: the strobe did not rise).
        window: Option<StrobeWindow>,
    },
}

/// Everything the device sends: replies to requests and events.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, MaxSize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum ToHost {
    /// Answer to the request with the frame's sequence number.
    Reply(Reply),
    /// Unsolicited; the frame's sequence number is the event counter.
    Event(Event),
}
