"""The web console in a real browser: Debian's Chromium, driven by Playwright (the
Python package, launched with the system Chromium). The paper's setup runs as
processes (simulator, broker, tracking and delivery systems) with `muster web` in
front; every process is started here and stopped by PID.

Run by `bash scripts/test` (which installs Playwright; `.ci/run` installs Chromium).
Without them the tests are skipped, or fail when MUSTER_REQUIRE_BROWSER is set.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BIN = os.environ.get("MUSTER_BIN", str(REPO / "target" / "debug" / "muster"))
CHROMIUM = os.environ.get("MUSTER_CHROMIUM", "/usr/bin/chromium")
# As the machine's own probe starts it: no sandbox as root, and nothing reaching out
# to a network this machine does not have.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
PAPER = ["delivery/D1", "tracking/blue", "tracking/green", "tracking/red"]


def _missing(why: str):
    if os.environ.get("MUSTER_REQUIRE_BROWSER"):
        pytest.fail(why + " (bash scripts/test sets it up)")
    pytest.skip(why)


try:
    from playwright.sync_api import expect, sync_playwright
except ImportError:  # pragma: no cover - depends on the machine
    sync_playwright = None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {timeout} s")
        time.sleep(0.05)


class Paper:
    """The paper's setup and `muster web`, on an instance of its own."""

    def __init__(self):
        self.inst = f"web{os.getpid() % 100000}"
        self.dir = Path(tempfile.mkdtemp(prefix=f"muster-web-{self.inst}-"))
        self.procs: list[subprocess.Popen] = []
        lines = []
        for user, allow, *role in [("guest", "*"), ("vera", "*"), ("ursula", "tracking/*"),
                                   ("olga", "*", "--operator")]:
            r = subprocess.run([BIN, "keygen", "--user", user, "--web", "--out", str(self.dir),
                                "--allow", allow, *role], capture_output=True, text=True, timeout=30)
            assert r.returncode == 0, r.stderr
            lines.append(r.stdout)
        self.access = self.dir / "access"
        self.access.write_text("".join(lines))
        self.spawn("sim", "--speed", "2", "--seed", "1")
        self.spawn("broker")
        self.spawn("system", "tracking", "--mobile", "T3", "--seed", "1")
        self.spawn("system", "delivery", "--seed", "1")
        self.url = self.web()

    def spawn(self, *args: str, name: str | None = None) -> subprocess.Popen:
        label = name or args[0] + ("-" + args[1] if len(args) > 1 and args[0] == "system" else "")
        out = open(self.dir / f"{label}.out", "w")
        err = open(self.dir / f"{label}.err", "w")
        p = subprocess.Popen([BIN, "--instance", self.inst, "--time-scale", "2", *args],
                             stdout=out, stderr=err, stdin=subprocess.DEVNULL)
        self.procs.append(p)
        return p

    def web(self, label: str = "web", *extra: str) -> str:
        port = free_port()
        self.spawn("web", "--listen", f"127.0.0.1:{port}", "--access", str(self.access),
                   "--wait", "30s", *extra, name=label)
        out = self.dir / f"{label}.out"
        line = wait_until(lambda: out.read_text().strip(), 30, "muster web listening")
        return json.loads(line.splitlines()[0])["url"]

    def token(self, user: str) -> str:
        return (self.dir / f"{user}.web").read_text().strip()

    def close(self):
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(self.procs):
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(self.dir, ignore_errors=True)


@pytest.fixture(scope="module")
def paper():
    if not Path(CHROMIUM).exists():
        _missing(f"no Chromium at {CHROMIUM} (apt-get install chromium)")
    if sync_playwright is None:
        _missing("no Playwright for Python (pip install playwright)")
    p = Paper()
    try:
        yield p
    finally:
        p.close()


@pytest.fixture(scope="module")
def browser(paper):
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def sign_in(browser, url: str, user: str, token: str):
    page = browser.new_context(viewport={"width": 1280, "height": 1000}).new_page()
    page.goto(url)
    page.fill("#signin-user", user)
    page.fill("#signin-token", token)
    page.click("#signin-button")
    expect(page.locator("#who")).to_have_text(re.compile("^" + user + r"( \(operator\))?$"), timeout=10_000)
    return page


