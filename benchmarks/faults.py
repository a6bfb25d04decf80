"""Fault matrix: each way the monitor was found silenced, crashed or fooled, the test that reproduces it now,
and whether the monitor survives it.

    python benchmarks/faults.py        # runs the tests below, writes benchmarks/faults.md (about 15 min)

Each row names a fault, what the monitor does about it now, and the tests (in ``tests/``) that reproduce it
against the real code: the monitor process, a real SQLite file, a real Mosquitto where a broker is involved.
The outcome column is what pytest reported in this run. Rows whose handling is not built yet say so.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from report import machine, table  # noqa: E402

HERE = Path(__file__).parent
ROOT = HERE.parent

ROWS = (
    ("a nurse sets 200 mmHg, a dose limit of 5 or a 12 h turn interval",
     "refused outside the safe range, naming the setting, its value and the range; a ward policy bounds nurses",
     ["tests/test_settings.py::test_a_setting_that_would_blind_the_monitor_is_refused_naming_it_its_value_and_its_range",
      "tests/test_settings.py::test_a_configuration_file_outside_the_safe_range_stops_the_monitor_at_start_with_exit_2",
      "tests/test_settings.py::test_only_an_admin_sets_the_ward_policy_and_it_bounds_what_a_nurse_may_set"]),
    ("a change of settings would end an open alarm",
     "the alarm is held until the site is relieved for the relief time",
     ["tests/test_settings.py::test_an_open_pressure_alarm_outlives_a_change_of_settings_until_the_site_is_relieved"]),
    ("an empty-mat reference captured with a light patient on the mat",
     "refused while the mat reads 10 mmHg or more against the present reference",
     ["tests/test_engineering.py::test_capture_reference_refuses_a_light_load_below_the_alert_threshold_and_takes_a_"
      "first_one_as_it_is"]),
    ("an all-zero or flat pressure calibration ends an active alarm",
     "refused as constant, falling or implausible; a calibration reading less holds open alarms",
     ["tests/test_engineering.py::test_an_implausible_calibration_upload_is_refused_naming_what_is_wrong",
      "tests/test_engineering.py::test_an_open_pressure_alarm_outlives_a_calibration_that_reads_less_until_the_site_is_"
      "relieved"]),
    ("two monitors share one data folder",
     "the second exits 2 naming the folder and the holder; after a SIGKILL a new one starts",
     ["tests/test_fault_survival.py::test_a_second_monitor_on_a_folder_exits_2_and_one_after_a_sigkill_starts"]),
    ("a garbled database, configuration, settings or calibration file",
     "refused at start with one line naming the file (exit 2, no restart loop), the file left as found",
     ["tests/test_fault_survival.py::test_a_damaged_store_is_refused_naming_it_and_left_as_found",
      "tests/test_fault_survival.py::test_a_damaged_configuration_settings_or_calibration_file_is_refused_naming_it"]),
    ("a damaged saved alert state or live view",
     "starts afresh under a technical alarm; the screen shows stale, naming the file",
     ["tests/test_fault_survival.py::test_a_damaged_saved_alert_state_starts_afresh_under_a_technical_alarm",
      "tests/test_fault_survival.py::test_a_damaged_live_view_shows_the_screen_stale_naming_the_file"]),
    ("a full disk",
     "records held in memory in order (bounded, counted) under a technical alarm, written when there is room",
     ["tests/test_fault_survival.py::test_a_full_disk_is_a_technical_alarm_and_every_record_is_written_once_it_has_"
      "room",
      "tests/test_fault_survival.py::test_what_a_full_disk_holds_is_bounded_and_what_is_dropped_is_counted"]),
    ("the live-view writer (or a notifier) thread dies on an error",
     "supervised: a technical alarm, restarted with a back-off",
     ["tests/test_fault_survival.py::test_a_failing_helper_thread_is_a_technical_alarm_and_is_restarted"]),
    ("the wall clock is set back",
     "frame times on the monotonic clock, the step recorded; the stale banner and the ward's silent-bed test hold",
     ["tests/test_fault_survival.py::test_the_board_monitor_carries_on_over_a_wall_clock_step_back_and_logs_it",
      "tests/test_fault_survival.py::test_the_screen_goes_stale_when_the_monitor_stops_even_if_the_clock_was_set_back",
      "tests/test_fault_survival.py::test_the_ward_station_judges_a_bed_silent_on_the_monotonic_clock"]),
    ("SIGKILL at 20 random moments",
     "no alarm, dose, turn or episode lost or repeated",
     ["tests/test_crash_recovery.py::test_sigkill_at_20_random_moments_loses_and_repeats_nothing"]),
    ("the broker is down (or restarts, losing what it acknowledged) while alarms are raised",
     "each change kept in the bed's durable outbox under its number and resent until the ward station confirms "
     "it; the bed raises technical:ward-link after 10 s and shows each alarm 'at this bed only'",
     ["tests/test_ward_link.py::test_a_broker_restart_that_loses_what_it_acknowledged_loses_no_alarm",
      "tests/test_ward_link.py::test_the_link_down_and_unconfirmed_changes_are_technical_alarms_that_clear",
      "tests/test_ward_link.py::test_the_monitor_raises_a_technical_alarm_while_the_ward_is_not_hearing_it_and_"
      "shows_each_alarms_delivery",
      "tests/test_ward_delivery.py::test_no_alarm_is_lost_to_the_ward_across_20_sigkills_and_a_broker_outage"]),
    ("the monitor is killed between numbering an alarm change and sending it, or during a disk failure",
     "the outbox keeps the number (an event handed in again keeps its first); a restart never reuses one",
     ["tests/test_ward_link.py::test_numbers_grow_by_one_survive_a_restart_and_an_event_handed_in_again_keeps_its_"
      "number",
      "tests/test_ward_link.py::test_a_crash_during_a_disk_failure_never_reuses_a_number",
      "tests/test_ward_link.py::test_close_does_not_wait_for_confirmations_and_the_next_start_resends"]),
    ("any client publishes a bed's summary ('all quiet') or confirms its alarms",
     "per-bed broker logins and an ACL from `appliance ward-broker`: a bed writes only its own topics, only a "
     "station confirms",
     ["tests/test_ward_broker.py::test_a_bed_cannot_hide_another_beds_alarms_with_a_spoofed_summary",
      "tests/test_ward_broker.py::test_a_bed_reads_only_its_own_confirmations_and_cannot_write_them",
      "tests/test_ward_broker.py::test_the_station_confirms_to_a_bed_but_cannot_publish_as_one",
      "tests/test_ward_broker.py::test_a_bed_and_the_station_log_in_with_their_generated_passwords_and_others_are_"
      "refused"]),
    ("failed logins with user names of any length",
     "names over 64 characters refused before hashing; every audit entry bounded",
     ["tests/test_web_hardening.py::test_an_over_long_user_name_is_refused_at_once_and_logged_cut_short",
      "tests/test_web_hardening.py::test_every_audit_entry_is_bounded"]),
    ("48 live streams or 100 idle connections exhaust the screen",
     "streams bounded (503 + Retry-After), idle connections cost no thread (benchmarks/web_load.md)",
     ["tests/test_web_hardening.py::test_open_streams_leave_the_server_threads_for_pages",
      "tests/test_web_hardening.py::test_a_hundred_and_fifty_idle_connections_do_not_shut_out_a_browser"]),
    ("a login redirects off-site; sessions outlive logout or a new password",
     "local paths only; server-side sessions ended on logout, password change or reset",
     ["tests/test_web_hardening.py::test_a_login_never_sends_the_browser_off_site",
      "tests/test_web_hardening.py::test_a_copied_cookie_stops_working_at_logout_but_other_sessions_of_the_user_go_on",
      "tests/test_web_hardening.py::test_a_changed_password_ends_every_other_session_of_the_user"]),
    ("weak passwords; five failures lock every account from an address",
     "a password policy; limits per account and address that never lock the bedside screen",
     ["tests/test_web_hardening.py::test_weak_passwords_are_refused_everywhere_with_the_reason",
      "tests/test_web_hardening.py::test_failures_from_one_address_lock_that_account_there_not_others_nor_other_"
      "addresses",
      "tests/test_web_hardening.py::test_guesses_from_many_addresses_lock_the_account_but_never_on_the_bedside_"
      "screen"]),
    ("no CSP, X-Frame-Options or nosniff; a world-readable audit database",
     "the headers on every response; accounts database and key 0600",
     ["tests/test_web_hardening.py::test_every_kind_of_response_carries_the_security_headers",
      "tests/test_web_hardening.py::test_the_accounts_database_and_the_session_key_are_made_owner_only"]),
    ("bad input on the command line and the forms (24 tracebacks, 16 silent acceptances of 277)",
     "a table of 374 cases (313 commands, every number bounded; 61 forms): exit 2 or a 4xx naming what is wrong",
     ["tests/test_bad_input.py"]),
)


def outcomes(node_ids: list[str]) -> dict[str, str]:
    """pytest's outcome of every test case under each node id ("passed", "failed", "skipped", "error")."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.xml"
        subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}",
                        *node_ids], cwd=ROOT, check=False)
        cases = ET.parse(report).getroot().iter("testcase")
        out = {}
        for case in cases:
            name = f"{case.get('classname').replace('.', '/')}.py::{case.get('name')}"
            kinds = [child.tag for child in case]
            out[name] = ("failed" if "failure" in kinds else "error" if "error" in kinds
                         else "skipped" if "skipped" in kinds else "passed")
        return out


