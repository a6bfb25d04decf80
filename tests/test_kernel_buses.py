"""The Linux board against the Linux kernel's own bus simulators, gpio-sim and i2c-stub, in a VM.

The VM boots once for this module (``tests/kernel/vm.py``: Debian's kernel under QEMU, the host's files
shared read-only, so the guest runs this checkout with this Python). Inside it, pytest runs
``tests/kernel/guest_linux_board.py`` as root, and each test there is one test here that passes when it
passed in the guest (every parametrised case of it). The first run downloads and caches the kernel.

Marked ``kernel``: ``pytest -m "not kernel"`` leaves them out of a quick run. They fail, not skip, when
QEMU or busybox-static is missing (``.ci/run`` installs both; the message says what to install).
"""

import ast
import shlex
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

from appliance.drivers.profile import board_profile
from kernel import vm

pytestmark = pytest.mark.kernel

REPO = Path(__file__).resolve().parents[1]
GUEST_TESTS = Path(__file__).with_name("kernel") / "guest_linux_board.py"
GUEST_TIMEOUT_S = 900
"""Boot and run take 30 to 40 s under TCG emulation on the 2-vCPU build machine; a slower one gets room."""


def guest_test_names() -> list[str]:
    tree = ast.parse(GUEST_TESTS.read_text())
    return [node.name for node in tree.body if isinstance(node, ast.FunctionDef) and node.name.startswith("test_")]


def guest_command(out: Path) -> str:
    """The shell line the guest runs: this checkout's guest tests under this Python, as JUnit XML into ``out``."""
    pytest_args = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--noconftest",
                   f"--junitxml={out / 'guest.xml'}", str(GUEST_TESTS.relative_to(REPO))]
    return (f"cd {shlex.quote(str(REPO))} && APPLIANCE_KERNEL_GUEST=1 PYTHONDONTWRITEBYTECODE=1 "
            f"PYTHONPATH={shlex.quote(str(REPO))} exec {shlex.join(pytest_args)}")


@pytest.fixture(scope="module")
def guest_results(tmp_path_factory) -> dict[str, list[str | None]]:
    """{guest test function: [None for each case that passed, else its failure]}, from one VM run."""
    kernel = vm.prepare()
    out = tmp_path_factory.mktemp("kernel-vm")
    chips = board_profile({"profile": "reference"}).i2c
    run = vm.run(kernel, guest_command(out), out, i2c_chips=[chips["adc"], chips["thermometer"]],
                 timeout_s=GUEST_TIMEOUT_S)
    report = out / "guest.xml"
    if run.status is None or not report.exists():
        pytest.fail(f"the VM (kernel {kernel.version}, {run.accelerator}) left no test report; "
                    f"guest status {run.status}\n--- output ---\n{run.output[-3000:]}\n"
                    f"--- console ---\n{run.console[-3000:]}", pytrace=False)
    results: dict[str, list[str | None]] = {}
    for case in ElementTree.parse(report).iter("testcase"):
        problem = case.find("failure") if case.find("failure") is not None else case.find("error")
        skipped = case.find("skipped")
        verdict = None
        if problem is not None:
            verdict = f"{problem.get('message')}\n{problem.text}"
        elif skipped is not None:
            verdict = f"skipped in the guest: {skipped.get('message')}"
        results.setdefault(case.get("name").partition("[")[0], []).append(verdict)
    return results


@pytest.mark.parametrize("name", guest_test_names())
def test_in_the_vm(guest_results, name):
    assert name in guest_results, f"{name} did not run in the guest"
    failures = [verdict for verdict in guest_results[name] if verdict is not None]
    assert not failures, "\n\n".join(failures)
