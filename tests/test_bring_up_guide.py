"""docs/bring-up.md cannot drift from the code: its wiring tables are what ``appliance wiring`` makes now, and
every failure the self-test, the board check and the analogue check can report is explained in it. The
failures are read from the code itself (the parts each self-test check names, the fixed words of every
problem message), so a new check or message fails this test until the guide explains it."""

import ast
import re
from pathlib import Path

import pytest

from appliance.cli import main
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile
from appliance.drivers.wiring import wiring_markdown

ROOT = Path(__file__).resolve().parent.parent
GUIDE = ROOT / "docs" / "bring-up.md"
DRIVERS = ROOT / "appliance" / "drivers"
BEGIN, END = "<!-- wiring tables: made by `appliance wiring`; do not edit -->", "<!-- end of wiring tables -->"
SHORTEST_FRAGMENT = 10      # shorter fixed words ("is already ", ": ") say nothing on their own


def guide() -> str:
    return GUIDE.read_text(encoding="utf-8")


def test_the_guides_wiring_tables_are_what_the_generator_makes_now():
    text = guide()
    assert text.count(BEGIN) == 1 and text.count(END) == 1, "the guide marks its generated tables once"
    generated = text[text.index(BEGIN) + len(BEGIN):text.index(END)].strip("\n")
    expected = "\n".join(wiring_markdown(board_profile({"profile": name})) for name in BUILTIN_PROFILES)
    assert generated == expected.strip("\n"), "run `appliance wiring` and paste its output between the markers"


def test_the_wiring_command_prints_and_writes_the_same_tables(tmp_path, capsys):
    assert main(["wiring"]) == 0
    printed = capsys.readouterr().out
    assert printed == "\n".join(wiring_markdown(board_profile({"profile": name})) for name in BUILTIN_PROFILES)
    assert main(["wiring", "--profile", "parallel", "--out", str(tmp_path / "parallel.md")]) == 0
    assert (tmp_path / "parallel.md").read_text() == wiring_markdown(board_profile({"profile": "parallel"}))


def _constants(node) -> list[str]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def _longest_fragment(node) -> str | None:
    parts = [p.strip() for p in _constants(node)]
    best = max(parts, key=len, default="")
    return best if len(best) >= SHORTEST_FRAGMENT else None


def problem_phrases(path: Path) -> set[str]:
    """The fixed words of every problem a check appends, returns or raises as a mismatch."""
    phrases = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        message = None
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "append" \
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "problems":
            message = node.args[0]
        elif isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call) and \
                getattr(node.exc.func, "id", "") in ("AnalogueMismatch", "BoardMismatch"):
            message = node.exc.args[0]
        elif isinstance(node, ast.Return) and isinstance(node.value, ast.Tuple):
            message = ast.Tuple(elts=[e for e in node.value.elts if isinstance(e, ast.JoinedStr)])
        if message is not None and (fragment := _longest_fragment(message)):
            phrases.add(fragment)
    return phrases


def self_test_failures() -> set[str]:
    """Every part a self-test check names, and every hint it adds to a failed check's detail."""
    failures = set()
    for path in [DRIVERS / "selftest.py", *DRIVERS.glob("frontend*.py")]:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("check", "ChipCheck") and node.args \
                    and isinstance(node.args[0], ast.Constant):
                failures.add(node.args[0].value)
            if isinstance(node, ast.Call) and (getattr(node.func, "attr", None) or getattr(node.func, "id", "")
                                               ).endswith("run_checks"):
                for entry in ast.walk(node.args[0]):
                    if isinstance(entry, ast.Tuple) and isinstance(entry.elts[0], ast.Constant):
                        failures.add(entry.elts[0].value)
        if path.name == "selftest.py":
            failures |= {c.strip(": ;") for c in _constants(tree)
                         if re.match(r"[:;] ", c) and len(c) >= SHORTEST_FRAGMENT}
    return failures


def test_the_failures_are_read_from_the_code():
    """The derivation finds what is known to be there, so an empty list cannot pass the test below."""
    failures = self_test_failures()
    assert {"AD8251 gain steps", "AD7606 ranges", "contact check", "ADS1115 ADC", "ADG1414 drive switches",
            "programmable gain wrong"} <= failures
    assert any("holds the pin" in p for p in problem_phrases(DRIVERS / "board_check.py"))
    assert any("cannot drive at all" in p for p in problem_phrases(DRIVERS / "rails.py"))


@pytest.mark.parametrize("failure", sorted(self_test_failures()))
def test_every_self_test_failure_is_explained(failure):
    assert f"`{failure}`" in guide(), f"docs/bring-up.md does not explain the self-test's {failure!r}"


@pytest.mark.parametrize("phrase", sorted(problem_phrases(DRIVERS / "board_check.py") | problem_phrases(
    DRIVERS / "rails.py") | problem_phrases(DRIVERS / "profile.py")))
def test_every_board_and_analogue_problem_is_explained(phrase):
    assert phrase in guide(), f"docs/bring-up.md does not explain the problem worded {phrase!r}"
