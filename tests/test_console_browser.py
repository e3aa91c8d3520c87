"""Issue 44's console in a browser: ``passt-mav demo --view PORT`` (one boat, vehicle-sim in lockstep), the
page opened at the address the demo prints (its token), driven by headless Chromium.

Pause -> the boat's panel shows the vehicle's HOLD (its heartbeat, through the controller's status file);
Resume -> AUTO at the item it was paused at (the controller's answers name the item); End (RTL) -> RTL,
the run ends ("ended") and the page says "finished". The same page opened without the token is read-only
(its buttons disabled). Every wait is on a condition; Chromium is Debian's through Playwright
(tests/test_view_browser.py's helpers: it skips without a browser, fails with PASST_REQUIRE_BROWSER=1).
~40-60 s on two cores.
"""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
import time

import pytest
from test_view_browser import FLAGS, _free_port, _need_browser, _wait

MODE = "(() => { const t = document.querySelector('#boat-0 table'); if (!t) return null; "
MODE += "const m = t.textContent.match(/mode \\/ armed(\\w+)/); return m ? m[1] : null; })()"
RESULT = "(() => { const e = document.querySelector('#boat-0 .cmd-result'); return e ? e.textContent : ''; })()"


@contextlib.contextmanager
def demo_page(tmp_path, *extra, moves: int = 3, speedup: float = 100):
    """``passt-mav demo`` on the ocean field (one boat, lockstep; legs of ``moves`` moves, paced at ``speedup``) with
    ``extra`` options, and Chromium; yields
    (demo process, its log, the address it printed (with the token), browser context, page, page.evaluate)."""
    sync_playwright, exe = _need_browser()
    port, out = _free_port(), tmp_path / "demo.log"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    # the North Atlantic mission's 6.6 km cells: a 3-move leg lasts ~4000 s of simulated time, ~40 s of wall
    # time at 100x in lockstep: time to click (a leg ending first would answer Pause in the next leg)
    cmd = [
        sys.executable,
        "-m",
        "passt_mav.cli",
        "demo",
        "--field",
        "builtin:ocean",
        "--legs",
        "2",
        "--moves",
        str(moves),
    ]
    cmd += ["--speedup", str(speedup), "--view", str(port), "--no-report", "--out", str(tmp_path / "demo"), *extra]
    with open(out, "w") as log:
        demo = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        pattern = rf"http://127\.0\.0\.1:{port}/\?token=[\w-]+"
        found = _wait(lambda: re.search(pattern, out.read_text()), 90, "the address", demo, out)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=exe, headless=True, args=FLAGS)
            ctx = browser.new_context(viewport={"width": 1400, "height": 900})
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("dialog", lambda d: d.accept())  # End asks for confirmation
            yield demo, out, found.group(0), ctx, page, page.evaluate
            assert not errors, errors
            browser.close()
    finally:
        if demo.poll() is None:
            demo.terminate()
            demo.wait(30)


