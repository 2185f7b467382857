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
    assert "default study" in capsys.readouterr().out


def test_default_study_runs_and_writes_results(tmp_path, capsys):
    assert cli.main(["--draws", "8", "--out", str(tmp_path), "--no-plot"]) == 0
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
