"""MLflow's server with the UI opening in *Model training* mode: ``mlflow server --app-name orbis2``.

MLflow 3's UI (3.17 checked) shows an experiment and its runs as GenAI pages (the overview of traces, a
run as an "Evaluation run", its models as "Agent versions") unless the page's address says
``?workflowType=machine_learning`` or the browser's local storage holds ``mlflow.workflowType_v1 =
"machine_learning"``, which only a click on its *Model training* switch writes. The experiment's
``mlflow.experimentKind`` tag is not read for this (the UI derives the kind from that workflow type
alone), and a link from the runs view to a run drops the address's parameter, so a fresh browser
shows every run page as GenAI.

Its runs table also starts with three attribute columns (source, models, dataset) and none of the
params or metrics, which sit among hundreds of hidden columns; it keeps its columns in local storage per
experiment (``MLflowLocalStorage-1.1-ExperimentPage-["<id>"]-ReactComponentState``, the table's whole
state as JSON).

This app is MLflow's own (``mlflow.server.fastapi_app.create_fastapi_app`` over its Flask app), with one
change: the UI's page starts with a line that sets those storage keys where the browser has none yet,
before MLflow's scripts read them: model training, MLflow's LLM assistant not opened on a fresh browser's
first page, and for every experiment with a pipeline run a runs table showing the parent run's params
(profile, commit, params digest) and headline metrics. A browser that chose otherwise keeps its choice. It is
registered as an ``mlflow.app`` entry point (pyproject.toml), the hook MLflow's server offers for
apps built on it (``--app-name basic-auth`` is MLflow's own).
"""

from __future__ import annotations

import json

from flask import Response, request
from mlflow.entities import ViewType
from mlflow.server import app as flask_app
from mlflow.server.fastapi_app import create_fastapi_app
from mlflow.server.handlers import _add_static_prefix, _get_tracking_store

# The UI's local-storage keys and the JSON values this app starts a fresh browser with: model training, and
# MLflow's LLM assistant not opened over a third of every page on the first visit (the button stays).
BROWSER_DEFAULTS = {"mlflow.workflowType_v1": '"machine_learning"',
                    "mlflow.assistant.fab.autoOpenedOnFirstLoad_v1": "true"}
# The runs table's state as MLflow 3.17 starts it (its defaults, read from a fresh browser's storage), but for
# the columns; the browser test (tests/test_mlflow_ui.py) checks that the UI still takes it.
RUNS_TABLE = {"searchFilter": "", "orderByKey": "attributes.start_time", "orderByAsc": False, "startTime": "ALL",
              "lifecycleFilter": "Active", "datasetsFilter": [], "modelVersionFilter": "All Runs",
              "columnOrder": [], "columnWidths": {}, "runsExpanded": {}, "runsPinned": [], "runsHidden": [],
              "runsVisibilityMap": {}, "runsHiddenMode": "FIRST_10_RUNS", "viewMaximized": False,
              "runListHidden": False, "isAccordionReordered": False, "useGroupedValuesInCharts": True,
              "hideEmptyCharts": True, "groupBy": None, "groupsExpanded": {}, "autoRefreshEnabled": True,
              "globalLineChartConfig": {"xAxisKey": "step", "lineSmoothness": 0, "selectedXAxisMetricKey": ""}}


def defaults_script(defaults: dict[str, str]) -> str:
    """A script that sets each local-storage key to its value where the browser has none."""
    lines = "".join(f"if(localStorage.getItem({json.dumps(key)})===null)"
                    f"localStorage.setItem({json.dumps(key)},{json.dumps(value)});" for key, value in defaults.items())
    return "<script>try{" + lines.replace("</", "<\\/") + "}catch(e){}</script>"  # no "</script>" inside


MODEL_TRAINING_FIRST = defaults_script(BROWSER_DEFAULTS)


def runs_table_defaults(store=None) -> dict[str, str]:
    """Per experiment with a pipeline run: its runs table's storage key and a state whose columns are the newest
    parent run's params and (of the newest parent that has them) headline metrics."""
    store = store or _get_tracking_store()
    defaults = {}
    for experiment in store.search_experiments(view_type=ViewType.ACTIVE_ONLY, max_results=1000):
        parents = store.search_runs([experiment.experiment_id], "tags.`orbis2.pipeline` = 'true'",
                                    ViewType.ACTIVE_ONLY, max_results=20, order_by=["attributes.start_time DESC"])
        if not parents:
            continue
        metrics = next((sorted(run.data.metrics) for run in parents if run.data.metrics), [])
        params = list(parents[0].data.params)  # what orbis2.tracking.parent_run logs: profile, commit, digest
        columns = [f"params.`{key}`" for key in params] + [f"metrics.`{key}`" for key in metrics]
        key = f"MLflowLocalStorage-1.1-ExperimentPage-{json.dumps([experiment.experiment_id])}-ReactComponentState"
        defaults[key] = json.dumps({**RUNS_TABLE, "selectedColumns": ["attributes.`Models`", *columns]},
                                   separators=(",", ":"))
    return defaults


def with_model_training_first(page: str, extra: str = "") -> str:
    """The UI's page with :data:`MODEL_TRAINING_FIRST` (and ``extra``, the runs tables' defaults) as the first
    thing its ``<head>`` runs."""
    if MODEL_TRAINING_FIRST in page or "<head>" not in page:
        return page
    return page.replace("<head>", "<head>" + MODEL_TRAINING_FIRST + extra, 1)


@flask_app.after_request
def _model_training_first(response: Response) -> Response:
    if request.path != _add_static_prefix("/") or response.status_code != 200 or response.mimetype != "text/html":
        return response
    response.direct_passthrough = False  # the page is sent as a file: read it to change it
    tables = runs_table_defaults()
    response.set_data(with_model_training_first(response.get_data(as_text=True),
                                                defaults_script(tables) if tables else ""))
    response.headers.pop("ETag", None)  # another page than the file's
    return response


app = create_fastapi_app(flask_app)
