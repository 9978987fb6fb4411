"""What the browser tests share (`make ui-check`): a page as a real headless Chromium renders it."""

from __future__ import annotations

import shutil
import subprocess


def dom(url: str) -> str:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "headless Chromium is needed: apt-get install chromium (make ui-check does)"
    page = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=20000",
         "--dump-dom", url],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    return page.stdout
