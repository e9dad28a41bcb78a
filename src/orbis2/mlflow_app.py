"""MLflow's server with the UI opening in *Model training* mode: ``mlflow server --app-name orbis2``.

MLflow 3's UI (3.17 checked) shows an experiment and its runs as GenAI pages (the overview of traces, a
run as an "Evaluation run", its models as "Agent versions") unless the page's address says
``?workflowType=machine_learning`` or the browser's local storage holds ``mlflow.workflowType_v1 =
"machine_learning"``, which only a click on its *Model training* switch writes. The experiment's
``mlflow.experimentKind`` tag is not read for this (the UI derives the kind from that workflow type
alone), and a link from the runs view to a run drops the address's parameter, so a fresh browser
shows every run page as GenAI.

This app is MLflow's own (``mlflow.server.fastapi_app.create_fastapi_app`` over its Flask app), with one
change: the UI's page starts with a line that sets that storage key to model training where the browser
has none yet, before MLflow's scripts read it (and keeps MLflow's LLM assistant from opening itself on a
fresh browser's first page). A browser that chose otherwise keeps its choice. It is
registered as an ``mlflow.app`` entry point (pyproject.toml), the hook MLflow's server offers for
apps built on it (``--app-name basic-auth`` is MLflow's own).
"""

from __future__ import annotations

from flask import Response, request
from mlflow.server import app as flask_app
from mlflow.server.fastapi_app import create_fastapi_app
from mlflow.server.handlers import _add_static_prefix

# The UI's local-storage keys and the JSON values this app starts a fresh browser with: model training, and
# MLflow's LLM assistant not opened over a third of every page on the first visit (the button stays).
BROWSER_DEFAULTS = {"mlflow.workflowType_v1": '"machine_learning"',
                    "mlflow.assistant.fab.autoOpenedOnFirstLoad_v1": "true"}
MODEL_TRAINING_FIRST = ("<script>try{" + "".join(f"if(localStorage.getItem('{key}')===null)"
                                                  f"localStorage.setItem('{key}','{value}');"
                                                  for key, value in BROWSER_DEFAULTS.items())
                        + "}catch(e){}</script>")


def with_model_training_first(page: str) -> str:
    """The UI's page with :data:`MODEL_TRAINING_FIRST` as the first thing its ``<head>`` runs."""
    if MODEL_TRAINING_FIRST in page or "<head>" not in page:
        return page
    return page.replace("<head>", "<head>" + MODEL_TRAINING_FIRST, 1)


@flask_app.after_request
def _model_training_first(response: Response) -> Response:
    if request.path != _add_static_prefix("/") or response.status_code != 200 or response.mimetype != "text/html":
        return response
    response.direct_passthrough = False  # the page is sent as a file: read it to change it
    response.set_data(with_model_training_first(response.get_data(as_text=True)))
    response.headers.pop("ETag", None)  # another page than the file's
    return response


app = create_fastapi_app(flask_app)
