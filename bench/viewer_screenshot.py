"""The README's viewer screenshot: headless Chromium on `/viewer` mid-episode, saved as docs/viewer.png.

    .venv/bin/python bench/viewer_screenshot.py --seed 200004 --step 90

Starts `python -m service` on a free loopback port, opens `/viewer?policy=...&seed=...&autoplay=1` in
Debian's chromium (through chromedriver), waits until the episode reaches `--step` and saves the page.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from service_fixtures import UvicornProcess  # noqa: E402  (the tests' real-server helper)


def main(argv: list[str] | None = None) -> int:
    """Take the screenshot; 0 when written."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="flow", help="policy to play")
    parser.add_argument("--seed", type=int, default=200004, help="episode seed")
    parser.add_argument("--step", type=int, default=90, help="step at which to take the picture")
    parser.add_argument("--out", default=str(REPO / "docs" / "viewer.png"), help="PNG to write")
    args = parser.parse_args(argv)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=760,900", "--hide-scrollbars"):
        options.add_argument(flag)
    with UvicornProcess({"PUSHT_MODELS_DIR": str(REPO / "models")}, entry="service") as server:
        driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
        try:
            driver.get(f"{server.url}/viewer?policy={args.policy}&seed={args.seed}&autoplay=1&fps=10")
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                status = driver.execute_script("return window.pushtViewer && window.pushtViewer.status()")
                if status and (status["step"] >= args.step or status["done"]):
                    break
                time.sleep(0.02)
            driver.execute_script("document.getElementById('fps').blur()")
            driver.save_screenshot(args.out)
        finally:
            driver.quit()
    print(f"wrote {args.out} at step {status['step']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
