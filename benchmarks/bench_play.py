"""Measure ``orbis2 play`` as a user meets it: generated and shown frames/s, key-to-frame latency, idle CPU, and the
CPU the server and the browser use while driving.

    python benchmarks/bench_play.py [--seconds 30] [--no-true-view] [--json out.json] [-- play options]

Run in a project whose main job has finished (the default profile's models), on an otherwise idle machine:
the figures mean nothing on a shared one. It starts ``orbis2 play`` (any options after ``--`` are passed on,
e.g. ``--abstract-nfe 2`` or model paths), opens its page in Debian's headless Chromium (the dev extra's
selenium and chromium-driver, as the tests use), drives the first scene for ``--seconds`` with the left key
pressed and released every 1.5 s, and reads the page's own HUD figures: the generated frames/s of each step
(model, decoder and the town's true view together), the frames/s shown, and every key-to-first-changed-frame
latency. Then it pauses the page and reads the server's CPU time over ``--idle`` seconds (a fraction of one
core). The targets (2 CPU cores, default profile): >= 20 generated frames/s, >= 15 with the true view, latency
<= 0.6 s, idle < 0.05 of a core.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil


def cpu_seconds(process: psutil.Process) -> float:
    """User and system CPU seconds of a process and its children (the browser's are chromedriver's children)."""
    total = 0.0
    for p in [process, *process.children(recursive=True)]:
        try:
            total += sum(p.cpu_times()[:2])
        except psutil.NoSuchProcess:
            pass
    return total


def code_commit() -> str | None:
    """The commit of the orbis2 code measured (its checkout's HEAD, "+dirty" with local changes)."""
    import orbis2

    where = Path(orbis2.__file__).parent
    try:
        head = subprocess.run(["git", "-C", str(where), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(where), "status", "--porcelain", "--", "."], capture_output=True,
                               text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


def main() -> None:
    argv = sys.argv[1:]
    passed = argv[argv.index("--") + 1:] if "--" in argv else []
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=30.0, help="how long to drive")
    p.add_argument("--idle", type=float, default=10.0, help="seconds of paused page to read the idle CPU over")
    p.add_argument("--profile", default=None, help="params.yaml profile (default: the file's)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    p.add_argument("--no-true-view", action="store_true", help="drive with the true view off (the T key)")
    a = p.parse_args(argv[: argv.index("--")] if "--" in argv else argv)

    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    command = [sys.executable, "-m", "orbis2.cli", "play", "--port", "0", *passed]
    if a.profile:
        command += ["--profile", a.profile]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = None
    for line in server.stdout:
        print(line, end="")
        if "ready at " in line:
            url = line.split("ready at ")[1].split()[0]
            break
    if url is None:
        sys.exit(f"orbis2 play did not start (exit {server.wait()})")
    profile_dir = tempfile.mkdtemp()
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", f"--user-data-dir={profile_dir}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    try:
        driver.get(url)
        page = lambda expression: driver.execute_script(f"return window.play.{expression}")  # noqa: E731
        while not page("shown"):
            time.sleep(0.1)
        if a.no_true_view:
            driver.find_element("tag name", "body").send_keys("t")
        generated, shown, held = [], [], False
        browser = psutil.Process(driver.service.process.pid)
        server_cpu, browser_cpu = cpu_seconds(psutil.Process(server.pid)), cpu_seconds(browser)
        started = toggled = time.monotonic()
        while time.monotonic() - started < a.seconds:
            if time.monotonic() - toggled > 1.5:
                chain = ActionChains(driver)
                (chain.key_up if held else chain.key_down)(Keys.LEFT).perform()
                held, toggled = not held, time.monotonic()
            generated.append(page("genFps"))
            shown.append(page("shownFps"))
            time.sleep(0.25)
        elapsed = time.monotonic() - started
        server_cores = (cpu_seconds(psutil.Process(server.pid)) - server_cpu) / elapsed
        browser_cores = (cpu_seconds(browser) - browser_cpu) / elapsed
        latencies = [s / 1000 for s in page("latencies")]
        true_view = page("trueView") and page("showTruth")
        driver.find_element("tag name", "body").send_keys(" ")  # pause
        time.sleep(2)  # the step in flight finishes
        before = cpu_seconds(psutil.Process(server.pid))
        time.sleep(a.idle)
        idle = (cpu_seconds(psutil.Process(server.pid)) - before) / a.idle
    finally:
        driver.quit()
        server.terminate()
        server.wait(timeout=30)
    figures = {
        "commit": code_commit(),
        "options": passed,
        "generated_fps_median": float(np.median(generated[4:])),
        "shown_fps_median": float(np.median(shown[8:])),
        "latency_s_median": float(np.median(latencies)) if latencies else None,
        "latency_s_max": float(np.max(latencies)) if latencies else None,
        "latency_samples": len(latencies),
        "idle_cores": idle,
        "server_cores_driving": server_cores,
        "browser_cores_driving": browser_cores,
        "true_view": bool(true_view),
        "cpu_count": psutil.cpu_count(),
        "load_average_1min_at_end": psutil.getloadavg()[0],
    }
    print(json.dumps(figures, indent=2))
    if a.json:
        a.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
