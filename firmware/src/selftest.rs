//! The controller's test suite as plain `no_std` functions, so that the same
//! tests run as host unit tests (`firmware/tests/core.rs`) and on a Cortex-M4
//! under QEMU (`firmware/qemu-tests`), which prints an "N passed, N failed"
//! line.
#![allow(missing_docs)] // test names say what they test

use protocol::{
    Axis, AxisSet, Capabilities, CaptureStep, DeviceError, Direction, Event, FaultFlags,
    FrameDecoder, HomingFailure, LightState, LogLevel, MAX_FRAME_LEN, MirrorPosition,
    MotionOutcome, MoveMode, ProtocolVersion, Reply, Request, ResetReason, ToHost, encode_frame,
};

use crate::config::{PersistedConfig, default_axes};
use crate::hal::{TICK_HZ, TICKS_PER_MS, TICKS_PER_US};
use crate::planner::{Profile, SegmentPlanner};
use crate::step::{QUEUE_LEN, StepGenerator};
use crate::testkit::{Output, Rig, Switch, Visit};

/// A test's outcome: `Err` carries what failed.
pub type TestResult = Result<(), &'static str>;

/// A named self-test.
pub type SelfTest = (&'static str, fn() -> TestResult);

macro_rules! ensure {
    ($cond:expr, $msg:expr) => {
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        if !$cond {
            return Err($msg);
        }
    };
}

/// Every test: (name, function).
pub const TESTS: &[SelfTest] = &[
    ("planner_step_times_within_one_tick", planner_step_times_within_one_tick),
    ("step_times_exact_near_2_32_and_2_40_ticks", step_times_exact_near_2_32_and_2_40_ticks),
    (
        "step_timer_loses_no_step_and_fires_none_early",
        step_timer_loses_no_step_and_fires_none_early,
    ),
    ("planner_respects_speed_and_acceleration", planner_respects_speed_and_acceleration),
    ("planner_stop_profile", planner_stop_profile),
    ("concurrent_move_reaches_targets", concurrent_move_reaches_targets),
    ("controlled_stop_decelerates", controlled_stop_decelerates),
    ("stop_while_stopping_changes_nothing", stop_while_stopping_changes_nothing),
    ("homing_deadline_only_while_searching", homing_deadline_only_while_searching),
    ("homing_all_axes", homing_all_axes),
    ("homing_starting_on_switch_backs_off", homing_starting_on_switch_backs_off),
    ("homing_switch_not_found", homing_switch_not_found),
    ("homing_switch_stuck", homing_switch_stuck),
    ("homing_timeout", homing_timeout),
    ("disk_takes_shortest_way", disk_takes_shortest_way),
    ("capture_step_sequence", capture_step_sequence),
    ("bare_trigger", bare_trigger),
    ("trigger_pulse_exact_on_the_timer_model", trigger_pulse_exact_on_the_timer_model),
    ("hardware_trigger_pulse_keeps_the_light_on", hardware_trigger_pulse_keeps_the_light_on),
    ("light_margin_around_the_pulse", light_margin_around_the_pulse),
    ("dispatcher_errors", dispatcher_errors),
    ("duplicate_sequence_not_reexecuted", duplicate_sequence_not_reexecuted),
    ("handshake_required_and_versions", handshake_required_and_versions),
    ("estop_input_latches", estop_input_latches),
    ("driver_fault_latches", driver_fault_latches),
    ("emergency_stop_request", emergency_stop_request),
    ("unexpected_home_switch", unexpected_home_switch),
    ("lost_steps_caught_at_the_index_flag", lost_steps_caught_at_the_index_flag),
    ("homing_when_homed_checks_the_count", homing_when_homed_checks_the_count),
    ("link_silence_while_moving", link_silence_while_moving),
    ("watchdog_boot_latches", watchdog_boot_latches),
    ("storage_failure_at_boot_latches", storage_failure_at_boot_latches),
    ("config_save_and_reload", config_save_and_reload),
    ("driver_fault_polarity_is_configurable", driver_fault_polarity_is_configurable),
    ("exposure_strobe_reports_each_exposure", exposure_strobe_reports_each_exposure),
    ("enter_bootloader_stops_everything_first", enter_bootloader_stops_everything_first),
    ("home_sensor_polarity_is_configurable", home_sensor_polarity_is_configurable),
    ("save_config_refused_while_moving_or_faulted", save_config_refused_while_moving_or_faulted),
    ("every_motion_request_refused_while_faulted", every_motion_request_refused_while_faulted),
    ("link_bytes_corruption_and_duplicates", link_bytes_corruption_and_duplicates),
    ("random_operation_keeps_the_safety_rules", random_operation_keeps_the_safety_rules),
];

/// Run every test; returns (passed, failed) and reports each through `report`.
pub fn run_all(mut report: impl FnMut(&str, TestResult)) -> (usize, usize) {
    let (mut passed, mut failed) = (0, 0);
    for (name, test) in TESTS {
        let result = test();
        if result.is_ok() {
            passed += 1
        } else {
            failed += 1
        }
        report(name, result);
    }
    (passed, failed)
}

// ----- planner ----------------------------------------------------------------

/// Drive a profile through the real step generator; call `visit(k, tick)` for
/// every step. Returns the number of steps.
fn generate(profile: Profile, start: u64, mut visit: impl FnMut(u32, u64)) -> u32 {
    let mut planner = SegmentPlanner::new(profile, TICK_HZ);
    let mut stepper = StepGenerator::new();
    for _ in 0..QUEUE_LEN {
        if let Some(s) = planner.next_segment() {
            let _ = stepper.push(s);
        }
    }
    let mut next = stepper.start(start, 1);
    let mut k = 0;
    while let Some(t) = next {
        k += 1;
        visit(k, t);
        next = stepper.step();
        while stepper.free() > 0 {
            match planner.next_segment() {
                Some(s) => {
                    let _ = stepper.push(s);
                }
                None => break,
            }
        }
    }
    k
}

/// (steps, v_max, a_max) cases: the three default axes at full range, short
/// triangles, a single step, slow homing moves.
const PROFILES: &[(u32, f64, f64)] = &[
    (320_000, 64_000.0, 320_000.0),
    (16_000, 4_000.0, 8_000.0),
    (18_666, 5_333.0, 16_000.0),
    (1_000, 64_000.0, 320_000.0),
    (37, 64_000.0, 320_000.0),
    (1, 4_000.0, 8_000.0),
    (2, 4_000.0, 8_000.0),
    (6_400, 1_600.0, 320_000.0),
    (400, 100.0, 8_000.0),
];

pub fn planner_step_times_within_one_tick() -> TestResult {
    for &(n, v, a) in PROFILES {
        let profile = Profile::trapezoid(n, 0.0, v, a);
        let start = 12_345;
        let mut worst = 0.0f64;
        let steps = generate(profile, start, |k, t| {
            let exact = start as f64 + profile.time_at(k as f64) * TICK_HZ as f64;
            worst = worst.max((t as f64 - exact).abs());
        });
        ensure!(steps == n, "step count differs from the move length");
        ensure!(worst <= 1.0, "a step deviates more than one tick from the trapezoid");
    }
    Ok(())
}

/// Moves that start just before the 32-bit counter wraps (358 s), just
/// before and after 2^40 ticks (25.45 h, where `now << 24` used to overflow)
/// and late in a 2^63-tick lifetime: every step within a tick of its exact
/// time after the start, none due at once.
pub fn step_times_exact_near_2_32_and_2_40_ticks() -> TestResult {
    let starts =
        [(1u64 << 32) - 5_000, (1 << 40) - 5_000, (1 << 40) + 12_345, (1 << 63) - (1 << 41)];
    for start in starts {
        for &(n, v, a) in &PROFILES[..4] {
            let profile = Profile::trapezoid(n, 0.0, v, a);
            let (mut worst, mut previous, mut ordered) = (0.0f64, start, true);
            let steps = generate(profile, start, |k, t| {
                let exact = profile.time_at(k as f64) * TICK_HZ as f64;
                worst = worst.max(((t - start) as f64 - exact).abs());
                ordered &= t > previous;
                previous = t;
            });
            ensure!(steps == n, "step count differs from the move length");
            ensure!(ordered, "steps not strictly after the start and each other");
            ensure!(worst <= 1.0, "a step deviates more than one tick (late in the uptime)");
        }
    }
    Ok(())
}

/// The step timer's arming logic (`crate::timer`) on a model of TIM2 in
/// which the counter runs on at every register access: three axes at
/// 64 000, 5 000 and 2 000 steps/s start, stop and are halted at random,
/// with idle gaps of a whole counter period (stale compare flags), from
/// epochs just before the 32-bit wrap and before 2^40 ticks. Every step
/// fires at or after its tick (none early), within a bounded latency (none
/// lost: a lost compare flag would wait a whole counter period), and the
/// overflow count keeps `now` exact.
/// The step interrupt (the board's handler) as long as a flag is pending:
/// every pulse at or after its tick and within `STEP_LATENCY` of it, none
/// for a halted axis.
fn isr(
    t: &mut crate::testkit::Tim2Model<'_>,
    overflows: &core::sync::atomic::AtomicU32,
    gens: &mut [StepGenerator; 3],
    armed: &mut [Option<u64>; 3],
    steps: &mut u64,
) -> TestResult {
    use crate::testkit::ModelPins;
    use crate::timer;
    while timer::pending(t) {
        let was = *armed;
        let mut pins = ModelPins { clock: t.clock, raised: [None; 3] };
        let due = timer::on_interrupt(t, overflows, gens, &mut pins);
        for ch in (0..3).filter(|&ch| due[ch]) {
            let tick = was[ch].ok_or("a step pulse for a halted or disarmed axis")?;
            let at = pins.raised[ch].ok_or("a due step without its pulse")?;
            ensure!(at >= tick, "a step fired early");
            ensure!(at - tick <= STEP_LATENCY, "a step came late (lost flag)");
            *steps += 1;
            armed[ch] = gens[ch].next_step_tick();
        }
        ensure!(pins.raised.iter().zip(due).all(|(r, d)| r.is_some() == d), "pulses");
    }
    Ok(())
}

/// The ISR runs as soon as a flag is pending (each register access costs
/// up to 8 ticks; thread mode may run up to 300 ticks between a halt and
/// its disarm): a step is never this late unless its flag was lost (then
/// it waits a whole counter period, 2^32 ticks).
const STEP_LATENCY: u64 = 1_000;

pub fn step_timer_loses_no_step_and_fires_none_early() -> TestResult {
    use crate::step::{ONE_TICK, Segment};
    use crate::testkit::Tim2Model;
    use crate::timer;
    use core::sync::atomic::AtomicU32;
    const STEPS: u64 = 1_000_000;
    let rates = [64_000u64, 5_000, 2_000];
    let epochs = [((1u64 << 32) - 3_000_000, 1u64), ((1 << 40) - 3_000_000, 2)];
    for (epoch, seed) in epochs {
        let clock = core::cell::Cell::new(epoch);
        let mut t = Tim2Model::new(&clock, seed, 8);
        let overflows = AtomicU32::new((epoch >> 32) as u32);
        let mut gens = [StepGenerator::new(), StepGenerator::new(), StepGenerator::new()];
        let mut armed: [Option<u64>; 3] = [None; 3];
        let (mut steps, mut long_idles, mut next_gap) = (0u64, 0, 0u64);
        while steps < STEPS {
            // Every 50 000 steps: let the moves end, then a whole counter
            // period passes idle (every old CCR is passed again: stale flags).
            let pausing = steps >= next_gap;
            if pausing && armed.iter().all(Option::is_none) {
                t.advance(u32::MAX as u64);
                long_idles += 1;
                next_gap += 50_000;
            }
            // Thread mode, in critical sections: start moves on idle axes,
            // now and then halt a moving one.
            for ch in 0..3 {
                if armed[ch].is_none() && !pausing && t.random().is_multiple_of(16) {
                    let count = 1 + (t.random() % 2_000) as u32;
                    let interval = TICK_HZ as u64 * ONE_TICK / rates[ch];
                    gens[ch].push(Segment { count, interval, add: 0 }).map_err(|_| "queue")?;
                    let now = timer::now(&mut t, &overflows);
                    let first = gens[ch].start(now, 1).ok_or("a first step")?;
                    armed[ch] = Some(first);
                    // Starting and arming are two critical sections on the
                    // board: the interrupt may run in between.
                    if t.random().is_multiple_of(2) {
                        isr(&mut t, &overflows, &mut gens, &mut armed, &mut steps)?;
                    }
                    timer::arm(&mut t, &overflows, ch, first);
                } else if armed[ch].is_some() && t.random().is_multiple_of(2_000) {
                    // Halting and disarming too (a fault halts every axis).
                    gens[ch].halt();
                    armed[ch] = None;
                    if t.random().is_multiple_of(2) {
                        let dt = t.random() % 300;
                        t.advance(dt);
                        isr(&mut t, &overflows, &mut gens, &mut armed, &mut steps)?;
                    }
                    timer::disarm(&mut t, ch);
                }
            }
            let dt = t.random() % 48;
            t.advance(dt);
            isr(&mut t, &overflows, &mut gens, &mut armed, &mut steps)?;
            for tick in armed.iter().flatten() {
                ensure!(t.time() <= tick + STEP_LATENCY, "an armed step never fired (lost flag)");
            }
            let before = t.time();
            let now = timer::now(&mut t, &overflows);
            ensure!(before <= now && now <= t.time(), "now is the counter, 64-bit");
        }
        ensure!(long_idles >= 20, "idle gaps of a counter period exercised");
    }
    Ok(())
}

pub fn planner_respects_speed_and_acceleration() -> TestResult {
    const W: usize = 16;
    for &(n, v_max, a_max) in PROFILES {
        let profile = Profile::trapezoid(n, 0.0, v_max, a_max);
        ensure!(profile.v_peak() <= v_max * (1.0 + 1e-12), "peak above v max");
        ensure!(profile.accel() <= a_max && profile.decel() <= a_max, "ramp above a max");
        let mut ring = [0u64; 2 * W + 1];
        let mut result = Ok(());
        generate(profile, 0, |k, t| {
            let k = k as usize;
            ring[k % ring.len()] = t;
            if k < 2 * W + 1 || result.is_err() {
                return;
            }
            // Three window edges: t0 < t1 < t2, W steps apart; ±1 tick each.
            let tick = |j: usize| ring[j % ring.len()] as f64;
            let (t0, t1, t2) = (tick(k - 2 * W), tick(k - W), tick(k));
            let hz = TICK_HZ as f64;
            let w = W as f64;
            let v_hi = |a: f64, b: f64| w * hz / (b - a - 2.0);
            let v_lo = |a: f64, b: f64| w * hz / (b - a + 2.0);
            if v_lo(t1, t2) > v_max {
                result = Err("windowed speed above v max");
            }
            let span = (t2 - t0 - 4.0) / 2.0 / hz;
            let a_lo = (v_lo(t1, t2) - v_hi(t0, t1)) / span;
            let a_hi = (v_hi(t1, t2) - v_lo(t0, t1)) / span;
            if a_lo > a_max * 1.001 || a_hi < -a_max * 1.001 {
                result = Err("windowed acceleration above a max");
            }
        });
        result?;
    }
    Ok(())
}

pub fn planner_stop_profile() -> TestResult {
    let profile = Profile::stop(64_000.0, 320_000.0);
    ensure!(profile.steps() == 6_400, "stop distance v²/2a");
    ensure!(profile.decel() <= 320_000.0, "stop ramp above a max");
    let mut last = 0;
    let n = generate(profile, 0, |_, t| last = t);
    ensure!(n == 6_400, "stop step count");
    let expected = 64_000.0 / 320_000.0 * TICK_HZ as f64;
    ensure!((last as f64 - expected).abs() <= 1.0, "stop duration v/a");
    Ok(())
}

// ----- motion -------------------------------------------------------------------

fn move_to(rig: &mut Rig, targets: [Option<i32>; 3]) -> Result<Reply, &'static str> {
    Ok(rig.request(Request::Move { mode: MoveMode::Absolute, targets }))
}

