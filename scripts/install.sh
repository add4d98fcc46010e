#!/usr/bin/env bash
# Installs rlu into a project-local venv (.venv) with the extras named as arguments.
#   bash scripts/install.sh                 # core only (numpy)
#   bash scripts/install.sh control agents  # plus extras
# Idempotent: a second run only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -U pip
extras=$(IFS=,; echo "$*")
# torch 2.13.0 is the CPU build on local disk; installing it first keeps pip from resolving a
# newer CUDA build for packages that depend on torch.
case ",$extras," in
  *,agents,*|*,dev,*) .venv/bin/python -m pip install -q --disable-pip-version-check "torch==2.13.0" ;;
esac
if [ -n "$extras" ]; then
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[$extras]"
else
  .venv/bin/python -m pip install -q --disable-pip-version-check -e .
fi
