import os
import sys
from pathlib import Path

import jax
import pytest

# the independent references (references/, plain NumPy/SciPy) import as `references` from any test
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# Tests run with float64 available; float32 cases pass dtype=jnp.float32 explicitly.
jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------- compiled-code mappings
# Every compiled XLA CPU program keeps about three memory mappings until JAX's caches drop it. A test
# worker compiles thousands of programs; at Linux's vm.max_map_count (65530 by default) the next
# mapping fails and XLA segfaults while compiling (seen twice near the end of a full run, in
# test_tune, with ~40,000 mappings in the surviving worker). Dropping the caches when the count
# passes a bound keeps every worker far from the limit (each test recompiles what it needs).
_MAX_MAPPINGS = 20_000


def _n_mappings() -> int:
    try:
        with open(f"/proc/{os.getpid()}/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


@pytest.fixture(autouse=True)
def _bounded_compiled_code():
    yield
    if _n_mappings() > _MAX_MAPPINGS:
        jax.clear_caches()


# --------------------------------------------------------------------------- crashed xdist workers
# Should a worker still die mid-test in native code, its test is run once more on a fresh worker; the
# crash stays visible: the first attempt is reported as "rerun" and listed in the summary, and a
# second crash fails the test.
_crashed: list[str] = []


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    if crashitem in _crashed:
        return
    _crashed.append(crashitem)
    sched.mark_test_pending(crashitem)
    report.outcome = "rerun"


def pytest_terminal_summary(terminalreporter):
    for nodeid in _crashed:
        terminalreporter.write_line(
            f"WORKER CRASH: {nodeid} crashed its worker once and was run again on a fresh worker "
            "(its result above is the second attempt's)",
            yellow=True,
        )
