"""Debian's Chromium, driven by Selenium through Debian's chromedriver (no browser download).

:func:`chromium` starts a headless Chromium with a fresh profile; skipped (a failure under
``STIPI_REQUIRE_TOOLCHAIN=1``, as in CI) when ``chromium`` or ``chromedriver`` is missing.
``STIPI_VIEW_SCREENSHOTS=DIR`` keeps the tests' screenshots of the page in ``DIR`` (how the
PNGs in docs/ are made).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from tests.conftest import require_tool

T = TypeVar("T")

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--window-size=1500,1100",
]


@contextmanager
def chromium(profile: Path) -> Iterator[Any]:
    """A headless Chromium (Selenium WebDriver) with a fresh profile in ``profile``."""
    require_tool("chromium", "chromedriver")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(shutil.which("chromium"))
    for a in [*CHROMIUM_ARGS, f"--user-data-dir={profile}"]:
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(str(shutil.which("chromedriver"))), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def wait_for(what: Callable[[], T | None], timeout_s: float = 20.0, why: str = "") -> T:
    """Poll ``what`` until it returns a true value; fail after ``timeout_s`` of wall time."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = what()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {why or what}")
        time.sleep(0.1)


def screenshot(driver: Any, name: str, tmp_path: Path) -> Path:
    """Save the page as ``name`` (PNG) in ``tmp_path`` and, with ``STIPI_VIEW_SCREENSHOTS``,
    in that directory too."""
    path = tmp_path / name
    driver.save_screenshot(str(path))
    keep = os.environ.get("STIPI_VIEW_SCREENSHOTS")
    if keep:
        shutil.copy(path, Path(keep) / name)
    return path


def text(driver: Any, element_id: str) -> str:
    """An element's textContent."""
    return str(driver.execute_script(f"return document.getElementById('{element_id}').textContent"))