def listed(page) -> list[str]:
    return sorted(page.eval_on_selector_all("#services tbody tr", "rs => rs.map(r => r.dataset.service)"))


def in_use(page, service: str) -> str:
    return page.inner_text(f'tr[data-service="{service}"] td.in-use')


def test_sign_in_request_watch_link_drive_by_map_and_end_as_a_second_browser_watches(paper, browser):
    page = sign_in(browser, paper.url, "guest", paper.token("guest"))
    wait_until(lambda: listed(page) == PAPER, 30, "the paper's four services listed")
    watcher = sign_in(browser, paper.url, "vera", paper.token("vera"))
    wait_until(lambda: listed(watcher) == PAPER, 30, "the watcher's list")
    assert in_use(watcher, "tracking/red") == "0/10"

    # Request red: the second browser sees the in-use count change.
    t0 = time.monotonic()
    page.click('tr[data-service="tracking/red"] button.request')
    wait_until(lambda: in_use(watcher, "tracking/red") == "1/10", 5, "the watcher sees red in use")
    seen_after = time.monotonic() - t0
    print(f"the second browser saw the in-use count change {seen_after * 1000:.0f} ms after the click")

    # Red's positions change in its session's card.
    card = page.locator('.session[data-service="tracking/red"]')
    expect(card).to_be_visible(timeout=10_000)
    values = set()

    def moved():
        v = card.locator(".value").inner_text()
        if re.search(r" x -?\d", v):
            values.add(re.sub(r"^#\d+\s+", "", v))
        return len(values) >= 3
    wait_until(moved, 60, "three different positions of red")

    # Link red -> D1: D1 drives toward her.
    page.select_option("#link-data", "tracking/red")
    page.select_option("#link-command", "delivery/D1")
    page.click("#link-button")
    d1 = page.locator('.session[data-service="delivery/D1"] .status')
    expect(d1).to_contain_text("driving", timeout=90_000)
    wait_until(lambda: in_use(watcher, "delivery/D1") == "1/1", 5, "the watcher sees D1 in use")

    # Unlink; ask for D1 directly and give it a goal by clicking on the map.
    page.click("#links li button")
    expect(page.locator('.session[data-service="delivery/D1"]')).to_have_count(0, timeout=15_000)
    page.click('tr[data-service="delivery/D1"] button.request')
    expect(page.locator('.session[data-service="delivery/D1"]')).to_have_count(1, timeout=15_000)
    expect(page.locator("#map-time")).to_contain_text("sim", timeout=10_000)
    goal = (20.0, 10.0)  # the corridor between the two rows of offices
    box = page.locator("#map").bounding_box()
    px, py = page.evaluate(f"toPx({goal[0]}, {goal[1]})")
    width = page.evaluate("document.getElementById('map').width")
    k = box["width"] / width
    page.locator("#map").click(position={"x": px * k, "y": py * k})
    status = page.locator('.session[data-service="delivery/D1"] .status')
    expect(status).to_contain_text("goal (", timeout=30_000)
    m = re.search(r"goal \((-?[\d.]+), (-?[\d.]+)\)", status.inner_text())
    assert m, status.inner_text()
    assert abs(float(m.group(1)) - goal[0]) < 0.2 and abs(float(m.group(2)) - goal[1]) < 0.2, m.group(0)
    fps = page.inner_text("#map-fps")
    print(f"map: {fps}")
    assert re.match(r"\d+ frames/s", fps), fps

    # End the session: its card goes, and the second browser sees D1 free.
    page.click('.session[data-service="delivery/D1"] button.end')
    expect(page.locator('.session[data-service="delivery/D1"]')).to_have_count(0, timeout=15_000)
    wait_until(lambda: in_use(watcher, "delivery/D1") == "0/1", 5, "the watcher sees D1 free")
    page.context.close()
    watcher.context.close()


