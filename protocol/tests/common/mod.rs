//! Canonical example messages shared by the golden-bytes tests and the benchmark.
#![allow(dead_code)]

use protocol::*;

/// A direction-tagged example message.
#[derive(Debug, Clone)]
pub enum Example {
    ToDevice(Request),
    ToHost(ToHost),
}

impl Example {
    pub fn encode(&self, seq: u8) -> Vec<u8> {
        let mut buf = [0u8; MAX_FRAME_LEN];
        let n = match self {
            Example::ToDevice(m) => encode_frame(seq, m, &mut buf),
            Example::ToHost(m) => encode_frame(seq, m, &mut buf),
        }
        .expect("examples fit");
        buf[..n].to_vec()
    }
}

/// The track's configuration as literals, not `track_default()`: the golden
/// bytes pin the encoding and must not move when a firmware default does.
pub fn default_axis_config() -> AxisConfig {
    AxisConfig {
        unit: Unit::Millimetre,
        steps_per_unit: 1600.0,
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
            timeout_ms: 30_000,
            home_position: 0,
        },
    }
}

pub fn capture_step() -> Request {
    Request::CaptureStep(CaptureStep {
        mirror: 17,
        settle_ms: DEFAULT_SETTLE_MS,
        exposure_us: DEFAULT_EXPOSURE_US,
        light_duty_permille: FULL_DUTY_PERMILLE,
    })
}

pub fn status() -> ToHost {
    ToHost::Reply(Reply::Status(Status {
        axes: [
            AxisStatus { position_steps: 8000, position_units: 180.0, moving: false, homed: true },
            AxisStatus { position_steps: 96_000, position_units: 60.0, moving: true, homed: true },
            AxisStatus {
                position_steps: -3_200,
                position_units: -12.0,
                moving: false,
                homed: true,
            },
        ],
        light: LightState { on: true, duty_permille: 1000 },
        faults: FaultFlags::NONE,
        state: DeviceState::Capturing,
        trigger_seq: 17,
        uptime_ms: 123_456,
    }))
}

fn reply(r: Reply) -> Example {
    Example::ToHost(ToHost::Reply(r))
}
fn event(e: Event) -> Example {
    Example::ToHost(ToHost::Event(e))
}

