import os
import sys
from pathlib import Path

# Tests check values, not speed: XLA compiles their thousands of small programs with LLVM's
# optimisation level 0, which takes about a quarter less compile time (test_contract: 150 s -> 110 s
# on 2 cores); it must be set before JAX starts its CPU backend. Benchmarks and users keep XLA's default.
# A test that checks two *different* programs for bit-identity checks what XLA's default compilation
# gives, so it compiles them in a subprocess with the default (``default_xla_env``).
TEST_XLA_FLAG = "--xla_backend_optimization_level=0"


def default_xla_env(**extra: str) -> dict:
    """``os.environ`` for a subprocess that compiles with XLA's default optimisation level."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if f != TEST_XLA_FLAG]
    return dict(os.environ, XLA_FLAGS=" ".join(flags), **extra)


if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + TEST_XLA_FLAG).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

# the independent references (references/, plain NumPy/SciPy) import as `references` from any test
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# Tests mirror the package (tests/reduction/ beside gmjax/reduction/, ...); the helpers they share
# (test_contract's tables, test_reduction_utils' random mixtures) import by name from tests/.
sys.path.insert(0, str(Path(__file__).resolve().parent))

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
