"""The web pages in a real headless Chromium (Debian's /usr/bin/chromium driven by Playwright): sign in with a
token, upload a submission with its method's description, watch it finish, find it on the leaderboard (ties,
best per account, one scene, CSV, comparing two), open its page with every figure and its plots, download and
withdraw it; a failing form keeps its values and chosen file; /docs with no network; relocalize two real photos
(refused without the depth the method needs); create a multi-photo anchor on the page, add and delete a photo;
every page at a 390 px wide phone viewport. Screenshots go to
test-artifacts/."""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

import pytest

from mapfree.data import Dataset

from .conftest import ARTIFACTS, make_submission
from .test_leaderboard import fresh_users, submit_done

CHROMIUM = os.environ.get("MAPFREE_CHROMIUM", "/usr/bin/chromium")
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(
        not Path(CHROMIUM).exists(), reason=f"{CHROMIUM} is absent (apt-get install chromium; .ci/services.sh does)"
    ),
]
PHONE = {"width": 390, "height": 844}


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        yield b
        b.close()


def _new_page(browser, server, viewport: dict):
    ctx = browser.new_context(base_url=server.url, viewport=viewport, accept_downloads=True)
    pg = ctx.new_page()
    pg.set_default_timeout(60_000)
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    return ctx, pg, errors


@pytest.fixture
def page(browser, sqlite_server):
    ctx, pg, errors = _new_page(browser, sqlite_server, {"width": 1280, "height": 900})
    yield pg
    ctx.close()
    assert not errors, f"JavaScript errors: {errors}"


@pytest.fixture
def phone(browser, sqlite_server):
    ctx, pg, errors = _new_page(browser, sqlite_server, PHONE)
    yield pg
    ctx.close()
    assert not errors, f"JavaScript errors: {errors}"


def shot(page, name: str) -> None:
    ARTIFACTS.mkdir(exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / f"{name}.png"), full_page=True)


def _sign_in(page, server, user: str = "alice") -> None:
    page.goto("/login")
    page.fill("#token", server.tokens[user])
    page.click("#login-button")
    page.wait_for_url("**/me")
    assert user in page.inner_text("#nav-me")


def _row(page, name: str):
    return page.locator("#leaderboard tr.entry", has_text=name)


def test_submit_watch_leaderboard_and_plots(page, sqlite_server, tmp_path):
    (user,) = fresh_users(sqlite_server, "web")
    _sign_in(page, sqlite_server, user)
    zip_path = tmp_path / "browser-run.zip"
    zip_path.write_bytes(make_submission(sqlite_server.data.root / "val", noise=0.2, seed=7))
    page.goto("/submit")
    assert re.search(r"Test evaluations left today: \d+ of \d+", page.inner_text("#quota"))
    page.fill("#name", "browser-run")
    page.select_option("#split", "val")
    page.check("#public")
    page.set_input_files("#file", str(zip_path))
    page.fill("#description", "SIFT + PnP on sensor depth")
    page.fill("#paper_url", "https://arxiv.org/abs/2210.05494")
    page.fill("#code_url", "https://github.com/example/reloc")
    page.fill("#runtime_ms", "120")
    page.check("#extra_data")
    page.click("#submit-button")
    page.wait_for_url("**/submissions/*")
    page.wait_for_selector("#status[data-status=done]")  # the page polls and reloads when finished
    assert page.inner_text("#status") == "done"
    metrics = page.inner_text("#metrics")
    for key in (
        "AUC @ VCRE < 90px",
        "AUC @ VCRE < 45px",
        "Precision @ Pose Error < (50.0cm, 10deg)",
        "AUC @ Pose Error < (50.0cm, 10deg)",
    ):
        assert key in metrics
    assert page.locator("#metrics tr").count() == 12, metrics
    assert "SIFT + PnP on sensor depth" in page.inner_text("#method")
    sub_url = page.url
    if page.locator("img.plot").count():
        page.wait_for_function("() => [...document.images].every(i => i.complete && i.naturalWidth > 0)")
    shot(page, "submission")
    page.goto("/leaderboard/val")
    row = _row(page, "browser-run")
    assert row.count() == 1
    cells = row.locator("td").all_inner_texts()
    assert re.fullmatch(r"\d{4}-\d\d-\d\d", cells[4].strip())  # the date column
    assert row.locator("a.paper").get_attribute("href") == "https://arxiv.org/abs/2210.05494"
    assert "extra data" in row.inner_text() and cells[-1].strip() == "120"
    assert page.locator("th[aria-sort=descending]").inner_text().startswith("VCRE AUC ▼")
    # the published rows: a table of their own, with the dataset they come from and MicKey's precision
    assert "RPR R(q)+t" not in page.inner_text("#leaderboard")
    mickey = page.locator("#reference tr", has_text="MicKey").locator("td").all_inner_texts()
    assert mickey[1] == "Map-free val (real)" and mickey[3] == "0.450"
    page.click("#sort-med_trans")
    page.wait_for_url("**sort=med_trans**")
    assert page.locator("th[aria-sort=ascending]").inner_text().startswith("Med. trans. (m) ▲")
    shot(page, "leaderboard")
    page.click("text=browser-run")
    page.wait_for_url(sub_url)
    page.goto("/me")
    assert "browser-run" in page.inner_text("#history")


