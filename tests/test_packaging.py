"""The wheel works from a clean environment (issue 13): built from a copy of the source, installed
into a fresh venv that sees the project's third-party dependencies (a ``.pth`` to ``.venv``'s
site-packages) but not the source tree, and run from another directory: every subpackage, the
shipped parameter sets (package data found through ``importlib.resources``) and the watchdog
applet are in it, and ``scenario``, ``replay``, ``diagnose`` and ``ardupilot-script`` give the
figures they give in the checkout."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: what a wheel is built from (the checkout's build/ and egg-info are left alone)
SOURCES = ("pyproject.toml", "README.md", "companion", "simvehicle", "configs")
SUBPACKAGES = ("companion", "companion.step", "companion.mavlink", "companion.recordings",
               "companion.recordings.importers", "companion.tools", "companion.diagnose",
               "companion.diagnose.closed_loop", "companion.diagnose.sensor", "companion.fleet",
               "simvehicle", "simvehicle.model", "simvehicle.engines", "simvehicle.server", "simvehicle.tools")
SHIPPED_CONFIGS = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "configs").rglob("*.toml"))


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, f"{' '.join(cmd)} -> {out.returncode}\n{out.stdout[-2000:]}\n{out.stderr[-2000:]}"
    return out


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / name, src / name)
    dist = tmp_path_factory.mktemp("dist")
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
          "-w", str(dist), str(src)], cwd=dist)
    (whl,) = dist.glob("flowhold-*.whl")
    return whl


@pytest.fixture(scope="module")
def installed(wheel, tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A fresh venv with the wheel installed; its python and the environment to run it in."""
    env_dir = tmp_path_factory.mktemp("venv")
    venv.create(env_dir, with_pip=False)
    py = env_dir / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q", str(wheel)],
         cwd=env_dir)
    site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=env_dir).stdout.strip())
    # the third-party dependencies from the project's venv (appended after the wheel's own
    # site-packages; a path line, so .venv's editable-install hook there is not run)
    (site / "zz_flowhold_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    return py, env


def test_wheel_holds_every_subpackage_and_the_package_data(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for pkg in SUBPACKAGES:
        assert f"{pkg.replace('.', '/')}/__init__.py" in names, pkg
    assert {f"companion/{c}" for c in SHIPPED_CONFIGS} <= names
    assert "companion/configs/sensors/stampfly.toml" in names
    assert "companion/ardupilot/flowhold_watchdog.lua" in names
    assert "companion/native/kernels.c" in names  # the compiled kernels' source, built on first use
    for c in SHIPPED_CONFIGS:  # real files in the wheel, equal to the checkout's
        assert zipfile.ZipFile(wheel).read(f"companion/{c}") == (ROOT / c).read_bytes(), c


def test_installed_package_imports_from_the_venv_with_its_configs(installed, tmp_path):
    py, env = installed
    probe = ("import importlib, json, sys\n"
             "mods = {m: importlib.import_module(m).__file__ for m in sys.argv[1:]}\n"
             "from companion.config import DEFAULT_CONFIG, load_config\n"
             "cfg = load_config()\n"
             "print(json.dumps({'mods': mods, 'default': str(DEFAULT_CONFIG), 'q': cfg.flow_sensor.q_rad_per_count,"
             " 'path': sys.path}))\n")
    out = json.loads(_run([str(py), "-c", probe, *SUBPACKAGES, "companion.diagnose.closed_loop.command",
                           "companion.diagnose.sensor.api", "simvehicle.engines.fastsim"],
                          cwd=tmp_path, env=env).stdout)
    venv_dir = py.parent.parent.resolve()
    for mod, file in out["mods"].items():
        assert Path(file).resolve().is_relative_to(venv_dir), (mod, file)
    assert Path(out["default"]).resolve().is_relative_to(venv_dir)
    assert out["q"] == pytest.approx(0.09 / 57.3)  # Table VI
    assert not any(Path(p).resolve() == ROOT for p in out["path"] if p)


def test_installed_commands_run_from_another_directory(installed, tmp_path):
    py, env = installed
    work = tmp_path / "elsewhere"
    work.mkdir()
    _run([str(py), "-m", "simvehicle", "scenario", "gust", "--tlog", "gust.tlog", "--json", "gust.json"],
         cwd=work, env=env)
    figures = json.loads((work / "gust.json").read_text())
    # the paper's gust (Fig. 17): 4 N on 2.3 kg held by about 10 deg of pitch, velocity back to 0
    assert figures["x"]["held_angle_deg"] == pytest.approx(-10.05, abs=0.05)
    assert abs(figures["x"]["final_velocity_m_s"]) < 0.01

    _run([str(py), "-m", "companion", "replay", "gust.tlog", "--csv", "replay.csv"], cwd=work, env=env)
    with (work / "replay.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1251  # one per flow frame of the 25 s scenario at 50 Hz
    assert {"t_s", "vx_m_s", "vy_m_s", "roll_cmd_rad", "pitch_cmd_rad"} <= set(rows[0])
    assert abs(float(rows[-1]["vx_m_s"])) < 0.05

    _run([str(py), "-m", "companion", "diagnose", "gust.tlog", "--json", "diag.json"], cwd=work, env=env)
    report = json.loads((work / "diag.json").read_text())
    wind = [f for f in report["findings"] if f["effect"] == "wind_force" and f["significant"]]
    assert len(wind) == 1
    assert wind[0]["parameters"]["fx"] == pytest.approx(-4.0, abs=0.05)
    assert wind[0]["parameters"]["start_s"] == pytest.approx(5.0, abs=0.1)

    lua = _run([str(py), "-m", "companion", "ardupilot-script"], cwd=work, env=env).stdout
    assert lua == (ROOT / "companion" / "ardupilot" / "flowhold_watchdog.lua").read_text(encoding="utf-8")
