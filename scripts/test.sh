#!/usr/bin/env bash
# Set up (first time), lint, and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check core app tests
.venv/bin/lint-imports  # the layering contracts of pyproject.toml [tool.importlinter]

# browser: the real-browser tests (tests/app/test_browser.py) drive the system chromium through
# playwright (never `playwright install`). Install it when missing; if that fails they skip.
install_chromium() {
    local sudo=()
    if [[ $(id -u) -ne 0 ]]; then
        command -v sudo >/dev/null 2>&1 || return 1
        sudo=(sudo -n)
    fi
    "${sudo[@]}" apt-get install -y chromium \
        || { "${sudo[@]}" apt-get update && "${sudo[@]}" apt-get install -y chromium; }
}
if [[ ! -x /usr/bin/chromium ]]; then
    echo "test.sh: /usr/bin/chromium is missing: installing it with apt-get" >&2
    if ! install_chromium || [[ ! -x /usr/bin/chromium ]]; then
        echo "test.sh: WARNING: could not install chromium (apt-get install -y chromium):" \
            "the browser tests will be skipped" >&2
    fi
fi

# The core's kernels are compiled once per checkout (core/compiled.py, ~95 s of CPU on a fresh
# one): built here with every core instead of one after the other by the first test.
# A build that has not finished in 15 minutes is stopped (with its whole process group) and
# left to the tests, which build what is missing themselves: the suite never waits forever here.
timeout 900 .venv/bin/python scripts/build_kernels.py \
    || echo "test.sh: WARNING: the parallel kernel build did not finish (exit $?):" \
        "the tests build the missing kernels one after the other" >&2

# The debugger's server runs numba's JIT kernels (they release the GIL: app/server.py), which
# numba compiles on their first call and caches beside the sources: on a fresh checkout ~100 s
# of CPU, more than a browser test waits for its first frame on a slow 2-core machine. One
# reconstruction of every bundled frame in that mode fills the cache first (the same kernels
# and argument types the browser tests' server calls); a failure here is left to the tests.
THREADRECON_KERNELS=jit timeout 900 .venv/bin/python -m threadrecon.app.cli evaluate sample_data \
    >/dev/null || echo "test.sh: WARNING: warming numba's JIT cache did not finish (exit $?)" >&2

# The suite on every core (pytest-xdist; TEST_WORKERS=0 runs it in this process): a test file
# runs whole on one worker (--dist loadfile), so a module's server, browser or generated data
# set is made once. While one worker waits on a server or a browser, the other computes.
# Files go out in collection order (--no-loadscope-reorder), not largest first: the browser
# and server files (one slow test each) start early and the core's many short files fill the
# end, instead of the slowest single tests coming last with one worker left idle.
.venv/bin/python -m pytest -n "${TEST_WORKERS:-auto}" --dist loadfile --no-loadscope-reorder "$@"
