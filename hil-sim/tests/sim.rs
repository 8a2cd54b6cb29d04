//! The simulated scanner: the firmware's controller on simulated hardware.

mod common;

use std::time::Duration;

use common::{Client, capture_all, load_mirror_table};
use hil_sim::physics::SwitchFault;
use hil_sim::{FaultEvent, FaultPlan, FaultSpec, FaultWhen, SimConfig};
use host::link::LinkError;
use protocol::*;

fn config(seed: u64, faults: FaultPlan) -> SimConfig {
    let mut c = SimConfig::new(seed);
    c.faults = faults;
    c
}

fn assert_at(actual: [i64; 3], target: &MirrorPosition, what: &str) {
    let disk = (actual[0] - target.steps[0] as i64).rem_euclid(16_000);
    assert!(disk <= 1 || disk >= 15_999, "{what}: disk {actual:?} vs {target:?}");
    assert!(
        (actual[1] - target.steps[1] as i64).abs() <= 1,
        "{what}: track {actual:?} vs {target:?}"
    );
    assert!(
        (actual[2] - target.steps[2] as i64).abs() <= 1,
        "{what}: tilt {actual:?} vs {target:?}"
    );
}

#[test]
fn homing_and_40_mirror_capture_reach_the_physical_positions() {
    let mut c = Client::new(config(7, FaultPlan::none()));
    let info = c.info();
    assert_eq!(info.board, BOARD_SIMULATOR);
    c.home_all();
    // Homing puts each counter on the physical switch edge.
    let s = c.status();
    for axis in Axis::ALL {
        let phys = c.device(|d| d.physical_position(axis));
        let count = s.axes[axis.index()].position_steps as i64;
        let d = if axis == Axis::Disk {
            (phys - count).rem_euclid(16_000).min((count - phys).rem_euclid(16_000))
        } else {
            (phys - count).abs()
        };
        assert!(d <= 1, "{axis:?}: physical {phys} vs counter {count}");
        assert!(s.axes[axis.index()].homed);
    }
    let table = load_mirror_table(&mut c);
    let fired = capture_all(&mut c, 40);
    let truth = c.device(|d| d.truth().clone());
    assert_eq!(truth.triggers.len(), 40);
    for (l, (t, rec)) in fired.iter().zip(&truth.triggers).enumerate() {
        assert_eq!(t.trigger_seq, l as u32 + 1);
        assert_eq!(
            t.timestamp_us,
            rec.rise / firmware::hal::TICKS_PER_US,
            "reported time = physical edge"
        );
        assert_at(rec.positions, &table[l], &format!("mirror {l}"));
        let fall = rec.fall.expect("pulse ended");
        assert_eq!(fall - rec.rise, 50_000 * firmware::hal::TICKS_PER_US, "exposure");
        assert_eq!(rec.light_duty, FULL_DUTY_PERMILLE, "lit while exposing");
        assert!(rec.honoured);
    }
    assert_eq!(c.device(|d| d.light()), 0, "light off after the scan");
    assert!(Axis::ALL.iter().all(|a| c.device(|d| d.lost_steps(*a)) == 0));
    // A pulse ends at its tick, not at the board's next 200 µs poll: an
    // exposure that is not a multiple of the poll period lasts what was
    // asked (3.2 ms for 3.09 ms was 3.5 % more light than the host counted).
    for (k, exposure_us) in [1_001u32, 3_090, 15_453].into_iter().enumerate() {
        let request = if k == 1 {
            Request::Trigger { exposure_us }
        } else {
            Request::CaptureStep(CaptureStep {
                mirror: 3,
                settle_ms: DEFAULT_SETTLE_MS,
                exposure_us,
                light_duty_permille: FULL_DUTY_PERMILLE,
            })
        };
        assert_eq!(c.request(request), Reply::Ack);
        assert_eq!(c.wait_idle(Duration::from_secs(2)).state, DeviceState::Idle);
        let rec = c.device(|d| *d.truth().triggers.last().expect("a trigger"));
        let ticks = rec.fall.expect("pulse ended") - rec.rise;
        assert_eq!(ticks, exposure_us as u64 * firmware::hal::TICKS_PER_US, "{exposure_us} µs");
    }
    assert!(c.now_ticks() > 30 * firmware::hal::TICK_HZ as u64, "simulates tens of seconds");
}

