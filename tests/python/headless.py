"""Debian's Chromium, headless, under Selenium: the one setup the console's browser scripts share."""

import tempfile

from selenium import webdriver
from selenium.webdriver.chrome.service import Service


def chromium(binary="/usr/bin/chromium", driver="/usr/bin/chromedriver"):
    """A headless Chromium driven through chromedriver, with a fresh profile, 1400×1250."""
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=1400,1250",
        f"--user-data-dir={tempfile.mkdtemp()}",
    ):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(executable_path=driver), options=options)
