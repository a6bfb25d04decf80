"""Web screen under load: 20 browsers on the live view, and the monitor's frame rate with and without them.

    python benchmarks/webui_load.py      # writes benchmarks/webui_load.md (about 15 min; needs chromium)

The processes are the appliance's: ``appliance run`` on the grid-8x16 virtual
bed and ``python -m webui`` (waitress), both pinned to CPU 0, standing in for
the appliance. The clients are real headless Chromium browsers, each its own
process with its own connection, logged in with their own session and showing
the live view (server-sent events, canvas drawing), pinned to CPU 1, standing
in for the ward's screens.

* Responsiveness, with the monitor at its real pace (1 frame/s): how long after
  the monitor writes a frame each browser has it (``written_at`` to the event's
  arrival, same clock), and, from one more browser, the time to load the
  alarms page and to fetch ``/api/live``, with 0 and with 20 browsers connected.
* Interference: the monitor's frame period at 1 frame/s, and its frame rate
  unpaced (as fast as it goes, which any slowdown shows at once), in
  alternating windows without and with the 20 browsers connected (the idle
  browsers sit on about:blank), with the screen at the monitor's priority and
  at nice 10. Medians over the windows of each kind.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from appliance.cli_run import SCREEN_NICE  # the screen below the monitor's priority, as `run --screen` starts it

sys.path.insert(0, str(Path(__file__).parent))
from report import cpu_seconds, free_port, listening, machine, percentile, table, wait_for  # noqa: E402

HERE = Path(__file__).parent
CLIENTS = 20
PASSWORD = "load test password"
APPLIANCE_CPU, CLIENT_CPU = {0}, {1}


def on_appliance_cpu(nice: int = 0):
    def start() -> None:
        os.sched_setaffinity(0, APPLIANCE_CPU)
        os.nice(nice)
    return start


@contextlib.contextmanager
def appliance(folder: Path, *, speed: float, interval_s: float, screen_nice: int):
    """The monitor and the screen (at ``screen_nice``) on one data directory, on the appliance's CPU; yields
    (url, monitor, screen, live.json)."""
    data = folder / f"data-{speed:g}-{screen_nice}"
    subprocess.run([sys.executable, "-c", "from appliance.accounts.users import UserStore; import sys; "
                    "u = UserStore(sys.argv[1]); [u.create(f'nurse.{k:02d}', sys.argv[2], 'nurse', by='bench') "
                    f"for k in range({CLIENTS + 1})]", str(_mkdir(data) / "webui.db"), PASSWORD], check=True)
    port = free_port()
    monitor = subprocess.Popen([sys.executable, "-m", "appliance", "run", "--scenario", "turned-every-2h",
                                "--interval", str(interval_s), "--speed", str(speed), "--data-dir", str(data)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=on_appliance_cpu())
    screen = subprocess.Popen([sys.executable, "-m", "webui", "--data-dir", str(data), "--port", str(port),
                               "--plain-http"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              preexec_fn=on_appliance_cpu(screen_nice))
    try:
        wait_for(lambda: (data / "live.json").exists(), 300, "the monitor's first frame", poll_s=0.2)
        wait_for(lambda: listening(port), 30, "the screen", poll_s=0.2)
        yield f"http://127.0.0.1:{port}", monitor, screen, data / "live.json"
    finally:
        for process in (screen, monitor):
            process.terminate()
            process.wait(timeout=30)


def _mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def browser():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1280,800"):
        options.add_argument(argument)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)


def log_in(driver, url: str, name: str) -> None:
    from selenium.webdriver.common.by import By

    driver.get(url + "/login")
    driver.find_element(By.NAME, "name").send_keys(name)
    driver.find_element(By.NAME, "password").send_keys(PASSWORD)
    driver.find_element(By.CSS_SELECTOR, "button[type=submit]").click()


WATCH = """window.delays = [];
source.addEventListener('message', e => {
  const s = JSON.parse(e.data);
  if (s.written_at) window.delays.push(Date.now() / 1000 - s.written_at);
});"""


def open_live(drivers, url: str) -> None:
    for driver in drivers:
        driver.get(url + "/")
        driver.execute_script(WATCH)


def close_live(drivers, _url: str) -> None:
    for driver in drivers:
        driver.get("about:blank")


def page_times(driver, url: str, repeats: int = 10) -> dict[str, list[float]]:
    """Seconds to load the alarms page (navigation to load event) and to fetch /api/live, ``repeats`` times."""
    loads, fetches = [], []
    for _ in range(repeats):
        driver.get(url + "/alarms")
        loads.append(driver.execute_script(
            "const t = performance.getEntriesByType('navigation')[0]; return (t.loadEventEnd - t.startTime) / 1000;"))
        fetches.append(driver.execute_script(
            "const t0 = performance.now(); return fetch('/api/live').then(r => r.json())"
            ".then(() => (performance.now() - t0) / 1000);"))
    return {"load": loads, "fetch": fetches}


def frame_log(live_json: Path, seconds: float) -> list[tuple[int, float]]:
    """(maps made, written_at) of each new snapshot the monitor wrote during ``seconds``."""
    seen, out = None, []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            snapshot = json.loads(live_json.read_text())
        except (OSError, ValueError):
            continue
        if snapshot["written_at"] != seen:
            seen = snapshot["written_at"]
            out.append((snapshot["status"]["maps"], seen))
        time.sleep(0.01)
    return out


def frame_rate(log) -> float:
    if len(log) < 2:
        raise RuntimeError("the monitor wrote fewer than two frames in a window: has it stopped?")
    (m0, t0), (m1, t1) = log[0], log[-1]
    return (m1 - m0) / (t1 - t0)


def periods(log) -> list[float]:
    return [b[1] - a[1] for a, b in zip(log, log[1:]) if b[0] == a[0] + 1]


def responsiveness(url: str, live_json: Path, clients, probe, monitor, screen, window_s: float = 60.0) -> dict:
    """At the monitor's real pace: frame periods, screen CPU, page and fetch times, with and without clients."""
    out = {}
    for connected in (0, CLIENTS):
        (open_live if connected else close_live)(clients, url)
        time.sleep(3)
        cpu0 = {p.pid: cpu_seconds(p.pid) for p in (monitor, screen)}
        started = time.monotonic()
        log = frame_log(live_json, window_s)
        elapsed = time.monotonic() - started
        cpu = {p.pid: (cpu_seconds(p.pid) - cpu0[p.pid]) / elapsed for p in (monitor, screen)}
        times = page_times(probe, url)
        delays = [d for c in clients for d in (c.execute_script("return window.delays || [];") if connected else [])]
        out[connected] = {"periods": periods(log), "monitor_cpu": cpu[monitor.pid], "screen_cpu": cpu[screen.pid],
                          "delays": delays, **times}
    return out