def verdict(node_ids: list[str], results: dict[str, str]) -> str:
    """How the cases under ``node_ids`` went: "passed (n)" or the counts of each outcome."""
    if not node_ids:
        return "not built"
    def under(name: str, node_id: str) -> bool:
        return name.split("[")[0] == node_id if "::" in node_id else name.startswith(node_id + "::")

    got = [r for name, r in results.items() if any(under(name, n) for n in node_ids)]
    counts = {k: got.count(k) for k in ("passed", "failed", "error", "skipped") if got.count(k)}
    return ", ".join(f"{k} {v}" for k, v in counts.items()) or "not run"


def main() -> None:
    node_ids = [n for *_, ids in ROWS for n in ids]
    results = outcomes(node_ids)
    rows = [[fault, now, "<br>".join(f"`{n.split('::')[-1] if '::' in n else n}`" for n in ids) or "-",
             verdict(ids, results)] for fault, now, ids in ROWS]
    report = f"""# Fault matrix: silenced, crashed or fooled, and what the monitor does now

Made by `python benchmarks/faults.py` on {machine()}.
Each test runs the real code: the monitor process or its daemon, a real SQLite file, a real Mosquitto for the
broker rows; a full disk is injected (a store whose writes fail, and SQLite's page limit: no file system can be
mounted here), a clock step by an injected clock.

{table(["fault", "what the monitor does now", "tests", "outcome"], rows)}
"""
    (HERE / "faults.md").write_text(report, encoding="utf-8")
    print(report)


if __name__ == "__main__":
    main()
