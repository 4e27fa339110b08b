"""``make demo`` (scripts/demo.py) tells the truth about where to watch it (issue 14)."""

from __future__ import annotations

import re
import subprocess
import time

from loop_helpers import PY, REPO, Gcs, free_udp_port


def test_demo_prints_the_address_a_ground_station_can_watch_it_on(tmp_path):
    """The demo said "watch it live ... UDP 14550" while its lockstep vehicle was on another port. It
    now prints the vehicle's true address while it runs, and a ground station sent there is served
    (the vehicle's HEARTBEAT, then the companion's)."""
    port = free_udp_port()
    log = tmp_path / "demo.log"
    with open(log, "w") as fh:
        p = subprocess.Popen([PY, "scripts/demo.py", "--out", str(tmp_path / "demo"), "--port", str(port)], cwd=REPO,
                             stdout=fh, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not re.search(r"watch it live while it flies: mavproxy\.py --master=udpout:127\.0\.0\.1:(\d+)",
                            log.read_text()):
            assert p.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        m = re.search(r"--master=udpout:127\.0\.0\.1:(\d+)", log.read_text())
        assert int(m.group(1)) == port
        gcs = Gcs(int(m.group(1)))
        try:
            gcs.wait_vehicle(timeout_s=20)
            gcs.recv("HEARTBEAT", timeout_s=20, cond=lambda msg: msg.get_srcComponent() == 191)
        finally:
            gcs.close()
        assert p.wait(timeout=240) == 0, log.read_text()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    text = log.read_text()
    assert "UDP 14550" not in text.split("to watch a flight in real time")[0]
    assert re.search(r"vehicle: python -m simvehicle serve --lockstep on udp 127\.0\.0\.1:(\d+)", text).group(1) \
        == str(port)


def _demo_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("demo", REPO / "scripts" / "demo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_loop_png_draws_both_setpoints_and_marks_the_gust_from_the_demos_own_profile():
    """Issue 14: loop.png drew the x setpoint only and nothing showed the gust. The figure now draws
    both setpoints and a line at the gust on every panel, labelled with its size; time and size come
    from the demo's GUST_AT_S and GUST_N (what the ground station's PARAM_SET sends), not typed."""
    import matplotlib.pyplot as plt
    import numpy as np

    from simvehicle.engines.scenarios import _COLUMNS, Run
    from simvehicle.tools.plots import force_steps, run_figure

    demo = _demo_module()
    t = np.arange(0.0, demo.DURATION_S, 0.02)
    cols = {k: np.zeros_like(t) for k in _COLUMNS}
    cols["t_s"] = t
    sp = np.array([demo._setpoint_at(x) for x in t])
    cols["vx_set_m_s"], cols["vy_set_m_s"] = sp[:, 0], sp[:, 1]
    assert np.any(cols["vy_set_m_s"] != 0) and np.any(cols["vx_set_m_s"] != cols["vy_set_m_s"])
    fig = run_figure(Run("loop", cols), force=demo.gust_force)
    try:
        ax0 = fig.axes[0]
        lines = {ln.get_label(): ln for ln in ax0.get_lines()}
        np.testing.assert_array_equal(lines["setpoint vx"].get_ydata(), cols["vx_set_m_s"])
        np.testing.assert_array_equal(lines["setpoint vy"].get_ydata(), cols["vy_set_m_s"])
        t_gust = float(t[np.searchsorted(t, demo.GUST_AT_S - 1e-9)])
        assert force_steps(demo.gust_force, t) == [(t_gust, demo.GUST_N, 0.0)]
        for ax in fig.axes:  # the gust on every panel, and every panel's y axis has a unit
            assert any(np.allclose(ln.get_xdata(), t_gust) for ln in ax.get_lines()), ax.get_ylabel()
            assert re.search(r"\((m/s|deg|counts/frame|rad/s)\)$", ax.get_ylabel())
        texts = [a.get_text() for a in ax0.texts]
        assert texts == [f"gust: external force Fx {demo.GUST_N:+g} N from {t_gust:g} s"]
        assert fig.axes[-1].get_xlabel() == "time (s)"
    finally:
        plt.close(fig)
    assert demo.gust_force(demo.GUST_AT_S) == (demo.GUST_N, 0.0)
    assert demo.gust_force(demo.GUST_AT_S - 0.02) == (0.0, 0.0)