fn last_motion_outcome(rig: &Rig) -> Option<MotionOutcome> {
    rig.events.iter().rev().find_map(|e| match e {
        Event::MotionDone { outcome, .. } => Some(*outcome),
        _ => None,
    })
}

pub fn concurrent_move_reaches_targets() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    rig.events.clear();
    let reply = move_to(&mut rig, [Some(8_000), Some(160_000), Some(4_000)])?;
    ensure!(reply == Reply::Ack, "move accepted");
    // All three axes step during the same interval of time.
    rig.run_until(rig.now + 100 * TICKS_PER_MS);
    ensure!(Axis::ALL.iter().all(|a| rig.status().axes[a.index()].moving), "concurrent");
    ensure!(rig.run_until_idle(10_000), "move ends");
    ensure!(rig.position(Axis::Disk) == 8_000, "disk target");
    ensure!(rig.position(Axis::Track) == 160_000, "track target");
    ensure!(rig.position(Axis::Tilt) == 4_000, "tilt target");
    ensure!(last_motion_outcome(&rig) == Some(MotionOutcome::Completed), "MotionDone(Completed)");
    Ok(())
}

pub fn controlled_stop_decelerates() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    move_to(&mut rig, [None, Some(320_000), None])?;
    // Cruise at 64 000 steps/s (accelerating takes 200 ms).
    rig.run_until(rig.now + 400 * TICKS_PER_MS);
    let before = rig.position(Axis::Track);
    rig.clear_steps();
    ensure!(rig.request(Request::Stop) == Reply::Ack, "stop accepted");
    ensure!(rig.run_until_idle(2_000), "stops");
    let travelled = rig.position(Axis::Track) - before;
    // v²/2a = 6 400 steps, plus the one step already armed.
    ensure!((6_390..=6_402).contains(&travelled), "stop distance v²/2a");
    let (first, last) = rig.step_span[Axis::Track.index()].ok_or("steps")?;
    let dur = (last - first) as f64 / TICK_HZ as f64;
    ensure!((dur - 0.2).abs() < 0.002, "stop takes v/a");
    ensure!(last_motion_outcome(&rig) == Some(MotionOutcome::Stopped), "MotionDone(Stopped)");
    ensure!(rig.ctrl.is_homed(Axis::Track), "a controlled stop keeps homing");
    Ok(())
}

/// A `Stop` while the axes already ramp down changes nothing: right after
/// the first (the step a cut kept is still armed; found by the random
/// operation of `crate::chaos`: it underflowed) and halfway down.
pub fn stop_while_stopping_changes_nothing() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.request(Request::Home { axes: AxisSet::ALL }) == Reply::Ack, "homing");
    ensure!(rig.request(Request::Stop) == Reply::Ack, "first stop");
    ensure!(rig.request(Request::Stop) == Reply::Ack, "second stop at once");
    ensure!(rig.run_until_idle(2_000), "stops");
    ensure!(rig.ctrl.faults().is_empty(), "no fault");
    ensure!(rig.home_all(), "homing");
    move_to(&mut rig, [None, Some(320_000), None])?;
    rig.run_until(rig.now + 400 * TICKS_PER_MS);
    let before = rig.position(Axis::Track);
    ensure!(rig.request(Request::Stop) == Reply::Ack, "stop at cruise");
    rig.run_until(rig.now + 100 * TICKS_PER_MS);
    ensure!(rig.request(Request::Stop) == Reply::Ack, "stop halfway down");
    ensure!(rig.run_until_idle(2_000), "stops");
    let travelled = rig.position(Axis::Track) - before;
    ensure!((6_390..=6_402).contains(&travelled), "the first stop's distance, v²/2a");
    ensure!(rig.ctrl.is_homed(Axis::Track), "still homed");
    Ok(())
}

/// Run `rig` for `ms`, failing if after a poll the controller asks to be
/// woken in the past ([`Rig::stale_deadline`]).
fn run_without_stale_deadline(rig: &mut Rig, ms: u64) -> TestResult {
    rig.run_until_visiting(rig.now + ms * TICKS_PER_MS, |rig, visit| {
        match visit == Visit::Polled && rig.stale_deadline() {
            true => Err("the controller asks to be woken in the past"),
            false => Ok(()),
        }
    })
}