fn scripted_run(seed: u64) -> (Vec<u8>, hil_sim::Truth) {
    let plan = FaultPlan::none()
        .corrupt(1e-3)
        .drop_bytes(1e-4)
        .after_triggers(3, FaultEvent::IgnoreTriggers(1))
        .at_ms(200, FaultEvent::Switch { axis: Axis::Tilt, fault: SwitchFault::Chatter(0.0) });
    let mut c = Client::new(config(seed, plan));
    c.home_all();
    load_mirror_table(&mut c);
    capture_all(&mut c, 6);
    (c.received(), c.device(|d| d.truth().clone()))
}

#[test]
fn same_seed_same_run_byte_for_byte() {
    let (bytes_a, truth_a) = scripted_run(11);
    let (bytes_b, truth_b) = scripted_run(11);
    assert_eq!(bytes_a, bytes_b);
    assert_eq!(truth_a, truth_b);
    assert!(!truth_a.triggers[3].honoured, "the ignored trigger is recorded");
    let (bytes_c, _) = scripted_run(12);
    assert_ne!(bytes_a, bytes_c, "another seed, another run");
}

#[test]
fn capture_survives_corruption_and_lost_bytes() {
    let plan = FaultPlan::none().corrupt(1e-3).drop_bytes(2e-4);
    let mut c = Client::new(config(21, plan));
    c.home_all();
    let table = load_mirror_table(&mut c);
    capture_all(&mut c, 40);
    assert!(c.dev.stats.bad_frames > 0);
    let truth = c.device(|d| d.truth().clone());
    assert_eq!(truth.triggers.len(), 40, "every capture exactly once despite retransmissions");
    for (l, rec) in truth.triggers.iter().enumerate() {
        assert_at(rec.positions, &table[l], &format!("mirror {l}"));
    }
}

fn moving(c: &mut Client) {
    c.home_all();
    let mv =
        Request::Move { mode: MoveMode::Absolute, targets: [Some(8_000), Some(300_000), None] };
    assert_eq!(c.request(mv), Reply::Ack);
    c.sleep(Duration::from_millis(300));
}

fn fault_event(c: &mut Client, flag: FaultFlags) -> Option<Axis> {
    let e = c
        .wait_event(
            Duration::from_secs(5),
            |e| matches!(e, Event::FaultRaised { faults, .. } if faults.contains(flag)),
        )
        .unwrap_or_else(|| panic!("no FaultRaised({flag:?}) in {:?}", c.events));
    let Event::FaultRaised { axis, .. } = e else { unreachable!() };
    axis
}

fn assert_stopped(c: &mut Client) {
    let s = c.status();
    assert_eq!(s.state, DeviceState::Faulted);
    assert!(s.axes.iter().all(|a| !a.moving));
    let before = c.device(|d| d.physical_position(Axis::Track));
    c.sleep(Duration::from_millis(500));
    assert_eq!(c.device(|d| d.physical_position(Axis::Track)), before, "no motion after the fault");
    assert_eq!(c.device(|d| d.light()), 0);
}

#[test]
fn emergency_stop_input() {
    let mut c = Client::new(config(3, FaultPlan::none()));
    moving(&mut c);
    c.device(|d| d.set_estop(true));
    fault_event(&mut c, FaultFlags::EMERGENCY_STOP);
    assert_stopped(&mut c);
    assert_eq!(
        c.request(Request::ClearFault),
        Reply::Error(DeviceError::FaultLatched),
        "input still asserted"
    );
    c.device(|d| d.set_estop(false));
    c.sleep(Duration::from_millis(5));
    assert_eq!(c.request(Request::ClearFault), Reply::Ack);
}

#[test]
fn driver_fault_input_scheduled() {
    let plan = FaultPlan::none().after_triggers(2, FaultEvent::DriverFault(true));
    let mut c = Client::new(config(4, plan));
    c.home_all();
    load_mirror_table(&mut c);
    capture_all(&mut c, 1);
    // The driver fault is asserted at the second trigger.
    let step =
        CaptureStep { mirror: 20, settle_ms: 150, exposure_us: 50_000, light_duty_permille: 1000 };
    assert_eq!(c.request(Request::CaptureStep(step)), Reply::Ack);
    fault_event(&mut c, FaultFlags::DRIVER_FAULT);
    assert_stopped(&mut c);
}

