from pathlib import Path

import pytest
import scenes
from scenes import SceneFacts

REPO = Path(__file__).resolve().parents[1]

# Tests that only a real scene can answer are collected where it is (../shared/data), not
# skipped where it is not; every other scene test runs on the made scenes too.
collect_ignore = [] if scenes.real_scene(scenes.TUMBLER) else ["test_sfm_tumbler.py"]


@pytest.fixture(scope="session")
def made_scenes(tmp_path_factory) -> dict[str, SceneFacts]:
    """The two scenes of tests/scenes.py, made once per test run (a few seconds)."""
    root = tmp_path_factory.mktemp("scenes")
    return {"pinhole": scenes.make_pinhole_scene(root / "pinhole"),
            "distorted": scenes.make_distorted_scene(root / "distorted")}


def scene_by_name(name: str, made: dict[str, SceneFacts]) -> SceneFacts:
    return made[name] if name in made else {"tumbler": scenes.TUMBLER, "fern": scenes.FERN}[name]


@pytest.fixture(scope="session", params=scenes.pinhole_scene_names())
def pinhole_scene(request, made_scenes) -> SceneFacts:
    """A scene with pinhole cameras, a binary model and ``images_4``: the made one, and
    tumbler when ../shared/data holds it."""
    return scene_by_name(request.param, made_scenes)


@pytest.fixture(scope="session", params=scenes.distorted_scene_names())
def distorted_scene(request, made_scenes) -> SceneFacts:
    """A scene with distorted cameras and a text model: the made one, and fern when
    ../shared/data holds it."""
    return scene_by_name(request.param, made_scenes)


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
