#!/usr/bin/env bash
# Build ./wheelhouse: the wheels the gpu_run.sh DAG part needs on the GPU machine (Python 3.12) beyond what its
# image provides (tools/gpu_image_packages.txt). Every other part of the measurement imports only what the image
# has, so the wheelhouse is only for the DAG part. Run with index access; gpu_run.sh installs it offline.
# Left out on purpose: DVC (the measurement runs Snakemake; nothing imports DVC) and pulp (Snakemake's optional
# ILP scheduler; it falls back to its greedy one).
set -euo pipefail
cd "$(dirname "$0")/.."
WH=wheelhouse
mkdir -p "$WH"
PLATFORM=(--python-version 3.12 --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64
          --platform manylinux_2_28_x86_64 --platform any)
# Two dependencies publish source archives only: build their (pure-Python) wheels first.
pip wheel --no-deps -w "$WH" "connection_pool>=0.0.3"
pip download --only-binary=:all: --find-links "$WH" "${PLATFORM[@]}" -d "$WH" \
  snakemake==9.27.1 mlflow-skinny==3.17.2 sqlalchemy==2.0.58 alembic==1.20.1 webdataset==1.0.2 pydantic
rm -f "$WH"/pulp-*
python3 tools/wheelhouse_filter.py "$WH"
