#!/usr/bin/env bash
# Build ./wheelhouse: every wheel the project needs on a GPU machine with Python 3.12 that already has
# torch (CUDA), numpy, pandas, pyarrow, opencv and numba. Run with index access; tools/gpu_run.sh installs it
# offline. Excluded on purpose: torch and its dependencies (the machine's own build), numpy/pandas/pyarrow/
# opencv/numba and theirs, scipy (only a test's reference uses it) and pulp (snakemake's optional ILP
# scheduler; snakemake falls back to its greedy one). Result: about 62 MiB.
set -euo pipefail
cd "$(dirname "$0")/.."
WH=wheelhouse
mkdir -p "$WH"
PLATFORM=(--python-version 3.12 --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64
          --platform manylinux_2_28_x86_64 --platform any)
# Two dependencies publish source archives only: build their (pure-Python) wheels first.
pip wheel --no-deps -w "$WH" "connection_pool>=0.0.3" "antlr4-python3-runtime==4.9.3"
pip download --only-binary=:all: --find-links "$WH" "${PLATFORM[@]}" -d "$WH" \
  snakemake==9.27.1 mlflow-skinny==3.17.2 sqlalchemy==2.0.58 alembic==1.20.1 dvc==3.67.1 webdataset==1.0.2 \
  pytest==9.0.3 pyyaml tqdm pillow matplotlib threadpoolctl
cd "$WH"
rm -f numpy-* torch-* nvidia_* triton-* pandas-* pyarrow-* opencv* numba-* llvmlite-* scipy-* pulp-* \
  networkx-* jinja2-* [Mm]arkup[Ss]afe-* filelock-* fsspec-* typing_extensions-* setuptools-* sympy-* mpmath-* \
  python_dateutil-* six-*
du -sh .