/// A homing's timeout is a deadline only while an axis still searches:
/// not while the homing stops short, nor for an axis homed already while
/// another searches on (it was the earliest of all the homing's axes, and
/// stale then until the homing ended).
pub fn homing_deadline_only_while_searching() -> TestResult {
    /// A rig whose `axis` gives up homing after `timeout_ms`, the track
    /// 100 000 steps further from its switch (≈ 11 s of search).
    fn rig_with_homing_timeout(axis: Axis, timeout_ms: u32) -> Result<Rig, &'static str> {
        let mut rig = Rig::new();
        let mut config = rig.ctrl.config().axes[axis.index()];
        config.homing.timeout_ms = timeout_ms;
        ensure!(rig.request(Request::SetAxisConfig { axis, config }) == Reply::Ack, "config");
        rig.physical[Axis::Track.index()] += 100_000;
        Ok(rig)
    }
    // Stopped 50 ms before its timeout: it ramps down past it.
    let mut rig = rig_with_homing_timeout(Axis::Track, 400)?;
    ensure!(rig.request(Request::Home { axes: AxisSet(1 << 1) }) == Reply::Ack, "homing");
    run_without_stale_deadline(&mut rig, 350)?;
    ensure!(rig.request(Request::Stop) == Reply::Ack, "stop");
    run_without_stale_deadline(&mut rig, 1_000)?;
    ensure!(!rig.ctrl.is_moving() && rig.ctrl.faults().is_empty(), "stopped, no fault");
    // The tilt homes within its 6 s (≈ 4 s) while the track searches on.
    let mut rig = rig_with_homing_timeout(Axis::Tilt, 6_000)?;
    let axes = AxisSet((1 << 1) | (1 << 2));
    ensure!(rig.request(Request::Home { axes }) == Reply::Ack, "homing");
    run_without_stale_deadline(&mut rig, 8_000)?;
    ensure!(rig.ctrl.is_homed(Axis::Tilt), "tilt homed");
    ensure!(!rig.ctrl.is_homed(Axis::Track) && rig.ctrl.is_moving(), "track still searching");
    Ok(())
}

pub fn disk_takes_shortest_way() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    let before = rig.physical(Axis::Disk);
    move_to(&mut rig, [Some(15_000), None, None])?;
    rig.run_until_idle(5_000);
    // 0 → 15 000 of 16 000 is 1 000 steps backwards, not 15 000 forwards.
    ensure!(rig.position(Axis::Disk) == 15_000, "disk angle");
    ensure!(rig.physical(Axis::Disk) - before == -1_000, "went the short way");
    Ok(())
}

// ----- homing -------------------------------------------------------------------

pub fn homing_all_axes() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "all axes homed");
    // The switch edge is found to within one slow-approach step.
    // Switch edges: track at physical 0, tilt at −9 333; counters agree.
    let track_err = rig.physical(Axis::Track) - rig.position(Axis::Track) as i64;
    ensure!(
        track_err.abs() <= 1 && rig.physical(Axis::Track).abs() <= 1,
        "track home at its switch"
    );
    let tilt_err = rig.physical(Axis::Tilt) - rig.position(Axis::Tilt) as i64;
    ensure!(tilt_err.abs() <= 1, "tilt home at its switch");
    let disk = rig.physical(Axis::Disk).rem_euclid(16_000);
    ensure!(disk <= 1 || disk >= 15_999, "disk homes on its index flag");
    ensure!(rig.position(Axis::Tilt) == -9_333, "home position assigned");
    ensure!(last_motion_outcome(&rig) == Some(MotionOutcome::Completed), "MotionDone");
    ensure!(rig.ctrl.faults().is_empty(), "no fault");
    Ok(())
}

pub fn homing_starting_on_switch_backs_off() -> TestResult {
    let mut rig = Rig::new();
    rig.physical[1] = -500; // parked on the switch
    rig.poll();
    ensure!(rig.request(Request::Home { axes: AxisSet::single(Axis::Track) }) == Reply::Ack, "ack");
    rig.run_until_idle(30_000);
    ensure!(rig.ctrl.is_homed(Axis::Track), "homed");
    let err = rig.physical(Axis::Track) - rig.position(Axis::Track) as i64;
    ensure!(err.abs() <= 1, "edge found from the switch side");
    Ok(())
}

fn homing_fails_with(rig: &mut Rig, axis: Axis, why: HomingFailure) -> TestResult {
    ensure!(rig.request(Request::Home { axes: AxisSet::single(axis) }) == Reply::Ack, "ack");
    rig.run_until_idle(120_000);
    ensure!(!rig.ctrl.is_homed(axis), "not homed");
    ensure!(rig.ctrl.faults().contains(FaultFlags::HOMING_FAILED), "fault latched");
    ensure!(
        last_motion_outcome(rig) == Some(MotionOutcome::HomingFailed(axis, why)),
        "MotionDone reports the failure"
    );
    ensure!(
        rig.events
            .iter()
            .any(|e| matches!(e, Event::FaultRaised { axis: Some(a), .. } if *a == axis)),
        "FaultRaised names the axis"
    );
    Ok(())
}

pub fn homing_switch_not_found() -> TestResult {
    let mut rig = Rig::new();
    rig.switches[1] = Switch::Missing;
    homing_fails_with(&mut rig, Axis::Track, HomingFailure::SwitchNotFound)
}

pub fn homing_switch_stuck() -> TestResult {
    let mut rig = Rig::new();
    rig.switches[2] = Switch::Stuck;
    rig.poll();
    homing_fails_with(&mut rig, Axis::Tilt, HomingFailure::SwitchStuck)
}

pub fn homing_timeout() -> TestResult {
    let mut rig = Rig::new();
    let mut cfg = default_axes()[1];
    cfg.homing.timeout_ms = 1_000; // 80 000 steps from home at 16 000 steps/s: 5 s
    ensure!(
        rig.request(Request::SetAxisConfig { axis: Axis::Track, config: cfg }) == Reply::Ack,
        "cfg"
    );
    homing_fails_with(&mut rig, Axis::Track, HomingFailure::Timeout)
}

// ----- capture ------------------------------------------------------------------

pub fn capture_step_sequence() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    let pos = MirrorPosition { steps: [4_000, 120_000, -1_500] };
    ensure!(rig.request(Request::SetMirror { mirror: 5, position: pos }) == Reply::Ack, "set");
    rig.events.clear();
    rig.hw.outputs.clear();
    rig.clear_steps();
    let step =
        CaptureStep { mirror: 5, settle_ms: 150, exposure_us: 50_000, light_duty_permille: 800 };
    ensure!(rig.request(Request::CaptureStep(step)) == Reply::Ack, "capture accepted");
    ensure!(
        rig.request(Request::GoToMirror { mirror: 5 }) == Reply::Error(DeviceError::Busy),
        "busy"
    );
    ensure!(rig.run_until_idle(10_000), "capture ends");
    ensure!(rig.position(Axis::Track) == 120_000, "at the mirror");

    let moved_at = rig.events.iter().position(|e| matches!(e, Event::MotionDone { .. }));
    let fired = rig.events.iter().find_map(|e| match e {
        Event::TriggerFired(t) => Some(*t),
        _ => None,
    });
    let (Some(moved_at), Some(fired)) = (moved_at, fired) else { return Err("events") };
    ensure!(rig.events.len() > moved_at + 1, "TriggerFired after MotionDone");
    ensure!(fired.trigger_seq == 1 && fired.mirror == Some(5), "trigger seq and mirror");
    ensure!(fired.exposure_us == 50_000, "exposure reported");

    // Outputs: light on (800), trigger high, trigger low, light off.
    let [t_on, t_hi, t_lo, t_off] = capture_edges(&rig.hw.outputs)?;
    ensure!(t_on <= t_hi && t_lo <= t_off, "light spans the exposure");
    ensure!(t_lo - t_hi == 50_000 * TICKS_PER_US, "pulse width = exposure");
    ensure!(fired.timestamp_us == t_hi / TICKS_PER_US, "timestamp at the rising edge");
    let last_step = rig.step_span.iter().filter_map(|s| s.map(|(_, l)| l)).max().unwrap_or(0);
    ensure!(t_hi - last_step >= 150 * TICKS_PER_MS, "settled 150 ms after the last step");
    ensure!(t_hi - last_step <= 150 * TICKS_PER_MS + TICKS_PER_MS, "and no more than 1 ms later");
    Ok(())
}

/// A capture step's outputs at duty 800: the ticks of light on, trigger
/// high, trigger low and light off, in that order and nothing else.
fn capture_edges(o: &[Output]) -> Result<[u64; 4], &'static str> {
    ensure!(o.len() == 4, "four output edges");
    let (Output::Light(t_on, 800), Output::Trigger(t_hi, true)) = (o[0], o[1]) else {
        return Err("light on, then trigger high");
    };
    let (Output::Trigger(t_lo, false), Output::Light(t_off, 0)) = (o[2], o[3]) else {
        return Err("trigger low, then light off");
    };
    Ok([t_on, t_hi, t_lo, t_off])
}

pub fn bare_trigger() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.request(Request::Trigger { exposure_us: 2_000 }) == Reply::Ack, "trigger");
    rig.run_until_idle(100);
    ensure!(rig.hw.outputs.len() == 2 && !rig.hw.trigger, "one pulse");
    let reply = rig.request(Request::GetLastTrigger);
    let Reply::Trigger(Some(t)) = reply else { return Err("last trigger") };
    ensure!(t.trigger_seq == 1 && t.mirror.is_none(), "bare trigger recorded");
    Ok(())
}

