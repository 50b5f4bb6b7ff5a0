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
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

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
RECONNECT_S = 4.0  # past Chromium's EventSource reconnection delay (3 s)
RECORD_S = 300.0  # a CLI run on the virtual-time rig (a cold start, ~5 s of simulation), four side by side
ANALYSIS_S = 120.0  # a fit of one sweep (~16 s here) and a gap analysis (~22 s), one after the other
UNIT = "HD-BROWSER-1"  # the gear unit the recorded sweeps were made on: its trend has both
WIDTHS = (360, 1280, 1920)  # a phone, a lab PC, a wide lab monitor
SHOTS = ROOT / "out" / "browser"  # screenshots kept as the test's artifacts (/out/ is git-ignored)
AXE = ROOT / "tests" / "vendor" / "axe.min.js"  # axe-core from npm (MPL-2.0, tests/vendor/axe-core.LICENSE)


def _sweep_length_s() -> float:
    """A lower bound of the default speed sweep's length in wall-clock seconds on a realtime rig: every
    speed both ways, settle then hold (its ramps, the moves between passes and the whole turns of the
    fast speeds make it longer: ~53 s on the sim rig)."""
    p: Any = EXPERIMENTS["speed-sweep"].Params()  # the sweep's own fields, not the base class's
    return 2 * len(p.speeds_rad_s) * (p.settle_s + p.hold_s)


RUN_S = _sweep_length_s()


@dataclass
class Service:
    url: str
    key: str
    process: subprocess.Popen[bytes]
    log: Path
    sweeps: list[str]  # finished speed sweeps in the store before the service started
    others: dict[str, str] = field(default_factory=dict)  # experiment → a finished run of it (step, chirp)

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


def _record(env: dict[str, str], *settings: str, experiment: str = "speed-sweep") -> subprocess.Popen[str]:
    """A run recorded by the CLI on the virtual-time sim rig (seconds, not a bench's minutes)."""
    args = [str(HDRIG), "run", experiment, "--rig", "sim", "--unit", UNIT, "--json", "-q"]
    for setting in settings:
        args += ["--set", setting]
    return subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _recorded(process: subprocess.Popen[str]) -> str:
    out, err = process.communicate(timeout=RECORD_S)
    assert process.returncode == 0, err
    document = json.loads(out)
    run = document[0] if isinstance(document, list) else document
    return str(run["id"])


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """`hdrig serve` on a realtime sim rig, a store holding two finished sweeps (recorded by the CLI
    on the virtual-time rig), and an operator key made for the test."""
    tmp_path = tmp_path_factory.mktemp("browser")
    rig_file = tmp_path / "sim-realtime.yaml"
    rig = yaml.safe_load((ROOT / "configs" / "rigs" / "sim.yaml").read_text())
    rig["pace"] = "realtime"
    rig_file.write_text(yaml.safe_dump(rig))
    env = {**os.environ, "HDRIG_HOME": str(tmp_path / "home")}

    key = operator_key(env)
    recording = [_record(env), _record(env, "speeds_rad_s=[1,10,100]", "hold_s=0.3")]  # side by side
    recording += [_record(env, experiment="step"), _record(env, "periods=2", experiment="chirp")]
    step, chirp = [_recorded(process) for process in recording[2:]]
    sweeps = [_recorded(process) for process in recording[:2]]

    with serving(env, rig_file, tmp_path) as (url, process, log):
        yield Service(url, key, process, log, sweeps, {"step": step, "chirp": chirp})


def operator_key(env: dict[str, str]) -> str:
    """An operator key made by `hdrig keys create` in the store `env` names."""
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
    return key


@contextmanager
def serving(
    env: dict[str, str], rig_file: Path, tmp_path: Path
) -> Iterator[tuple[str, subprocess.Popen[bytes], Path]]:
    """`hdrig serve` on a free loopback port, healthy: (its URL, its process, its log); ended on exit
    (TERM, then KILL) if it has not ended by itself."""
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
        yield url, process, log
    finally:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=5)


@pytest.fixture(scope="module")
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


def _csp_refusal(text: str, errors: list[str]) -> None:
    if "Content Security Policy" in text:
        errors.append(text)


