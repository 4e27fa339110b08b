"""Start-up stays lean: ``replay`` and ``info`` load no numba, scipy, matplotlib or pyarrow
unless asked for what needs them (issue 17: on an hour-long recording the whole command is
measured against pymavlink's read, and numba alone costs about 0.35 s to import and load)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numba", "llvmlite", "scipy", "matplotlib", "pyarrow", "pandas", "dask")

PROBE = """
import contextlib, io, json, sys
from companion.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    code = main(sys.argv[1:])
heavy = sorted({m.split(".")[0] for m in sys.modules} & set(HEAVY))
print(json.dumps({"code": code, "heavy": heavy}))
""".replace("HEAVY", repr(HEAVY))


def _loaded(*args: str) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, cwd=ROOT, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("command", ["replay-csv", "info"])
def test_replay_and_info_load_nothing_heavy(command, flight_a_plain, tmp_path):
    args = (["replay", str(flight_a_plain), "--csv", str(tmp_path / "r.csv")] if command == "replay-csv"
            else ["info", str(flight_a_plain)])
    r = _loaded(*args)
    assert r["code"] == 0
    assert r["heavy"] == []


def test_the_closed_loop_diagnosis_loads_no_scipy_signal_or_stats(tmp_path):
    """issue 12's time budget (a quarter of pymavlink's read of an hour-long recording): the
    closed-loop ``diagnose`` does without scipy.signal and scipy.stats (about 0.3 s to import;
    its filters are companion.diagnose.filters, its tail probabilities scipy.special's)."""
    from companion import native

    if native.kernels() is None:
        pytest.skip("without the compiled kernels the filters are scipy.signal's own")
    gust = ROOT / "data" / "sitl" / "ardupilot" / "flight_c0_companion.tlog.gz"
    probe = PROBE.replace("heavy = sorted", "heavy = sorted(m for m in sys.modules if m in ('scipy.signal', "
                                            "'scipy.stats')) or sorted")
    out = subprocess.run([sys.executable, "-c", probe, "diagnose", str(gust), "--profile", "ardupilot", "--config",
                          str(ROOT / "configs" / "ardupilot_sitl.toml"), "--json", str(tmp_path / "d.json")],
                         capture_output=True, text=True, cwd=ROOT, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["code"] == 0
    assert "scipy" in r["heavy"] and not {"scipy.signal", "scipy.stats"} & set(r["heavy"])
    assert json.loads((tmp_path / "d.json").read_text())["findings"]


def test_parquet_loads_pyarrow_only_when_asked(flight_a_plain, tmp_path):
    pytest.importorskip("pyarrow")
    r = _loaded("replay", str(flight_a_plain), "--parquet", str(tmp_path / "r.parquet"))
    assert r["code"] == 0
    assert "pyarrow" in r["heavy"]
    assert not {"numba", "scipy", "matplotlib"} & set(r["heavy"])


@pytest.mark.parametrize("preset", [None, "3"])
def test_replay_and_info_load_numpy_with_one_blas_thread_unless_told(preset):
    """replay and info set OPENBLAS_NUM_THREADS=1 before numpy loads (its idle threads spin on
    the core the reader's and CSV writer's second thread needs); a value the user set stays."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    probe = ("import os, sys\nfrom companion.cli import _batch_process\n_batch_process()\n"
             "import numpy\nprint(os.environ['OPENBLAS_NUM_THREADS'])")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, env=env, check=True)
    assert out.stdout.strip() == (preset or "1")
