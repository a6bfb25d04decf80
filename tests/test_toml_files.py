"""The one TOML writer: every value the layouts, settings and provisioning write reads back equal."""

import dataclasses
import math
import re
import tomllib

import pytest

from appliance.core.layout_files import layout_from_mapping, layout_to_toml
from appliance.core.named_layouts import get_layout
from appliance.core.toml_files import toml_value
from appliance.service.settings import read_settings, settings_text

VALUES = {
    "plain": "ward3-bed12",
    "quotes": 'say "hello"',
    "backslashes": "C:\\data\\new",
    "lines": "one\ntwo\r\nthree\tfour",
    "controls": "\x00\x1f\x7f",
    "unicode": "Décubitus, 褥瘡, \u2028",
    "empty": "",
    "int": -42,
    "big": 2**62,
    "float": 0.1,
    "tiny": 1e-07,
    "huge": 1.5e300,
    "negative_zero": -0.0,
    "whole_float": 2.0,
    "infinite": math.inf,
    "negative_infinite": -math.inf,
    "true": True,
    "false": False,
    "list": [1, 2.5, "x\"y", False],
    "nested": [[1, 2], [], ["a"]],
    "tuple": (0.25, 0.5),
}


def test_every_value_reads_back_equal():
    text = "".join(f"{key} = {toml_value(value)}\n" for key, value in VALUES.items())
    back = tomllib.loads(text)
    expected = {key: list(v) if isinstance(v, tuple) else v for key, v in VALUES.items()}
    assert back == expected
    assert [type(back[k]) for k in ("int", "float", "whole_float", "true")] == [int, float, float, bool]
    assert math.copysign(1.0, back["negative_zero"]) == -1.0


def test_nan_reads_back_as_nan():
    assert math.isnan(tomllib.loads(f"x = {toml_value(math.nan)}")["x"])


@pytest.mark.parametrize("value", [None, {"a": 1}, {1, 2}, b"bytes"])
def test_a_value_toml_cannot_hold_here_is_refused_naming_it(value):
    with pytest.raises(TypeError, match=re.escape(f"got {value!r}")):
        toml_value(value)


def test_a_layout_named_with_quotes_and_backslashes_reads_back_unchanged():
    layout = dataclasses.replace(get_layout("grid-4x4"), name='bench "B" \\ 2')
    assert layout_from_mapping(tomllib.loads(layout_to_toml(layout))) == layout


def test_a_settings_file_reads_back_as_written(tmp_path):
    settings = {"alerts": {"threshold_mmhg": 40.5, "curve": "linder-ganz", "turn_interval_min": 90},
                "monitor": {"bed_id": "ward3-bed12"}}
    path = tmp_path / "settings.toml"
    path.write_text(settings_text(settings))
    assert read_settings(path) == settings