def _login(page: Any, service: Service) -> None:
    page.goto(service.url + "/")
    page.fill("#login-key", service.key)
    page.click("#login-submit")
    page.locator("#rig-state").wait_for(state="visible", timeout=10_000)


def _settled(page: Any) -> None:
    """Two animation frames: the charts' ResizeObservers have run after a change of the window's size."""
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")


def _no_horizontal_scroll(page: Any) -> None:
    _settled(page)
    wide = page.evaluate("() => [document.documentElement.scrollWidth, window.innerWidth]")
    if wide[0] > wide[1]:
        culprits = page.evaluate(
            """() => [...document.querySelectorAll('body *')]
                 .filter(e => e.getBoundingClientRect().right > innerWidth + 0.5 && e.offsetParent !== null &&
                         !e.closest('.table-wrap'))
                 .slice(-5).map(e => e.tagName + '#' + e.id + '.' + e.className + ' ' +
                                     Math.round(e.getBoundingClientRect().right))"""
        )
        pytest.fail(f"the page scrolls sideways: {wide[0]} px of content in {wide[1]} px: {culprits}")


def _stop_on_screen_and_uncovered(page: Any) -> None:
    """STOP inside the window wherever the page is scrolled, nothing drawn over it, and (at the top) the
    bar holding it covering no content."""
    for where in ("0", "document.documentElement.scrollHeight / 2", "document.documentElement.scrollHeight"):
        page.evaluate(f"() => window.scrollTo(0, {where})")
        box = page.evaluate(
            """() => { const r = document.querySelector('#stop').getBoundingClientRect();
                 const hit = document.elementFromPoint(r.x + r.width / 2, r.y + r.height / 2);
                 return {top: r.top, bottom: r.bottom, left: r.left, right: r.right, w: innerWidth,
                         h: innerHeight, onTop: hit === document.querySelector('#stop')}; }"""
        )
        assert box["top"] >= 0 and box["bottom"] <= box["h"], f"STOP off screen at scroll {where}: {box}"
        assert box["left"] >= 0 and box["right"] <= box["w"], f"STOP off screen sideways: {box}"
        assert box["onTop"], f"something covers STOP at scroll {where}"
    page.evaluate("() => window.scrollTo(0, 0)")
    overlaps = page.evaluate(
        """() => { const bar = document.querySelector('#bar').getBoundingClientRect();
             return [...document.querySelectorAll('main section, #message')]
               .filter(s => s.offsetParent !== null)
               .map(s => s.getBoundingClientRect())
               .filter(r => r.top < bar.bottom - 0.5 && r.bottom > bar.top && r.height > 0).length; }"""
    )
    assert overlaps == 0, f"the bar with STOP covers {overlaps} section(s) of the page"


def _axe(page: Any) -> None:
    """axe-core in the page (evaluated, so the page's CSP is not loosened for it): no serious or critical
    violation."""
    if not page.evaluate("() => typeof window.axe !== 'undefined'"):
        page.evaluate(AXE.read_text())
    violations = page.evaluate(
        "async () => (await axe.run(document, {resultTypes: ['violations']})).violations"
        ".map(v => ({id: v.id, impact: v.impact, nodes: v.nodes.slice(0, 3).map(n => n.target.join(' '))}))"
    )
    bad = [v for v in violations if v["impact"] in ("serious", "critical")]
    assert bad == [], f"axe-core: {bad}"


def _shot(page: Any, name: str, full_page: bool = False) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    width = page.viewport_size["width"]
    page.screenshot(path=str(SHOTS / f"{name}-{width}.png"), full_page=full_page)