/// The one-pulse trigger (`crate::trigger`) on a model of its timer whose
/// counter runs on by up to 40 ticks at every register access: every pulse
/// from 1 ms to 2 s lasts exactly its ticks, starts at the first tick after
/// `start`, has ended by the tick the board reports, and an abort lowers
/// the line at once and for good.
pub fn trigger_pulse_exact_on_the_timer_model() -> TestResult {
    use crate::testkit::PulseTimerModel;
    use crate::trigger::{force_low, running, start};
    use protocol::{MAX_EXPOSURE_US, MIN_EXPOSURE_US};
    let clock = core::cell::Cell::new(0u64);
    let mut m = PulseTimerModel::new(&clock, 0x9E37_79B9, 40);
    let mut rng = 0x2545_F491_4F6C_DD1Du64;
    let mut random = move || crate::testkit::xorshift64star(&mut rng);
    for i in 0..300 {
        let us = match i {
            0 => MIN_EXPOSURE_US,
            1 => MAX_EXPOSURE_US,
            2 => 3_090, // not a multiple of the 200 µs poll
            _ => {
                MIN_EXPOSURE_US + (random() % (MAX_EXPOSURE_US - MIN_EXPOSURE_US + 1) as u64) as u32
            }
        };
        let ticks = us as u64 * TICKS_PER_US;
        m.edges.clear();
        let called = clock.get();
        start(&mut m, ticks);
        let returned = clock.get();
        let ended_by = returned + ticks + 1; // what the board reports
        m.advance(random() % ticks);
        ensure!(running(&mut m) || clock.get() >= returned + ticks, "running during the pulse");
        m.advance(ticks + 1);
        ensure!(!m.is_high() && !running(&mut m), "the timer ended the pulse by itself");
        ensure!(m.edges.len() == 2, "one rise and one fall");
        let ((rise, up), (fall, down)) = (m.edges[0], m.edges[1]);
        ensure!(up && !down, "a rise, then a fall");
        ensure!(fall - rise == ticks, "the pulse lasts exactly the exposure");
        ensure!(rise > called && rise <= returned + 1, "it starts at the first tick after start");
        ensure!(fall <= ended_by, "it has ended by the reported tick");
        // The controller lowers the line at the reported tick: no edge.
        force_low(&mut m);
        ensure!(m.edges.len() == 2, "lowering an ended pulse changes nothing");
        m.advance(random() % 100_000);
    }
    // An abort in the middle of a pulse: low at once, and it stays low.
    m.edges.clear();
    start(&mut m, 100 * TICKS_PER_MS);
    m.advance(10 * TICKS_PER_MS);
    let before = clock.get();
    force_low(&mut m);
    let after = clock.get();
    ensure!(m.edges.len() == 2 && !m.is_high(), "an abort lowers the line");
    ensure!(m.edges[1].0 >= before && m.edges[1].0 <= after, "at the write");
    m.advance(200 * TICKS_PER_MS);
    ensure!(m.edges.len() == 2 && !running(&mut m), "and the counter stopped");
    // A pulse after the abort is whole.
    start(&mut m, 5 * TICKS_PER_MS);
    m.advance(6 * TICKS_PER_MS);
    ensure!(m.edges.len() == 4, "the next pulse");
    ensure!(m.edges[3].0 - m.edges[2].0 == 5 * TICKS_PER_MS, "is whole");
    Ok(())
}

/// With the pulse ended by the board's timer, the controller keeps the
/// light on until the tick the board reports and lowers the line after
/// it (no edge: the pulse is exact); an emergency stop in the middle of a
/// pulse still drops the line at once.
pub fn hardware_trigger_pulse_keeps_the_light_on() -> TestResult {
    let mut rig = Rig::new();
    rig.hw.hardware_pulse = true;
    ensure!(rig.home_all(), "homing");
    let pos = MirrorPosition { steps: [4_000, 120_000, -1_500] };
    ensure!(rig.request(Request::SetMirror { mirror: 5, position: pos }) == Reply::Ack, "set");
    rig.hw.outputs.clear();
    let step =
        CaptureStep { mirror: 5, settle_ms: 150, exposure_us: 3_090, light_duty_permille: 800 };
    ensure!(rig.request(Request::CaptureStep(step)) == Reply::Ack, "capture accepted");
    ensure!(rig.run_until_idle(10_000), "capture ends");
    let [t_on, t_hi, t_lo, t_off] = capture_edges(&rig.hw.outputs)?;
    ensure!(t_lo - t_hi == 3_090 * TICKS_PER_US, "pulse width = exposure");
    ensure!(t_on <= t_hi && t_lo < t_off, "the light outlasts the pulse");
    // An emergency stop 1 ms into a 100 ms pulse.
    rig.hw.outputs.clear();
    ensure!(rig.request(Request::Trigger { exposure_us: 100_000 }) == Reply::Ack, "trigger");
    rig.run_until(rig.now + TICKS_PER_MS);
    ensure!(rig.request(Request::EmergencyStop) == Reply::Ack, "stop");
    let o = &rig.hw.outputs;
    let (Some(Output::Trigger(t_hi, true)), Some(Output::Trigger(t_lo, false))) =
        (o.first().copied(), o.get(1).copied())
    else {
        return Err("trigger high, then low");
    };
    ensure!(t_lo - t_hi == TICKS_PER_MS, "the stop cut the pulse at once");
    ensure!(!rig.hw.trigger, "low");
    Ok(())
}

/// A `TimedCaptureStep` (protocol 1.3) lights the sample its margin before
/// the trigger rises and as long after the pulse, which stays exactly the
/// exposure; the step is over when the pulse ends. The margin still
/// running ends at a bare trigger (a dark frame sees the light as set) and
/// at the next step's light; a margin over the maximum is refused.
pub fn light_margin_around_the_pulse() -> TestResult {
    use protocol::{MAX_LIGHT_MARGIN_US, TimedCaptureStep};
    // Run until a step's pulse is over (its trigger fired and low again):
    // the step is done; its light margin may still run. The tick it ended.
    fn until_pulse_over(rig: &mut Rig) -> Result<u64, &'static str> {
        rig.events.clear();
        for _ in 0..100_000 {
            rig.run_until(rig.now + 50 * TICKS_PER_US);
            let fired = rig.events.iter().any(|e| matches!(e, Event::TriggerFired(_)));
            if fired && !rig.hw.trigger {
                return Ok(rig.now);
            }
        }
        Err("no pulse")
    }
    let mut rig = Rig::new();
    rig.hw.hardware_pulse = true;
    ensure!(rig.home_all(), "homing");
    let pos = MirrorPosition { steps: [4_000, 120_000, -1_500] };
    ensure!(rig.request(Request::SetMirror { mirror: 5, position: pos }) == Reply::Ack, "set");
    let step =
        CaptureStep { mirror: 5, settle_ms: 150, exposure_us: 3_090, light_duty_permille: 800 };
    let timed =
        |light_margin_us| Request::TimedCaptureStep(TimedCaptureStep { step, light_margin_us });
    rig.hw.outputs.clear();
    rig.events.clear();
    ensure!(rig.request(timed(250)) == Reply::Ack, "accepted");
    ensure!(rig.run_until_idle(10_000), "capture ends");
    let [t_on, t_hi, t_lo, t_off] = capture_edges(&rig.hw.outputs)?;
    ensure!(t_hi - t_on == 250 * TICKS_PER_US, "the light 250 µs before the pulse");
    ensure!(t_lo - t_hi == 3_090 * TICKS_PER_US, "pulse width = exposure");
    // The pulse ends in hardware; the light goes back 250 µs after the
    // tick the board reports it over by (a tick or two after the fall).
    let after = t_off - t_lo;
    ensure!((250 * TICKS_PER_US..=251 * TICKS_PER_US).contains(&after), "and 250 µs after it");
    let fired = rig.events.iter().find_map(|e| match e {
        Event::TriggerFired(t) => Some(*t),
        _ => None,
    });
    ensure!(fired.is_some_and(|f| f.timestamp_us == t_hi / TICKS_PER_US), "timestamp at the rise");
    // The step is over when its pulse is: the next request is not busy.
    rig.hw.outputs.clear();
    ensure!(rig.request(timed(5_000)) == Reply::Ack, "accepted");
    until_pulse_over(&mut rig)?;
    ensure!(rig.hw.light == 800, "the margin runs on");
    // A dark frame then sees the light as set: off before its pulse.
    ensure!(rig.request(Request::Trigger { exposure_us: 1_000 }) == Reply::Ack, "bare trigger");
    rig.run_until(rig.now + 10 * TICKS_PER_MS);
    let o = &rig.hw.outputs;
    let dark_rise = o.iter().rev().find_map(|e| match e {
        Output::Trigger(t, true) => Some(*t),
        _ => None,
    });
    let light_off = o.iter().find_map(|e| match e {
        Output::Light(t, 0) => Some(*t),
        _ => None,
    });
    ensure!(
        matches!((light_off, dark_rise), (Some(off), Some(rise)) if off <= rise),
        "the light off before the dark frame's pulse"
    );
    ensure!(o.iter().filter(|e| matches!(e, Output::Light(_, 800))).count() == 1, "lit once");
    // The next step's light ends the last one's margin: its own margin
    // and pulse run at its duty, undisturbed (no move, no settling: the
    // first margin would end in the middle of the second pulse).
    rig.hw.outputs.clear();
    let quick = CaptureStep { settle_ms: 0, exposure_us: 10_000, ..step };
    let quick = |light_margin_us| {
        Request::TimedCaptureStep(TimedCaptureStep { step: quick, light_margin_us })
    };
    ensure!(rig.request(quick(5_000)) == Reply::Ack, "accepted");
    until_pulse_over(&mut rig)?;
    ensure!(rig.request(quick(100)) == Reply::Ack, "the next step at once");
    let second_over = until_pulse_over(&mut rig)?;
    rig.run_until(rig.now + 10 * TICKS_PER_MS);
    let o = &rig.hw.outputs;
    let second_rise = o
        .iter()
        .filter_map(|e| match e {
            Output::Trigger(t, true) => Some(*t),
            _ => None,
        })
        .nth(1)
        .ok_or("two pulses")?;
    let dark_during = o.iter().any(|e| {
        matches!(e, Output::Light(t, d) if *d != 800
            && *t >= second_rise - 100 * TICKS_PER_US && *t < second_over)
    });
    ensure!(!dark_during, "the first margin never darkens the second step");
    ensure!(
        rig.request(timed(MAX_LIGHT_MARGIN_US + 1)) == Reply::Error(DeviceError::OutOfRange),
        "a margin over the maximum is refused"
    );
    Ok(())
}

// ----- dispatcher ---------------------------------------------------------------