/// One example of every request, reply and event variant, with the sequence
/// number used for its golden frame.
pub fn examples() -> Vec<(&'static str, u8, Example)> {
    use Example::ToDevice as Req;
    let v1 = PROTOCOL_VERSION;
    let trigger = TriggerFired {
        trigger_seq: 17,
        timestamp_us: 61_250_000,
        exposure_us: 50_000,
        mirror: Some(16),
    };
    vec![
        ("Request::Hello", 1, Req(Request::Hello { host_protocol: v1 })),
        ("Request::Ping", 2, Req(Request::Ping { token: 0xDEAD_BEEF })),
        ("Request::GetStatus", 3, Req(Request::GetStatus)),
        ("Request::Home", 4, Req(Request::Home { axes: AxisSet::ALL })),
        (
            "Request::Move",
            5,
            Req(Request::Move {
                mode: MoveMode::Absolute,
                targets: [Some(8000), None, Some(-3200)],
            }),
        ),
        ("Request::GoToMirror", 6, Req(Request::GoToMirror { mirror: 3 })),
        ("Request::GetMirror", 7, Req(Request::GetMirror { mirror: 3 })),
        (
            "Request::SetMirror",
            8,
            Req(Request::SetMirror {
                mirror: 3,
                position: MirrorPosition { steps: [4000, 120_000, -1500] },
            }),
        ),
        ("Request::SetMirrorCount", 9, Req(Request::SetMirrorCount { count: 40 })),
        (
            "Request::SetLight",
            10,
            Req(Request::SetLight(LightState { on: true, duty_permille: 500 })),
        ),
        ("Request::Trigger", 11, Req(Request::Trigger { exposure_us: 50_000 })),
        ("Request::CaptureStep", 12, Req(capture_step())),
        ("Request::Stop", 13, Req(Request::Stop)),
        ("Request::EmergencyStop", 14, Req(Request::EmergencyStop)),
        ("Request::ClearFault", 15, Req(Request::ClearFault)),
        ("Request::GetAxisConfig", 16, Req(Request::GetAxisConfig { axis: Axis::Track })),
        (
            "Request::SetAxisConfig",
            17,
            Req(Request::SetAxisConfig { axis: Axis::Track, config: default_axis_config() }),
        ),
        ("Request::SaveConfig", 18, Req(Request::SaveConfig)),
        ("Request::GetLastTrigger", 19, Req(Request::GetLastTrigger)),
        ("Request::Reset", 20, Req(Request::Reset)),
        ("Request::GetBoardConfig", 21, Req(Request::GetBoardConfig)),
        (
            "Request::SetBoardConfig",
            22,
            Req(Request::SetBoardConfig(BoardConfig { driver_fault_active_high: true })),
        ),
        ("Request::GetHomeSensors", 23, Req(Request::GetHomeSensors)),
        (
            "Request::SetHomeSensors",
            24,
            Req(Request::SetHomeSensors(HomeSensors { active_high: [true, false, true] })),
        ),
        ("Request::GetInputs", 25, Req(Request::GetInputs)),
        (
            "Request::TimedCaptureStep",
            26,
            Req(Request::TimedCaptureStep(TimedCaptureStep {
                step: CaptureStep {
                    mirror: 17,
                    settle_ms: DEFAULT_SETTLE_MS,
                    exposure_us: DEFAULT_EXPOSURE_US,
                    light_duty_permille: FULL_DUTY_PERMILLE,
                },
                light_margin_us: 200,
            })),
        ),
        ("Request::GetStrobe", 27, Req(Request::GetStrobe)),
        ("Request::SetStrobe", 28, Req(Request::SetStrobe(strobe()))),
        ("Request::EnterBootloader", 29, Req(Request::EnterBootloader)),
        ("Reply::Ack", 4, reply(Reply::Ack)),
        ("Reply::Error", 5, reply(Reply::Error(DeviceError::NotHomed))),
        (
            "Reply::Error(UnsupportedVersion)",
            1,
            reply(Reply::Error(DeviceError::UnsupportedVersion(v1))),
        ),
        (
            "Reply::Info",
            1,
            reply(Reply::Info(DeviceInfo {
                protocol: v1,
                firmware: FirmwareVersion { major: 0, minor: 1, patch: 0 },
                board: BOARD_STM32F411_BLACKPILL,
                device_id: [0x30, 0x00, 0x41, 0x00, 0x0D, 0x51, 0x33, 0x30, 0x37, 0x39, 0x33, 0x31],
                capabilities: Capabilities::PERSISTENT_CONFIG.union(Capabilities::PWM_LIGHT),
                mirror_count: 40,
                boot_id: 0x1234_5678,
            })),
        ),
        ("Reply::Status", 3, Example::ToHost(status())),
        (
            "Reply::Mirror",
            7,
            reply(Reply::Mirror {
                mirror: 3,
                position: Some(MirrorPosition { steps: [4000, 120_000, -1500] }),
            }),
        ),
        (
            "Reply::AxisConfig",
            16,
            reply(Reply::AxisConfig { axis: Axis::Track, config: default_axis_config() }),
        ),
        ("Reply::Pong", 2, reply(Reply::Pong { token: 0xDEAD_BEEF })),
        ("Reply::Trigger", 19, reply(Reply::Trigger(Some(trigger)))),
        (
            "Reply::BoardConfig",
            21,
            reply(Reply::BoardConfig(BoardConfig { driver_fault_active_high: true })),
        ),
        (
            "Reply::HomeSensors",
            23,
            reply(Reply::HomeSensors(HomeSensors { active_high: [false, true, false] })),
        ),
        (
            "Reply::Inputs",
            25,
            reply(Reply::Inputs(InputState {
                home_line_high: [true, true, false],
                home_actuated: [false, true, true],
                estop_open: false,
                driver_fault_line_high: true,
                driver_fault: false,
            })),
        ),
        ("Reply::Strobe", 27, reply(Reply::Strobe(strobe()))),
        (
            "Event::Boot",
            0,
            event(Event::Boot { boot_id: 0x1234_5678, reason: ResetReason::PowerOn }),
        ),
        (
            "Event::MotionDone",
            1,
            event(Event::MotionDone {
                axes: AxisSet::ALL,
                outcome: MotionOutcome::Completed,
                positions: [4000, 120_000, -1500],
            }),
        ),
        (
            "Event::MotionDone(HomingFailed)",
            2,
            event(Event::MotionDone {
                axes: AxisSet::single(Axis::Tilt),
                outcome: MotionOutcome::HomingFailed(Axis::Tilt, HomingFailure::SwitchNotFound),
                positions: [0, 0, 9333],
            }),
        ),
        ("Event::TriggerFired", 3, event(Event::TriggerFired(trigger))),
        (
            "Event::FaultRaised",
            4,
            event(Event::FaultRaised { faults: FaultFlags::LINK_TIMEOUT, axis: None }),
        ),
        (
            "Event::Log",
            5,
            event(Event::Log { level: LogLevel::Warn, text: LogText::truncated("stall?") }),
        ),
        (
            "Event::PositionChecked",
            6,
            event(Event::PositionChecked { axis: Axis::Disk, error_steps: -400 }),
        ),
        (
            "Event::Exposure",
            7,
            event(Event::Exposure {
                trigger_seq: 17,
                window: Some(StrobeWindow { delay_us: 400, length_us: 50_000, ended: true }),
            }),
        ),
        ("Event::Exposure(missed)", 8, event(Event::Exposure { trigger_seq: 18, window: None })),
    ]
}

/// A strobe watched on a push-pull line, 10 ms delay bound.
fn strobe() -> StrobeConfig {
    StrobeConfig { enabled: true, active_high: true, max_delay_us: DEFAULT_STROBE_DELAY_US }
}

pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect::<Vec<_>>().join(" ")
}
