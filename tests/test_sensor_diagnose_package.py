"""``companion.diagnose.sensor`` (once ``companion.sensor_diagnose``) as a package (issue 13): one module per
part, every name the single module held still importable from ``companion.diagnose.sensor.api``, each
defined once, and the figure drawn without touching matplotlib's global state."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import companion.diagnose.sensor.api as sd

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "companion" / "diagnose" / "sensor"
#: the public names ``companion/sensor_diagnose.py`` held at its top level before the split
FORMER_NAMES = (
    "GRAVITY_M_S2", "QUANT_RMS_COUNTS", "SensorDiagnosisSettings", "DocumentedMotion", "DOCUMENTED_MOTIONS",
    "SensorSeries", "extract_series", "TimingAnalysis", "analyse_timing", "merge_windows", "timing_findings",
    "range_finding", "still_rows", "BiasFit", "fit_gyro_bias", "window_integral", "window_integrals",
    "inband_velocity", "RotationBandFit", "Displacement", "displacement_parts", "AXIS_NAMES", "CROSS_END_S", "Leg",
    "find_legs", "LegScaleFit", "pattern_match", "PooledScale", "pool_scales", "SensorDiagnosis", "diagnose_sensor",
    "run_sensor_diagnosis", "plot_diagnosis", "write_report_dir", "markdown_report", "summary_lines",
    "run_sensor_cli", "ReadGrid", "find_read_grid",
)


def _defined(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.ClassDef):
            out.add(node.name)
        elif isinstance(node, ast.Assign):
            out |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out.add(node.target.id)
    return out


def test_every_former_name_is_exported_and_defined_in_one_module():
    assert set(FORMER_NAMES) <= set(sd.__all__)
    where: dict[str, list[str]] = {}
    for path in sorted(PACKAGE.glob("*.py")):
        if path.name not in ("__init__.py", "api.py"):
            for name in _defined(path):
                where.setdefault(name, []).append(path.stem)
    for name in FORMER_NAMES:
        assert callable(getattr(sd, name)) or getattr(sd, name) is not None, name
        if name not in ("ReadGrid", "find_read_grid"):  # (the CSV importers' read grid, re-exported)
            assert len(where.get(name, [])) == 1, (name, where.get(name))
    assert not _defined(PACKAGE / "api.py") - {"__all__"}  # the api module only re-exports
    assert not _defined(PACKAGE / "__init__.py")  # and the package's __init__ holds nothing


def test_the_documented_motions_are_data_in_their_own_module():
    assert _defined(PACKAGE / "motions.py") == {"DocumentedMotion", "DOCUMENTED_MOTIONS", "leg_reference"}
    assert sd.DOCUMENTED_MOTIONS["flow_test_x_axis_01.csv"].leg_m == 0.20


def test_the_figure_leaves_matplotlibs_state_alone(tmp_path):
    """Drawn with the ``Figure`` API: no backend chosen, pyplot never loaded."""
    probe = (
        "import sys, matplotlib\n"
        "from pathlib import Path\n"
        "from companion.config import load_config\n"
        "from companion.recordings.load import load_recording\n"
        "from companion.diagnose.sensor.api import run_sensor_diagnosis\n"
        "before = dict.__getitem__(matplotlib.rcParams, 'backend')  # (without resolving it)\n"
        f"rec = load_recording({str(ROOT / 'data/real/stampfly/static_final.csv.gz')!r}, "
        f"sensor_config={str(ROOT / 'configs/sensors/stampfly.toml')!r})\n"
        f"run_sensor_diagnosis(rec, load_config(), report_dir=Path({str(tmp_path)!r}))\n"
        "print(dict.__getitem__(matplotlib.rcParams, 'backend') == before, 'matplotlib.pyplot' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.split() == ["True", "False"]
    assert (tmp_path / "static_final_sensor.png").stat().st_size > 10_000
