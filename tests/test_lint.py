"""The code passes ruff, mypy and import-linter as ``pyproject.toml`` configures them, the versions the ``test``
extra pins.

Each tool is also shown a fault it must report, so a configuration that checks nothing (no files found, no rule
selected, no contract that can break) fails here rather than passing quietly.
"""

import importlib.util
import os
import re
import shutil
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


def lint_imports(cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """lint-imports on the packages found first from ``cwd`` (its copy of them), with the contracts of its
    pyproject.toml."""
    if importlib.util.find_spec("importlinter") is None:
        pytest.fail("import-linter is not installed: it comes with the test extra, pip install -e '.[test]'")
    return subprocess.run([sys.executable, "-c", "from importlinter.cli import lint_imports_command as c; c()",
                           "--no-cache", "--no-logo"], cwd=cwd, env={**os.environ, "PYTHONPATH": str(cwd)},
                          capture_output=True, text=True, check=False, timeout=600)


def test_imports_keep_every_contract():
    done = lint_imports()
    assert done.returncode == 0 and "Contracts: 3 kept, 0 broken." in done.stdout, done.stdout + done.stderr


def test_lint_imports_reports_a_planted_import_of_each_kind(tmp_path):
    for part in ("appliance", "webui"):
        shutil.copytree(ROOT / part, tmp_path / part, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)

    def plant(module: str, line: str) -> None:
        path = tmp_path.joinpath(*module.split(".")).with_suffix(".py")
        path.write_text(path.read_text() + line + "\n")

    plant("appliance.store.database", "import webui.live")                # a low layer importing the screen
    plant("appliance.service.settings", "import appliance.sim.scene_base")  # the screen reaching the simulator
    plant("appliance.drivers.bus", "import appliance.drivers.scan")       # the scan engine imports the bus
    done = lint_imports(tmp_path)
    assert done.returncode == 1 and "Contracts: 0 kept, 3 broken." in done.stdout, done.stdout + done.stderr
    assert "appliance.store.database -> webui.live" in done.stdout, done.stdout
    assert re.search(r"webui\.\w+ -> appliance\.service\.settings", done.stdout), done.stdout   # any page's chain
    assert "No cycles are allowed in appliance.drivers." in done.stdout and "- .bus -> .scan" in done.stdout, \
        done.stdout
