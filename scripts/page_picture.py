"""The picture of docs/serve.md and the README: `matfit serve` after a fit of the recoloured example.

Starts `matfit serve` (the shipped model) on a free port, opens the page in Debian's Chromium
(Playwright, a dev extra), uploads matfit/data/examples/recoloured.png, waits for the fit's Mitsuba
figures (the default fit: verification, what the picture decides, the clean answer) and for the
Mitsuba render of the answer, then saves the whole page to OUT (default data/serve/page.png).

Usage: python scripts/page_picture.py [OUT]  (needs /usr/bin/chromium; a minute on a 2-core CPU)
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request

from playwright.sync_api import sync_playwright

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHROMIUM = "/usr/bin/chromium"
EXAMPLE = os.path.join(ROOT, "matfit", "data", "examples", "recoloured.png")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for(url: str, seconds: float = 120.0) -> None:
    deadline = time.monotonic() + seconds
    while True:
        try:
            urllib.request.urlopen(url, timeout=5).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def main(out: str) -> None:
    port = free_port()
    server = subprocess.Popen([sys.executable, "-m", "matfit", "serve", "--port", str(port)], cwd=ROOT)
    try:
        url = f"http://127.0.0.1:{port}/"
        wait_for(url)
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.wait_for_selector("body[data-ready=yes]", timeout=120_000)
            page.set_input_files("#picture", EXAMPLE)
            page.wait_for_function(
                "document.getElementById('figures').textContent.includes('Mitsuba RMSE')", timeout=300_000
            )
            page.click("#render-button")
            page.wait_for_function(
                "document.getElementById('render-note').textContent.includes(' spp, ')", timeout=300_000
            )
            page.screenshot(path=out, full_page=True)
            browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "data", "serve", "page.png"))
