import jax
import pytest

# Tests run with float64 available; float32 cases pass dtype=jnp.float32 explicitly.
jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------- crashed xdist workers
# CI once saw an xdist worker die mid-test (a native crash inside the XLA CPU runtime, in a test that
# passes alone and in every other full run). A test whose worker crashes is run once more on a fresh
# worker; the crash stays visible: the first attempt is reported as "rerun" and listed in the summary,
# and a second crash fails the test.
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
