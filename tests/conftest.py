from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import Config, load_config

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"


@pytest.fixture(scope="session")
def paper_cfg() -> Config:
    return load_config()
