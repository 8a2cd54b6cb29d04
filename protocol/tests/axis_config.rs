//! The one rule for axis configurations a controller executes.

use protocol::{AxisConfig, AxisConfigProblem as P, MAX_AXIS_SPEED, default_axes};

#[test]
fn the_defaults_are_executable() {
    for c in default_axes() {
        assert_eq!(c.problem(), None, "{c:?}");
    }
}

#[test]
fn each_rule_is_named() {
    let track = default_axes()[1];
    let disk = default_axes()[0];
    let cases: [(AxisConfig, P); 11] = [
        (AxisConfig { steps_per_unit: f32::NAN, ..track }, P::StepsPerUnit),
        (AxisConfig { steps_per_unit: -1.0, ..track }, P::StepsPerUnit),
        (AxisConfig { v_max: MAX_AXIS_SPEED + 1, ..track }, P::MaxSpeed),
        (AxisConfig { a_max: 9, ..track }, P::MaxAcceleration),
        (AxisConfig { v_max: 1_000, ..track }, P::FastSpeed),
        (
            AxisConfig {
                homing: protocol::HomingConfig { slow_speed: 5, ..track.homing },
                ..track
            },
            P::SlowSpeed,
        ),
        (
            AxisConfig {
                homing: protocol::HomingConfig { backoff_steps: 0, ..track.homing },
                ..track
            },
            P::Backoff,
        ),
        (
            AxisConfig {
                homing: protocol::HomingConfig { max_travel_steps: 3_200, ..track.homing },
                ..track
            },
            P::MaxTravel,
        ),
        (
            AxisConfig {
                homing: protocol::HomingConfig { timeout_ms: 0, ..track.homing },
                ..track
            },
            P::Timeout,
        ),
        (AxisConfig { steps_per_rev: 0, ..disk }, P::StepsPerRev),
        (AxisConfig { min_steps: 320_000, ..track }, P::Limits),
    ];
    for (c, p) in cases {
        assert_eq!(c.problem(), Some(p), "{c:?}");
    }
    // A continuous axis has no limits to order.
    assert_eq!(AxisConfig { min_steps: 1, max_steps: 0, ..disk }.problem(), None);
}
