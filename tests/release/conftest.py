from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("google_crc32c", reason="the release extra (google-crc32c) is not installed")
pytest.importorskip("PIL", reason="the release extra (pillow) is not installed")

SHARED = Path(os.environ.get("RLU_SHARED", Path(__file__).resolve().parents[3] / "shared"))
FIXTURES = SHARED / "fixtures" / "rlu_release"


@pytest.fixture
def fixtures() -> Path:
    if not (FIXTURES / "data").is_dir():
        pytest.skip(f"release fixtures not found at {FIXTURES} (set RLU_SHARED)")
    return FIXTURES
