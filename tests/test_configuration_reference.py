"""docs/configuration.md: every TOML example in it is a configuration the monitor accepts, and every key of the
tables it documents in full is in its tables, so the reference cannot drift from the code."""

import re
import shutil
import tomllib
from pathlib import Path

from appliance.service.config import config_from_mapping
from appliance.service.config_sections import CONFIRMATION_KEYS, ENGINE_KEYS, HL7_KEYS, MQTT_KEYS

REFERENCE = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"


def test_every_example_is_accepted_as_written(tmp_path, ca_certificate):
    text = REFERENCE.read_text(encoding="utf-8")
    examples = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert len(examples) == 4
    for name in set(re.findall(r'"/etc/appliance/([^"]+)"', text)):    # the files the examples name, made here
        if name.endswith(".crt"):
            shutil.copy(ca_certificate, tmp_path / name)
        else:
            (tmp_path / name).write_text("a-password\n")
    for example in examples:
        config = config_from_mapping(tomllib.loads(example.replace("/etc/appliance/", f"{tmp_path}/")))
        assert (config.time_zone == "Europe/London" or config.hl7 is not None or config.mqtt is not None
                or config.engine is not None)


def test_every_key_of_the_documented_tables_has_a_row():
    first_cells = re.findall(r"^\| (`[a-z_]+`.*?) \|", REFERENCE.read_text(encoding="utf-8"), re.M)
    rows = {key for cell in first_cells for key in re.findall(r"`([a-z_]+)`", cell)}
    assert rows == {*HL7_KEYS, "time_zone", *MQTT_KEYS, *ENGINE_KEYS, *CONFIRMATION_KEYS}
