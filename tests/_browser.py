"""A catalog's report (index.html) opened in a real browser: Debian's Chromium, headless,
driven by Playwright, with the network switched off.

    .venv/bin/python tests/_browser.py CATALOG/index.html docs/report.png   # a screenshot

`.ci/run` (and `./dev test`, as root) install Debian's chromium when it is missing.
"""

from __future__ import annotations

import shutil
import sys
from contextlib import contextmanager
from pathlib import Path

# what Chromium needs on a machine with no network and no display (a closed network refuses
# its background connections, and root needs --no-sandbox)
FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def chromium() -> str:
    """The Chromium executable, or an error that says how to install it."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        raise RuntimeError(
            "the report's browser test needs Chromium: apt-get install chromium "
            "(.ci/run and ./dev test install it when run as root)"
        )
    return exe


@contextmanager
def offline_page(html: Path, width: int = 1500, height: int = 1150):
    """A Chromium page (Playwright) that has loaded ``html`` with the network off, and the
    record of what went wrong: ``(page, problems)``; ``problems`` holds ``failed`` requests,
    ``external`` (non-file) requests and ``errors`` (console errors and uncaught exceptions)."""
    from playwright.sync_api import sync_playwright

    problems = {"failed": [], "external": [], "errors": []}
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium(), args=FLAGS)
        try:
            context = browser.new_context(offline=True, viewport={"width": width, "height": height})
            page = context.new_page()
            page.on(
                "requestfailed",
                lambda r: problems["failed"].append(f"{r.url}: {r.failure}"),
            )
            page.on(
                "request",
                lambda r: (
                    None
                    if r.url.startswith(("file:", "data:", "blob:"))
                    else problems["external"].append(r.url)
                ),
            )
            page.on(
                "console",
                lambda m: problems["errors"].append(m.text) if m.type == "error" else None,
            )
            page.on("pageerror", lambda e: problems["errors"].append(str(e)))
            page.goto(Path(html).resolve().as_uri())
            page.wait_for_function("document.body.dataset.ready === '1'", timeout=30_000)
            # the hillshade picture is loaded (or there is none)
            page.wait_for_function(
                "Array.from(document.querySelectorAll('img.leaflet-image-layer'))"
                ".every(i => i.complete)",
                timeout=30_000,
            )
            yield page, problems
        finally:
            browser.close()


def screenshot(html: Path, png: Path) -> None:
    with offline_page(html) as (page, problems):
        page.screenshot(path=str(png), full_page=True)
    bad = [p for v in problems.values() for p in v]
    if bad:
        raise SystemExit(f"the report did not render cleanly: {bad}")


if __name__ == "__main__":
    screenshot(Path(sys.argv[1]), Path(sys.argv[2]))
    print(f"wrote {sys.argv[2]}")
