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
has none yet, before MLflow's scripts read it. A browser that chose GenAI keeps its choice. It is
registered as an ``mlflow.app`` entry point (pyproject.toml), the hook MLflow's server offers for
apps built on it (``--app-name basic-auth`` is MLflow's own).
"""

from __future__ import annotations

from flask import Response, request
from mlflow.server import app as flask_app
from mlflow.server.fastapi_app import create_fastapi_app
from mlflow.server.handlers import _add_static_prefix

STORAGE_KEY, MODEL_TRAINING = "mlflow.workflowType_v1", '"machine_learning"'  # the UI's key, JSON-encoded value
MODEL_TRAINING_FIRST = (f"<script>try{{if(!localStorage.getItem('{STORAGE_KEY}'))"
                        f"localStorage.setItem('{STORAGE_KEY}','{MODEL_TRAINING}')}}catch(e){{}}</script>")


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
