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
    args = ["study", "jump", "--runs", "2", "--filters", "NL-GSF", "PF", "--out", str(tmp_path)]
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    assert "NL-GSF" in out and "8.339" in out  # the paper's ARMSE printed beside ours
    data = json.loads((tmp_path / "jump.json").read_text())
    assert set(data["filters"]) == {"NL-GSF", "PF"}
    assert len(data["filters"]["PF"]["rmse"]) == 120
    assert (tmp_path / "jump.png").exists()


def test_reproduce_lists_tables_and_rejects_unknown(capsys):
    assert cli.main(["reproduce"]) == 0
    assert "seed000-table7" in capsys.readouterr().out
    assert cli.main(["reproduce", "nope"]) == 2
    assert cli.main(["study", "nope", "--runs", "1"]) == 2
    assert cli.main(["study", "jump", "--runs", "1", "--filters", "XYZ"]) == 2