pub fn dispatcher_errors() -> TestResult {
    use DeviceError::*;
    let mut rig = Rig::new();
    let e = |r: &mut Rig, req| match r.request(req) {
        Reply::Error(e) => Some(e),
        _ => None,
    };
    let mv = |t| Request::Move { mode: MoveMode::Absolute, targets: [None, Some(t), None] };
    ensure!(e(&mut rig, mv(1_000)) == Some(NotHomed), "NotHomed");
    ensure!(e(&mut rig, Request::GoToMirror { mirror: 3 }) == Some(MirrorNotSet), "MirrorNotSet");
    ensure!(e(&mut rig, Request::GoToMirror { mirror: 64 }) == Some(OutOfRange), "mirror index");
    ensure!(e(&mut rig, Request::Home { axes: AxisSet(0x08) }) == Some(BadRequest), "axis set");
    ensure!(e(&mut rig, Request::Home { axes: AxisSet::NONE }) == Some(BadRequest), "empty set");
    ensure!(e(&mut rig, Request::Trigger { exposure_us: 999 }) == Some(OutOfRange), "short exp");
    ensure!(e(&mut rig, Request::Trigger { exposure_us: 2_000_001 }) == Some(OutOfRange), "long");
    let light = Request::SetLight(LightState { on: true, duty_permille: 1_001 });
    ensure!(e(&mut rig, light) == Some(OutOfRange), "duty");
    let mut bad = default_axes()[1];
    bad.v_max = 0;
    let set = Request::SetAxisConfig { axis: Axis::Track, config: bad };
    ensure!(e(&mut rig, set) == Some(BadRequest), "bad config");
    let off_table = MirrorPosition { steps: [0, 400_000, 0] };
    let set = Request::SetMirror { mirror: 1, position: off_table };
    ensure!(e(&mut rig, set) == Some(OutOfRange), "mirror entry beyond limits");
    ensure!(e(&mut rig, Request::SetMirrorCount { count: 65 }) == Some(OutOfRange), "count");
    rig.hw.storage_fails = true;
    ensure!(e(&mut rig, Request::SaveConfig) == Some(Storage), "Storage");
    rig.hw.storage_fails = false;
    let mut volatile = Rig::with_capabilities(ResetReason::PowerOn, Capabilities::SIMULATED);
    ensure!(e(&mut volatile, Request::SaveConfig) == Some(Unsupported), "Unsupported");

    ensure!(rig.home_all(), "homing");
    ensure!(e(&mut rig, mv(320_001)) == Some(OutOfRange), "beyond soft limit");
    ensure!(e(&mut rig, mv(-1)) == Some(OutOfRange), "below soft limit");
    let rel = Request::Move { mode: MoveMode::Relative, targets: [None, None, Some(20_000)] };
    ensure!(e(&mut rig, rel) == Some(OutOfRange), "relative beyond limit");
    ensure!(
        e(&mut rig, Request::Move { mode: MoveMode::Absolute, targets: [None; 3] })
            == Some(BadRequest),
        "no axis"
    );
    ensure!(rig.request(mv(300_000)) == Reply::Ack, "move");
    ensure!(e(&mut rig, mv(1_000)) == Some(Busy), "Busy");
    ensure!(e(&mut rig, Request::Home { axes: AxisSet::ALL }) == Some(Busy), "Busy homing");
    ensure!(e(&mut rig, Request::Trigger { exposure_us: 5_000 }) == Some(Busy), "Busy trigger");
    let cfg = Request::SetAxisConfig { axis: Axis::Disk, config: default_axes()[0] };
    ensure!(e(&mut rig, cfg) == Some(Busy), "Busy config");
    ensure!(matches!(rig.request(Request::GetStatus), Reply::Status(_)), "status while busy");
    ensure!(rig.request(Request::Ping { token: 9 }) == Reply::Pong { token: 9 }, "ping while busy");
    rig.run_until_idle(20_000);
    ensure!(rig.request(Request::EmergencyStop) == Reply::Ack, "estop");
    ensure!(e(&mut rig, mv(1_000)) == Some(FaultLatched), "FaultLatched");
    ensure!(e(&mut rig, Request::Trigger { exposure_us: 5_000 }) == Some(FaultLatched), "trigger");
    let light = Request::SetLight(LightState { on: true, duty_permille: 10 });
    ensure!(e(&mut rig, light) == Some(FaultLatched), "light");
    Ok(())
}

pub fn duplicate_sequence_not_reexecuted() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    let rel = Request::Move { mode: MoveMode::Relative, targets: [None, Some(1_600), None] };
    let before = rig.position(Axis::Track);
    ensure!(rig.request_seq(200, rel) == Reply::Ack, "first");
    // The reply was lost: the host sends the same frame again (twice).
    ensure!(rig.request_seq(200, rel) == Reply::Ack, "re-acknowledged");
    ensure!(rig.request_seq(200, rel) == Reply::Ack, "re-acknowledged again");
    rig.run_until_idle(5_000);
    ensure!(rig.position(Axis::Track) - before == 1_600, "executed once");
    // A new number executes again; so does an old number after another one.
    ensure!(rig.request_seq(201, rel) == Reply::Ack, "next");
    rig.run_until_idle(5_000);
    ensure!(rig.position(Axis::Track) - before == 3_200, "executed twice");
    Ok(())
}

pub fn handshake_required_and_versions() -> TestResult {
    let mut rig = Rig::new();
    let v2 = ProtocolVersion { major: 2, minor: 0 };
    let reply = rig.request(Request::Hello { host_protocol: v2 });
    ensure!(
        matches!(reply, Reply::Error(DeviceError::UnsupportedVersion(v)) if v.major == 1),
        "incompatible major refused with the device version"
    );
    ensure!(rig.request(Request::GetStatus) == Reply::Error(DeviceError::NoHandshake), "refused");
    let v1_9 = ProtocolVersion { major: 1, minor: 9 };
    let Reply::Info(info) = rig.request(Request::Hello { host_protocol: v1_9 }) else {
        return Err("compatible minor accepted");
    };
    ensure!(info.boot_id == 0x1234_5678 && info.protocol.major == 1, "info");
    ensure!(matches!(rig.request(Request::GetStatus), Reply::Status(_)), "talks after Hello");
    Ok(())
}

// ----- safety ---------------------------------------------------------------------

fn assert_faulted(rig: &Rig, fault: FaultFlags) -> TestResult {
    ensure!(rig.ctrl.faults().contains(fault), "fault latched");
    ensure!(!rig.ctrl.is_moving(), "motion stopped");
    ensure!(rig.hw.armed.iter().all(Option::is_none), "no step armed");
    ensure!(rig.hw.light == 0 && !rig.hw.trigger, "light and trigger off");
    ensure!(rig.events.iter().any(|e| matches!(e, Event::FaultRaised { .. })), "FaultRaised");
    Ok(())
}

fn moving_with_light(rig: &mut Rig) -> TestResult {
    ensure!(rig.home_all(), "homing");
    let on = Request::SetLight(LightState { on: true, duty_permille: 500 });
    ensure!(rig.request(on) == Reply::Ack, "light on");
    move_to(rig, [Some(8_000), Some(300_000), None])?;
    rig.run_until(rig.now + 300 * TICKS_PER_MS);
    ensure!(rig.ctrl.is_moving() && rig.hw.light == 500, "moving, lit");
    Ok(())
}

/// `EnterBootloader`: refused on a board that cannot, and on one that
/// can, every axis stopped, light and trigger off before the `Ack` (the
/// board resets once it is sent).
pub fn enter_bootloader_stops_everything_first() -> TestResult {
    let mut rig = Rig::new();
    moving_with_light(&mut rig)?;
    ensure!(
        rig.request(Request::EnterBootloader) == Reply::Error(DeviceError::Unsupported),
        "no bootloader without the capability"
    );
    ensure!(!rig.ctrl.bootloader_requested(), "not requested");
    ensure!(rig.ctrl.is_moving() && rig.hw.light == 500, "refused: nothing changed");
    let caps = Capabilities::SIMULATED.union(Capabilities::SYSTEM_BOOTLOADER);
    let mut rig = Rig::with_capabilities(ResetReason::PowerOn, caps);
    moving_with_light(&mut rig)?;
    ensure!(rig.request(Request::EnterBootloader) == Reply::Ack, "accepted");
    ensure!(rig.ctrl.bootloader_requested() && !rig.ctrl.reset_requested(), "requested");
    ensure!(!rig.ctrl.is_moving(), "motion stopped");
    ensure!(rig.hw.armed.iter().all(Option::is_none), "no step armed");
    ensure!(rig.hw.light == 0 && !rig.hw.trigger, "light and trigger off");
    Ok(())
}

/// Sample the inputs as the board does (every 200 µs) until `done` or
/// `max_us`; returns the time it took, µs.
fn sample_until(rig: &mut Rig, max_us: u64, done: impl Fn(&Rig) -> bool) -> Option<u64> {
    let start = rig.now;
    while rig.now - start <= max_us * TICKS_PER_US {
        if done(rig) {
            return Some((rig.now - start) / TICKS_PER_US);
        }
        rig.run_until(rig.now + 200 * TICKS_PER_US);
    }
    None
}

/// An input glitch of one 5 kHz sample latches nothing; held, it stops
/// everything within the stated bound (`DEBOUNCE_US` + one sample), leaves
/// the motors unpowered, and cannot be cleared while held.
fn input_latches(set: fn(&mut Rig, bool), fault: FaultFlags) -> TestResult {
    use crate::controller::DEBOUNCE_US;
    let mut rig = Rig::new();
    moving_with_light(&mut rig)?;
    set(&mut rig, true);
    rig.poll();
    rig.run_until(rig.now + 200 * TICKS_PER_US);
    set(&mut rig, false);
    rig.run_until(rig.now + 5 * TICKS_PER_MS);
    ensure!(rig.ctrl.faults().is_empty() && rig.ctrl.is_moving(), "a glitch latches nothing");
    set(&mut rig, true);
    let took = sample_until(&mut rig, 10_000, |r| r.ctrl.faults().contains(fault));
    ensure!(took.is_some_and(|t| t <= DEBOUNCE_US + 200), "stopped within 600 µs");
    assert_faulted(&rig, fault)?;
    ensure!(last_motion_outcome(&rig) == Some(MotionOutcome::Aborted), "MotionDone(Aborted)");
    ensure!(!rig.hw.drivers_enabled, "motors de-energised");
    ensure!(Axis::ALL.iter().all(|a| !rig.ctrl.is_homed(*a)), "unpowered axes lose homing");
    ensure!(rig.request(Request::ClearFault) == Reply::Error(DeviceError::FaultLatched), "held");
    set(&mut rig, false);
    rig.poll();
    rig.run_until(rig.now + TICKS_PER_MS);
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared after release");
    ensure!(rig.ctrl.faults().is_empty(), "no fault");
    // The next move energises the drivers again.
    ensure!(rig.home_all(), "homing after the fault");
    ensure!(rig.hw.drivers_enabled, "energised to move");
    Ok(())
}

