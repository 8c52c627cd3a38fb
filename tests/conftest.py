"""Shared pytest fixtures. Test helpers that users may also want live in the packages
(e.g. ``sim_backend.testing``); this file only wires them into pytest."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis.database import DirectoryBasedExampleDatabase

# Headless plotting everywhere in the test suite.
os.environ.setdefault("MPLBACKEND", "Agg")

# Hypothesis profiles, chosen by HYPOTHESIS_PROFILE (default "ci"):
# - "ci" (`make test`, .ci/run): derandomised, so the same commit gives the same answer every
#   time (each test's examples come from a seed fixed by the test's name); no example database
#   (nothing carried from run to run); no deadline and no too_slow health check (a loaded
#   2-core machine); tests without their own max_examples draw 50.
# - "fuzz" (`make fuzz`): random exploration, FUZZ_FACTOR x each test's max_examples (at least
#   FUZZ_MIN), failures kept in .hypothesis/examples (replayed first by the next run) and printed
#   with a @reproduce_failure blob.
FUZZ_FACTOR = int(os.environ.get("HYPOTHESIS_FUZZ_FACTOR", "20"))
FUZZ_MIN = int(os.environ.get("HYPOTHESIS_FUZZ_MIN", "500"))
settings.register_profile("ci", derandomize=True, database=None, deadline=None, max_examples=50,
                          suppress_health_check=[HealthCheck.too_slow], print_blob=True)
settings.register_profile("fuzz", derandomize=False, deadline=None, max_examples=FUZZ_MIN, print_blob=True,
                          database=DirectoryBasedExampleDatabase(
                              str(Path(__file__).resolve().parent.parent / ".hypothesis" / "examples")),
                          suppress_health_check=[HealthCheck.too_slow])
HYPOTHESIS_PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
settings.load_profile(HYPOTHESIS_PROFILE)


def _scale_for_fuzzing(item) -> None:
    """Fuzz profile: a test's own ``@settings(max_examples=N)`` beats the profile, so scale it
    here (FUZZ_FACTOR x N, at least FUZZ_MIN). Hypothesis reads a test's settings when the test
    runs, from the attribute its ``@given`` wrapper keeps them in."""
    fn = getattr(item, "obj", None)
    fn = getattr(fn, "__func__", fn)
    own = getattr(fn, "_hypothesis_internal_use_settings", None)
    if own is not None:
        fn._hypothesis_internal_use_settings = settings(
            own, max_examples=max(own.max_examples * FUZZ_FACTOR, FUZZ_MIN))


# Whole files of end-to-end tests (subprocesses, the demo, real zenoh sessions and processes,
# vendor clients and simulators on ptys, hardware-in-the-loop with the simulator): marked `slow`,
# so that `make test-fast` (pytest -m "not slow") stays an inner loop. Single slow tests elsewhere
# are listed in SLOW_TESTS (or carry @pytest.mark.slow themselves).
SLOW_FILES = frozenset({
    "test_demo.py", "test_drift_scenario.py", "test_examples.py", "test_fuzz_files.py", "test_hil.py",
    "test_hil_live_tip.py", "test_sim_cli.py", "test_sim_zenoh.py",
    "test_vendor_clients.py", "test_view_feed.py", "test_zenoh_bridge.py", "test_zenoh_config.py",
    "test_zenoh_e2e.py", "test_zenoh_process.py", "test_zenoh_run_process.py",
})


# Single tests that took about 0.3 s or more on the shared 2-core machine (pytest --durations=0, all
# parametrisations summed): identifications on long records, property searches and fuzzing,
# subprocesses, plots, wall-time and reconnect waits. What stays fast: codecs, operators (block
# equals step), config, the safety layer, the loop in-process, CLI offline basics, architecture.
# The figure for the fast set is in docs/ARCHITECTURE.md ("Working on afmctl").
SLOW_TESTS = frozenset({
    "test_measured.py::test_auto_scores_and_fits_only_what_was_measured",
    "test_lag.py::test_the_loop_advances_the_setpoints_by_the_paths_ticks",
    "test_wave_run.py::test_can_fifo_plays_the_table_on_its_clock_through_host_stalls",
    "test_wave_run.py::test_estop_flushes_the_fifo_and_ramps_within_the_slew_limit",
    "test_wave_run.py::test_gcs_wave_generator_plays_the_table_on_the_servo_clock",
    "test_wave_run.py::test_afmctl_run_refuses_what_a_wave_cannot_play",
    "test_wave_run.py::test_afmctl_run_plays_a_raster_as_a_gcs_wave",
    "test_wave_run.py::test_nv200_waveform_buffer_plays_the_table",
    "test_wave_run.py::test_a_stop_during_the_upload_starts_nothing",
    "test_wave_run.py::test_an_axis_the_scanner_does_not_drive_keeps_its_output",
    "test_wave_run.py::test_no_target_makes_a_table_beyond_the_limits_or_the_slew",
    "test_amp_cli.py::test_stream_keeps_the_time_column",
    "test_amp_cli.py::test_stream_three_axes_in_order_and_reports_the_rate",
    "test_amp_cli.py::test_stream_warns_when_the_rate_is_not_reached",
    "test_amplifier_contract.py::test_host_limits_narrow_the_device_range_and_refuse_before_sending",
    "test_amplifier_contract.py::test_reconnect_after_the_device_disappears_and_returns",
    "test_amplifier_contract.py::test_reconnect_gives_up_with_a_connection_error",
    "test_amplifier_contract.py::test_timeout_when_the_device_goes_silent",
    "test_architecture.py::test_known_exception_lists_are_still_needed",
    "test_chain.py::test_chain_block_equals_step_and_round_trips",
    "test_chain.py::test_identify_auto_picks_a_creep_chain_and_beats_static_preisach",
    "test_chain.py::test_identify_chain_bad_input_is_one_line",
    "test_chain.py::test_run_says_which_model_drives_which_axis",
    "test_cli_offline.py::test_bad_data_files",
    "test_cli_offline.py::test_bad_model_files",
    "test_cli_offline.py::test_identify_epi_and_creep_then_compensate",
    "test_cli_offline.py::test_param_option_passed_to_identify",
    "test_cli_offline.py::test_real_subprocess_bad_and_good",
    "test_cli_offline.py::test_wrong_kind_for_invert_and_other_errors",
    "test_cli_skeleton.py::test_version_runs_as_module",
    "test_compensator_contract.py::test_bouc_wen_huge_steps_and_stiff_models_stay_finite",
    "test_drift_kalman_loop.py::test_huge_measured_drift_cannot_push_voltages_out",
    "test_drift_kalman_loop.py::test_loop_estimate_model_then_measurement",
    "test_drift_measure.py::test_drift_measure_recovers_known_shifts",
    "test_drift_watch.py::test_frames_feed_the_kalman_filter_while_running",
    "test_driver_limits.py::test_max_step_holds_between_concurrent_callers",
    "test_driver_limits.py::test_no_value_outside_the_limits_leaves_the_driver",
    "test_driver_robustness.py::test_any_reply_gives_an_amplifier_error_or_a_sane_connection",
    "test_driver_robustness.py::test_concurrent_callers_are_serialised",
    "test_driver_robustness.py::test_misbehaving_devices_give_a_clear_error_fast",
    "test_dynamics.py::test_any_block_split_gives_the_same_numbers",
    "test_dynamics.py::test_identify_recovers_a_known_model",
    "test_dynamics.py::test_zoh_discretisation_matches_continuous_simulation",
    "test_dynamics_sim.py::test_compensate_with_dynamics_beats_static_alone_at_speed",
    "test_dynamics_sim.py::test_excite_writes_playable_voltages_within_range_and_slew",
    "test_dynamics_sim.py::test_identified_frf_matches_the_simulators_true_one",
    "test_dynamics_sim.py::test_limited_inverse_never_exceeds_range_or_slew_and_reports",
    "test_epi.py::test_epi_halves_the_dwell_error_of_pi_on_a_creeping_plant",
    "test_error_holes.py::test_report_names_its_quantities_and_shows_the_tracking_error_when_known",
    "test_identify_artefacts.py::test_absolute_offset_is_fitted",
    "test_identify_artefacts.py::test_bom_csv_is_accepted",
    "test_identify_artefacts.py::test_control_voltage_range_0_to_10_V",
    "test_identify_artefacts.py::test_creep_with_holds_is_seen_and_not_taken_for_a_delay",
    "test_identify_artefacts.py::test_delay_is_estimated_and_stored",
    "test_identify_artefacts.py::test_excitation_check_names_what_is_missing",
    "test_identify_artefacts.py::test_mid_scale_start_fit_and_residuals_not_distorted",
    "test_identify_artefacts.py::test_non_uniform_sampling",
    "test_identify_artefacts.py::test_spikes_are_removed",
    "test_identify_artefacts.py::test_units_kV_and_um_are_refused_with_the_allowed_range",
    "test_identify_artefacts.py::test_validate_reports_without_start_distortion_and_offset",
    "test_image_identify.py::test_compensated_grating_period_is_uniform",
    "test_image_identify.py::test_image_identification_matches_true_position_identification",
    "test_imaging.py::test_compensator_mapping_and_callable_and_png",
    "test_loop.py::test_drift_correction_and_temperature",
    "test_loop.py::test_fault_holds_reconnects_and_resumes_from_readback",
    "test_loop.py::test_temperature_from_file",
    "test_messages.py::test_fuzzed_trajectories_raise_only_message_error",
    "test_phase_corr.py::test_sub_pixel_on_non_periodic_windows",
    "test_pi_identify.py::test_pi_feedforward_beats_best_linear_scaling_3x_on_preisach_plant",
    "test_plant.py::test_extra_modes_in_series_match_the_linear_response_and_blocks",
    "test_preisach_cli.py::test_bad_options_are_one_line_errors",
    "test_preisach_cli.py::test_identify_and_compensate_preisach",
    "test_preisach_cli.py::test_identify_bouc_wen",
    "test_preisach_identify.py::test_feedforward_on_asymmetric_relay_plant_beats_pi",
    "test_preisach_identify.py::test_nnls_identification_reproduces_a_finer_plant",
    "test_realdata.py::test_pi_identified_on_ident_predicts_validate_within_120_nm",
    "test_report.py::test_report_default_out_dir",
    "test_report.py::test_report_writes_plots_and_summary",
    "test_run_cli_errors.py::test_missing_trajectory_file_through_a_real_process",
    "test_runlog.py::test_kill_9_keeps_every_flushed_record",
    "test_runlog.py::test_killed_run_log_is_not_reported_complete",
    "test_runlog.py::test_reader_stops_at_first_torn_or_corrupt_chunk",
    "test_runlog_errors.py::test_afmctl_run_exits_3_when_the_run_log_directory_vanishes",
    "test_runlog_errors.py::test_disk_full_stops_the_run_and_keeps_the_records",
    "test_runlog_errors.py::test_vanished_directory_stops_the_run_and_copies_the_records_back",
    "test_safety.py::test_controller_fuzz_never_emits_unsafe_voltage",
    "test_safety.py::test_faults_reconnects_stops_and_readbacks_never_make_an_unsafe_step",
    "test_safety.py::test_loop_catching_up_after_a_stall_keeps_the_slew_rate",
    "test_safety.py::test_slew_limit_holds_per_wall_time_between_sends",
    "test_scan_files.py::test_identify_from_image_files_equals_npz",
    "test_sim_amplifiers.py::test_mdt_is_no_faster_than_115200_baud",
    "test_trajectories.py::test_smooth_move_respects_limits",
    "test_recorders.py::test_gcs_driver_records_position_and_voltage_aligned_with_the_wave",
    "test_recorders.py::test_nv200_driver_records_position_and_voltage_started_by_the_waveform_generator",
    "test_recorders.py::test_can_driver_records_the_stream_from_its_first_played_sample",
    "test_amp_cli.py::test_wave_record_writes_the_measured_motion_as_a_motion_file",
    "test_recorders.py::test_sim_gcs_recorder_options_commanded_actual_and_error_from_the_sensor",
    "test_stop_bound.py::test_stop_in_ramp_run_and_finish",
    "test_stop_bound.py::test_close_ends_every_thread_from_every_phase",
    "test_stop_bound.py::test_issue_22_example_inside_the_limits_resumes_into_settle_and_ends",
    "test_stop_bound.py::test_close_reports_a_driver_call_that_does_not_return",
    "test_hypothesis_profiles.py::test_ci_profile_draws_the_same_examples_every_run_and_fuzz_does_not",
})


# The longest files, longest first (pytest --durations=0 on a quiet 2-core machine, seconds in
# one process): `make test` runs the suite on two workers with `--dist loadfile` (a file's
# tests on one worker, so its module fixtures are built once), and starting these first keeps
# one long file from running alone at the end while the other worker idles.
# test_doc_blocks.py (the documents' shell blocks) is mostly waiting on simulated devices' clocks:
# 8-9 min of wall time and under 3 min of CPU at load 12-18 (2026-11-28), so it starts first.
LONG_FILES = ("test_doc_blocks.py", "test_unseen_plant.py", "test_demo.py", "test_vendor_clients.py",  # ? 120+ 80 70
              "test_calibrate.py", "test_soak.py",
              "test_view_live.py", "test_lab_router.py", "test_wave_run.py", "test_image_dynamics.py", "test_chain.py",  # 40 34 24 15
              "test_learn_device.py", "test_hil.py", "test_dynamics_sim.py", "test_dynamics_source.py",
              "test_fit_health.py", "test_realdata.py", "test_realdata_splits.py")


def _long_files_first(items: list) -> None:
    rank = {name: k for k, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))   # stable: order within a file kept


def pytest_collection_modifyitems(config, items):
    _long_files_first(items)
    for item in items:
        name = f"{item.path.name}::{item.originalname}"
        if item.path.name in SLOW_FILES or name in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
        if HYPOTHESIS_PROFILE == "fuzz":
            _scale_for_fuzzing(item)


def pytest_report_header(config):
    return f"hypothesis profile: {HYPOTHESIS_PROFILE} (HYPOTHESIS_PROFILE=ci|fuzz; tests/conftest.py)"


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    """Keep each phase's report on the item (``item.rep_call``): the leak check below needs
    to know whether the test itself failed."""
    outcome = yield
    rep = outcome.get_result()
    setattr(item, "rep_" + rep.when, rep)


@pytest.fixture
def no_leaked_threads(request):
    """After the test: every ``afmctl-`` thread (controller loop, dispatcher, feeder,
    reconnect, run log, zenoh bridge) must have ended. What leaked is stopped (running
    controllers closed: stop, then estop; threads joined) before anything is reported, so
    that a leak cannot starve the tests after it; then a test that passed fails on the leak
    (a teardown error), and a test that already failed is not failed twice (the leak is
    added to its report). Use with ``pytestmark = pytest.mark.usefixtures("no_leaked_threads")``."""
    yield
    from afmctl.testing import stop_leaked_threads
    leaked, survivors = stop_leaked_threads("afmctl-")
    if not leaked:
        return
    msg = (f"threads left running: {leaked}; "
           + (f"still running after stopping them: {survivors}" if survivors else "stopped them"))
    rep = getattr(request.node, "rep_call", None)
    if rep is not None and rep.failed:
        request.node.add_report_section("teardown", "leaked threads", msg)
        return
    pytest.fail(msg, pytrace=False)


@pytest.fixture
def chain_file(tmp_path):
    """A pi+dynamics chain model file (1 kHz mode, ζ 0.03; real pole 3 kHz), 50 nm/V, 0..150 V:
    a compensator with a preview horizon for loop and wave tests."""
    from afmctl.compensators.chain import ChainModel
    from afmctl.compensators.dynamics import LinearDynamicsModel
    from afmctl.compensators.models import save_model
    from afmctl.compensators.pi import PIModel
    pi = PIModel(thresholds=[0.0, 20.0, 50.0], weights=[40.0, 6.0, 4.0], initial_state=[0.0] * 3)
    dyn = LinearDynamicsModel.from_modes([(1000.0, 0.03)], real_poles_Hz=[3000.0])
    path = tmp_path / "x_chain.json"
    save_model(ChainModel(hysteresis=pi, dynamics=dyn), path)
    return path
