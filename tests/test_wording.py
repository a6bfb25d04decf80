"""Alarm keys and setting values in a nurse's words."""

import pytest

from appliance.alerts.anatomy import SITES
from appliance.alerts.wording import SETTING_WORDS, TECHNICAL_WORDS, alarm_words, setting_words
from appliance.alerts.dose import BUILT_IN, RECOVERY_MODES


@pytest.mark.parametrize(("key", "words"), [
    ("pressure:sacrum", "Pressure at the sacrum"), ("pressure:heel-left:3", "Pressure at the left heel"),
    ("pressure:unidentified", "Pressure at the unidentified loaded spot"),
    ("turn:due", "Turn due"), ("turn:overdue:2", "Turn overdue"), ("bed-exit", "Out of bed"),
    ("technical:electrode:5", "Equipment: electrode 5"), ("technical:ward-link", "Equipment: link to the ward station"),
    ("technical:notifier:webhook", "Equipment: notification webhook"), (None, ""), ("", ""),
])
def test_each_kind_of_alarm_key_reads_in_words(key, words):
    assert alarm_words(key) == words


def test_every_site_and_technical_part_has_words_without_the_key_s_punctuation():
    for site in SITES:
        assert ":" not in alarm_words(f"pressure:{site}:1") and "-" not in alarm_words(f"pressure:{site}")
    for part in TECHNICAL_WORDS:
        assert ":" not in alarm_words(f"technical:{part}").removeprefix("Equipment:")


def test_every_built_in_choice_is_named_by_its_source_or_in_words():
    assert set(BUILT_IN) | set(RECOVERY_MODES) <= set(SETTING_WORDS)
    assert setting_words("reswick-rogers") == "Reswick and Rogers (1976)"
    assert setting_words(32) == "32" and setting_words("a ward curve") == "a ward curve"
