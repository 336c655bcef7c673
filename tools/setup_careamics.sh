#!/usr/bin/env bash
# The CAREamics peer's environment (.venv-careamics) for `bench_denoise.py careamics`, from the pinned
# tools/careamics-requirements.txt. Separate from .venv: careamics 0.3.5 pins torch < 2.14 and
# numpy <= 2.4.6, below the project's. Idempotent (uv installs only what is missing or different).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .tools/bin/uv ] || [ ! -x .venv/bin/python ]; then
    bash tools/setup_env.sh
fi
if [ ! -x .venv-careamics/bin/python ]; then
    .tools/bin/uv venv --quiet --python "$(.venv/bin/python -c 'import sys; print(sys.executable)')" .venv-careamics
fi
.tools/bin/uv pip install --quiet --python .venv-careamics/bin/python -r tools/careamics-requirements.txt