pub fn estop_input_latches() -> TestResult {
    input_latches(|r, on| r.estop = on, FaultFlags::EMERGENCY_STOP)
}

/// A TMC2209 clears its fault when its EN is released: the controller
/// releases EN on the fault, so the host's `ClearFault` succeeds once the
/// driver has let go of its fault line.
pub fn driver_fault_latches() -> TestResult {
    input_latches(|r, on| r.driver_fault = on, FaultFlags::DRIVER_FAULT)
}

pub fn emergency_stop_request() -> TestResult {
    let mut rig = Rig::new();
    moving_with_light(&mut rig)?;
    ensure!(rig.request(Request::EmergencyStop) == Reply::Ack, "ack");
    assert_faulted(&rig, FaultFlags::EMERGENCY_STOP)?;
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "clear");
    Ok(())
}

pub fn unexpected_home_switch() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    move_to(&mut rig, [None, Some(200_000), None])?;
    rig.run_until_idle(10_000);
    // The carriage slipped: physically it is now 50 000 steps nearer home
    // than the controller believes, and the next move hits the switch.
    rig.physical[1] -= 50_000;
    move_to(&mut rig, [None, Some(20_000), None])?;
    rig.run_until_idle(10_000);
    assert_faulted(&rig, FaultFlags::UNEXPECTED_HOME_SWITCH)?;
    ensure!(
        rig.events.iter().any(|e| matches!(e, Event::FaultRaised { axis: Some(Axis::Track), .. })),
        "names the axis"
    );
    Ok(())
}

fn reported_error(rig: &Rig, axis: Axis) -> Option<i32> {
    rig.events.iter().rev().find_map(|e| match e {
        Event::PositionChecked { axis: a, error_steps } if *a == axis => Some(*error_steps),
        _ => None,
    })
}

pub fn lost_steps_caught_at_the_index_flag() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    // Round the disk both ways: the index flag's home edge agrees.
    for t in [8_000, 15_000, 3_000, 12_000, 1_000] {
        move_to(&mut rig, [Some(t), None, None])?;
        rig.run_until_idle(10_000);
        ensure!(rig.ctrl.faults().is_empty(), "no false alarm at the index flag");
    }
    // The disk slips 400 steps (the back-off distance): physically behind
    // its count; the next pass of the flag downwards shows it.
    rig.physical[0] -= 400;
    move_to(&mut rig, [Some(14_000), None, None])?;
    rig.run_until_idle(10_000);
    assert_faulted(&rig, FaultFlags::POSITION_LOST)?;
    let error = reported_error(&rig, Axis::Disk).ok_or("PositionChecked")?;
    ensure!((error - 400).abs() <= 2, "the error is reported");
    ensure!(!rig.ctrl.is_homed(Axis::Disk), "homing lost");
    Ok(())
}

pub fn homing_when_homed_checks_the_count() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    ensure!(reported_error(&rig, Axis::Track).is_none(), "plain homing checks nothing");
    move_to(&mut rig, [Some(6_000), Some(100_000), Some(3_000)])?;
    rig.run_until_idle(10_000);
    // Slips: the track by less than its back-off, the tilt by more.
    rig.physical[1] -= 1_000;
    rig.physical[2] -= 1_500;
    ensure!(rig.home_all(), "the check homes");
    let e = |a| reported_error(&rig, a).ok_or("PositionChecked");
    ensure!((e(Axis::Track)? - 1_000).abs() <= 2, "track error");
    ensure!((e(Axis::Tilt)? - 1_500).abs() <= 2, "tilt error (wide search)");
    ensure!(e(Axis::Disk)?.abs() <= 2, "disk kept its count");
    let track_err = rig.physical(Axis::Track) - rig.position(Axis::Track) as i64;
    ensure!(track_err.abs() <= 1, "counts right again");
    ensure!(rig.ctrl.faults().is_empty(), "a check is not a fault");
    Ok(())
}

pub fn link_silence_while_moving() -> TestResult {
    let mut rig = Rig::new();
    moving_with_light(&mut rig)?;
    let track = rig.position(Axis::Track);
    rig.keepalive = false;
    // The silence starts at the last frame the host sent.
    let _ = rig.request(Request::Ping { token: 1 });
    let silent_from = rig.now;
    rig.run_until(silent_from + 499 * TICKS_PER_MS);
    ensure!(rig.ctrl.faults().is_empty(), "499 ms of silence is fine");
    rig.run_until(silent_from + 501 * TICKS_PER_MS);
    ensure!(rig.ctrl.faults().contains(FaultFlags::LINK_TIMEOUT), "500 ms: fault");
    ensure!(rig.hw.light == 0, "light off");
    ensure!(rig.run_until_idle(2_000), "decelerates to rest");
    ensure!(
        rig.position(Axis::Track) < 300_000 && rig.position(Axis::Track) > track,
        "stopped short"
    );
    ensure!(rig.ctrl.is_homed(Axis::Track), "decelerated, so still homed");
    // Idle silence is not a fault.
    let mut idle = Rig::new();
    idle.keepalive = false;
    idle.run_until(5_000 * TICKS_PER_MS);
    ensure!(idle.ctrl.faults().is_empty(), "idle silence is fine");
    Ok(())
}

pub fn watchdog_boot_latches() -> TestResult {
    let rig = Rig::booted(ResetReason::Watchdog);
    ensure!(rig.ctrl.faults().contains(FaultFlags::WATCHDOG_RESET), "latched");
    ensure!(
        matches!(rig.events.first(), Some(Event::Boot { reason: ResetReason::Watchdog, .. })),
        "Boot event first"
    );
    Ok(())
}

/// A boot whose flash could not store its counter reports it as a fault:
/// the host sees it, motion waits for `ClearFault`.
pub fn storage_failure_at_boot_latches() -> TestResult {
    let mut rig = Rig::with_storage_failure();
    ensure!(rig.ctrl.faults().contains(FaultFlags::STORAGE_FAILED), "latched");
    ensure!(
        rig.events.iter().any(|e| matches!(e, Event::FaultRaised { faults, .. }
            if faults.contains(FaultFlags::STORAGE_FAILED))),
        "reported"
    );
    ensure!(
        rig.request(Request::Home { axes: AxisSet::ALL })
            == Reply::Error(DeviceError::FaultLatched),
        "motion refused"
    );
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    ensure!(rig.home_all(), "then homes");
    Ok(())
}

pub fn config_save_and_reload() -> TestResult {
    let mut rig = Rig::new();
    let mut cfg = default_axes()[2];
    cfg.v_max = 4_000;
    cfg.homing.direction = Direction::Positive;
    ensure!(
        rig.request(Request::SetAxisConfig { axis: Axis::Tilt, config: cfg }) == Reply::Ack,
        "set"
    );
    let pos = MirrorPosition { steps: [1, 2, 3] };
    ensure!(rig.request(Request::SetMirror { mirror: 39, position: pos }) == Reply::Ack, "mirror");
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "save");
    let loaded = PersistedConfig::decode(&rig.hw.saved).ok_or("saved blob decodes")?;
    ensure!(loaded.axes[2] == cfg && loaded.mirrors.len() == 40, "contents");
    ensure!(loaded.mirrors[39] == Some(pos), "mirror entry");
    ensure!(
        PersistedConfig::decode(&rig.hw.saved[..rig.hw.saved.len() - 1]).is_none(),
        "truncated"
    );
    // A format-1 blob (before the board options) still loads.
    let v1 = (1u16, loaded.axes, loaded.mirrors.clone());
    let mut buf = [0u8; crate::config::PERSISTED_MAX_LEN];
    let old = postcard::to_slice(&v1, &mut buf).map_err(|_| "encode v1")?;
    let upgraded = PersistedConfig::decode(old).ok_or("format 1 loads")?;
    ensure!(upgraded.axes == loaded.axes && upgraded.mirrors == loaded.mirrors, "v1 contents");
    ensure!(upgraded.board == protocol::BoardConfig::default(), "default board options");
    ensure!(upgraded.home == protocol::HomeSensors::default(), "default home sensors");
    // So does a format-2 blob (before the home sensors' polarity).
    let board = protocol::BoardConfig { driver_fault_active_high: true };
    let v2 = (2u16, loaded.axes, loaded.mirrors.clone(), board);
    let old = postcard::to_slice(&v2, &mut buf).map_err(|_| "encode v2")?;
    let upgraded = PersistedConfig::decode(old).ok_or("format 2 loads")?;
    ensure!(upgraded.axes == loaded.axes && upgraded.mirrors == loaded.mirrors, "v2 contents");
    ensure!(upgraded.board == board, "v2 board options");
    ensure!(upgraded.home == protocol::HomeSensors::default(), "default home sensors");
    // And a format-3 blob (before the exposure strobe).
    let home = protocol::HomeSensors { active_high: [true, false, true] };
    let v3 = (3u16, loaded.axes, loaded.mirrors.clone(), board, home);
    let old = postcard::to_slice(&v3, &mut buf).map_err(|_| "encode v3")?;
    let upgraded = PersistedConfig::decode(old).ok_or("format 3 loads")?;
    ensure!(upgraded.axes == loaded.axes && upgraded.mirrors == loaded.mirrors, "v3 contents");
    ensure!(upgraded.board == board && upgraded.home == home, "v3 options");
    ensure!(upgraded.strobe == crate::config::strobe_default(), "default strobe");
    // A format this firmware does not know is refused, not misread.
    let v9 = (9u16, loaded.axes, loaded.mirrors.clone(), board, [true; 3]);
    let unknown = postcard::to_slice(&v9, &mut buf).map_err(|_| "encode v9")?;
    ensure!(PersistedConfig::decode(unknown).is_none(), "unknown format");
    Ok(())
}

