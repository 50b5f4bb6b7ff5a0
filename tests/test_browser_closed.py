"""The browser page when the service goes away (issue 28 item 4: truthful state).

A service of its own (it is killed here), on the wall-clock-paced sim rig: the page follows a speed sweep
live, the service gets SIGTERM, and the bar says `closed` with the service's own reason, in grey: no green
health left over from before. And a service that does not answer the page's polls is said `unreachable`
in the bar until it answers again.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_browser import (  # the same Chromium, launch flags, checks and screenshot folder
    ROOT,
    Service,
    _axe,
    _login,
    _no_horizontal_scroll,
    _shot,
    _stop_on_screen_and_uncovered,
    browser,
    operator_key,
    serving,
)

__all__ = ["browser"]  # the fixture, used by name below

LIVE_RIG = ROOT / "configs" / "rigs" / "sim-live.yaml"  # pace: realtime, a sweep lasts ~18 s
FIRST_POINTS_S = 15.0  # the worker opens the rig and publishes its first block
CLOSED_S = 10.0  # SIGTERM → quick stop, the run sealed, the `closed` event (the service exits within 5 s)
POLLS_S = 3.0  # three of the page's 1 s rig polls: the bar must still say why after they fail
GREY = "rgb(89, 89, 89)"  # --grey in style.css: health unknown


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    env = {**os.environ, "HDRIG_HOME": str(tmp_path / "home")}
    key = operator_key(env)
    with serving(env, LIVE_RIG, tmp_path) as (url, process, log):
        yield Service(url, key, process, log, [])


def _unknown_health(page: Any, text: str) -> None:
    from playwright.sync_api import expect

    health = page.locator("#rig-health")
    expect(health).to_have_attribute("data-level", "unknown", timeout=CLOSED_S * 1000)
    expect(health).to_contain_text(text)
    assert health.evaluate("e => getComputedStyle(e).backgroundColor") == GREY
    expect(page.locator("#rig-drive")).to_have_text("drive unknown")
    expect(page.locator("#reset")).to_be_hidden()


def test_the_bar_says_unreachable_then_closed_with_why(browser: object, service: Service) -> None:
    from playwright.sync_api import Browser, Route, expect

    assert isinstance(browser, Browser)
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page_errors: list[str] = []
    page.on("pageerror", lambda error: page_errors.append(str(error)))
    _login(page, service)
    expect(page.locator("#rig-state")).to_have_text("idle", timeout=10_000)
    expect(page.locator("#rig-health")).to_have_attribute("data-level", "ok")

    # The rig polls refused: the bar says so in grey (no green left over), then recovers.
    def refuse(route: Route) -> None:
        route.abort("connectionrefused")

    page.route("**/api/v1/rig", refuse)
    expect(page.locator("#rig-state")).to_have_text("unreachable", timeout=5_000)
    _unknown_health(page, "service unreachable")
    _shot(page, "unreachable")
    page.unroute("**/api/v1/rig")
    expect(page.locator("#rig-state")).to_have_text("idle", timeout=5_000)
    expect(page.locator("#rig-health")).to_have_attribute("data-level", "ok")

    # A sweep followed live, then SIGTERM to the service.
    page.click("#start")
    expect(page.locator("#rig-state")).to_have_text("running", timeout=10_000)
    expect(page.locator("#live-received")).not_to_have_text("0", timeout=FIRST_POINTS_S * 1000)
    service.process.send_signal(signal.SIGTERM)

    # The run ends aborted naming the signal, then the service's `closed` event: the bar says why.
    expect(page.locator("#live-status")).to_have_text("aborted", timeout=CLOSED_S * 1000)
    expect(page.locator("#rig-state")).to_have_text("closed", timeout=CLOSED_S * 1000)
    assert page.locator("#rig-state").evaluate("e => e.className") == "state closed"
    why = "quick stop: the service got SIGTERM"  # the worker's reason, in its `closed` event
    _unknown_health(page, f"the service closed: {why}")
    expect(page.locator("#message")).to_contain_text(f"The service closed: {why}")
    expect(page.locator("#abort")).to_be_hidden()
    # The runs table says how the run ended, though the service cannot be asked for the list again.
    run_id = page.locator("#live-run").inner_text()
    expect(page.locator(f"#runs tbody tr[data-id='{run_id}']")).to_have_attribute("data-status", "aborted")
    service.process.wait(timeout=CLOSED_S)

    # Gone: the polls fail, and the bar keeps the reason it was given rather than a bare "unreachable".
    time.sleep(POLLS_S)  # waiting for polls that must change nothing: there is no event to wait on
    expect(page.locator("#rig-state")).to_have_text("closed")
    _unknown_health(page, "SIGTERM")
    for width in (360, 1280, 1920):
        page.set_viewport_size({"width": width, "height": 900 if width == 1280 else 800})
        _no_horizontal_scroll(page)
        _stop_on_screen_and_uncovered(page)
        _axe(page)
        _shot(page, "closed")
    assert page_errors == []
    page.close()
