from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "tumbler").is_dir():
        pytest.skip(f"test scenes not found at {SHARED_DATA}")
    return SHARED_DATA