def test_operator_starts_a_sweep_watches_it_live_and_stops_it(browser: object, service: Service) -> None:
    from playwright.sync_api import Browser, Page, expect

    assert isinstance(browser, Browser)
    page: Page = browser.new_page(viewport={"width": 1280, "height": 900})
    page_errors: list[str] = []
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    # The service's Content-Security-Policy (own scripts and styles only) refuses nothing the page does.
    page.on("console", lambda message: _csp_refusal(message.text, page_errors))
    streams: list[str] = []  # every event stream the page opens (EventSource reconnects by itself)
    page.on("request", lambda request: streams.append(request.url) if "/events" in request.url else None)

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
    # Labels in words from the schema's descriptions, not the machine-made titles ("Hold S").
    described = EXPERIMENTS["speed-sweep"].Params.model_json_schema()["properties"]["hold_s"]["description"]
    words = re.sub(r"\s*\[[^\]]*\]\s*$", "", described)  # "... direction [s]" → "... direction"
    expect(page.locator("[data-field=hold_s] .label-text")).to_have_text(words[0].upper() + words[1:])
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
    # The notice follows the run: it says running, not the "queued" it said before.
    expect(page.locator("#message")).to_contain_text("running", timeout=5_000)
    expect(page.locator("#rig-drive")).to_have_text("drive enabled")

    # While it runs: every width fits, STOP in reach, axe clean; at 1280x900 the plots are above the fold.
    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 900 if width == 1280 else 800})
        _no_horizontal_scroll(page)
        _stop_on_screen_and_uncovered(page)
        if width == 1280:
            for plot in ("#plot-omega", "#plot-current", "#plot-position", "#plot-error"):
                box = page.locator(plot).bounding_box()
                assert box is not None and box["height"] > 100, plot
                assert box["y"] + box["height"] <= 900, f"{plot} below the fold at 1280x900: {box}"
                assert page.locator(f"{plot} canvas").count() >= 1, f"{plot}: no uPlot canvas"
        _axe(page)
        _shot(page, "running")
    page.set_viewport_size({"width": 1280, "height": 900})
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
    # The health says the run aborted (amber) until a person resets, though the rig is idle again.
    expect(page.locator("#rig-health")).to_have_attribute("data-level", "warn", timeout=STOP_S * 1000)
    expect(page.locator("#rig-health")).to_contain_text("aborted")
    expect(page.locator("#message")).to_contain_text("aborted")
    expect(page.locator("#message")).not_to_contain_text("running")
    _shot(page, "aborted")
    page.click("#reset")
    expect(page.locator("#rig-health")).to_have_attribute("data-level", "ok", timeout=5_000)
    expect(page.locator("#reset")).to_be_hidden()
    row = page.locator(f"#runs tbody tr[data-id='{run_id}']")
    expect(row).to_have_attribute("data-status", "aborted", timeout=STOP_S * 1000)
    expect(row.locator("a[data-format=csv]")).to_be_visible()

    run = service.get(f"/api/v1/runs/{run_id}")
    assert isinstance(run, dict)
    assert run["status"] == "aborted"
    # The stream the service ended after the final document is not opened again: Chromium reconnects
    # 3 s after a stream ends, so this waits past that for a request that must not come.
    page.wait_for_timeout(RECONNECT_S * 1000)
    opened = [url for url in streams if f"/runs/{run_id}/events" in url]
    assert len(opened) == 1, streams

    # The next run starts clean: the last stop's alarm belongs to the last run, not to this one. Slow
    # speeds: the stop left the motor anywhere along the stroke, and the default sweep's 200 rad/s pass
    # may not fit in what is left (then the run ends by itself, `aborted: ... the stroke ahead has ...`).
    page.fill("#param-speeds_rad_s", "1, 2")
    page.click("#start")
    expect(page.locator("#live-run")).not_to_have_text(run_id, timeout=10_000)
    expect(page.locator("#live-received")).not_to_have_text("0", timeout=FIRST_POINTS_S * 1000)
    expect(page.locator("#alarms")).to_be_hidden()
    page.click("#stop")
    expect(page.locator("#live-status")).to_have_text("aborted", timeout=STOP_S * 1000)
    expect(page.locator("#alarms")).to_contain_text("quick_stop")
    assert page_errors == []


def test_a_failed_stop_is_shown_at_stop_and_retried(browser: object, service: Service) -> None:
    """The service unreachable for the STOP request: the failure shows beside STOP, and it is sent again."""
    from playwright.sync_api import Browser, Route, expect

    assert isinstance(browser, Browser)
    page = browser.new_page(viewport={"width": 360, "height": 740})
    _login(page, service)
    attempts: list[str] = []

    def refuse(route: Route) -> None:
        attempts.append(route.request.method)
        route.abort("connectionrefused")

    page.route("**/api/v1/rig/stop", refuse)
    page.click("#stop")
    problem = page.locator("#stop-problem")
    expect(problem).to_be_visible(timeout=5_000)
    expect(problem).to_contain_text("STOP FAILED")
    # Beside STOP, in the bar: in view without scrolling, at a phone's width.
    box = problem.bounding_box()
    assert box is not None and box["y"] + box["height"] <= 740
    retried = "() => document.querySelector('#stop-problem').textContent.includes('2/')"
    page.wait_for_function(retried, timeout=5_000)  # the first retry comes after STOP_RETRY_MS = 1 s
    assert len(attempts) >= 2, attempts
    _shot(page, "stop-failed")
    page.unroute("**/api/v1/rig/stop")
    page.click("#stop")
    expect(problem).to_be_hidden(timeout=5_000)
    page.close()


