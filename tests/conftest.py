from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from companion.config import Config, load_config

REPO = Path(__file__).resolve().parent.parent
#: the recordings the tests and docs use, gzip-compressed, in the repository (data/*/README.md)
DATA = REPO / "data"
STAMPFLY_DIR = DATA / "real" / "stampfly"
ARDUPILOT_DIR = DATA / "sitl" / "ardupilot"
FLIGHT_A_GZ = ARDUPILOT_DIR / "flight_a.tlog.gz"


@pytest.fixture(scope="session")
def paper_cfg() -> Config:
    return load_config()


@pytest.fixture(scope="session")
def flight_a_plain(tmp_path_factory) -> Path:
    """``data/sitl/ardupilot/flight_a.tlog.gz`` decompressed once into a temporary
    ``flight_a.tlog``, for pymavlink (which reads only plain files) and the plain-vs-gzip tests."""
    out = tmp_path_factory.mktemp("flight_a") / "flight_a.tlog"
    out.write_bytes(gzip.decompress(FLIGHT_A_GZ.read_bytes()))
    return out