def test_ties_best_view_scene_csv_and_compare(page, sqlite_server):
    u1, u2 = fresh_users(sqlite_server, "tie-x", "tie-y")
    val = sqlite_server.data.root / "val"
    good = make_submission(val, noise=0.1, seed=31)
    a = submit_done(sqlite_server, u1, good, f"{u1}-same")
    b = submit_done(sqlite_server, u2, good, f"{u2}-same")
    c = submit_done(sqlite_server, u1, make_submission(val, noise=0.6, seed=32, drop_every=2), f"{u1}-worse")
    page.goto("/leaderboard/val")
    rank = lambda name: _row(page, name).locator("td.rank").inner_text()  # noqa: E731
    assert rank(a["name"]) == rank(b["name"])  # equal scores, equal rank
    assert int(rank(c["name"])) > int(rank(a["name"])) + 1
    # compare two checked rows
    _row(page, a["name"]).locator("input[type=checkbox]").check()
    _row(page, c["name"]).locator("input[type=checkbox]").check()
    page.click("#compare-button")
    page.wait_for_url("**/compare?**")
    table = page.inner_text("#compare")
    assert "AUC @ VCRE < 45px" in table and "B − A" in table
    vcre = page.locator("#compare tr", has_text="AUC @ VCRE < 90px").locator("td").all_inner_texts()
    assert vcre[3] == "A" and vcre[2].startswith("-")
    assert page.locator("#compare-scenes tr").count() == 1 + len(a["per_scene"])
    shot(page, "compare")
    # each account's best only
    page.goto("/leaderboard/val")
    page.select_option("#view", "best")
    page.click("#apply")
    page.wait_for_url("**view=best**")
    users = [t.strip() for t in page.locator("#leaderboard tr.entry td:nth-child(4)").all_inner_texts()]
    assert len(users) == len(set(users)) and u1 in users and _row(page, c["name"]).count() == 0
    shot(page, "leaderboard-best")
    # one scene
    scene = sorted(a["per_scene"])[0]
    page.select_option("#scene", scene)
    page.click("#apply")
    page.wait_for_url(f"**scene={scene}**")
    assert scene in page.inner_text("h1")
    want = f"{a['per_scene'][scene]['AUC @ VCRE < 90px']:.3f}"
    assert _row(page, a["name"]).locator("td").nth(5).inner_text() == want
    shot(page, "leaderboard-scene")
    # CSV of what is shown
    with page.expect_download() as dl:
        page.click("#csv")
    rows = list(csv.DictReader(io.StringIO(Path(dl.value.path()).read_text())))
    assert {r["user"] for r in rows} >= {u1, u2} and len({r["user"] for r in rows}) == len(rows)


def test_form_errors_keep_the_form_and_the_user(page, sqlite_server, tmp_path):
    (user,) = fresh_users(sqlite_server, "forms")
    page.goto("/login")
    page.fill("#token", "mf_not-a-token")
    page.click("#login-button")
    page.wait_for_selector("#form-error:not([hidden])")
    assert "invalid or revoked" in page.inner_text("#form-error") and page.locator("#login-form").count() == 1
    _sign_in(page, sqlite_server, user)
    zip_path = tmp_path / "kept.zip"
    zip_path.write_bytes(make_submission(sqlite_server.data.root / "val", seed=41))
    page.goto("/submit")
    page.fill("#name", "kept-file")
    page.set_input_files("#file", str(zip_path))
    page.fill("#paper_url", "javascript:alert(1)")
    page.evaluate("document.getElementById('paper_url').type = 'text'")  # let the server judge it
    page.click("#submit-button")
    page.wait_for_selector("#form-error:not([hidden])")
    assert "paper_url" in page.inner_text("#form-error")
    assert page.url.endswith("/submit") and user in page.inner_text("#nav-me")
    assert page.eval_on_selector("#file", "e => e.files.length") == 1  # the chosen file is still there
    assert page.input_value("#name") == "kept-file"
    shot(page, "submit-error")
    page.fill("#paper_url", "https://example.org/paper")
    page.click("#submit-button")
    page.wait_for_url("**/submissions/*")
    assert "kept-file" in page.inner_text("h1")
    # without JavaScript's help (a plain navigation) the error page still knows who is signed in
    page.goto("/submissions/" + "0" * 32)
    assert "no such submission" in page.inner_text("#error-message")
    assert user in page.inner_text("#nav-me") and page.locator("#nav-login").count() == 0


