"""The README's screenshots from a real run: the page's default comparison, start to end.

Starts ``python -m app.server`` (viewer on) with a temporary data folder, opens the page in
Debian's chromium (Playwright), presses Start without touching anything (sim2d, strep vs
strep-nolink, from scratch, the default iterations), waits for both jobs, and writes
``page.png`` and ``viewer.png`` into the folder given (docs/screenshots for the README). Every
request to another host is blocked and listed. About 4 minutes on 2 busy cores.

    python scripts/readme_screenshots.py docs/screenshots
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

import httpx
from playwright.sync_api import sync_playwright

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
FINAL = {"succeeded", "failed", "cancelled", "interrupted"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="strep-shots-"))
    port, viewer_port = free_port(), free_port()
    env = {**os.environ, "STREP_VIEWER_ENABLED": "true", "STREP_VIEWER_PORT": str(viewer_port)}
    env.pop("STREP_API_TOKEN", None)
    log = (tmp / "server.log").open("wb")
    args = ["--host", "127.0.0.1", "--port", str(port), "--data-dir", str(tmp / "data")]
    proc = subprocess.Popen([sys.executable, "-m", "app.server", *args], cwd=ROOT, stdout=log, stderr=log, env=env)
    url = f"http://127.0.0.1:{port}"
    foreign: list[str] = []
    try:
        for _ in range(300):
            try:
                health = httpx.get(f"{url}/api/health", timeout=2).json()
                break
            except httpx.TransportError:
                time.sleep(0.3)
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path=os.environ.get("STREP_CHROMIUM", "/usr/bin/chromium"), args=ARGS
            )
            context = browser.new_context(viewport={"width": 1280, "height": 900})
            local = ("127.0.0.1", "localhost")
            context.route(
                lambda u: not (u.startswith(("blob:", "data:")) or urlsplit(u).hostname in local),
                lambda route: (foreign.append(route.request.url), route.abort()),
            )
            page = context.new_page()
            page.goto(url)
            page.wait_for_selector("#methods input")
            started = time.monotonic()
            page.click("#start")
            while True:
                jobs = page.evaluate("() => strepPage.followed.map((f) => f.state && f.state.status)")
                if jobs and set(jobs) <= FINAL:
                    break
                time.sleep(1.0)
            print(f"both jobs {jobs} after {time.monotonic() - started:.0f} s")
            page.locator("#comparison-rrd").wait_for(timeout=60_000)
            page.evaluate("() => document.activeElement && document.activeElement.blur()")
            page.screenshot(path=out / "page.png", full_page=True)
            print(page.inner_text("#results tbody"))
            viewer = context.new_page()
            viewer.set_viewport_size({"width": 1280, "height": 760})
            viewer.goto(health["viewer_url"])
            viewer.get_by_text("finished: ").first.wait_for(timeout=60_000)
            notice = viewer.get_by_text("Software WebGL rendering detected")
            if notice.count():
                viewer.locator(".mantine-Notification-root button, .mantine-Notification-closeButton").first.click()
            time.sleep(3.0)
            viewer.screenshot(path=out / "viewer.png")
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    print("requests to other hosts:", foreign or "none")
    return 0 if not foreign else 1


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/screenshots")))
