"""Progress bars (issue 14): on a terminal, a bar for long reads, imports and CSV writing; quiet
when stderr is not a terminal. The importers (DataFlash, ULog, CSV) report their stages."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

import companion.recordings.load
from companion.progress import Stages
from companion.recordings.importers import csv_columns, dataflash, ulog
from companion.recordings.load import load_recording

REPO = Path(__file__).resolve().parent.parent
BIN = REPO / "data" / "sitl" / "ardupilot" / "flight_c0.BIN.gz"
ULG = REPO / "tests" / "data" / "importers" / "px4_flow.ulg"
CSV = REPO / "data" / "real" / "stampfly" / "flow_test_x_axis_01.csv.gz"
MAP = REPO / "configs" / "sensors" / "stampfly.toml"


def test_a_stage_bar_shows_the_stages_done_and_nothing_when_disabled():
    out = io.StringIO()
    with Stages(True, "importing x.bin", 3, file=out, delay_s=0.0) as done:
        done("read")
        done("indexed")
        done.bar.refresh()
        shown = out.getvalue()
    assert "importing x.bin: 2/3 stages" in shown and "indexed" in shown
    quiet = io.StringIO()
    with Stages(False, "importing x.bin", 3, file=quiet, delay_s=0.0) as done:
        done("read")
    assert quiet.getvalue() == ""


def test_a_short_import_draws_no_bar_before_its_delay():
    out = io.StringIO()
    with Stages(True, "importing x.bin", 3, file=out) as done:  # the default delay: a second
        for stage in ("a", "b", "c"):
            done(stage)
    assert out.getvalue() == ""


@pytest.mark.parametrize("path, module, kwargs", [
    (BIN, dataflash, {}), (ULG, ulog, {}), (CSV, csv_columns, {"sensor_config": MAP})])
def test_each_importer_reports_every_stage_in_order(path, module, kwargs, monkeypatch):
    seen: list[tuple[str, ...]] = []

    class Recorder(Stages):
        def __init__(self, enabled: bool, desc: str, total: int, **_kw) -> None:
            super().__init__(False, desc, total)
            self.enabled, self.desc, self.total, self.stages = enabled, desc, total, []

        def __call__(self, stage: str) -> None:
            self.stages.append(stage)

        def close(self) -> None:
            seen.append((self.desc, str(self.enabled), str(self.total), *self.stages))

    monkeypatch.setattr(companion.recordings.load, "Stages", Recorder)
    load_recording(path, progress=True, **kwargs)
    assert seen == [(f"importing {path.name}", "True", str(len(module.STAGES)), *module.STAGES)]


def test_commands_in_a_pipe_draw_no_bar(tmp_path):
    """stderr is a pipe here, as in CI and logs: no bar, whatever the file."""
    for args in (["info", str(BIN)], ["replay", str(BIN), "--profile", "ardupilot", "--csv", str(tmp_path / "r.csv")]):
        r = subprocess.run([sys.executable, "-m", "companion", *args], cwd=REPO, capture_output=True, text=True,
                           timeout=120, check=False)
        assert r.returncode == 0, r.stderr
        assert "stages|" not in r.stderr and "\r" not in r.stderr
