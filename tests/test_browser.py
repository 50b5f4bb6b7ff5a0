"""The browser page end to end: a real headless Chromium on the real service over a simulated rig.

`hdrig serve` runs as a subprocess on a realtime-paced copy of the sim rig (so a speed sweep lasts as
long as on a bench, ~18 s) with a fresh store; Playwright drives Debian's Chromium, never a browser of
its own. The page is used as an operator would: log in with a key, start a speed sweep from the form,
watch live points arrive, press Stop, see the rig stop and the run end `aborted`.

Chromium missing is a failure, not a skip: CI installs it (`.ci/run`), so a page nobody tested cannot
pass as green.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from rig.experiments import EXPERIMENTS

ROOT = Path(__file__).resolve().parents[1]
HDRIG = Path(sys.executable).with_name("hdrig")  # the command of the venv running the tests
CHROMIUM = os.environ.get("HDRIG_CHROMIUM", "/usr/bin/chromium")
# As the lab machines run it: no sandbox (root in CI), and nothing that phones out of a closed network.
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

SERVICE_START_S = 60.0  # a cold start imports numpy, numba's kernels, matplotlib...
FIRST_POINTS_S = 15.0  # the worker opens the rig and the first 0.25 s block is published
STOP_S = 10.0  # quick stop: the motor coasts to rest and the run is sealed


def _sweep_length_s() -> float:
    """The default speed sweep's length in wall-clock seconds on a realtime rig: every speed both ways,
    settle then hold (the travel limit can only shorten holds)."""
    p = EXPERIMENTS["speed-sweep"].Params()
    return 2 * len(p.speeds_rad_s) * (p.settle_s + p.hold_s)


RUN_S = _sweep_length_s()


@dataclass
class Service:
    url: str
    key: str
    process: subprocess.Popen[bytes]
    log: Path

    def get(self, path: str) -> object:
        request = urllib.request.Request(self.url + path, headers={"Authorization": f"Bearer {self.key}"})
        with urllib.request.urlopen(request, timeout=10) as response:
            return json.load(response)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_healthy(url: str, process: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + SERVICE_START_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            pytest.fail(f"hdrig serve exited with {process.returncode}:\n{log.read_text()}")
        try:
            with urllib.request.urlopen(url + "/api/v1/health", timeout=2) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.2)  # polling a socket that is not up yet, not waiting for the page
    pytest.fail(f"hdrig serve not healthy within {SERVICE_START_S:.0f} s:\n{log.read_text()}")


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    """`hdrig serve` on a realtime sim rig, a fresh store, and an operator key made for the test."""
    rig_file = tmp_path / "sim-realtime.yaml"
    rig = yaml.safe_load((ROOT / "configs" / "rigs" / "sim.yaml").read_text())
    rig["pace"] = "realtime"
    rig_file.write_text(yaml.safe_dump(rig))
    env = {**os.environ, "HDRIG_HOME": str(tmp_path / "home")}

    made = subprocess.run(
        [str(HDRIG), "keys", "create", "--role", "operator", "--name", "browser"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    key = made.stdout.strip()
    assert key, "hdrig keys create printed no key"

    port = _free_port()
    log = tmp_path / "serve.log"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [str(HDRIG), "serve", "--rig", str(rig_file), "--port", str(port)],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    url = f"http://127.0.0.1:{port}"
    try:
        _wait_healthy(url, process, log)
        yield Service(url, key, process, log)
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5)


@pytest.fixture
def browser() -> Iterator[object]:
    """Debian's Chromium driven by Playwright; missing either is a failure (CI must provide both)."""
    if not (Path(CHROMIUM).is_file() and os.access(CHROMIUM, os.X_OK)) and not shutil.which(CHROMIUM):
        pytest.fail(f"no Chromium at {CHROMIUM}: install Debian's package (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("Playwright for Python is missing: pip install -e '.[dev]'")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield chromium
        finally:
            chromium.close()


def test_operator_starts_a_sweep_watches_it_live_and_stops_it(browser: object, service: Service) -> None:
    from playwright.sync_api import Browser, Page, expect

    assert isinstance(browser, Browser)
    page: Page = browser.new_page(viewport={"width": 1280, "height": 1000})
    page_errors: list[str] = []
    page.on("pageerror", lambda error: page_errors.append(str(error)))

    # Before login: the login form, and the Stop button already on screen.
    page.goto(service.url + "/")
    expect(page.locator("#stop")).to_be_visible()
    expect(page.locator("#login-form")).to_be_visible()

    page.fill("#login-key", service.key)
    page.click("#login-submit")
    expect(page.locator("#rig-state")).to_have_text("idle", timeout=10_000)
    expect(page.locator("#rig-mode")).to_have_text("SIM")
    expect(page.locator("#stop")).to_be_visible()

    # The form is built from the experiment's params_schema, defaults filled in, units shown.
    page.select_option("#experiment", "speed-sweep")
    expect(page.locator("#param-hold_s")).to_have_value("0.7")
    expect(page.locator("#param-speeds_rad_s")).to_have_value(re.compile(r"^0\.5, 1, 2, .*200$"))
    expect(page.locator("[data-field=hold_s] .unit")).to_have_text("s")

    # A bad value: the service's problem details appear next to the form, naming the field.
    page.fill("#param-hold_s", "abc")
    page.click("#start")
    expect(page.locator("#start-problem")).to_be_visible(timeout=10_000)
    expect(page.locator("#start-problem")).to_contain_text("hold_s")
    expect(page.locator("#rig-state")).to_have_text("idle")

    # Start the default sweep: the rig runs and live points arrive, more and more of them.
    page.fill("#param-hold_s", "0.7")
    page.click("#start")
    expect(page.locator("#start-problem")).to_be_hidden()
    expect(page.locator("#rig-state")).to_have_text("running", timeout=10_000)
    expect(page.locator("#live-received")).not_to_have_text("0", timeout=FIRST_POINTS_S * 1000)
    first = int(page.locator("#live-received").inner_text())
    # Points come every block (~0.25 s); well inside the run's length they must have grown.
    page.wait_for_function(
        "n => Number(document.querySelector('#live-received').textContent) > n",
        arg=first,
        timeout=RUN_S / 4 * 1000,
    )
    assert int(page.locator("#live-points").inner_text()) > 0
    expect(page.locator("#progress-text")).to_contain_text("speed-sweep")
    run_id = page.locator("#live-run").inner_text()
    assert run_id
    # Stopped well before its end, so an `aborted` below is the Stop button's doing.
    assert float(page.locator("#progress").evaluate("p => p.value")) < 0.9

    # Stop: the rig leaves `running` at once and the run ends aborted, in the page and in the store.
    page.click("#stop")
    expect(page.locator("#rig-state")).to_have_text(re.compile("^(stopping|idle)$"), timeout=STOP_S * 1000)
    expect(page.locator("#live-status")).to_have_text("aborted", timeout=STOP_S * 1000)
    expect(page.locator("#alarms")).to_be_visible()
    expect(page.locator("#rig-state")).to_have_text("idle", timeout=STOP_S * 1000)
    row = page.locator(f"#runs tbody tr[data-id='{run_id}']")
    expect(row).to_have_attribute("data-status", "aborted", timeout=STOP_S * 1000)
    expect(row.locator("a[data-format=csv]")).to_be_visible()

    run = service.get(f"/api/v1/runs/{run_id}")
    assert isinstance(run, dict)
    assert run["status"] == "aborted"

    # The next run starts clean: the last stop's alarm belongs to the last run, not to this one.
    page.click("#start")
    expect(page.locator("#live-run")).not_to_have_text(run_id, timeout=10_000)
    expect(page.locator("#live-received")).not_to_have_text("0", timeout=FIRST_POINTS_S * 1000)
    expect(page.locator("#alarms")).to_be_hidden()
    page.click("#stop")
    expect(page.locator("#live-status")).to_have_text("aborted", timeout=STOP_S * 1000)
    expect(page.locator("#alarms")).to_contain_text("quick_stop")
    assert page_errors == []