@pytest.mark.long(reason="a demo in wall time driven from headless Chromium: ~35 s")
def test_pause_resume_end_from_the_page(tmp_path):
    t0 = time.monotonic()
    with demo_page(tmp_path) as (demo, out, url, ctx, page, js):
        # without the token: read-only
        ro = ctx.new_page()
        ro.goto(url.split("?")[0])
        _wait(lambda: ro.evaluate("document.querySelectorAll('#boat-0 button').length") == 6, 120, "a panel", demo, out)
        assert ro.evaluate("Array.from(document.querySelectorAll('#boat-0 button')).every(b => b.disabled)")
        assert "read-only" in ro.evaluate("document.getElementById('console-note').textContent")
        ro.close()

        page.goto(url)
        assert "token" not in page.url  # sessionStorage holds it now (per port), never a cookie (issue 55)
        assert js("sessionStorage.getItem('passt_view_token')") == url.split("?token=")[1] and not ctx.cookies()
        page.check("#alarm")  # the operator's consent to beep
        _wait(lambda: js(MODE) == "AUTO", 120, "the boat in AUTO", demo, out)
        page.click("#boat-0 button[data-act=pause]")
        _wait(lambda: "LOITER at item" in js(RESULT), 60, "the answer to Pause", demo, out)
        _wait(lambda: js(MODE) == "LOITER", 30, "the vehicle to report LOITER", demo, out)
        item = re.search(r"LOITER at item (\d+)/", js(RESULT)).group(1)
        page.click("#boat-0 button[data-act=resume]")
        _wait(lambda: "resumed" in js(RESULT), 60, "the answer to Resume", demo, out)
        assert f"AUTO at item {item}/" in js(RESULT), js(RESULT)
        _wait(lambda: js(MODE) == "AUTO", 30, "the vehicle to report AUTO", demo, out)
        page.click("#boat-0 button[data-act='end:RTL']")
        _wait(lambda: "mission ended" in js(RESULT), 60, "the answer to End", demo, out)
        _wait(lambda: js(MODE) == "RTL", 30, "the vehicle to report RTL", demo, out)
        _wait(lambda: demo.poll() is not None, 120, "the demo to end")
        _wait(lambda: js("window.passtView.last.status") == "ended", 20, "the ended run on the page")
        assert js("window.passtView.beeps") >= 1  # the run's end ("stopped", an alert) beeped
        conn = "document.getElementById('conn').textContent"
        _wait(lambda: js(conn) in ("finished", "server gone (run finished)"), 20, "the page to say finished")
        # the finished run reopened: a record, not "connected"
        view = subprocess.Popen(
            [sys.executable, "-m", "passt_mav.cli", "view", str(tmp_path / "demo")],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            page.goto(re.search(r"http://\S+", view.stdout.readline()).group(0))
            _wait(lambda: js(conn) == "finished", 60, "finished")
            assert js("Array.from(document.querySelectorAll('#boat-0 button')).every(b => b.disabled)")
        finally:
            view.terminate()
            view.wait(10)
    print(f"console in Chromium: pause at item {item}, resumed there, RTL; {time.monotonic() - t0:.1f} s")


@pytest.mark.long(reason="a demo in wall time driven from headless Chromium through two approvals: ~1 min")
def test_approve_one_leg_and_reject_one_from_the_page(tmp_path):
    """``demo --approve``: leg 1 is approved and flies; leg 2 is rejected (planned again, the rejected attempt kept)
    and its new plan approved; the run completes. (Short legs: the approvals come between them.)"""
    import json

    box = "(() => { const e = document.querySelector('#boat-0 .approval'); return e ? e.dataset.leg : null; })()"
    with demo_page(tmp_path, "--approve", moves=1, speedup=400) as (demo, out, url, _ctx, page, js):
        page.goto(url)
        _wait(lambda: js(box) == "0", 120, "leg 1 awaiting approval", demo, out)
        assert "awaits approval" in js("document.querySelector('#boat-0 .approval').textContent")
        page.click("#boat-0 .approval button[data-act=approve]")
        _wait(lambda: "leg 1 approved" in js(RESULT), 60, "the answer to Approve", demo, out)
        _wait(lambda: js(MODE) == "AUTO", 60, "leg 1 flying", demo, out)
        _wait(lambda: js(box) == "1", 180, "leg 2 awaiting approval", demo, out)
        page.click("#boat-0 .approval button[data-act=reject]")
        _wait(lambda: "rejected: planned again" in js(RESULT), 60, "the answer to Reject", demo, out)
        attempt = tmp_path / "demo" / "legs" / "001" / "attempt_1" / "leg.json"
        _wait(lambda: attempt.exists() and js(box) == "1", 60, "leg 2 planned again, awaiting approval", demo, out)
        page.click("#boat-0 .approval button[data-act=approve]")
        _wait(lambda: "leg 2 approved" in js(RESULT), 60, "the answer to the second Approve", demo, out)
        _wait(lambda: demo.poll() is not None, 240, "the demo to end")
        assert demo.returncode == 0, out.read_text()[-3000:]
    summary = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert summary["status"] == "complete" and [lg["approval"]["answer"] for lg in summary["legs"]] == ["approve"] * 2
    assert summary["legs"][1]["attempts"][0]["status"] == "rejected by the operator"


#: before the page's own script: ``document.hidden`` under the test's control (``window.__hidden``: the page in the
#: background), and ``window.Notification`` recording each notification the page creates (after Chromium made it)
NOTIFY_INIT = """
(() => {
  window.__hidden = false;
  Object.defineProperty(document, 'hidden', {configurable: true, get: () => window.__hidden});
  Object.defineProperty(document, 'visibilityState', {configurable: true,
    get: () => (window.__hidden ? 'hidden' : 'visible')});
  window.__notes = [];
  const Real = window.Notification;
  if (!Real) return;
  class Recorded extends Real {
    constructor(title, options) {
      super(title, options);
      window.__notes.push({title: title, body: (options || {}).body, tag: (options || {}).tag});
    }
  }
  Object.defineProperty(Recorded, 'permission', {get: () => Real.permission});
  Recorded.requestPermission = (...a) => Real.requestPermission(...a);
  window.Notification = Recorded;
})();
"""


@pytest.mark.long(reason="a run flown on the lockstep simulator while headless Chromium watches it: ~15-35 s")
def test_an_alert_while_the_page_is_in_the_background_is_a_browser_notification(tmp_path):
    """``passt-mav view`` of a run still flying (a one-leg run on lockstep vehicle-sim, its summary marked running),
    Chromium with the notifications permission granted and alarms ticked: an alert while the page is hidden creates
    one notification (its title names the boat, its body the alert) and beeps; an alert while it is visible only
    beeps."""
    import json

    from test_console import lockstep_session

    from passt_mav.runs.live import RecordWriter

    sync_playwright, exe = _need_browser()
    with lockstep_session(tmp_path) as (_sim, make, rd):
        make(legs=1).run()
    summary = json.loads(rd.summary_file.read_text())
    rd.summary_file.write_text(json.dumps({**summary, "status": "running", "finished_utc": None}))
    view = subprocess.Popen(
        [sys.executable, "-m", "passt_mav.cli", "view", str(rd.root), "--port", str(_free_port())],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        url = re.search(r"http://\S+", view.stdout.readline()).group(0)
        origin = re.match(r"http://[^/]+", url).group(0)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=exe, headless=True, args=FLAGS)
            ctx = browser.new_context(viewport={"width": 1200, "height": 800})
            ctx.grant_permissions(["notifications"], origin=origin)
            ctx.add_init_script(NOTIFY_INIT)
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            js = page.evaluate
            page.goto(url)
            _wait(lambda: js("Notification.permission") == "granted", 30, "the permission")
            _wait(lambda: js("window.passtView.last") is not None, 60, "the first snapshot", view)
            page.check("#alarm")
            record = RecordWriter(rd.root)
            js("window.__hidden = true")
            record.event("fence_breach", "the vehicle reports a fence breach (boundary, breach 1)")
            _wait(lambda: js("window.__notes.length") >= 1, 60, "a notification", view)
            assert js("window.__notes") == [
                {
                    "title": "passt-mav: boat 0",
                    "body": "the vehicle reports a fence breach (boundary, breach 1)",
                    "tag": "passt-fence_breach",
                }
            ]
            beeps = js("window.passtView.beeps")
            assert beeps >= 1
            js("window.__hidden = false")
            record.event("vehicle_alert", "the vehicle says: GCS Failsafe (severity 4)")
            _wait(lambda: js("window.passtView.beeps") > beeps, 60, "the second alert's beep", view)
            assert js("window.__notes.length") == 1  # the page in front: no notification
            assert not errors, errors
            browser.close()
    finally:
        view.terminate()
        view.wait(10)
