#!/usr/bin/env bash
# Installs rlu with every extra the tests exercise into .venv, then runs the test suite on CPU.
#   bash scripts/test.sh            # the fast suite (the tests marked slow are left out)
#   RLU_SLOW=1 bash scripts/test.sh # CI's suite: the slow learning checks too, not those marked long
#   RLU_SLOW=2 bash scripts/test.sh # everything: the long reproductions of whole jobs too
# The tests run on every core (pytest-xdist; RLU_TEST_WORKERS=1 runs them in one process).
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh control locomotion atari bsuite agents jax distributed report video dev tensorboard wandb docs
# MuJoCo renders offscreen through Mesa's EGL (in the base image); without MUJOCO_GL set,
# rendering fails looking for an X display.
export MUJOCO_GL=${MUJOCO_GL:-egl}
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# The slow report test screenshots report.html in Debian's headless chromium; install it where
# it is missing and apt-get can (root), else that one test skips and says why.
if [ "${RLU_SLOW:-0}" != "0" ] && ! command -v chromium >/dev/null; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = "0" ]; then
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; } \
      || echo "scripts/test.sh: installing chromium failed; the browser test will skip"
  else
    echo "scripts/test.sh: no chromium and no root apt-get; the browser test will skip"
  fi
fi
# the linters run first, as in d3rlpy's CI: a lint failure fails the test command
echo "scripts/test.sh: ruff check and ruff format --check"
.venv/bin/ruff check .
.venv/bin/ruff format --check rlu tests bench scripts
# mypy over all of rlu/ (pyproject.toml's [tool.mypy]; docs/getting_started.md says how strict)
echo "scripts/test.sh: mypy"
.venv/bin/mypy
# The documentation site (mkdocs.yml), warnings as errors: a broken link or anchor, a page left
# out of the nav, a docstring mkdocstrings cannot read. Into build/site (git-ignored). Not
# --quiet: with it, mkdocs 1.6 counts no warning and --strict passes whatever the site holds.
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --site-dir build/site
case "${RLU_SLOW:-0}" in
  0) marker=(-m "not slow") ;;
  1) marker=(-m "not long") ;;
  *) marker=() ;;
esac
workers=${RLU_TEST_WORKERS:-auto}
parallel=()
[ "$workers" != "1" ] && parallel=(-n "$workers" --dist worksteal)
set +e
.venv/bin/python -m pytest -q --durations=15 "${parallel[@]}" "${marker[@]}" "$@"
rc=$?
set -e
# pytest exits 5 when it collected no test; that is not a failure of the code under test.
[ "$rc" = "5" ] && { echo "pytest: no tests collected"; exit 0; }
exit "$rc"
