"""The /viewer page in a real headless Chromium (Debian's chromium + chromedriver) against a real server and the shipped models."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from service_fixtures import SHIPPED_MODELS, UvicornProcess, shipped_models_available

from acting import load_policy
from training.data import load_replay
from training.evaluate import evaluate_policy

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is in the test extra")
pytestmark = [
    pytest.mark.skipif(not shipped_models_available(), reason="needs the shipped models/flow and models/mse"),
    pytest.mark.skipif(
        not (Path(CHROMIUM).is_file() and Path(CHROMEDRIVER).is_file()),
        reason="needs Debian's chromium and chromium-driver (.ci/run installs them)",
    ),
]
KEY = "browser-test-key"


def chromium():
    """A headless Chromium driven through chromedriver (root needs --no-sandbox)."""
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1000,1000"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def wait_for(driver, script: str, timeout: float = 30.0):
    """Poll a JavaScript expression until it is truthy; its value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(f"return window.pushtViewer ? ({script}) : null")
        if value:
            return value
        time.sleep(0.05)
    raise TimeoutError(
        f"{script} still falsy after {timeout} s; page said {driver.execute_script('return window.pushtViewer && window.pushtViewer.lastError()')}"
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("viewer-data")
    with UvicornProcess({"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_VIEWER_DATA_DIR": str(data)}, entry="service") as proc:
        proc.data_dir = data
        yield proc


@pytest.fixture(scope="module")
def driver():
    browser = chromium()
    yield browser
    browser.quit()


def hold(driver, points: list[tuple[float, float]], pause: float = 0.05) -> None:
    """Press the button at the first board point, drag through the others, release (board pixels = env pixels)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    canvas = driver.find_element(By.ID, "board")
    chain = ActionChains(driver, duration=10)
    x0, y0 = points[0]
    chain.move_to_element_with_offset(canvas, int(x0 - 256), int(y0 - 256)).click_and_hold().pause(pause)
    for (xa, ya), (xb, yb) in zip(points, points[1:]):
        chain.move_by_offset(int(xb - xa), int(yb - ya)).pause(pause)
    chain.pause(0.3).release().perform()


def test_browser_plays_the_episode_training_evaluate_scores(server, driver):
    seed = 200000
    driver.get(f"{server.url}/viewer?policy=flow&seed={seed}&autoplay=1&fps=200")
    status = wait_for(driver, "window.pushtViewer.status().done && window.pushtViewer.status()")
    reference = evaluate_policy(load_policy(SHIPPED_MODELS / "flow.onnx"), episodes=1, seed=seed).episodes[0]
    assert status == {
        "step": reference.length,
        "coverage": reference.final_coverage,
        "maxReward": reference.max_reward,
        "done": True,
        "success": reference.success,
    }
    # the canvas shows the goal (light green) and the block (slate grey)
    counts = driver.execute_script("""
        const d = document.getElementById('board').getContext('2d').getImageData(0, 0, 512, 512).data;
        let green = 0, grey = 0;
        for (let i = 0; i < d.length; i += 4) {
          if (d[i] === 0x90 && d[i + 1] === 0xee && d[i + 2] === 0x90) green++;
          if (d[i] === 0x77 && d[i + 1] === 0x88 && d[i + 2] === 0x99) grey++;
        }
        return [green, grey];""")
    # the tee covers 6,300 px; a block that landed hides most of the goal under it (edges are anti-aliased)
    assert counts[1] > 5000 and counts[0] + counts[1] > 5500 + 1000 * (1 - status["coverage"])


def test_browser_teleop_hold_save_and_load(server, driver):
    driver.get(f"{server.url}/viewer?mode=teleop&seed=7&autoplay=1&fps=50")
    wait_for(driver, "window.pushtViewer.connected() && window.pushtViewer.status()")
    time.sleep(0.3)
    assert driver.execute_script("return window.pushtViewer.status().step") == 0  # teleop waits for the button
    path = [(200.0, 200.0), (230.0, 210.0), (260.0, 230.0), (290.0, 250.0), (300.0, 300.0)]
    hold(driver, path)
    steps = wait_for(driver, "window.pushtViewer.status().step")
    time.sleep(0.3)
    after_release = driver.execute_script("return window.pushtViewer.status().step")
    time.sleep(0.3)
    assert driver.execute_script("return window.pushtViewer.status().step") == after_release >= steps  # stopped at the release
    from selenium.webdriver.common.by import By

    driver.find_element(By.ID, "save").click()
    saved = wait_for(driver, "window.pushtViewer.lastSaved()")
    assert saved["steps"] == saved["humanSteps"] == after_release > 10
    store = Path(saved["path"])
    assert store.parent == server.data_dir
    replay = load_replay(store)
    human = zarr.open_group(str(store), mode="r")["data/human"][...]
    assert len(replay.states) == after_release and human.all()
    # the pointer was the action: the last actions are the drag's end, and the first ones its start
    assert np.allclose(replay.actions[-1], path[-1], atol=2.0) and np.allclose(replay.actions[0], path[0], atol=2.0)


def test_browser_takeover_hands_back_to_the_policy(server, driver):
    driver.get(f"{server.url}/viewer?policy=flow&seed=200004&autoplay=1&fps=40")
    wait_for(driver, "window.pushtViewer.status().step > 20")
    hold(driver, [(100.0, 400.0), (120.0, 380.0), (140.0, 360.0)])
    status = wait_for(driver, "window.pushtViewer.status().done && window.pushtViewer.status()")
    driver.execute_script("window.pushtViewer.save()")
    saved = wait_for(driver, "window.pushtViewer.lastSaved()")
    human = zarr.open_group(saved["path"], mode="r")["data/human"][...].astype(bool)
    assert saved["steps"] == status["step"] == len(human)
    assert not human[:20].any() and human.any() and not human[-1]  # the policy, you, then the policy again


def test_browser_asks_for_the_api_key():
    from selenium.webdriver.common.by import By

    with UvicornProcess({"PUSHT_MODELS_DIR": str(SHIPPED_MODELS), "PUSHT_API_KEY": KEY}) as server:
        browser = chromium()
        try:
            browser.get(f"{server.url}/viewer?policy=mse&seed=3&autoplay=1&fps=200")
            assert wait_for(browser, "window.pushtViewer.lastError()")["status"] == 401
            browser.find_element(By.ID, "key").send_keys(KEY)
            browser.find_element(By.ID, "connect").click()
            assert wait_for(browser, "window.pushtViewer.status().done")
        finally:
            browser.quit()