/// The `PositionChecked` event of `axis` among the events received so far.
fn position_error(c: &Client, axis: Axis) -> Option<i32> {
    c.events.iter().rev().find_map(|e| match e {
        Event::PositionChecked { axis: a, error_steps } if *a == axis => Some(*error_steps),
        _ => None,
    })
}

#[test]
fn lost_steps_on_disk_are_caught_at_the_index_flag() {
    // 1 000 steps, and 400 (the back-off distance, which the old
    // "far from home" rule let through), moving up and moving down.
    for (lost, forward) in [(1_000, true), (400, true), (400, false), (40, false)] {
        let mut c = Client::new(config(5, FaultPlan::none()));
        c.home_all();
        let mv = |t| Request::Move { mode: MoveMode::Absolute, targets: [Some(t), None, None] };
        // Slip while turning half a revolution.
        assert_eq!(c.request(mv(8_000)), Reply::Ack);
        inject(&mut c, FaultEvent::LoseSteps { axis: Axis::Disk, steps: lost });
        c.wait_idle(Duration::from_secs(10));
        assert_eq!(c.device(|d| d.lost_steps(Axis::Disk)), lost);
        // Continue round (or back) across the index flag's home edge.
        let route: &[i32] = if forward { &[15_000, 3_000] } else { &[1_000, 12_000] };
        for &t in route {
            assert_eq!(c.request(mv(t)), Reply::Ack);
            c.wait_idle(Duration::from_secs(10));
        }
        let axis = fault_event(&mut c, FaultFlags::POSITION_LOST);
        assert_eq!(axis, Some(Axis::Disk));
        // Counted more than made going up: +lost; going down the count is
        // short of home by as much the other way round.
        let error = position_error(&c, Axis::Disk).expect("the error is reported");
        assert!((error - lost as i32).abs() <= 8, "lost {lost}, reported {error}");
        assert_stopped(&mut c);
        assert!(!c.status().axes[0].homed, "an axis that lost steps must be homed again");
    }
}

#[test]
fn the_index_flag_is_passed_both_ways_without_a_false_alarm() {
    let mut c = Client::new(config(5, FaultPlan::none()));
    c.home_all();
    let mv = |t| Request::Move { mode: MoveMode::Absolute, targets: [Some(t), None, None] };
    for t in [8_000, 15_000, 3_000, 12_000, 100, 15_900, 7_000, 2_000] {
        assert_eq!(c.request(mv(t)), Reply::Ack);
        let s = c.wait_idle(Duration::from_secs(10));
        assert!(s.faults.is_empty(), "to {t}: {:?}", c.events);
    }
    assert_eq!(position_error(&c, Axis::Disk), None, "no error to report");
}

