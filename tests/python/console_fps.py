"""How many camera frames a second the web console's page draws (docs/console.md).

Usage: console_fps.py URL [SECONDS]

URL is what `stitch run … --console` printed (with its #token=). Opens it in Debian's headless
Chromium (Selenium through /usr/bin/chromedriver), waits for two frames, then counts the
frames the page draws over SECONDS (default 10) and prints the rate.
"""

import sys
import time

from headless import chromium
from selenium.webdriver.common.by import By

url = sys.argv[1]
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
driver = chromium()
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
