//! The controller's self-test suite (`firmware::selftest`), one `#[test]` per
//! case. The same functions run on a Cortex-M4 under QEMU in CI.

macro_rules! selftests {
    ($($name:ident),* $(,)?) => {
        $(
            #[test]
            fn $name() {
                firmware::selftest::$name().unwrap_or_else(|e| panic!("{}: {e}", stringify!($name)));
            }
        )*

        #[test]
        fn every_selftest_is_listed_here() {
            let listed = [$(stringify!($name)),*];
            for (name, _) in firmware::selftest::TESTS {
                assert!(listed.contains(name), "{name} is not run on the host");
            }
            assert_eq!(listed.len(), firmware::selftest::TESTS.len());
        }
    };
}

selftests!(
    planner_step_times_within_one_tick,
    step_times_exact_near_2_32_and_2_40_ticks,
    step_timer_loses_no_step_and_fires_none_early,
    planner_respects_speed_and_acceleration,
    planner_stop_profile,
    concurrent_move_reaches_targets,
    controlled_stop_decelerates,
    stop_while_stopping_changes_nothing,
    homing_deadline_only_while_searching,
    homing_all_axes,
    homing_starting_on_switch_backs_off,
    homing_switch_not_found,
    homing_switch_stuck,
    homing_timeout,
    disk_takes_shortest_way,
    capture_step_sequence,
    bare_trigger,
    trigger_pulse_exact_on_the_timer_model,
    hardware_trigger_pulse_keeps_the_light_on,
    light_margin_around_the_pulse,
    dispatcher_errors,
    duplicate_sequence_not_reexecuted,
    handshake_required_and_versions,
    estop_input_latches,
    driver_fault_latches,
    emergency_stop_request,
    unexpected_home_switch,
    lost_steps_caught_at_the_index_flag,
    homing_when_homed_checks_the_count,
    link_silence_while_moving,
    watchdog_boot_latches,
    storage_failure_at_boot_latches,
    config_save_and_reload,
    driver_fault_polarity_is_configurable,
    exposure_strobe_reports_each_exposure,
    enter_bootloader_stops_everything_first,
    home_sensor_polarity_is_configurable,
    save_config_refused_while_moving_or_faulted,
    every_motion_request_refused_while_faulted,
    link_bytes_corruption_and_duplicates,
    random_operation_keeps_the_safety_rules,
);