#[test]
fn homing_a_homed_axis_checks_its_count() {
    let mut c = Client::new(config(11, FaultPlan::none()));
    c.home_all();
    assert!(c.events.iter().all(|e| !matches!(e, Event::PositionChecked { .. })), "plain homing");
    let mv = Request::Move {
        mode: MoveMode::Absolute,
        targets: [Some(6_000), Some(200_000), Some(4_000)],
    };
    assert_eq!(c.request(mv), Reply::Ack);
    // Off the switches first (a loss on the switch is caught at its edge).
    c.wait_event(Duration::from_millis(1_000), |_| false);
    inject(&mut c, FaultEvent::LoseSteps { axis: Axis::Track, steps: 400 });
    inject(&mut c, FaultEvent::LoseSteps { axis: Axis::Tilt, steps: 2_000 });
    let s = c.wait_idle(Duration::from_secs(20));
    assert!(s.faults.is_empty(), "{s:?} {:?}", c.events);
    c.clear_events();
    let t0 = c.now_ticks();
    c.home_all();
    let seconds = (c.now_ticks() - t0) as f64 / firmware::hal::TICK_HZ as f64;
    // Lost moving up: the axes are short of their count by what they lost.
    assert!((position_error(&c, Axis::Track).unwrap() - 400).abs() <= 16, "{:?}", c.events);
    // The tilt lost more than its back-off: found by the wide search.
    assert!((position_error(&c, Axis::Tilt).unwrap() - 2_000).abs() <= 16, "{:?}", c.events);
    let disk = position_error(&c, Axis::Disk).unwrap();
    assert!(disk.abs() <= POSITION_TOLERANCE_STEPS, "disk {disk}");
    // Checking is homing: the counts are right again.
    for axis in Axis::ALL {
        let phys = c.device(|d| d.physical_position(axis));
        let count = c.status().axes[axis.index()].position_steps as i64;
        let d = if axis == Axis::Disk { (phys - count).rem_euclid(16_000) } else { phys - count };
        assert!(d.abs() <= 1 || d >= 15_999, "{axis:?}: physical {phys} vs counter {count}");
    }
    // Straight back at full speed: the track's 125 mm at 40 mm/s, then
    // 2 mm slowly, not a 10 mm/s search.
    assert!(seconds < 8.0, "the check took {seconds:.1} s: {:?}", c.events);
    // An axis without a lost step reports it.
    c.clear_events();
    c.home_all();
    for axis in Axis::ALL {
        let e = position_error(&c, axis).unwrap();
        assert!(e.abs() <= POSITION_TOLERANCE_STEPS, "{axis:?}: {e}");
    }
}

/// Inject a fault now, through the device's fault plan.
fn inject(c: &mut Client, event: FaultEvent) {
    let now_ms = c.now_ticks() / firmware::hal::TICKS_PER_MS;
    let spec = FaultSpec { when: FaultWhen::AtTick(now_ms * firmware::hal::TICKS_PER_MS), event };
    c.device(|d| d.schedule(spec));
    c.sleep(Duration::from_millis(1));
}

#[test]
fn motor_stalls_above_its_torque_limit() {
    let mut c = Client::new(config(6, FaultPlan::none()));
    c.home_all();
    let Reply::AxisConfig { mut config, .. } =
        c.request(Request::GetAxisConfig { axis: Axis::Track })
    else {
        panic!()
    };
    config.v_max = 100_000; // above the motor's 80 000 steps/s pull-out speed
    config.homing.fast_speed = 16_000;
    let s = c.status();
    assert_eq!(s.state, DeviceState::Idle, "{s:?} {:?}", c.events);
    assert_eq!(c.request(Request::SetAxisConfig { axis: Axis::Track, config }), Reply::Ack);
    c.home_all();
    let mv = Request::Move { mode: MoveMode::Absolute, targets: [None, Some(300_000), None] };
    assert_eq!(c.request(mv), Reply::Ack);
    c.wait_idle(Duration::from_secs(10));
    let lost = c.device(|d| d.lost_steps(Axis::Track));
    assert!(lost > 1_000, "steps above pull-out are lost ({lost})");
    let physical = c.device(|d| d.physical_position(Axis::Track));
    assert_eq!(physical + lost as i64, 300_000, "every step either moved the rotor or was lost");
}

#[test]
fn stuck_switch_fails_homing() {
    let plan = FaultPlan::none()
        .at_ms(0, FaultEvent::Switch { axis: Axis::Track, fault: SwitchFault::Stuck(true) });
    let mut c = Client::new(config(8, plan));
    assert_eq!(c.request(Request::Home { axes: AxisSet::single(Axis::Track) }), Reply::Ack);
    let e =
        c.wait_event(Duration::from_secs(30), |e| matches!(e, Event::MotionDone { .. })).unwrap();
    assert_eq!(
        e,
        Event::MotionDone {
            axes: AxisSet::single(Axis::Track),
            outcome: MotionOutcome::HomingFailed(Axis::Track, HomingFailure::SwitchStuck),
            positions: match e {
                Event::MotionDone { positions, .. } => positions,
                _ => unreachable!(),
            },
        }
    );
    fault_event(&mut c, FaultFlags::HOMING_FAILED);
}

