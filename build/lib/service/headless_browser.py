"""Debian's Chromium, headless, through selenium: how the page's tests and its benchmark look at
the page as a person would (``tests/test_web_page.py``, ``bench/page_sliders.py``).

``scripts/install-system-deps.sh`` installs ``chromium`` and ``chromium-driver``; selenium is a
development dependency (``pip install -e '.[dev]'``). Nothing is downloaded: Chromium's own
network calls fail on a closed network, so the flags keep it quiet (see the machine notes).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver")
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--window-size=1400,1000",
)


def missing() -> str | None:
    """Why no headless Chromium can start here (a sentence), or None when it can."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[dev]')"
    if not (Path(CHROMIUM).exists() and CHROMEDRIVER):
        return "no Chromium / chromium-driver here (scripts/install-system-deps.sh installs them)"
    return None


def start_chromium():
    """A headless Chromium (selenium ``WebDriver``) with a fresh profile folder; returns the
    driver and that folder, for the caller to ``quit()`` and remove."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    profile = tempfile.mkdtemp(prefix="eva-chromium-")
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    return driver, profile
