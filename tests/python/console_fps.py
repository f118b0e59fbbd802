"""How many camera frames a second the web console's page draws (docs/console.md).

Usage: console_fps.py URL [SECONDS]

URL is what `stitch run … --console` printed (with its #token=). Opens it in Debian's headless
Chromium (Selenium through /usr/bin/chromedriver), waits for two frames, then counts the
frames the page draws over SECONDS (default 10) and prints the rate.
"""

import sys
import tempfile
import time

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By

url = sys.argv[1]
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
options = webdriver.ChromeOptions()
options.binary_location = "/usr/bin/chromium"
for flag in (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--no-first-run",
    "--window-size=1400,1250",
    f"--user-data-dir={tempfile.mkdtemp()}",
):
    options.add_argument(flag)
driver = webdriver.Chrome(service=Service(executable_path="/usr/bin/chromedriver"), options=options)
try:
    driver.get(url)
    drawn = lambda: int(driver.find_element(By.TAG_NAME, "body").get_attribute("data-frames") or 0)
    end = time.monotonic() + 60
    while drawn() < 2:
        if time.monotonic() > end:
            raise SystemExit("no camera frames drawn within 60 s")
        time.sleep(0.05)
    a, t0 = drawn(), time.monotonic()
    time.sleep(seconds)
    b, t1 = drawn(), time.monotonic()
    print(f"frames drawn: {b - a} in {t1 - t0:.2f} s = {(b - a) / (t1 - t0):.1f} per second")
finally:
    driver.quit()