def interference(url: str, live_json: Path, clients, windows: int = 3, window_s: float = 20.0) -> dict:
    """Unpaced frame rates in alternating windows without and with the clients connected."""
    rates = {0: [], CLIENTS: []}
    for _ in range(windows):
        for connected in (0, CLIENTS):
            (open_live if connected else close_live)(clients, url)
            time.sleep(2)
            rates[connected].append(frame_rate(frame_log(live_json, window_s)))
    return rates


def run() -> dict:
    os.sched_setaffinity(0, CLIENT_CPU)                 # this process and the browsers it starts
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        clients = [browser() for _ in range(CLIENTS)]
        probe = browser()
        result = {}
        try:
            with appliance(folder, speed=1, interval_s=1, screen_nice=SCREEN_NICE) as (url, monitor, screen, live):
                for k, driver in enumerate(clients + [probe]):
                    log_in(driver, url, f"nurse.{k:02d}")
                result["paced"] = responsiveness(url, live, clients, probe, monitor, screen)
            for nice in (0, SCREEN_NICE):
                # 2 s frames: 43200 in the scenario's day, some 15 min at the unpaced rate
                with appliance(folder, speed=0, interval_s=2, screen_nice=nice) as (url, _, _, live):
                    for k, driver in enumerate(clients):
                        log_in(driver, url, f"nurse.{k:02d}")
                    result[f"unpaced-nice-{nice}"] = interference(url, live, clients)
                (HERE / "webui_load.json").write_text(json.dumps(result))        # the raw figures, so far
        finally:
            for driver in clients + [probe]:
                driver.quit()
    return result


def ms(values, q=0.5) -> str:
    return f"{1000 * (statistics.median(values) if q == 0.5 else percentile(values, q)):.0f}" if values else "-"


def report(result: dict) -> str:
    paced = result["paced"]
    rows = []
    for connected in (0, CLIENTS):
        r = paced[connected]
        rows.append([connected, f"{1 / statistics.median(r['periods']):.3f}", ms(r["periods"], 0.95),
                     f"{100 * r['monitor_cpu']:.1f}", f"{100 * r['screen_cpu']:.1f}",
                     ms(r["delays"]), ms(r["delays"], 0.95), ms(r["load"]), ms(r["load"], 0.95),
                     ms(r["fetch"]), ms(r["fetch"], 0.95)])
    paced_table = table(["browsers", "frames/s", "frame period p95 ms", "monitor CPU %", "screen CPU %",
                         "frame to browser ms (median)", "p95", "alarms page load ms (median)", "p95",
                         "/api/live fetch ms (median)", "p95"], rows)
    rows, ratios = [], {}
    for nice in (0, SCREEN_NICE):
        rates = result[f"unpaced-nice-{nice}"]
        ratio = ratios[nice] = statistics.median(rates[CLIENTS]) / statistics.median(rates[0])
        rows += [[nice, c, f"{statistics.median(rates[c]):.2f}", ", ".join(f"{v:.2f}" for v in rates[c]),
                  "" if c == 0 else f"{ratio:.2f}"] for c in (0, CLIENTS)]
    unpaced_table = table(["screen's nice", "browsers", "unpaced frames/s (median of windows)", "windows",
                           "rate with / without browsers"], rows)
    return f"""# Web screen under load

`python benchmarks/webui_load.py` on {machine()}.

{__doc__.split(chr(10) + chr(10), 1)[1].strip()}

## At the monitor's real pace (1 frame/s), 60 s per row

{paced_table}

Frames reach the browsers {ms(paced[CLIENTS]['delays'])} ms (median, p95 {ms(paced[CLIENTS]['delays'], 0.95)} ms)
after the monitor writes them, inside the 1 s the screen must meet; {len(paced[CLIENTS]['delays'])} deliveries
measured across {CLIENTS} browsers.

## Unpaced monitor, alternating 20 s windows

{unpaced_table}

With {CLIENTS} browsers connected, the unpaced monitor runs at {ratios[0]:.2f} of its rate without them when the
screen shares its core at the same priority, and at {ratios[SCREEN_NICE]:.2f} with the screen at nice {SCREEN_NICE},
as `appliance run --screen` starts it.
"""


if __name__ == "__main__":
    result = run()
    (HERE / "webui_load.json").write_text(json.dumps(result))
    text = report(result)
    (HERE / "webui_load.md").write_text(text)
    print(text)