def test_results_render_in_the_page_at_every_width(browser: object, service: Service) -> None:
    """A sweep's friction plot and tables, two runs overlaid, a fit's parameters with σ and a gap
    analysis' steps, all in the page at 360, 1280 and 1920 px."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    sweep, short = service.sweeps
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page_errors: list[str] = []
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    # The service's Content-Security-Policy (own scripts and styles only) refuses nothing the page does.
    page.on("console", lambda message: _csp_refusal(message.text, page_errors))
    _login(page, service)

    # A fit and a gap analysis of the short sweep, started from the page; they run while we look.
    page.fill("#analysis-data", short)
    page.select_option("#analysis-kind", "fits")
    page.click("#analysis-form button[type=submit]")
    expect(page.locator("#jobs tbody tr[data-kind=fit]")).to_have_count(1, timeout=10_000)
    page.select_option("#analysis-kind", "gaps")
    page.click("#analysis-form button[type=submit]")
    expect(page.locator("#jobs tbody tr[data-kind=gaps]")).to_have_count(1, timeout=10_000)

    # The sweep's results: friction against speed with its law (a uPlot chart), its table, its PNG.
    page.click(f"button[data-results='{sweep}']")
    figure = page.locator("figure[data-artifact='friction_vs_velocity.csv']")
    expect(figure.locator(".uplot canvas").first).to_be_visible(timeout=10_000)
    expect(figure.locator(".u-title")).to_have_text("friction against speed")
    expect(figure.locator(".table-wrap table tbody tr")).to_have_count(18)  # 9 speeds, both ways
    expect(figure.locator(".table-wrap th").first).to_have_text("omega_set [rad/s]")
    expect(page.locator("#results-body figure img").first).to_be_visible()
    assert page.locator("#results-body figure img").first.evaluate("i => i.naturalWidth") > 0

    # The unit's trend: a metric of each complete sweep of the unit, against when it ran.
    trend = page.locator("[data-testid=trend]")
    expect(trend).to_have_attribute("data-points", "2", timeout=10_000)
    expect(trend.locator(".uplot canvas").first).to_be_visible()

    # Two runs overlaid on one time axis.
    page.select_option("#overlay-run", short)
    page.click("#overlay-form button[type=submit]")
    expect(page.locator("#overlay .uplot canvas").first).to_be_visible(timeout=10_000)
    expect(page.locator("#overlay .u-legend")).to_contain_text(short)
    expect(page.locator("#overlay .u-legend")).to_contain_text(sweep)

    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 900})
        page.locator("#run-results").scroll_into_view_if_needed()
        _no_horizontal_scroll(page)
        _stop_on_screen_and_uncovered(page)
        page.evaluate("() => document.querySelector('#run-results').scrollIntoView()")
        chart = figure.locator(".uplot").bounding_box()
        assert chart is not None and chart["x"] >= 0 and chart["x"] + chart["width"] <= width, chart
        _shot(page, "run-results")

    # The fit: parameters with σ (numbers where determined), a model named after its run and fit.
    fit_row = page.locator("#jobs tbody tr[data-kind=fit]")
    expect(fit_row).to_have_attribute("data-status", "complete", timeout=ANALYSIS_S * 1000)
    fit_id = fit_row.get_attribute("data-id")
    fit_row.locator("button").click()
    table = page.locator("[data-testid=fit-parameters]")
    expect(table).to_be_visible(timeout=10_000)
    sigma = table.locator("tr[data-param=s3] td").nth(1).inner_text()
    assert float(sigma) > 0, sigma
    expect(table.locator("tr[data-param=K_s] td").nth(1)).to_have_text("not determined")
    download = page.locator("[data-testid=model-download]")
    expect(download).to_be_visible()
    name = download.get_attribute("download") or ""
    assert short in name and str(fit_id) in name and "seed" not in name, name
    report = page.locator("#job-results [data-testid=report]")
    expect(report.locator("table").first).to_be_visible(timeout=10_000)  # rendered Markdown, not text
    expect(report).not_to_contain_text("|---")
    page.evaluate("() => document.querySelector('#job-results').scrollIntoView()")
    _shot(page, "fit")

    # The gap analysis: its steps and verdict as a table and text.
    gaps_row = page.locator("#jobs tbody tr[data-kind=gaps]")
    expect(gaps_row).to_have_attribute("data-status", "complete", timeout=ANALYSIS_S * 1000)
    gaps_row.locator("button").click()
    steps = page.locator("[data-testid=gaps-steps]")
    expect(steps.locator("tbody tr").first).to_have_text(re.compile(r"start"), timeout=10_000)
    expect(page.locator("[data-testid=gaps-verdict]")).to_contain_text("verdict")

    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 900})
        _no_horizontal_scroll(page)
        _stop_on_screen_and_uncovered(page)
        _axe(page)
        page.evaluate("() => document.querySelector('#job-results').scrollIntoView()")
        _shot(page, "analyses")
        _shot(page, "page", full_page=True)
    assert page_errors == []
    page.close()


def test_tracking_and_frequency_responses_render_in_the_page(browser: object, service: Service) -> None:
    """A step's set-point against its output (the gear ratio applied, from where it started), and a
    chirp's FRFs: magnitude and phase against log frequency with their ±1 σ band and the coherence."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page_errors: list[str] = []
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    page.on("console", lambda message: _csp_refusal(message.text, page_errors))
    _login(page, service)

    step: Any = EXPERIMENTS["step"].Params()
    page.click(f"button[data-results='{service.others['step']}']")
    tracking = page.locator("figure[data-artifact=tracking]")
    expect(tracking.locator(".uplot canvas")).to_have_count(2, timeout=10_000)
    expect(tracking.locator("[data-testid=tracking-response] .u-legend")).to_contain_text("set-point")
    expect(tracking.locator("[data-testid=tracking-response] .u-legend")).to_contain_text("load θ_l")
    expect(tracking.locator("[data-testid=tracking-error] .u-title")).to_contain_text("tracking error")
    # At the output and from the start: the set-point goes from 0 to the step's height, and the load
    # ends back near 0 (the step goes there and back), not at the motor's angle (×1/r).
    low, high = (float(v) for v in (tracking.get_attribute("data-setpoint-range") or "").split(" to "))
    assert abs(low) < 1e-3 and abs(high - step.amp_out_rad) < 1e-3, (low, high)
    assert abs(float(tracking.get_attribute("data-load-end") or "nan")) < 0.05 * step.amp_out_rad
    page.evaluate("() => document.querySelector('figure[data-artifact=tracking]').scrollIntoView()")
    _shot(page, "step")

    page.click(f"button[data-results='{service.others['chirp']}']")
    for name in ("frf_speed.csv", "frf_load.csv", "frf_closed_loop.csv"):
        figure = page.locator(f"figure[data-artifact='{name}']")
        expect(figure.locator(".uplot")).to_have_count(2, timeout=10_000)
        expect(figure.locator(".u-title").nth(0)).to_contain_text("magnitude")
        expect(figure.locator(".u-title").nth(1)).to_contain_text("phase")
        expect(figure.locator(".u-legend").first).to_contain_text("coherence")
        expect(figure.locator(".u-legend").first).to_contain_text("1 σ")
        rows = figure.locator(".table-wrap tbody tr").count()
        assert int(figure.locator(".chart").first.get_attribute("data-lines") or 0) >= rows > 5
    for width in WIDTHS:
        page.set_viewport_size({"width": width, "height": 900})
        _no_horizontal_scroll(page)
        _stop_on_screen_and_uncovered(page)
        _axe(page)
        page.locator("figure[data-artifact='frf_speed.csv']").evaluate("e => e.scrollIntoView()")
        _shot(page, "chirp")
    assert page_errors == []
    page.close()
