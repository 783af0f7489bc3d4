"""The web pages in a real headless Chromium (Debian's /usr/bin/chromium driven by Playwright): sign in with a
token, upload a submission, watch it finish, find it on the leaderboard, open its page and plots; relocalize
two real photos. Screenshots go to test-artifacts/."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mapfree.data import Dataset

from .conftest import ARTIFACTS, make_submission

CHROMIUM = os.environ.get("MAPFREE_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(not Path(CHROMIUM).exists(),
                                 reason=f"{CHROMIUM} is absent (apt-get install chromium; .ci/services.sh does)")]


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield b
        b.close()


@pytest.fixture
def page(browser, sqlite_server):
    ctx = browser.new_context(base_url=sqlite_server.url, viewport={"width": 1280, "height": 900})
    pg = ctx.new_page()
    pg.set_default_timeout(60_000)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    yield pg
    ctx.close()
    assert not errors, f"JavaScript errors: {errors}"


def _sign_in(page, server, user: str = "alice") -> None:
    page.goto("/login")
    page.fill("#token", server.tokens[user])
    page.click("#login-button")
    page.wait_for_url("**/me")
    assert user in page.inner_text("#nav-me")


def test_submit_watch_leaderboard_and_plots(page, sqlite_server, tmp_path):
    ARTIFACTS.mkdir(exist_ok=True)
    _sign_in(page, sqlite_server)
    zip_path = tmp_path / "browser-run.zip"
    zip_path.write_bytes(make_submission(sqlite_server.data.root / "val", noise=0.2, seed=7))
    page.goto("/submit")
    page.fill("#name", "browser-run")
    page.select_option("#split", "val")
    page.check("#public")
    page.set_input_files("#file", str(zip_path))
    page.click("#submit-button")
    page.wait_for_url("**/submissions/*")
    page.wait_for_selector("#status[data-status=done]")  # the page polls and reloads when finished
    assert page.inner_text("#status") == "done"
    assert "AUC @ VCRE < 90px" in page.inner_text("#metrics")
    sub_url = page.url
    plots = page.locator("img.plot")
    if plots.count():
        page.wait_for_function("() => [...document.images].every(i => i.complete && i.naturalWidth > 0)")
    page.screenshot(path=str(ARTIFACTS / "submission.png"), full_page=True)
    page.goto("/leaderboard/val")
    board = page.inner_text("#leaderboard")
    assert "browser-run" in board and "RPR R(q)+t" in board
    page.click("#sort-med_trans")
    page.wait_for_url("**sort=med_trans")
    page.screenshot(path=str(ARTIFACTS / "leaderboard.png"), full_page=True)
    page.click("text=browser-run")
    page.wait_for_url(sub_url)
    page.goto("/me")
    assert "browser-run" in page.inner_text("#history")


def test_relocalize_two_real_photos(page, sqlite_server, realmini_dir):
    ARTIFACTS.mkdir(exist_ok=True)
    _sign_in(page, sqlite_server, "bob")
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    page.goto("/relocalize")
    page.set_input_files("#reference", str(ref.image_path))
    page.set_input_files("#reference_depth", str(ref.depth_path("sensor")))
    page.set_input_files("#query", str(query.image_path))
    for prefix, K in (("ref", ref.intrinsics), ("q", query.intrinsics)):
        for k in ("fx", "fy", "cx", "cy"):
            page.fill(f"#{prefix}_{k}", str(getattr(K, k)))
    page.fill("#method", "sift_pnp_sensor")
    page.click("#reloc-button")
    page.wait_for_selector("#figure")
    page.wait_for_function("() => document.getElementById('figure').naturalWidth > 0")
    assert page.locator("#pose").count() == 1, page.inner_text("#result")
    assert "Pose found" in page.inner_text("#result")
    page.screenshot(path=str(ARTIFACTS / "relocalize.png"), full_page=True)