def test_a_user_without_delivery_neither_sees_it_nor_gets_it_through_the_socket(paper, browser):
    page = sign_in(browser, paper.url, "ursula", paper.token("ursula"))
    wait_until(lambda: listed(page) == PAPER[1:], 30, "ursula's three tracking services")
    # Straight through a socket of her own, past the app: refused as unknown.
    frame = page.evaluate("""() => new Promise((done, fail) => {
        const ws = new WebSocket('ws://' + location.host + '/ws');
        ws.onmessage = (ev) => {
            const f = JSON.parse(ev.data);
            if (f.t === 'state') ws.send(JSON.stringify({op: 'request', service: 'delivery/D1'}));
            if (f.t === 'refused' || f.t === 'granted') { ws.close(); done(f); }
        };
        ws.onerror = () => fail('socket error');
        setTimeout(() => fail('no answer'), 10000);
    })""")
    assert frame["t"] == "refused" and frame["code"] == "unknown", frame
    assert frame["service"] == "delivery/D1"
    page.context.close()


def test_an_operator_ends_another_users_session_and_withdraws_and_restores_a_service(paper, browser):
    user = sign_in(browser, paper.url, "vera", paper.token("vera"))
    op = sign_in(browser, paper.url, "olga", paper.token("olga"))
    expect(op.locator("#operator")).to_be_visible()
    expect(user.locator("#operator")).to_be_hidden()
    wait_until(lambda: listed(user) == PAPER, 30, "vera's list")
    user.click('tr[data-service="tracking/green"] button.request')
    expect(user.locator('.session[data-service="tracking/green"]')).to_have_count(1, timeout=15_000)
    # The operator's table shows vera's session under her web user; End ends it.
    row = op.locator('#op-sessions tr', has_text="tracking/green").filter(has_text="web-vera-")
    expect(row).to_have_count(1, timeout=10_000)
    row.locator("button.op-end").click()
    expect(user.locator('.session[data-service="tracking/green"]')).to_have_count(0, timeout=15_000)
    expect(user.locator("#log")).to_contain_text("tracking/green: session ended", timeout=5_000)
    # Withdraw and restore: vera's row follows.
    op.click('tr[data-service="tracking/blue"] button.withdraw')
    expect(user.locator('tr[data-service="tracking/blue"]')).to_have_class("withdrawn", timeout=5_000)
    expect(user.locator('tr[data-service="tracking/blue"] button.request')).to_be_disabled()
    op.click('tr[data-service="tracking/blue"] button.restore')
    expect(user.locator('tr[data-service="tracking/blue"]')).not_to_have_class("withdrawn", timeout=5_000)
    user.context.close()
    op.context.close()


def test_bad_sign_ins_are_refused_then_rate_limited(paper, browser):
    # A web server of its own: the limit holds this address for a minute.
    url = paper.web("web-limit")
    page = browser.new_context().new_page()
    page.goto(url)
    for i in range(5):
        page.fill("#signin-user", "guest")
        page.fill("#signin-token", f"not-the-token-{i}")
        page.click("#signin-button")
        expect(page.locator("#signin-error")).to_have_text("wrong user name or token", timeout=5_000)
        page.evaluate("document.getElementById('signin-error').textContent = ''")
    page.fill("#signin-token", paper.token("guest"))
    page.click("#signin-button")
    expect(page.locator("#signin-error")).to_contain_text("too many failed sign-ins", timeout=5_000)
    expect(page.locator("#console")).to_be_hidden()
    page.context.close()


def test_over_tls_the_console_works_and_its_session_cookie_is_secure(paper, browser):
    certs = paper.dir / "certs"
    r = subprocess.run([BIN, "certs", "--out", str(certs), "--hosts", "web", "--san", "127.0.0.1"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    url = paper.web("web-tls", "--tls", str(certs / "web.pem"), str(certs / "web.key"))
    assert url.startswith("https://"), url
    # The certificate is the test's own CA's, which this browser does not know.
    ctx = browser.new_context(ignore_https_errors=True)
    page = ctx.new_page()
    page.goto(url)
    page.fill("#signin-user", "guest")
    page.fill("#signin-token", paper.token("guest"))
    page.click("#signin-button")
    wait_until(lambda: listed(page) == PAPER, 30, "the list over wss://")
    cookie = [c for c in ctx.cookies() if c["name"] == "muster_session"]
    assert len(cookie) == 1, ctx.cookies()
    assert cookie[0]["secure"] and cookie[0]["httpOnly"] and cookie[0]["sameSite"] == "Strict", cookie
    ctx.close()
