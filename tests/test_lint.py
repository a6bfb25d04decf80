"""The code passes ruff and mypy as ``pyproject.toml`` configures them, the versions the ``test`` extra pins.

Each tool is also shown a small module with a fault it must report, so a configuration that checks
nothing (no files found, no rule selected) fails here rather than passing quietly.
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINTED = ("appliance", "webui", "tests")


def run(tool: str, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    if importlib.util.find_spec(tool) is None:
        pytest.fail(f"{tool} is not installed: it comes with the test extra, pip install -e '.[test]'")
    return subprocess.run([sys.executable, "-m", tool, *args], cwd=cwd, capture_output=True, text=True,
                          check=False, timeout=600)


def test_ruff_finds_nothing_in_the_code():
    done = run("ruff", "check", "--no-cache", *LINTED)
    assert done.returncode == 0, done.stdout + done.stderr


def test_mypy_finds_nothing_in_the_packages():
    done = run("mypy")                      # the packages and options of [tool.mypy]
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.startswith("Success: no issues found in "), done.stdout


def test_the_checks_report_a_planted_fault(tmp_path):
    (tmp_path / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text())
    (tmp_path / "faulty.py").write_text(
        "def callbacks(names: list[str]) -> list:\n"
        "    out = []\n"
        "    for name in names:\n"
        "        out.append(lambda: name)\n"      # late-bound loop variable: bugbear's B023
        "    return out\n"
        "\n"
        "\n"
        "def half(n: int) -> int:\n"
        "    return n / 2\n")                     # a float returned as an int
    ruff = run("ruff", "check", "--no-cache", "faulty.py", cwd=tmp_path)
    assert ruff.returncode == 1 and "B023" in ruff.stdout, ruff.stdout + ruff.stderr
    mypy = run("mypy", "--no-incremental", "faulty.py", cwd=tmp_path)
    assert mypy.returncode == 1 and "faulty.py:9: error" in mypy.stdout and "[return-value]" in mypy.stdout, \
        mypy.stdout + mypy.stderr
