"""``orbis2 play`` in a real browser: Debian's headless Chromium through chromedriver, on the smoke project's models.

One server and one browser serve every test of the module: the page loads with no request
outside the server and frames arrive; a held left key turns the commanded path and the town's true view left; a
saved recording replays through ``orbis2 rollout --trajectory`` to the same frames; replay drives the clip's
recorded commands; a closed page stops the generation. Bad input gets one line and exit status 2.
``ORBIS2_PLAY_SCREENSHOT=path`` keeps the browser's screenshot (the README's).
"""

import json
import os
import queue
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image, ImageSequence

from conftest import project_env

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(CHROMIUM is None or DRIVER is None,
                                reason="needs Debian's chromium and chromium-driver (.ci/run installs them)")
# Few Euler steps: the test is about the server and the page, not the samples' quality.
FAST = ["--abstract-nfe", "2", "--detail-nfe", "2"]


def play(root: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "orbis2.cli", "play", *FAST, *args], cwd=root,
                            env=project_env(root), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_ready(proc: subprocess.Popen, timeout: float = 300) -> str:
    """The server's address, from its 'ready at' line. The lines are read by a thread: a select() on the pipe
    beside a buffered readline misses lines that arrived together (the buffer holds them, the pipe is empty)."""
    lines: queue.Queue[str | None] = queue.Queue()

    def read() -> None:  # to the end, so that the server never blocks on a full pipe; None: it exited
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=read, daemon=True).start()
    seen, deadline = [], time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        try:
            line = lines.get(timeout=left)
        except queue.Empty:
            break
        if line is None:  # the server exited
            break
        seen.append(line)
        if "ready at " in line:
            return line.split("ready at ")[1].split()[0]
    proc.kill()
    pytest.fail("orbis2 play did not become ready:\n" + "".join(seen))


