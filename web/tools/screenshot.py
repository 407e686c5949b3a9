"""A screenshot of the web console during `muster up` (the README's picture).

    cargo build --release && .venv/bin/python web/tools/screenshot.py docs/web-console.png

Starts `muster up` (release build), signs in as its guest in Chromium (Playwright),
requests the three trackers and D1 (queued behind up's own link), waits, and saves
the whole page.
"""

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from playwright.sync_api import expect, sync_playwright

REPO = Path(__file__).resolve().parents[2]
BIN = REPO / "target" / "release" / "muster"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def main(out: str, wait_s: float = 40.0):
    up = subprocess.Popen([str(BIN), "--instance", "shot", "up", "--web", "127.0.0.1:0",
                           "--duration", "120s"], stdout=subprocess.PIPE, text=True)
    try:
        url = token_file = None
        for line in up.stdout:
            m = re.match(r"== web console: (\S+) \(sign in as guest with the token in (\S+)\) ==", line)
            if m:
                url, token_file = m.group(1), m.group(2)
                break
        assert url, "no web console line"
        token = Path(token_file).read_text().strip()
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
            page = b.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.fill("#signin-user", "guest")
            page.fill("#signin-token", token)
            page.click("#signin-button")
            expect(page.locator('tr[data-service="tracking/red"]')).to_be_visible(timeout=30_000)
            for s in ["tracking/red", "tracking/green", "tracking/blue", "delivery/D1"]:
                page.click(f'tr[data-service="{s}"] button.request')
            time.sleep(wait_s)
            page.screenshot(path=out, full_page=True)
            b.close()
    finally:
        up.send_signal(signal.SIGINT)
        up.wait(timeout=60)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 40.0)
