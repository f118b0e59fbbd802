#!/usr/bin/env python3
"""The screenshot in docs/journal.md: headless Chromium driving a Lichtblick web build (the
open-source fork of Foxglove Studio) through a recorded run with docs/foxglove/stitch-layout.json.

Not part of the tests: Lichtblick is built from its source (github.com/Lichtblick-Suite/
lichtblick, commit 9554e1e4, 2025-03-21), which package registries do not ship. How it was
done here (2-core machine, registries only): Yarn 3.6.3 from npm (`@yarnpkg/cli-dist`) instead
of corepack; `yarn install` with ELECTRON_SKIP_BINARY_DOWNLOAD=1 PUPPETEER_SKIP_DOWNLOAD=1
PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 (3.5 min); the Git LFS fonts replaced with the same faces
from npm's @fontsource/inter and @fontsource/ibm-plex-mono (without fonts the app stays
blank); `yarn web:build:prod` (about a minute with type checks and source maps off). Serve
the build directory with a static server that answers HTTP Range requests (the remote-file
source needs them; `python3 docs/foxglove/serve.py BUILD_DIR 8080`), with the recording in
it, then:

    stitch run scripts/stitch_thread.rhai --seed 1 --perception pipeline --record-frames 1 \
        --journal BUILD_DIR/thread.mcap
    python3 docs/foxglove/screenshot.py --mcap thread.mcap --time 1970-01-01T00:02:09Z \
        --out docs/foxglove/stitch-layout.png

(selenium from PyPI; Debian's chromium and chromium-driver.) The app is opened with
`?ds=remote-file&ds.url=…&time=…` (load and seek); the layout goes in through the Layouts
sidebar's "Import from file…", the browser's file picker stubbed to hand it over.
"""
import argparse
import json
import shutil
import tempfile
import os
import sys
import time
import urllib.parse

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.by import By

ap = argparse.ArgumentParser()
ap.add_argument("--url", default="http://127.0.0.1:8080/")
ap.add_argument("--mcap", default="thread.mcap", help="path of the .mcap relative to --url")
ap.add_argument("--layout", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "stitch-layout.json"))
ap.add_argument("--time", default="1970-01-01T00:02:30Z", help="RFC3339 time to seek to")
ap.add_argument("--out", default="stitch-layout.png")
ap.add_argument("--wait", type=float, default=40, help="seconds to let panels render")
ap.add_argument("--width", type=int, default=1600)
ap.add_argument("--height", type=int, default=1000)
ap.add_argument("--play", type=float, default=0, help="seconds of playback before pausing (0: none)")
args = ap.parse_args()

layout_text = open(args.layout).read()
json.loads(layout_text)  # fail early on bad JSON

profile = tempfile.mkdtemp(prefix="stitch-lichtblick-")
opts = webdriver.ChromeOptions()
opts.binary_location = "/usr/bin/chromium"
for a in [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    f"--user-data-dir={profile}", f"--window-size={args.width},{args.height}",
    "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--hide-scrollbars", "--force-device-scale-factor=1",
]:
    opts.add_argument(a)
opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)

# Stub the File System Access picker before any page script runs.
stub = """
window.__layoutText = %s;
window.__pickerCalls = 0;
window.showOpenFilePicker = async () => { window.__pickerCalls++; return [{
  kind: 'file', name: 'stitch-layout.json',
  getFile: async () => new File([window.__layoutText], 'stitch-layout.json', {type: 'application/json'}),
}]; };
""" % json.dumps(layout_text)
driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": stub})
driver.set_window_size(args.width, args.height + 200)
driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                       {"width": args.width, "height": args.height, "deviceScaleFactor": 1, "mobile": False})


def log(*a):
    print(f"[{time.strftime('%H:%M:%S')}]", *a, flush=True)


def shot(name):
    driver.save_screenshot(name)
    log("saved", name)


def click_text(text, tag="*", timeout=20, exact=True):
    end = time.time() + timeout
    cond = f"normalize-space(.)={json.dumps(text)}" if exact else f"starts-with(normalize-space(.),{json.dumps(text)})"
    while time.time() < end:
        els = [e for e in driver.find_elements(By.XPATH, f"//{tag}[{cond}]") if e.is_displayed()]
        if els:
            els[-1].click()
            return els[-1]
        time.sleep(0.5)
    raise RuntimeError(f"no visible element with text {text!r}")


try:
    base = args.url.rstrip("/") + "/"
    q = urllib.parse.urlencode({"ds": "remote-file", "ds.url": base + args.mcap, "time": args.time})
    url = base + "?" + q
    log("open", url)
    driver.get(url)

    # wait for the app bar
    end = time.time() + 120
    while time.time() < end and not driver.find_elements(By.ID, "app-menu-button"):
        time.sleep(1)
    if not driver.find_elements(By.ID, "app-menu-button"):
        raise RuntimeError("app bar never appeared")
    log("app loaded")
    time.sleep(5)

    # Import the layout through the Layouts sidebar's "Import layout" button (LayoutBrowser).
    # (App menu > View > "Import layout from file..." is a no-op in this Lichtblick version:
    # CurrentLayoutProvider's setCurrentLayout is `() => {}`.)
    def import_button():
        return [e for e in driver.find_elements(By.CSS_SELECTOR, '[aria-label="Import layout"]') if e.is_displayed()]
    if not import_button():
        for e in driver.find_elements(By.CSS_SELECTOR, '[aria-label="Show left sidebar"]'):
            if e.is_displayed():
                e.click()
                time.sleep(1)
    if not import_button():
        click_text("Layouts", timeout=10)
        time.sleep(1)
    if import_button():
        import_button()[0].click()
    else:  # new top nav: a list item in the Layouts tab
        click_text("Import from file", timeout=10, exact=False, tag="div")
    time.sleep(3)
    log("layout import clicked; picker calls:", driver.execute_script("return window.__pickerCalls"))
    shot(args.out.replace(".png", "-import.png"))

    # close sidebars if open, so the panels get the full window
    # (keyboard shortcuts "[" and "]", not the buttons: a clicked button keeps its tooltip open)
    driver.execute_script("document.activeElement && document.activeElement.blur()")
    for label, key in [("Hide left sidebar", "["), ("Hide right sidebar", "]")]:
        if any(e.is_displayed() for e in driver.find_elements(By.CSS_SELECTOR, f'[aria-label="{label}"]')):
            ActionChains(driver).send_keys(key).perform()
            time.sleep(0.5)

    if args.play > 0:
        driver.find_element(By.TAG_NAME, "body").send_keys(" ")
        time.sleep(args.play)
        driver.find_element(By.TAG_NAME, "body").send_keys(" ")

    log(f"waiting {args.wait}s for panels")
    step = max(1.0, args.wait / 4)
    waited = 0.0
    while waited < args.wait:
        time.sleep(step)
        waited += step
        shot(args.out.replace(".png", f"-progress.png"))
    shot(args.out)
except Exception:
    shot(args.out.replace(".png", "-error.png"))
    raise
finally:
    try:
        for entry in driver.get_log("browser"):
            if entry["level"] in ("SEVERE", "WARNING"):
                print("console:", entry["level"], entry["message"][:400], file=sys.stderr)
    except Exception as e:  # noqa
        print("no console log:", e, file=sys.stderr)
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)