def test_download_and_withdraw(page, sqlite_server, tmp_path):
    (user,) = fresh_users(sqlite_server, "owner")
    data = make_submission(sqlite_server.data.gt / "test", noise=0.2, seed=51)
    d = submit_done(sqlite_server, user, data, "withdraw-me", split="test")
    _sign_in(page, sqlite_server, user)
    with sqlite_server.client(user) as c:
        left = c.get("/api/me").json()["test_evaluations_left_today"]
    page.goto("/me")
    assert int(page.locator("#quota b").inner_text()) == left  # the quota on the page, not only in /api/me
    page.goto(d["url"])
    assert page.locator("#metrics tr").count() == 12
    with page.expect_download() as dl:
        page.click("#download")
    assert Path(dl.value.path()).read_bytes() == data
    shot(page, "submission-owner")
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("#withdraw")
    page.wait_for_url("**/me")
    row = page.locator("#history tr", has_text="withdraw-me")
    assert "withdrawn" in row.inner_text() and row.locator("a").count() == 1
    assert int(page.locator("#quota b").inner_text()) == left  # the evaluation stays counted
    shot(page, "history-withdrawn")
    # its owner still sees its page, linked from their history (it used to be a 404, which contradicted that
    # list): marked withdrawn, no scores, nothing left to change; others get 404 (test_withdraw_and_download)
    row.locator("a").click()
    page.wait_for_url(f"**{d['url']}")
    assert page.inner_text("#status") == "withdrawn" and "Withdrawn " in page.inner_text("#withdrawn")
    assert page.locator("#metrics").count() == 0 and page.locator("#owner-actions").count() == 0
    assert page.locator("#method-form").count() == 0
    page.goto("/leaderboard/test")
    assert "withdraw-me" not in page.inner_text("#leaderboard")


def test_docs_work_offline(page, sqlite_server):
    outside: list[str] = []

    def only_local(route):
        if route.request.url.startswith(sqlite_server.url):
            route.continue_()
        else:
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", only_local)
    page.goto("/docs")
    page.wait_for_selector(".swagger-ui .info .title")
    assert "mapfree service" in page.inner_text(".swagger-ui .info .title")
    page.get_by_text("/api/leaderboard/{split}", exact=True).first.wait_for()
    assert not outside, outside
    shot(page, "docs")


def test_relocalize_two_real_photos(page, sqlite_server, realmini_dir):
    _sign_in(page, sqlite_server, "bob")
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, query = scene.reference, scene.frame("seq1/frame_00009.jpg")
    page.goto("/relocalize")
    page.set_input_files("#reference", str(ref.image_path))
    page.set_input_files("#query", str(query.image_path))
    for prefix, K in (("ref", ref.intrinsics), ("q", query.intrinsics)):
        for k in ("fx", "fy", "cx", "cy"):
            page.fill(f"#{prefix}_{k}", str(getattr(K, k)))
    page.fill("#method", "sift_pnp_sensor")
    page.click("#reloc-button")  # no depth: refused up front, with the photos still chosen
    page.wait_for_selector("#form-error:not([hidden])")
    assert "needs the reference depth" in page.inner_text("#form-error")
    assert page.locator("#figure").count() == 0
    assert page.eval_on_selector("#reference", "e => e.files.length") == 1
    shot(page, "relocalize-no-depth")
    page.set_input_files("#reference_depth", str(ref.depth_path("sensor")))
    page.click("#reloc-button")
    page.wait_for_selector("#figure")
    page.wait_for_function("() => document.getElementById('figure').naturalWidth > 0")
    assert page.locator("#form-error").is_hidden()
    assert page.locator("#pose").count() == 1, page.inner_text("#result")
    assert "Pose found" in page.inner_text("#result")
    shot(page, "relocalize")