#[test]
fn a_chattering_switch_is_debounced_a_stuck_one_is_an_unexpected_home_switch() {
    let mut c = Client::new(config(9, FaultPlan::none()));
    c.home_all();
    // Glitches (5 % of samples) never read pressed for 400 µs on end.
    inject(&mut c, FaultEvent::Switch { axis: Axis::Track, fault: SwitchFault::Chatter(0.05) });
    let mv = |t| Request::Move { mode: MoveMode::Absolute, targets: [None, Some(t), None] };
    assert_eq!(c.request(mv(250_000)), Reply::Ack);
    let s = c.wait_idle(Duration::from_secs(10));
    assert!(s.faults.is_empty() && s.axes[1].position_steps == 250_000, "{s:?} {:?}", c.events);
    // Pressed for good, far from home: a crash or a broken switch.
    assert_eq!(c.request(mv(100_000)), Reply::Ack);
    inject(&mut c, FaultEvent::Switch { axis: Axis::Track, fault: SwitchFault::Stuck(true) });
    let axis = fault_event(&mut c, FaultFlags::UNEXPECTED_HOME_SWITCH);
    assert_eq!(axis, Some(Axis::Track));
    assert_stopped(&mut c);
}

#[test]
fn disconnect_while_moving_latches_link_timeout() {
    let mut c = Client::new(config(10, FaultPlan::none()));
    moving(&mut c);
    inject(&mut c, FaultEvent::Disconnect { duration_ms: 1_000 });
    assert!(!c.rig.is_connected());
    c.sleep(Duration::from_millis(1_100));
    assert!(c.rig.is_connected());
    let s = c.status();
    assert!(s.faults.contains(FaultFlags::LINK_TIMEOUT), "{s:?}");
    assert!(s.axes.iter().all(|a| !a.moving), "decelerated to rest");
    assert!(s.axes[1].homed, "a controlled stop keeps homing");
    assert!(s.axes[1].position_steps < 300_000);
}

#[test]
fn device_reset_is_a_new_boot_without_homing() {
    let plan = FaultPlan::none().after_triggers(2, FaultEvent::Reset);
    let mut c = Client::new(config(12, plan));
    let first = c.info();
    c.home_all();
    load_mirror_table(&mut c);
    assert_eq!(c.request(Request::SaveConfig), Reply::Ack);
    capture_all(&mut c, 1);
    // The board resets at the second trigger.
    let step =
        CaptureStep { mirror: 1, settle_ms: 150, exposure_us: 50_000, light_duty_permille: 1000 };
    assert_eq!(c.request(Request::CaptureStep(step)), Reply::Ack);
    // The host's client sees the Boot event of a new boot id, greets the
    // device again and reports the reset.
    let reset = c.dev.wait_event(Duration::from_secs(5), |_| false);
    let Err(LinkError::Reset { old, new }) = reset else { panic!("no reset: {reset:?}") };
    assert_eq!(old, first.boot_id);
    assert_ne!(new, old);
    // A new session: nothing homed, the table back from flash.
    let info = c.info();
    assert_eq!(info.boot_id, new);
    assert_eq!(info.mirror_count, 40);
    let s = c.status();
    assert!(s.axes.iter().all(|a| !a.homed));
    assert!(s.faults.contains(FaultFlags::WATCHDOG_RESET));
    assert_eq!(c.device(|d| d.boot_count()), 2);
}

#[test]
fn ignored_trigger_is_recorded_in_the_truth_only() {
    let plan = FaultPlan::none().after_triggers(1, FaultEvent::IgnoreTriggers(1));
    let mut c = Client::new(config(13, plan));
    c.home_all();
    load_mirror_table(&mut c);
    let fired = capture_all(&mut c, 3);
    assert_eq!(fired.len(), 3, "the device reports every trigger it fired");
    let honoured: Vec<bool> =
        c.device(|d| d.truth().clone()).triggers.iter().map(|t| t.honoured).collect();
    assert_eq!(honoured, [true, false, true]);
}

