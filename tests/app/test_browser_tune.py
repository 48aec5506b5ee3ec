"""Tuning in a real browser: vary two parameters of the page's sliders, start a small tune
(3 trials on 2 frames of the sample set) with the page's controls, watch it finish, see the
plots drawn, and load the best trial into the sliders of the viser panel."""

from __future__ import annotations

import time
from typing import Any

import pytest
from browser_support import VIEWPORT, Server, missing_browser

pytestmark = pytest.mark.browser

_reason = missing_browser()
if _reason is not None:
    pytest.skip(_reason, allow_module_level=True)

EPS1 = ("3. reliability", 0)  # viser folder, slider index of reliability.eps1
N_CTRL = ("7. spline", 0)  # spline.n_ctrl


def slider_value(page: Any, folder: str, index: int) -> float:
    header = page.frame_locator("#viewer").get_by_text(folder, exact=True)
    header.wait_for(timeout=60_000)
    sliders = header.locator("xpath=..").get_by_role("slider")
    if sliders.count() == 0:
        header.click()
        sliders.first.wait_for(timeout=30_000)
    return float(sliders.nth(index).get_attribute("aria-valuenow"))


def wait_slider(page: Any, slider: tuple[str, int], value: float, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    got = None
    while time.monotonic() < deadline:
        got = slider_value(page, *slider)
        if got == pytest.approx(value):
            return
        page.wait_for_timeout(200)
    raise AssertionError(f"{slider} shows {got}, expected {value}")


def vary(page: Any, key: str) -> Any:
    page.select_option("#tune-param", key)
    page.click("#tune-add")
    return page.locator(f'#tune-space tr[data-key="{key}"]')


def test_a_tune_started_from_the_page_loads_its_best_trial_into_the_sliders(new_context):
    with Server() as server:
        page = new_context(viewport=VIEWPORT).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(server.url + "/")
        page.wait_for_function("window.threadrecon && window.threadrecon.state", timeout=60_000)
        assert slider_value(page, *EPS1) == pytest.approx(8.0)  # the defaults
        assert slider_value(page, *N_CTRL) == 15

        page.click("#tune-section summary")
        page.wait_for_function("document.querySelectorAll('#tune-param option').length > 10")
        eps1 = vary(page, "reliability.eps1")
        eps1.locator("input.low").fill("3")
        eps1.locator("input.high").fill("12")
        eps1.locator("input.step").fill("0.5")
        n_ctrl = vary(page, "spline.n_ctrl")
        n_ctrl.locator("input.low").fill("10")
        n_ctrl.locator("input.high").fill("20")
        n_ctrl.locator("input.step").fill("10")  # 10 or 20: never the default 15
        page.select_option("#tune-objective", "e_S")
        page.fill("#tune-trials-n", "3")
        page.fill("#tune-frames", "2")
        page.click("#tune-start")
        page.wait_for_selector('#tune-status[data-state="running"]', timeout=30_000)
        page.wait_for_selector('#tune-status[data-state="done"]', timeout=240_000)
        assert page.locator("#tune-live tbody tr").count() == 3

        # results: a table of the best trials and real plots (SVG dots, one per trial)
        page.wait_for_selector("#tune-best tbody tr", timeout=30_000)
        assert page.locator("#tune-scatter svg").count() == 2  # one per varied parameter
        assert page.locator("#tune-pareto svg").count() == 2
        assert page.locator("#tune-scatter svg").first.locator("circle").count() >= 1
        best_trial = int(page.locator("#tune-best tbody tr").first.get_attribute("data-trial"))
        best = page.evaluate(
            "(n) => window.threadreconTune.results.trials.find((t) => t.number === n).values",
            best_trial,
        )
        assert best["spline.n_ctrl"] in (10, 20)

        page.locator("#tune-best tbody tr").first.locator("button.load").click()
        page.wait_for_function(
            "(n) => document.querySelector('#tune-msg').textContent.includes(`trial ${n} loaded`)",
            arg=best_trial,
        )
        wait_slider(page, N_CTRL, best["spline.n_ctrl"])
        wait_slider(page, EPS1, best["reliability.eps1"])
        # the badge follows the session's state push, which may land after the sliders' update
        page.wait_for_function(
            "(name) => document.querySelector('#preset-badge').textContent === name",
            arg=f"tune-trial-{best_trial}",
        )

        # save it as a preset; a built-in name is refused with a message
        page.fill("#tune-preset-name", "default")
        page.locator("#tune-best tbody tr").first.locator("button.save").click()
        page.wait_for_function(
            "document.querySelector('#tune-msg').textContent.includes('built in')"
        )
        page.fill("#tune-preset-name", "from-tune")
        page.locator("#tune-best tbody tr").first.locator("button.save").click()
        page.wait_for_function("document.querySelector('#tune-msg').textContent.includes('saved')")
        assert "from-tune" in server.api("/api/presets")
        assert not errors, errors
