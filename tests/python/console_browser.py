"""The web console in a real headless Chromium (cli/tests/console.rs runs this).

Usage: console_browser.py URL SCREENSHOT CHROMIUM CHROMEDRIVER

Opens the console of a running `stitch run --console --pace 1.0`, sees the state change
live and the camera's frames drawn, takes control, pauses mid-step, checks the page says paused, saves a screenshot,
resumes, aborts and sees the run end aborted. Exits non-zero with the reason otherwise.
"""

import sys
import time

from headless import chromium
from selenium.webdriver.common.by import By

url, shot, chromium_path, chromedriver = sys.argv[1:5]


def wait_for(what, check, limit=60.0):
    end = time.monotonic() + limit
    while time.monotonic() < end:
        got = check()
        if got:
            return got
        time.sleep(0.05)
    raise SystemExit(f"timed out after {limit} s waiting for {what}")


driver = chromium(chromium_path, chromedriver)
try:
    driver.get(url)
    state = lambda: driver.find_element(By.ID, "state").text
    link = lambda: driver.find_element(By.ID, "link").text
    wait_for("the stream (viewer N)", lambda: link().startswith("live"))
    first = wait_for("a state", lambda: state() if "(" in state() else None)
    print("first state:", first)
    # Live: the state changes while the page is open.
    second = wait_for("the state to change", lambda: state() if state() != first else None)
    print("then:", second)
    # The camera: frames drawn, one in flight, the next asked for when one is drawn.
    frames = lambda: int(driver.find_element(By.TAG_NAME, "body").get_attribute("data-frames") or 0)
    wait_for("three camera frames", lambda: frames() >= 3, limit=60)
    print("camera:", driver.find_element(By.ID, "fps").text)
    driver.find_element(By.ID, "take-control").click()
    wait_for("control", lambda: driver.find_element(By.TAG_NAME, "body").get_attribute("data-control") == "mine")
    # Mid-step: a moving step's state (not between steps, not paused).
    moving = ("inserting", "sweeping", "extracting", "cinching", "handing_over", "correcting")
    # Just after a step starts (a step lasts seconds at real time), so the pause lands in it.
    before = state()
    wait_for("the next step to start", lambda: state() != before and state().startswith(moving), limit=90)
    driver.find_element(By.ID, "btn-pause").click()
    paused = wait_for("paused mid-step", lambda: state() if state().startswith("paused") else None)
    print("after pause:", paused)
    if "mid-step" not in paused and "committed" not in paused:
        raise SystemExit(f"the pause did not land mid-step: {paused}")
    time.sleep(0.5)
    if state() != paused:
        raise SystemExit(f"paused, yet the state moved on: {paused} -> {state()}")
    driver.save_screenshot(shot)
    driver.find_element(By.ID, "btn-resume").click()
    resumed = wait_for("resumed", lambda: state() if not state().startswith("paused") else None)
    print("after resume:", resumed)
    driver.find_element(By.ID, "btn-abort").click()
    wait_for("aborted", lambda: state() == "aborted")
    wait_for("the run's end", lambda: link() in ("run ended", "connection lost"))
    print("ended:", state(), "/", link())
finally:
    driver.quit()
