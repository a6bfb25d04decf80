"""The configured time zone: checked by name, the system's by default, and daylight-saving changes read right."""

from datetime import UTC, datetime

import pytest

from appliance import time_zones
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping
from appliance.service.settings import check_settings
from appliance.time_zones import clock_text, system_zone, time_zone

LONDON = time_zone("Europe/London")


def utc(*fields) -> float:
    return datetime(*fields, tzinfo=UTC).timestamp()


def test_the_spring_change_skips_an_hour_and_the_autumn_change_repeats_one_told_apart_by_the_zone():
    # Europe/London: 29 March 2026 01:00 UTC clocks go forward to 02:00 BST; 25 October 2026 01:00 UTC back to GMT.
    assert [clock_text(utc(2026, 3, 29, h, 30), LONDON) for h in (0, 1, 2)] == [
        "2026-03-29 00:30:00 GMT", "2026-03-29 02:30:00 BST", "2026-03-29 03:30:00 BST"]
    assert [clock_text(utc(2026, 10, 25, h, 30), LONDON) for h in (0, 1, 2)] == [
        "2026-10-25 01:30:00 BST", "2026-10-25 01:30:00 GMT", "2026-10-25 02:30:00 GMT"]
    new_york = time_zone("America/New_York")          # its own change, a week later: 1 November 2026, 06:00 UTC
    assert clock_text(utc(2026, 10, 25, 12, 0), new_york) == "2026-10-25 08:00:00 EDT"
    assert clock_text(utc(2026, 11, 1, 12, 0), new_york) == "2026-11-01 07:00:00 EST"


def test_a_simulated_beds_seconds_stay_seconds_since_its_start():
    assert clock_text(3725.0, LONDON) == "1:02:05"


@pytest.mark.parametrize("name", ["Mars/Base", "Europe/Londn", "../etc/passwd", "/usr/share/zoneinfo/UTC", "", 5])
def test_an_unknown_zone_is_refused_by_name_in_the_configuration_and_the_settings(name):
    with pytest.raises(ConfigError, match=r"\[monitor\] time_zone: (unknown time zone|a time zone is named)") as made:
        config_from_mapping({"monitor": {"time_zone": name}})
    assert repr(name) in str(made.value)
    with pytest.raises(ConfigError, match=r"\[monitor\] time_zone"):
        check_settings({"monitor": {"time_zone": name}})


def test_the_configured_zone_is_kept_and_the_default_is_the_systems(monkeypatch):
    assert config_from_mapping({"monitor": {"time_zone": "Europe/London"}}).time_zone == "Europe/London"
    monkeypatch.setenv("TZ", ":Australia/Adelaide")
    assert config_from_mapping({}).time_zone == system_zone() == "Australia/Adelaide"


def test_the_system_zone_is_read_from_the_localtime_link_then_debians_file_then_utc(monkeypatch, tmp_path):
    monkeypatch.delenv("TZ", raising=False)
    link, named = tmp_path / "localtime", tmp_path / "timezone"
    link.symlink_to("/usr/share/zoneinfo/Asia/Kolkata")
    monkeypatch.setattr(time_zones, "LOCALTIME", link)
    monkeypatch.setattr(time_zones, "TIMEZONE_FILE", named)
    assert system_zone() == "Asia/Kolkata"
    link.unlink()
    link.write_bytes(b"TZif")                              # a copied file names no zone
    named.write_text("Europe/Berlin\n")
    assert system_zone() == "Europe/Berlin"
    named.write_text("Not/AZone\n")
    assert system_zone() == "UTC"
