"""A real headless browser for the tests: Debian's Chromium driven by Selenium through Debian's chromedriver.

No browser is downloaded (the network is closed): scripts/setup.sh installs the packages ``chromium`` and
``chromium-driver`` when it runs as root. Chromium gets a new empty profile and every switch that keeps it from
calling home.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
)
ARTIFACTS = Path(__file__).resolve().parents[2] / "build" / "test-output"


def chromium(width: int = 1400, height: int = 1000, log: Path | None = None) -> Any:
    """A Selenium WebDriver on the system's Chromium (fails the test with what to install when it is missing)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or shutil.which("chromium.chromedriver")
    if binary is None or driver is None:
        pytest.fail(
            "the browser tests need Debian's chromium and chromium-driver (apt-get install chromium chromium-driver; "
            "scripts/setup.sh installs them when run as root)"
        )
    opts = webdriver.ChromeOptions()
    opts.binary_location = binary
    for a in CHROMIUM_ARGS:
        opts.add_argument(a)
    opts.add_argument(f"--user-data-dir={tempfile.mkdtemp(prefix='bac-chromium-')}")
    opts.add_argument(f"--window-size={width},{height}")
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(executable_path=driver, log_output=str(log) if log else None)
    d = webdriver.Chrome(service=service, options=opts)
    d.set_page_load_timeout(60)
    d.set_script_timeout(30)
    return d


def wait_js(driver: Any, script: str, timeout: float = 60.0, what: str = "", interval: float = 0.1) -> Any:
    """The first truthy value of ``script`` (``return ...``) in the page; fails the test after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = driver.execute_script(script)
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting in the page for {what or script}")
        time.sleep(interval)


def wait_until(cond: Callable[[], Any], timeout: float, what: str, interval: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def page_errors(driver: Any) -> list[str]:
    """The page's console errors (a missing file, a script that threw)."""
    return [e["message"] for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def save(driver: Any, name: str, folder: Path) -> Path:
    """A screenshot in the test's folder and in build/test-output/ (kept after the run, to be looked at)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    driver.save_screenshot(str(path))
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(path, ARTIFACTS / name)
    return ARTIFACTS / name
