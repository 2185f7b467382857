import json
import subprocess
import sys

import pytest

import gmjax
from gmjax import cli


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert gmjax.__version__ in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "Table 7" in capsys.readouterr().out


def test_static_study_runs_and_writes_results(tmp_path, capsys):
    assert cli.main(["static", "--draws", "8", "--out", str(tmp_path), "--no-plot"]) == 0
    out = capsys.readouterr().out
    assert "30 -> 20" in out and "100 -> 60" in out
    data = json.loads((tmp_path / "default_study.json").read_text())
    assert data["dtype"] == "float64" and data["seed"] == 0 and data["gmjax_version"] == gmjax.__version__
    for case in data["cases"].values():
        for row in case.values():
            assert 0.0 <= row["nise"]["mean"] <= 1.0
            assert row["ise"]["mean"] >= 0.0


def test_bench_lists_and_rejects_unknown(capsys):
    assert cli.main(["bench"]) == 0
    assert "metrics" in capsys.readouterr().out
    assert cli.main(["bench", "no_such_benchmark"]) == 2


def test_console_script_entry_point():
    res = subprocess.run([sys.executable, "-m", "gmjax.cli", "--version"], capture_output=True, text=True)
    assert res.returncode == 0 and "gmjax" in res.stdout


def test_study_prints_table_beside_paper_and_writes_json(tmp_path, capsys):
    args = ["study", "jump", "--runs", "2", "--filters", "NL-GSF", "PF", "--out", str(tmp_path), "--no-plot"]
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    assert "NL-GSF" in out and "8.339" in out  # the paper's ARMSE printed beside ours
    assert "float64" in out.splitlines()[0] and "seed 0" in out.splitlines()[0]  # the header says the dtype
    data = json.loads((tmp_path / "jump.json").read_text())
    assert set(data["filters"]) == {"NL-GSF", "PF"}
    assert len(data["filters"]["PF"]["rmse"]) == 120
    cfg = data["config"]
    assert cfg["dtype"] == "float64" and cfg["seed"] == 0 and cfg["n_runs"] == 2
    assert cfg["gmjax_version"] == gmjax.__version__ and cfg["jax_version"] and cfg["key"]["data"]
    assert data["filters"]["PF"]["config"]["filter"]["params"]  # each filter's own configuration
    assert not (tmp_path / "jump.png").exists()  # --no-plot


def _strict_json(text):
    def refuse(name):
        raise AssertionError(f"invalid JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_json_output_is_strict_json_for_one_run_and_still_plots(tmp_path, capsys):
    """Issue 15 item 7: one run has no standard error: ``null``, never ``NaN``."""
    assert (
        cli.main(["study", "jump", "--runs", "1", "--filters", "NL-GSF", "--out", str(tmp_path), "--json"])
        == 0
    )
    data = _strict_json(capsys.readouterr().out)
    assert data["filters"]["NL-GSF"]["armse_stderr"] is None
    assert data["filters"]["NL-GSF"]["n_runs"] == 1
    _strict_json((tmp_path / "jump.json").read_text())
    assert (tmp_path / "jump.png").exists()  # --json still writes the plot


@pytest.mark.parametrize(
    "argv, match",
    [
        (["static", "--draws", "0"], "--draws"),
        (["static", "--seed", str(2**70)], "--seed"),
        (["study", "jump", "--seed", "-1"], "--seed"),
        (["study", "jump", "--runs", "0"], "--runs"),
        (["study", "jump", "--chunk-size", "0"], "--chunk-size"),
        (["study", "jump", "--runs", "1", "--filters", "XYZ"], "filters"),
        (["reproduce", "nope"], "unknown table"),
    ],
)
def test_user_errors_are_one_line_and_exit_2(argv, match, capsys):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("gmjax: ") and match in err and err.count("\n") == 1 and "Traceback" not in err


def test_bad_out_folder_is_a_one_line_error(tmp_path, capsys):
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    for out in (a_file, a_file / "sub"):
        assert cli.main(["static", "--draws", "2", "--out", str(out), "--no-plot"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("gmjax: --out") and err.count("\n") == 1


def test_user_error_in_a_real_process_has_no_traceback():
    res = subprocess.run(
        [sys.executable, "-m", "gmjax.cli", "static", "--draws", "0"], capture_output=True, text=True
    )
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "Traceback" not in res.stderr


@pytest.fixture
def restore_x64():
    import jax

    before = jax.config.jax_enable_x64
    yield
    jax.config.update("jax_enable_x64", before)


@pytest.mark.slow  # a second compile of the static study, in float32
def test_float32_flag_runs_in_float32_and_says_so(tmp_path, capsys, restore_x64):
    assert cli.main(["static", "--draws", "4", "--out", str(tmp_path), "--no-plot", "--float32"]) == 0
    assert "float32" in capsys.readouterr().out.splitlines()[0]
    assert json.loads((tmp_path / "default_study.json").read_text())["dtype"] == "float32"


def test_reproduce_lists_tables_and_rejects_unknown(capsys):
    assert cli.main(["reproduce"]) == 0
    assert "seed000-table7" in capsys.readouterr().out
    assert cli.main(["reproduce", "nope"]) == 2
    assert cli.main(["study", "nope", "--runs", "1"]) == 2