#[test]
fn fault_specs_parse() {
    let f: FaultSpec = "reset@trigger=10".parse().unwrap();
    assert_eq!(f, FaultSpec { when: FaultWhen::AfterTriggers(10), event: FaultEvent::Reset });
    let f: FaultSpec = "lose-steps:disk:400@ms=9000".parse().unwrap();
    assert_eq!(f.event, FaultEvent::LoseSteps { axis: Axis::Disk, steps: 400 });
    assert_eq!(f.when, FaultWhen::AtTick(9_000 * firmware::hal::TICKS_PER_MS));
    let f: FaultSpec = "chatter:tilt:0.2@ms=1".parse().unwrap();
    assert_eq!(f.event, FaultEvent::Switch { axis: Axis::Tilt, fault: SwitchFault::Chatter(0.2) });
    let f: FaultSpec = "slow-light:200@ms=0".parse().unwrap();
    assert_eq!(f.event, FaultEvent::SlowLight { edge_ns: 200 });
    // The light that fault makes: 1 µs of every 50 µs at 20 ‰, less 0.2 µs.
    use hil_sim::camera::light_output;
    assert_eq!(light_output(20, 0), 0.02);
    assert!((light_output(20, 200) - 0.016).abs() < 1e-12);
    assert_eq!(light_output(1000, 200), 1.0, "at full duty no edges");
    assert_eq!(light_output(2, 200), 0.0);
    for bad in [
        "slow-light@ms=0",
        "slow-light:-3@ms=0",
        "reset",
        "reset@ms=x",
        "stuck:wheel:on@ms=1",
        "chatter:tilt:2@ms=1",
        "nope@ms=1",
        "estop:maybe@ms=1",
    ] {
        let err = bad.parse::<FaultSpec>().unwrap_err();
        assert!(err.to_string().contains(bad), "{err}");
    }
}

#[test]
fn pty_serves_the_protocol_in_real_time() {
    let server =
        hil_sim::PtyServer::start(hil_sim::SimDevice::new(SimConfig::new(1)), 1.0).unwrap();
    let info = common::connect_over_serial(server.path()).expect("Info over the pty");
    assert_eq!(info.board, BOARD_SIMULATOR);
    let device = server.stop().unwrap();
    assert!(device.now() > 0, "simulated time followed the wall clock");
}

/// The port appears once the board has booted: a driver-fault line asserted
/// from power-on is latched before the host can ask. (CI once saw "faults
/// none" at uptime 0: on a busy machine the server's thread first ran after
/// the host had written, and answered before the first debounce ended.)
#[test]
fn a_pty_port_appears_after_the_boards_first_debounce() {
    let mut config = SimConfig::new(1);
    config.driver_fault_active_high = true;
    let server = hil_sim::PtyServer::start(hil_sim::SimDevice::new(config), 1.0).unwrap();
    // Stopped at once, whether or not its thread has run.
    let device = server.stop().unwrap();
    assert!(device.faults().contains(FaultFlags::DRIVER_FAULT), "{:?}", device.faults());
}

/// Where a USB-like port's link points now (`None`: unplugged).
fn link_target(link: &std::path::Path) -> Option<std::path::PathBuf> {
    std::fs::read_link(link).ok()
}