def test_anchor_from_several_photos_then_add_and_delete_one(page, sqlite_server, realmini_dir):
    """The relocalize page creates a multi-photo anchor (multiple file inputs, one cameras line per photo); a
    failing form keeps its files and text; the anchor's page adds a photo and deletes one."""
    scene = Dataset(realmini_dir).scene("val", "s00000")
    ref, second, third = scene.reference, scene.frame("seq1/frame_00022.jpg"), scene.frame("seq1/frame_00005.jpg")

    def line(f, pose: bool) -> str:
        K, (q, t) = f.intrinsics, f.pose.qt()
        return f"{f.image_path.name} {K.fx} {K.fy} {K.cx} {K.cy}" + (
            " " + " ".join(f"{x:.9f}" for x in [*q, *t]) if pose else ""
        )

    cameras = line(ref, False) + "\n" + line(second, True)
    _sign_in(page, sqlite_server, "alice")
    page.goto("/relocalize")
    page.fill("#new-name", "browser anchor")
    page.fill("#new-method", "sift_pnp_sensor")
    page.set_input_files("#new-photos", [str(ref.image_path), str(second.image_path)])
    assert page.input_value("#cameras").split() == [ref.image_path.name, second.image_path.name]  # started
    page.fill("#cameras", cameras)
    page.set_input_files("#new-depths", [str(ref.depth_path("sensor"))])  # photo 1's depth forgotten
    page.click("#create-anchor-button")
    page.wait_for_selector("#anchor-error:not([hidden])")
    assert "photo 1 ('frame_00022.jpg'): method sift_pnp_sensor" in page.inner_text("#anchor-error")
    assert page.locator("#form-error").is_hidden()  # the other form's box stays empty
    assert page.eval_on_selector("#new-photos", "e => e.files.length") == 2
    assert page.input_value("#cameras") == cameras and page.input_value("#new-name") == "browser anchor"
    shot(page, "anchor-create-error")
    page.set_input_files("#new-depths", [str(ref.depth_path("sensor")), str(second.depth_path("sensor"))])
    page.click("#create-anchor-button")
    page.wait_for_url("**/relocalize/anchors/*")
    aid = page.url.rsplit("/", 1)[1]
    try:
        assert page.locator("figure.anchor-photo").count() == 2
        assert page.locator("#delete-photo-0").count() == 0  # the anchor's frame stays
        # add a photo: a bad pose first (the values typed and the file stay), then the right one
        K = third.intrinsics
        page.set_input_files("#add-image", str(third.image_path))
        page.set_input_files("#add-depth", str(third.depth_path("sensor")))
        for k in ("fx", "fy", "cx", "cy"):
            page.fill(f"#add-{k}", str(getattr(K, k)))
        page.fill("#add-pose", "1 0 0")
        page.click("#add-photo-button")
        page.wait_for_selector("#form-error:not([hidden])")
        assert "photo 2 ('frame_00005.jpg'): pose: expected 7 numbers" in page.inner_text("#form-error")
        assert page.input_value("#add-fx") == str(K.fx) and page.eval_on_selector("#add-image", "e => e.files.length")
        page.fill("#add-pose", line(third, True).split(" ", 5)[5])
        page.click("#add-photo-button")
        page.wait_for_selector("#photo-2")
        assert page.inner_text("#photo-count") == "3 photos"
        page.once("dialog", lambda dialog: dialog.accept())
        page.click("#delete-photo-1")
        page.wait_for_selector("#photo-1", state="detached")
        ids = page.eval_on_selector_all("figure.anchor-photo", "fs => fs.map(f => f.id)")
        assert ids == ["photo-0", "photo-2"], ids
        page.wait_for_function("() => [...document.images].every(i => i.complete && i.naturalWidth > 0)")
        shot(page, "anchor-page")
        page.set_viewport_size(PHONE)
        assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
        shot(page, "phone-anchor-page")
    finally:
        with sqlite_server.client("alice") as alice:
            assert alice.delete(f"/anchors/{aid}").status_code == 204


def test_phone_width(phone, sqlite_server):
    """Nothing wider than a 390 px phone screen: wide tables scroll inside their box, the page does not."""
    _sign_in(phone, sqlite_server, "alice")
    with sqlite_server.client("alice") as c:
        done = [s for s in c.get("/api/submissions").json() if s["status"] == "done" and s["split"] == "val"]
    if not done:
        done = [submit_done(sqlite_server, "alice", make_submission(sqlite_server.data.root / "val"), "phone")]
    pages = {
        "leaderboard-val": "/leaderboard/val",
        "leaderboard-test": "/leaderboard/test",
        "submit": "/submit",
        "relocalize": "/relocalize",
        "me": "/me",
        "submission": done[0]["url"],
        "compare": f"/compare?id={done[0]['id']}&id={done[-1]['id']}",
    }
    too_wide = {}
    for name, path in pages.items():
        phone.goto(path)
        width = phone.evaluate("document.documentElement.scrollWidth")
        if width > PHONE["width"]:
            too_wide[path] = width
        shot(phone, f"phone-{name}")
    assert not too_wide, f"wider than {PHONE['width']} px: {too_wide}"