/// The home / index sensors' polarity follows `HomeSensors`: a sensor whose
/// line is high when actuated cannot home while the axis is set active low
/// (it reads actuated everywhere but at the switch: the back-off never
/// leaves it), homes exactly as a default-wired one once set, and the
/// setting is saved; changing it un-homes the axis, and is refused while
/// anything moves.
pub fn home_sensor_polarity_is_configurable() -> TestResult {
    use protocol::HomeSensors;
    let mut reference = Rig::new();
    ensure!(reference.home_all(), "a default-wired rig homes");
    let mut rig = Rig::new();
    rig.switch_active_high = [false, true, false];
    ensure!(
        rig.request(Request::GetHomeSensors) == Reply::HomeSensors(HomeSensors::default()),
        "default: active low"
    );
    // Away from its switch the track's line is low: read active low, that
    // is actuated; GetInputs shows both.
    let inputs = |rig: &mut Rig| match rig.request(Request::GetInputs) {
        Reply::Inputs(i) => Ok(i),
        _ => Err("GetInputs answers Inputs"),
    };
    // (sampled once, then accepted after the debounce time)
    for _ in 0..2 {
        let later = rig.now + TICKS_PER_MS;
        rig.run_until(later);
    }
    let i = inputs(&mut rig)?;
    ensure!(i.home_line_high == [true, false, true], "line levels");
    ensure!(i.home_actuated == [false, true, false], "the track reads actuated");
    ensure!(!i.estop_open && i.driver_fault_line_high && !i.driver_fault, "the other inputs");
    ensure!(!rig.home_all(), "the track's sensor read the wrong way round");
    ensure!(rig.ctrl.faults().contains(FaultFlags::HOMING_FAILED), "homing failed");
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    let track_high = HomeSensors { active_high: [false, true, false] };
    ensure!(rig.request(Request::SetHomeSensors(track_high)) == Reply::Ack, "set");
    ensure!(rig.request(Request::GetHomeSensors) == Reply::HomeSensors(track_high), "read back");
    let i = inputs(&mut rig)?;
    ensure!(!i.home_line_high[1] && !i.home_actuated[1], "read active high: not actuated");
    // Where the failed homing left it does not matter: from the reference's
    // start, it homes to the same count at the same physical place.
    ensure!(rig.home_all(), "homes once set");
    ensure!(rig.ctrl.faults().is_empty(), "no fault");
    for axis in Axis::ALL {
        let offset = |r: &Rig| r.physical(axis) - r.position(axis) as i64;
        ensure!(offset(&rig) == offset(&reference), "the same home as a default-wired sensor");
    }
    // Out and back: no fault.
    for target in [200_000, 2_000] {
        ensure!(move_to(&mut rig, [None, Some(target), None])? == Reply::Ack, "move");
        rig.run_until_idle(20_000);
        ensure!(rig.position(Axis::Track) == target, "there");
    }
    ensure!(rig.ctrl.faults().is_empty(), "no fault on the way");
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "saved");
    let loaded = PersistedConfig::decode(&rig.hw.saved).ok_or("decodes")?;
    ensure!(loaded.home == track_high, "persisted");
    // Not while moving.
    ensure!(move_to(&mut rig, [None, Some(150_000), None])? == Reply::Ack, "a move");
    ensure!(
        rig.request(Request::SetHomeSensors(HomeSensors::default()))
            == Reply::Error(DeviceError::Busy),
        "busy"
    );
    rig.run_until_idle(10_000);
    // Changed back: the track is no longer homed, the others are.
    ensure!(rig.request(Request::SetHomeSensors(HomeSensors::default())) == Reply::Ack, "reset");
    ensure!(!rig.ctrl.is_homed(Axis::Track), "the track un-homed");
    ensure!(rig.ctrl.is_homed(Axis::Disk) && rig.ctrl.is_homed(Axis::Tilt), "others homed");
    ensure!(rig.ctrl.faults().is_empty(), "no edge, no fault");
    ensure!(
        move_to(&mut rig, [None, Some(10_000), None])? == Reply::Error(DeviceError::NotHomed),
        "no move until homed again"
    );
    Ok(())
}

/// The driver-fault line's polarity follows `BoardConfig`: active low by
/// default (DRV8825 nFAULT), active high when set (TMC2209 DIAG); the
/// setting is saved with the configuration. Changing it reads the line the
/// other way at once: a board whose drivers signal the other way latches a
/// fault at power-on that cannot be cleared, and is rescued by setting the
/// polarity, clearing and saving, with no wait between.
pub fn driver_fault_polarity_is_configurable() -> TestResult {
    use crate::hal::Inputs;
    use protocol::BoardConfig;
    // Hold the fault line at `high` for 2 ms of 200 µs samples.
    fn hold(rig: &mut Rig, high: bool) {
        for _ in 0..10 {
            rig.now += 200 * TICKS_PER_US;
            rig.hw.now = rig.now;
            let inputs = Inputs { driver_fault_line: high, ..rig.inputs() };
            rig.ctrl.poll(rig.now, &inputs, &mut rig.hw);
        }
    }
    let mut rig = Rig::new();
    ensure!(
        rig.request(Request::GetBoardConfig) == Reply::BoardConfig(BoardConfig::default()),
        "default"
    );
    hold(&mut rig, true);
    ensure!(rig.ctrl.faults().is_empty(), "active low: a high line is no fault");
    hold(&mut rig, false);
    ensure!(rig.ctrl.faults().contains(FaultFlags::DRIVER_FAULT), "active low: low is a fault");
    hold(&mut rig, true);
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    let high = BoardConfig { driver_fault_active_high: true };
    // The line stays high: read active high, that is a fault, from the next poll.
    ensure!(rig.request(Request::SetBoardConfig(high)) == Reply::Ack, "set");
    let inputs = Inputs { driver_fault_line: true, ..rig.inputs() };
    rig.ctrl.poll(rig.now, &inputs, &mut rig.hw);
    ensure!(rig.ctrl.faults().contains(FaultFlags::DRIVER_FAULT), "the same level, now a fault");
    hold(&mut rig, false);
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    hold(&mut rig, false);
    ensure!(rig.ctrl.faults().is_empty(), "active high: a low line is no fault");
    hold(&mut rig, true);
    ensure!(rig.ctrl.faults().contains(FaultFlags::DRIVER_FAULT), "active high: high is a fault");
    hold(&mut rig, false);
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "saved");
    let loaded = PersistedConfig::decode(&rig.hw.saved).ok_or("decodes")?;
    ensure!(loaded.board == high, "persisted");
    // A board set active low whose drivers hold the line low when all is
    // well (TMC2209 DIAG): a fault from power-on that cannot be cleared…
    let mut rig = Rig::new();
    hold(&mut rig, false);
    ensure!(rig.ctrl.faults().contains(FaultFlags::DRIVER_FAULT), "wrong way round: a fault");
    ensure!(
        rig.request(Request::ClearFault) == Reply::Error(DeviceError::FaultLatched),
        "the line still reads a fault"
    );
    ensure!(
        rig.request(Request::SaveConfig) == Reply::Error(DeviceError::FaultLatched),
        "nothing saved while it is latched"
    );
    // …until the polarity is set: cleared and saved at once, no poll between.
    ensure!(rig.request(Request::SetBoardConfig(high)) == Reply::Ack, "set");
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared at once");
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "saved");
    hold(&mut rig, false);
    ensure!(rig.ctrl.faults().is_empty(), "and it stays clear");
    // Not while moving.
    ensure!(rig.home_all(), "homing");
    move_to(&mut rig, [None, Some(200_000), None])?;
    ensure!(
        rig.request(Request::SetBoardConfig(BoardConfig::default()))
            == Reply::Error(DeviceError::Busy),
        "busy"
    );
    Ok(())
}