def until(condition, timeout: float = 120, what: str = ""):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.1)
    pytest.fail(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def server(smoke_main, tmp_path_factory):
    records = tmp_path_factory.mktemp("recordings")
    proc = play(smoke_main, "--port", "0", "--record-dir", str(records))
    url = wait_ready(proc)
    yield url, records
    proc.terminate()
    proc.wait(timeout=30)


@pytest.fixture(scope="module")
def chromium(server, tmp_path_factory):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--window-size=1280,800",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium')}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    yield driver
    driver.quit()


@pytest.fixture
def browser(chromium, server):
    """The shared browser on the page: the tests run in order, but a worker of pytest-xdist may get only some."""
    if not chromium.current_url.startswith(server[0]):
        chromium.get(server[0])
    until(lambda: chromium.execute_script("return window.play && window.play.ready"), what="the page")
    return chromium


def page(browser, expression: str):
    return browser.execute_script(f"return window.play.{expression}")


def test_page_loads_with_no_outside_request_and_streams_frames(server, browser):
    until(lambda: page(browser, "shown") >= 10, what="ten frames shown")
    assert page(browser, "genFps") > 0 and page(browser, "shownFps") > 0
    assert page(browser, "trueView"), "a town clip must come with its true view"
    requested = []
    for entry in browser.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            requested.append((message["params"].get("documentURL", ""), message["params"]["request"]["url"]))
    from_page = [u for doc, u in requested if doc.startswith(server[0])]
    assert from_page and any(u.startswith(f"{server[0]}thumb/") for u in from_page)
    outside = [u for u in from_page if not u.startswith((server[0], server[0].replace("http", "ws"), "data:"))]
    assert not outside, outside
    browser.find_element("id", "forecast-toggle").click()
    until(lambda: (browser.find_element("id", "forecast").get_attribute("src") or "").startswith("data:"),
          what="the abstract level's forecast, decoded")
    browser.find_element("id", "forecast-toggle").click()


def test_held_left_key_turns_the_path_and_the_true_view_left(browser):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    browser.find_element("tag name", "body").send_keys(Keys.ENTER)  # reset: a straight start
    # The reset clears the path before its first step draws it again: wait for that step's path, not the old one's.
    straight = until(lambda: page(browser, "steps") >= 1 and page(browser, "ready") and page(browser, "path"),
                     what="the reset scene")
    assert max(abs(y) for _, y in straight) < 1e-6, "no key: the first step goes straight on"
    steps = page(browser, "steps")
    ActionChains(browser).key_down(Keys.LEFT).perform()
    until(lambda: page(browser, "steps") >= steps + 4, what="four steps with the key held")
    ActionChains(browser).key_up(Keys.LEFT).perform()
    x, y = page(browser, "path")[-1]
    assert y > 0.5 and x > 0, f"the commanded path ends at ({x}, {y}): not to the left"
    assert page(browser, "trueHeading") > 0.1, "the true view's camera must have turned left (counter-clockwise)"
    assert page(browser, "latency") is not None
    if os.environ.get("ORBIS2_PLAY_SCREENSHOT"):
        browser.save_screenshot(os.environ["ORBIS2_PLAY_SCREENSHOT"])


def gif_frames(path: Path) -> np.ndarray:
    return np.stack([np.array(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(path))])


def test_a_recording_replays_to_the_same_frames(server, browser, smoke_main):
    until(lambda: page(browser, "steps") >= 2, what="two steps to record")
    browser.execute_script("window.play.saved = null")
    browser.find_element("id", "save").click()
    saved = until(lambda: page(browser, "saved"), what="the recording")
    video, gif, trajectory = (Path(p) for p in saved["paths"])
    assert video.is_file() and trajectory.read_text().startswith("timestamp,speed,yaw_rate\n")
    command = shlex.split(saved["replay"])
    assert command[:2] == ["orbis2", "rollout"]
    subprocess.run([sys.executable, "-m", "orbis2.cli", *command[1:]], cwd=smoke_main,
                   env=project_env(smoke_main), check=True, capture_output=True)
    replayed = Path(command[command.index("--out") + 1]).with_suffix(".gif")
    assert np.array_equal(gif_frames(gif), gif_frames(replayed))


def test_replay_drives_the_clips_recorded_commands(browser, smoke_main):
    from selenium.webdriver.common.keys import Keys

    body = browser.find_element("tag name", "body")
    body.send_keys("r")
    body.send_keys(Keys.ENTER)
    until(lambda: page(browser, "ready") and page(browser, "steps") >= 2, what="two replayed steps")
    browser.execute_script("window.play.saved = null")
    browser.find_element("id", "save").click()
    saved = until(lambda: page(browser, "saved"), what="the replay's recording")
    body.send_keys("r")
    driven = np.loadtxt(saved["paths"][2], delimiter=",", skiprows=1)
    video = Path(shlex.split(saved["replay"])[3])
    recorded = pq.read_table(smoke_main / video.with_suffix(".parquet")).to_pydict()
    for column, name in ((1, "speed"), (2, "yaw_rate")):
        assert np.array_equal(driven[:, column], np.interp(driven[:, 0], recorded["t"], recorded[name]))


def test_a_closed_page_stops_generation(server, browser):
    def status():
        with urllib.request.urlopen(f"{server[0]}status") as response:
            return json.load(response)

    before = status()["steps_generated"]
    until(lambda: status()["steps_generated"] > before, what="generation while the page is open")
    browser.get("about:blank")
    until(lambda: status()["clients"] == 0, what="the page's websocket to close")
    stopped = status()["steps_generated"]
    time.sleep(1.5)
    assert status()["steps_generated"] == stopped


def test_bad_input_gets_one_line_and_a_nonzero_exit(smoke_main, make_video, tmp_path):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    no_odometry = make_video("no_odometry.mp4", 30, 10)
    cases = {
        "port": (["--port", str(busy.getsockname()[1])], "cannot listen"),
        "odometry": (["--port", "0", "--video", str(no_odometry)], "no odometry beside it"),
        "model": (["--port", "0", "--detail-predictor", str(tmp_path / "missing.pt")], "missing.pt"),
    }
    try:
        for name, (args, expected) in cases.items():
            proc = play(smoke_main, *args)
            out, _ = proc.communicate(timeout=120)
            lines = out.strip().splitlines()
            assert proc.returncode == 2 and len(lines) == 1, f"{name}: {out}"
            assert lines[0].startswith("orbis2 play: error: ") and expected in lines[0], f"{name}: {out}"
    finally:
        busy.close()


def test_scenes_are_the_held_out_town_clips_and_imported_videos_with_odometry(make_video, tmp_path, monkeypatch):
    from orbis2.drive import find_scenes
    from orbis2.errors import OrbisError

    monkeypatch.chdir(tmp_path)
    town = make_video("data/raw/town/heldout/town_heldout_00000.mp4", 30, 10)
    columns = {"frame": np.arange(30, dtype=np.int32), "t": np.arange(30) / 10, "speed": np.full(30, 5.0),
               "yaw_rate": np.zeros(30), "x": np.arange(30) / 2, "y": np.zeros(30), "yaw": np.zeros(30)}
    pq.write_table(pa.table(columns), town.with_suffix(".parquet"))
    mine = make_video("data/videos/val/mine.mp4", 30, 10)
    mine.with_suffix(".csv").write_text("timestamp,speed,yaw_rate\n0,5,0\n3,5,0\n")
    make_video("data/videos/val/no_odometry.mp4", 30, 10)
    assert [s.name for s in find_scenes([])] == ["town_heldout_00000", "mine"]
    with pytest.raises(OrbisError, match="no odometry beside it"):
        find_scenes([tmp_path / "data/videos/val/no_odometry.mp4"])
