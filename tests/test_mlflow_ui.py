"""MLflow's UI as a reviewer first sees it, in headless Chromium with a fresh browser profile: the README's
server command and address open the smoke run's experiment, and its parent run's page, in model-training mode
(orbis2.mlflow_app), not on MLflow 3's GenAI pages. The screenshots are the ones docs/tracking.md shows
(docs/review/). Needs the Debian packages chromium and chromium-driver (.ci/run installs them); the first test
checks the page the app serves without them."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from conftest import ROOT, project_env

REVIEW = ROOT / "docs" / "review"
CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
# What only MLflow 3's GenAI pages show (its side bar, a run as an evaluation, models as agent versions).
GENAI = ("Agent versions", "Evaluation runs", "Training runs", "Observability", "Judges")
BROWSER_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--window-size=1600,1000")


def readme_server_and_address() -> tuple[str, str]:
    """The README's `mlflow ...` command and the address it says to open."""
    readme = (ROOT / "README.md").read_text()
    command = re.search(r"^(mlflow (?:ui|server) .*)$", readme, re.MULTILINE).group(1)
    address = re.search(r"`(http://127\.0\.0\.1:5000/[^`]+)`", readme).group(1)
    return command, address


def start_server(command: str, store: Path, port: int) -> subprocess.Popen:
    words = shlex.split(command)
    words[words.index("--backend-store-uri") + 1] = f"sqlite:///{store}"
    env = {**project_env(store.parent), "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}  # no GenAI job runners
    return subprocess.Popen([*words, "--host", "127.0.0.1", "--port", str(port), "--workers", "1"], cwd=store.parent,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def wait_for(proc: subprocess.Popen, url: str) -> None:
    for _ in range(240):
        if proc.poll() is not None:
            pytest.fail(f"the MLflow server exited with {proc.returncode}: {proc.stdout.read()[-2000:]}")
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    pytest.fail("the MLflow server did not answer within 120 s")


def page_text(driver, wanted: str, timeout_s: float = 60) -> str:
    """The page's text once ``wanted`` shows in it (the UI renders after its API calls)."""
    deadline = time.monotonic() + timeout_s
    while True:
        text = driver.find_element("tag name", "body").text
        if wanted in text or time.monotonic() > deadline:
            return text
        time.sleep(0.5)


def test_the_ui_page_starts_by_choosing_model_training_where_the_browser_has_no_choice():
    """What the browser test sees, without a browser: MLflow's page with the defaults first in its head."""
    from orbis2.mlflow_app import BROWSER_DEFAULTS, MODEL_TRAINING_FIRST, flask_app, with_model_training_first

    page = flask_app.test_client().get("/")
    text = page.get_data(as_text=True)
    assert page.status_code == 200 and text.startswith("<!doctype html><html lang=\"en\"><head>" + MODEL_TRAINING_FIRST)
    assert BROWSER_DEFAULTS["mlflow.workflowType_v1"] == '"machine_learning"' and text.count(MODEL_TRAINING_FIRST) == 1
    assert 'localStorage.getItem("mlflow.workflowType_v1")===null' in MODEL_TRAINING_FIRST  # a choice made stays
    assert with_model_training_first(text) == text
    assert flask_app.test_client().get("/health").get_data(as_text=True) == "OK"


@pytest.mark.slow
def test_the_readme_address_and_the_parent_run_open_in_model_training_mode(smoke_main, tmp_path):
    if not (CHROMIUM and DRIVER):
        pytest.skip("needs headless Chromium: apt-get install chromium chromium-driver (.ci/run does)")
    webdriver = pytest.importorskip("selenium.webdriver")
    from mlflow.tracking import MlflowClient
    from test_docs import free_port

    store = tmp_path / "mlflow.db"  # a copy: the server may write; the artifacts stay where the run put them
    shutil.copy2(smoke_main / "mlflow.db", store)
    client = MlflowClient(tracking_uri=f"sqlite:///{store}")
    experiment = client.get_experiment_by_name("orbis2")
    [parent] = client.search_runs([experiment.experiment_id], "tags.`orbis2.pipeline` = 'true'",
                                  order_by=["attributes.start_time ASC"], max_results=1)
    command, address = readme_server_and_address()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(command, store, port)
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*BROWSER_FLAGS, f"--user-data-dir={tmp_path / 'browser'}"):  # a fresh profile: nothing chosen
        options.add_argument(flag)
    driver = None
    try:
        wait_for(server, f"{base}/health")
        driver = webdriver.Chrome(service=webdriver.ChromeService(DRIVER), options=options)
        driver.get(address.replace("http://127.0.0.1:5000", base).replace("/experiments/1/",
                                                                         f"/experiments/{experiment.experiment_id}/"))
        runs = page_text(driver, parent.info.run_name)
        assert parent.info.run_name in runs and not [m for m in GENAI if m in runs], runs[:2000]
        headline = sorted(client.get_run(parent.info.run_id).data.metrics)[0]  # the first column the table shows
        assert headline in page_text(driver, headline), runs[:2000]  # the parent's columns, not MLflow's defaults
        REVIEW.mkdir(exist_ok=True)
        driver.save_screenshot(str(REVIEW / "runs.png"))

        driver.set_window_size(1600, 1900)  # the parent's page to its params and metrics
        driver.get(f"{base}/#/experiments/{experiment.experiment_id}/runs/{parent.info.run_id}")  # as a link opens it
        page = page_text(driver, "params_sha256")
        assert "params_sha256" in page and "profile" in page and "claim 1" in page, page[:2000]
        assert not [m for m in GENAI if m in page] and "Evaluations" not in page, page[:2000]
        assert "main_table/hierarchical/fvd_heldout" in page
        driver.save_screenshot(str(REVIEW / "parent.png"))

        driver.set_window_size(1600, 1000)
        artifacts = f"{base}/#/experiments/{experiment.experiment_id}/runs/{parent.info.run_id}/artifacts/"
        for artifact, shot in (("figures/intervals.png", "intervals.png"), ("gallery/hierarchical_val.gif",
                                                                            "gallery.png")):
            driver.get("about:blank")  # a page load, not only a new address fragment
            driver.get(artifacts + artifact)
            assert Path(artifact).name in page_text(driver, Path(artifact).name)
            time.sleep(3)  # the image itself
            driver.save_screenshot(str(REVIEW / shot))
    finally:
        if driver is not None:
            driver.quit()
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=30)
