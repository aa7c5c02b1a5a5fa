from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "tumbler").is_dir():
        pytest.skip(f"test scenes not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def toy(tmp_path_factory) -> Path:
    """A small toy scene with five tiny drones and no SfM points on them (128×96, 16 views)."""
    from promptgs_engine.bench.toy_scene import QUICK_TOY, make_toy_scene

    return make_toy_scene(tmp_path_factory.mktemp("toy") / "scene", QUICK_TOY)


@pytest.fixture(scope="session")
def blender_envs():
    """Every supported Blender line's Python, made in the background (tests/blender_lines.py)."""
    from blender_lines import LineEnvironments

    envs = LineEnvironments()
    yield envs
    envs.close()


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory) -> Path:
    """The extension zip built from this checkout, once: every line installs the same file."""
    import sys

    sys.path.insert(0, str(REPO / "tools"))
    import build_extension

    return build_extension.build(tmp_path_factory.mktemp("extension"))
