#!/usr/bin/env bash
# Create or update the project environment (.venv) from the committed uv.lock.
# Idempotent: when .venv matches uv.lock nothing is downloaded or reinstalled.
set -euo pipefail
cd "$(dirname "$0")/.."

UV_VERSION=0.13.8
TOOLS=.tools

# 1. Python 3.12 (mrcal ships wheels for 3.12+ only; the lockfile targets 3.12).
find_python() {
    local c
    for c in "${PYTHON:-}" python3.12 "$HOME"/.pyenv/versions/3.12*/bin/python3.12 \
             /usr/local/bin/python3.12 /usr/bin/python3.12; do
        [ -n "$c" ] || continue
        if "$c" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
            command -v "$c" 2>/dev/null || echo "$c"
            return 0
        fi
    done
    return 1
}
if ! PY=$(find_python); then
    echo "setup: Python 3.12 not found." >&2
    echo "  fix: install it (Debian/Ubuntu: 'apt-get install python3.12 python3.12-venv'," >&2
    echo "       or 'pyenv install 3.12'), or point PYTHON=/path/to/python3.12 at it." >&2
    exit 2
fi

# 2. uv, pinned, in a private tool venv (no global installs).
if [ ! -x "$TOOLS/bin/uv" ] || [ "$("$TOOLS/bin/uv" --version | awk '{print $2}')" != "$UV_VERSION" ]; then
    echo "setup: installing uv $UV_VERSION into $TOOLS/" >&2
    "$PY" -m venv "$TOOLS"
    "$TOOLS/bin/python" -m pip install --quiet --disable-pip-version-check "uv==$UV_VERSION"
fi

# 3. System library needed by `import open3d`: libusb-1.0.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: installing libusb-1.0-0 (needed by open3d)" >&2
        (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) >&2
    else
        echo "setup: open3d needs the system library libusb-1.0, which is missing." >&2
        echo "  fix: sudo apt-get install libusb-1.0-0   (Fedora: sudo dnf install libusb1)" >&2
        exit 2
    fi
fi

# 4. The environment, exactly as locked (uv.lock is committed; --frozen never re-resolves).
"$TOOLS/bin/uv" sync --frozen --compile-bytecode --python "$PY" --quiet "$@"
