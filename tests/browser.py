"""A real headless browser for the report tests: Debian's chromium driven through chromedriver
(`make browser` installs both, selenium comes with the test extra). Where either is missing the
caller skips with the reason; nothing here passes without a browser."""

from __future__ import annotations

import contextlib
import shutil
import time
from pathlib import Path

import pytest

CHROMIUM = ("chromium", "chromium-browser", "google-chrome")


def browser_or_skip():
    """(chromium path, chromedriver path), or pytest.skip saying what is missing."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[test]')")
    chromium = next((p for p in map(shutil.which, CHROMIUM) if p), None)
    driver = shutil.which("chromedriver")
    if chromium is None or driver is None:
        pytest.skip("no chromium / chromedriver on this machine: run `make browser` first")
    return chromium, driver


@contextlib.contextmanager
def chromium_driver(width: int = 1400, height: int = 1000, webgl: bool = False):
    """A headless chromium (selenium driver) that logs the console; with `webgl`, WebGL2 on
    its software renderer (SwiftShader: no GPU, no display)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    chromium, driver_path = browser_or_skip()
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--allow-file-access-from-files"):  # fmt: skip
        options.add_argument(arg)
    if webgl:
        options.add_argument("--use-angle=swiftshader")
        options.add_argument("--enable-unsafe-swiftshader")
    else:
        options.add_argument("--disable-gpu")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def console_errors(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def open_page(page: Path, screenshot: Path, width: int = 1400, height: int = 1000) -> dict:
    """Load `page` (a file) in headless chromium; return its console errors, the images that
    failed to load, the videos that failed to decode, and write a screenshot."""
    with chromium_driver(width, height, webgl=True) as driver:
        driver.get(page.resolve().as_uri())
        deadline = time.time() + 15
        while time.time() < deadline:  # videos decode their first frame after the load event
            pending = driver.execute_script(
                "return Array.from(document.querySelectorAll('video'))"
                ".filter(v => v.readyState < 2 && !v.error).length"
            )
            if not pending:
                break
            time.sleep(0.2)
        broken = driver.execute_script(
            "return Array.from(document.images)"
            ".filter(i => i.getAttribute('src') !== null)"  # the viewer sets its photo's src
            ".filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute('src'))"
        )
        bad_videos = driver.execute_script(
            "return Array.from(document.querySelectorAll('video'))"
            ".filter(v => v.error || v.readyState < 2).map(v => v.getAttribute('src'))"
        )
        images = driver.execute_script("return document.images.length")
        errors = console_errors(driver)
        full = driver.execute_script("return document.documentElement.scrollHeight")
        driver.set_window_size(width, min(max(height, full + 100), 8000))  # the whole page
        driver.save_screenshot(str(screenshot))
    return {"errors": errors, "broken": broken, "bad_videos": bad_videos, "images": images}