/// Wait (wall time, up to `limit`) until `done` says so.
fn wait_until(limit: Duration, mut done: impl FnMut() -> bool) -> bool {
    let end = std::time::Instant::now() + limit;
    while std::time::Instant::now() < end {
        if done() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    done()
}

/// A [`hil_sim::Port::Usb`] board unplugs as a USB one does: on a
/// disconnect the link goes and the host's open port fails (not a silent
/// link); back, the link names a new pty and the host's link reopens it
/// by the link's path. A reset unplugs it too, and the host learns of the
/// reset when it greets the board again.
#[test]
fn a_usb_like_port_unplugs_on_a_disconnect_and_a_reset_and_the_host_follows() {
    let ms = firmware::hal::TICKS_PER_MS;
    let mut config = SimConfig::new(3);
    config.faults = FaultPlan::none()
        .with(FaultWhen::AtTick(1_500 * ms), FaultEvent::Disconnect { duration_ms: 700 })
        .with(FaultWhen::AtTick(4_000 * ms), FaultEvent::Reset);
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyACM-scanner");
    // A stale link from a killed run is replaced; anything else is not.
    std::os::unix::fs::symlink("/nonexistent", &link).unwrap();
    let taken = dir.path().join("taken");
    std::fs::write(&taken, b"keep").unwrap();
    let err = hil_sim::PtyServer::start_with_camera(
        hil_sim::SimDevice::new(config.clone()),
        1.0,
        None,
        hil_sim::Port::Usb(Some(taken.clone())),
    )
    .unwrap_err();
    assert!(err.to_string().contains("no symbolic link; not replaced"), "{err}");
    assert_eq!(std::fs::read(&taken).unwrap(), b"keep");

    let server = hil_sim::PtyServer::start_with_camera(
        hil_sim::SimDevice::new(config),
        1.0,
        None,
        hil_sim::Port::Usb(Some(link.clone())),
    )
    .unwrap();
    assert_eq!(server.path(), link.to_str().unwrap());
    let first = link_target(&link).expect("plugged in at start");
    // A second server on the same link is refused; the first keeps it.
    let second = hil_sim::PtyServer::start_with_camera(
        hil_sim::SimDevice::new(SimConfig::new(4)),
        1.0,
        None,
        hil_sim::Port::Usb(Some(dir.path().join(".").join("ttyACM-scanner"))),
    )
    .unwrap_err();
    assert!(second.to_string().contains("another simulator serves its board there"), "{second}");
    assert_eq!(link_target(&link).as_ref(), Some(&first));
    assert!(first.starts_with("/dev/pts"), "{first:?}");
    // A second opener of the pty (before the host's, which is exclusive)
    // watches what an open port sees on the unplug.
    let mut watcher = {
        use std::os::unix::fs::OpenOptionsExt;
        std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(0o400) // O_NOCTTY
            .open(&first)
            .unwrap()
    };
    let transport = host::link::SerialTransport::open(server.path()).unwrap();
    let mut device = host::link::Device::connect(Box::new(transport)).unwrap();
    let boot = device.info().boot_id;

    // The disconnect: the link goes, and the open port fails (hung up).
    assert!(wait_until(Duration::from_secs(5), || link_target(&link).is_none()), "unplugged");
    use std::io::Write as _;
    let hung_up = watcher.write_all(b"x").and_then(|_| watcher.flush());
    assert!(hung_up.is_err(), "an open port fails once the board is unplugged");
    // Back, on a new pty (the old one may be reused for it: the link is
    // what is followed).
    assert!(wait_until(Duration::from_secs(5), || link_target(&link).is_some()), "plugged again");
    device.request(Request::Ping { token: 7 }).expect("the host reopens the link");
    assert!(device.stats.reconnects >= 1, "{:?}", device.stats);
    assert_eq!(device.info().boot_id, boot);

    // The reset: unplugged for its boot and enumeration, then the host's
    // next request finds a board that booted again.
    assert!(wait_until(Duration::from_secs(8), || link_target(&link).is_none()), "reset unplugs");
    let unplugged = std::time::Instant::now();
    assert!(
        wait_until(Duration::from_secs(5), || link_target(&link).is_some()),
        "back after reset"
    );
    assert!(
        unplugged.elapsed() >= Duration::from_millis(hil_sim::link::REPLUG_MS / 2),
        "away for the boot and enumeration: {:?}",
        unplugged.elapsed()
    );
    let reconnects = device.stats.reconnects;
    let answered = (0..2).map(|_| device.request(Request::Ping { token: 8 })).collect::<Vec<_>>();
    assert!(
        matches!(answered[0], Err(LinkError::Reset { old, .. }) if old == boot),
        "{answered:?}"
    );
    assert!(answered[1].is_ok(), "{answered:?}");
    assert!(device.stats.reconnects > reconnects, "{:?}", device.stats);
    assert_ne!(device.info().boot_id, boot);

    let device = server.stop().unwrap();
    assert_eq!(device.boot_count(), 2);
    assert!(link_target(&link).is_none(), "the link goes with the server");
    // Then the path is free for another.
    let again = hil_sim::PtyServer::start_with_camera(
        hil_sim::SimDevice::new(SimConfig::new(4)),
        1.0,
        None,
        hil_sim::Port::Usb(Some(link.clone())),
    )
    .unwrap();
    assert!(link_target(&link).is_some());
    drop(again);
}