/// `SaveConfig` erases flash, which stalls the step interrupt on the F411:
/// refused (busy) while an axis moves, and (like motion) while a fault is
/// latched; accepted again once idle and cleared.
/// The camera's exposure strobe, once enabled on a board that has the
/// input, is watched after every pulse: an exposure is reported with its
/// delay and length within a 200 µs sample, a camera that ignores its
/// trigger is reported as such once the strobe is overdue, either
/// polarity, and the setting is saved; refused without the input, with a
/// delay bound out of range, or while busy; off, no report.
pub fn exposure_strobe_reports_each_exposure() -> TestResult {
    use crate::testkit::CameraStrobe;
    use protocol::{DEFAULT_STROBE_DELAY_US, MAX_STROBE_DELAY_US, StrobeConfig, StrobeWindow};
    // Poll every 200 µs (the board's input sampling) for `ms`.
    fn sample(rig: &mut Rig, ms: u64) {
        for _ in 0..ms * 5 {
            rig.now += 200 * TICKS_PER_US;
            rig.run_until(rig.now);
        }
    }
    // Fire a bare trigger of `us`, sample for `ms`: the exposure reports.
    fn pulse(rig: &mut Rig, us: u32, ms: u64) -> Result<heapless::Vec<Event, 4>, &'static str> {
        rig.events.clear();
        ensure!(rig.request(Request::Trigger { exposure_us: us }) == Reply::Ack, "trigger");
        sample(rig, ms);
        let mut reports = heapless::Vec::new();
        for e in &rig.events {
            if let Event::Exposure { .. } = e {
                let _ = reports.push(e.clone());
            }
        }
        Ok(reports)
    }
    let on = |active_high| StrobeConfig {
        enabled: true,
        active_high,
        max_delay_us: DEFAULT_STROBE_DELAY_US,
    };
    let mut rig = Rig::new();
    let default = crate::config::strobe_default();
    ensure!(rig.request(Request::GetStrobe) == Reply::Strobe(default), "off by default");
    ensure!(
        rig.request(Request::SetStrobe(on(true))) == Reply::Error(DeviceError::Unsupported),
        "no input, no watch"
    );
    ensure!(rig.request(Request::SetStrobe(default)) == Reply::Ack, "off is always accepted");
    let caps = Capabilities::SIMULATED
        .union(Capabilities::PERSISTENT_CONFIG)
        .union(Capabilities::EXPOSURE_STROBE);
    let mut rig = Rig::with_capabilities(ResetReason::PowerOn, caps);
    for max_delay_us in [0, MAX_STROBE_DELAY_US + 1] {
        let bad = StrobeConfig { max_delay_us, ..on(true) };
        ensure!(
            rig.request(Request::SetStrobe(bad)) == Reply::Error(DeviceError::OutOfRange),
            "delay bound out of range"
        );
    }
    // Not watched yet: no report.
    rig.strobe =
        Some(CameraStrobe { delay: 300 * TICKS_PER_US, active_high: true, ignores: false });
    ensure!(pulse(&mut rig, 5_000, 30)?.is_empty(), "off: no report");
    ensure!(rig.request(Request::SetStrobe(on(true))) == Reply::Ack, "enabled");
    ensure!(rig.request(Request::GetStrobe) == Reply::Strobe(on(true)), "read back");
    for active_high in [true, false] {
        ensure!(rig.request(Request::SetStrobe(on(active_high))) == Reply::Ack, "polarity");
        rig.strobe = Some(CameraStrobe { delay: 300 * TICKS_PER_US, active_high, ignores: false });
        let seq = rig.ctrl.status(&mut rig.hw).trigger_seq + 1;
        let reports = pulse(&mut rig, 5_000, 30)?;
        let [Event::Exposure { trigger_seq, window: Some(w) }] = reports.as_slice() else {
            return Err("one exposure reported");
        };
        let StrobeWindow { delay_us, length_us, ended } = *w;
        ensure!(*trigger_seq == seq && ended, "this pulse's, ended");
        ensure!((300..=500).contains(&delay_us), "the delay, within a sample");
        ensure!(length_us.abs_diff(5_000) <= 200, "the length, within a sample");
        // The camera misses: reported once the strobe is overdue.
        rig.strobe = Some(CameraStrobe { delay: 300 * TICKS_PER_US, active_high, ignores: true });
        let start = rig.now;
        let reports = pulse(&mut rig, 5_000, 30)?;
        ensure!(
            reports.as_slice() == [Event::Exposure { trigger_seq: seq + 1, window: None }],
            "a missed trigger"
        );
        ensure!(rig.now - start >= 15_000 * TICKS_PER_US, "not before the bound");
    }
    // Refused while busy; saved with the configuration.
    ensure!(rig.request(Request::Trigger { exposure_us: 5_000 }) == Reply::Ack, "a pulse");
    ensure!(
        rig.request(Request::SetStrobe(on(true))) == Reply::Error(DeviceError::Busy),
        "busy while exposing"
    );
    sample(&mut rig, 30);
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "saved");
    let loaded = PersistedConfig::decode(&rig.hw.saved).ok_or("decodes")?;
    ensure!(loaded.strobe == on(false), "persisted");
    Ok(())
}

pub fn save_config_refused_while_moving_or_faulted() -> TestResult {
    let mut rig = Rig::new();
    moving_with_light(&mut rig)?;
    ensure!(
        rig.request(Request::SaveConfig) == Reply::Error(DeviceError::Busy),
        "busy while moving"
    );
    ensure!(rig.hw.saved.is_empty(), "nothing written while moving");
    ensure!(rig.request(Request::EmergencyStop) == Reply::Ack, "stopped");
    ensure!(
        rig.request(Request::SaveConfig) == Reply::Error(DeviceError::FaultLatched),
        "refused while faulted"
    );
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    ensure!(rig.request(Request::SaveConfig) == Reply::Ack, "saved when idle");
    ensure!(!rig.hw.saved.is_empty(), "written");
    Ok(())
}

/// With a fault latched, every request that moves, lights, triggers or
/// writes flash is refused with `FaultLatched` (the same answer for all),
/// and nothing moves; queries and `Stop` are still answered.
pub fn every_motion_request_refused_while_faulted() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    let pos = MirrorPosition { steps: [4_000, 120_000, -1_500] };
    ensure!(rig.request(Request::SetMirror { mirror: 1, position: pos }) == Reply::Ack, "set");
    ensure!(rig.request(Request::EmergencyStop) == Reply::Ack, "stop");
    let refused = [
        Request::Home { axes: AxisSet::ALL },
        Request::Move { mode: MoveMode::Absolute, targets: [Some(100), None, None] },
        Request::Move { mode: MoveMode::Relative, targets: [None, Some(10), None] },
        Request::GoToMirror { mirror: 1 },
        Request::CaptureStep(CaptureStep {
            mirror: 1,
            settle_ms: 10,
            exposure_us: 20_000,
            light_duty_permille: 1000,
        }),
        Request::Trigger { exposure_us: 20_000 },
        Request::SetLight(LightState { on: true, duty_permille: 500 }),
        Request::SaveConfig,
    ];
    for r in refused {
        ensure!(rig.request(r) == Reply::Error(DeviceError::FaultLatched), "refused while faulted");
        rig.run_until(rig.now + 10 * TICKS_PER_MS);
        ensure!(!rig.ctrl.is_moving() && rig.hw.armed.iter().all(Option::is_none), "nothing moves");
        ensure!(rig.hw.light == 0 && !rig.hw.trigger, "dark");
        ensure!(rig.hw.saved.is_empty(), "nothing written");
    }
    ensure!(matches!(rig.request(Request::GetStatus), Reply::Status(_)), "status answered");
    ensure!(rig.request(Request::Stop) == Reply::Ack, "stop answered");
    ensure!(rig.request(Request::ClearFault) == Reply::Ack, "cleared");
    let after = rig.request(Request::GoToMirror { mirror: 1 });
    ensure!(after == Reply::Error(DeviceError::NotHomed), "after clearing: homing needed");
    Ok(())
}

/// Frames through `on_bytes`: garbage and a corrupted copy are dropped, the
/// good frame is answered once, a retransmission is re-answered but not
/// re-executed, and events are framed with their own counter.
pub fn link_bytes_corruption_and_duplicates() -> TestResult {
    let mut rig = Rig::new();
    ensure!(rig.home_all(), "homing");
    let mut out: heapless::Vec<u8, 1024> = heapless::Vec::new();
    let mut frame = [0u8; MAX_FRAME_LEN];
    let rel = Request::Move { mode: MoveMode::Relative, targets: [None, Some(800), None] };
    let n = encode_frame(42, &rel, &mut frame).map_err(|_| "encode")?;
    let mut corrupted = [0u8; MAX_FRAME_LEN];
    corrupted[..n].copy_from_slice(&frame[..n]);
    corrupted[2] ^= 0x10;
    let before = rig.position(Axis::Track);
    let mut stream: heapless::Vec<u8, 512> = heapless::Vec::new();
    let _ = stream.extend_from_slice(&[0x13, 0x37, 0xFF, 0x00]); // line noise
    let _ = stream.extend_from_slice(&corrupted[..n]);
    let _ = stream.extend_from_slice(&frame[..n]);
    let _ = stream.extend_from_slice(&frame[..n]); // a retransmission
    // Deliver in awkward chunks.
    for chunk in stream.chunks(5) {
        rig.on_bytes(chunk, &mut |b: &[u8]| {
            let _ = out.extend_from_slice(b);
        });
    }
    rig.run_until_idle(5_000);
    ensure!(rig.position(Axis::Track) - before == 800, "executed exactly once");
    let mut decoder = FrameDecoder::<ToHost>::new();
    let mut replies = 0;
    for f in decoder.feed(&out) {
        let f = f.map_err(|_| "device frames decode")?;
        ensure!(f.seq == 42 && f.msg == ToHost::Reply(Reply::Ack), "Ack for seq 42");
        replies += 1;
    }
    ensure!(replies == 2, "answered the frame and its retransmission, not the corrupted copy");
    // Events go out framed, numbered by the controller's event counter
    // (every event so far was taken by the rig).
    out.clear();
    let counted = rig.events.len() as u8;
    rig.ctrl.log(LogLevel::Warn, "hello");
    rig.ctrl.drain_events(&mut |b: &[u8]| {
        let _ = out.extend_from_slice(b);
    });
    let mut frames = decoder.feed(&out);
    let Some(Ok(f)) = frames.next() else { return Err("one event frame") };
    ensure!(f.seq == counted, "event sequence number counts events");
    let ToHost::Event(Event::Log { level: LogLevel::Warn, text }) = f.msg else {
        return Err("the log event");
    };
    ensure!(text.as_str() == "hello", "log text");
    ensure!(frames.next().is_none(), "nothing else queued");
    // Every device frame starts with a delimiter: noise that hides the end
    // of one event costs that event, not the next one too.
    out.clear();
    rig.ctrl.log(LogLevel::Warn, "first");
    rig.ctrl.log(LogLevel::Warn, "second");
    rig.ctrl.drain_events(&mut |b: &[u8]| {
        let _ = out.extend_from_slice(b);
    });
    ensure!(out.first() == Some(&0), "a device frame starts with a delimiter");
    let end = 1 + out[1..].iter().position(|&b| b == 0).ok_or("the first frame's end")?;
    out[end] = 0x42;
    let mut frames = decoder.feed(&out);
    ensure!(matches!(frames.next(), Some(Err(_))), "the first event is lost");
    let Some(Ok(f)) = frames.next() else { return Err("the second event arrives") };
    let ToHost::Event(Event::Log { text, .. }) = f.msg else { return Err("a log event") };
    ensure!(text.as_str() == "second", "the second event's text");
    ensure!(frames.next().is_none(), "nothing else");
    Ok(())
}

/// A short random operation ([`crate::chaos`]; the PC runs many more in
/// `firmware/tests/chaos.rs`): on the Cortex-M4, the same rules hold with
/// its own integer and float arithmetic.
pub fn random_operation_keeps_the_safety_rules() -> TestResult {
    let mut total = crate::chaos::Report::default();
    // Two runs that home the axes (one sensor wired active high among
    // them) and move them homed.
    for seed in [15, 33] {
        let report = crate::chaos::run(&mut crate::chaos::Seeded::new(seed), 150)
            .map_err(|v| v.rule.describe())?;
        total.add(&report);
    }
    ensure!(total.homings > 0 && total.homed_steps > 100_000, "the runs homed and moved axes");
    ensure!(total.homed_active_high > 0, "a homing at a sensor wired active high");
    Ok(())
}
