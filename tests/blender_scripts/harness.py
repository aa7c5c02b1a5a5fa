"""Shared set-up for scripts run inside a bpy subprocess by tests/test_blender_*.py.

``python SCRIPT CONFIG.json RESULTS.json`` (bpy module) or
``blender -b --factory-startup --python-exit-code 1 --python SCRIPT -- CONFIG.json RESULTS.json``
(a Blender binary): CONFIG holds paths prepared by the test;
each check's outcome goes to RESULTS as ``{name: {"ok": bool, "error": str, ...}}``.
Imports of torch and promptgs_engine are blocked for the whole process, so any attempt
by the add-on fails loudly and is recorded.
"""

import json
import os
import sys
import time
import traceback
from pathlib import Path

BLOCKED = ("torch", "promptgs_engine", "pycolmap", "plyfile")
blocked_attempts: list[str] = []


class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            blocked_attempts.append(name)
            raise ImportError(f"blocked in the Blender test process: {name}")
        return None


sys.meta_path.insert(0, _Block())

ARGS = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
config = json.loads(open(ARGS[0]).read())
results: dict = {}


def save():
    with open(ARGS[1], "w") as handle:
        json.dump(results, handle, indent=1)


def check(fn, *args, name: str = ""):
    """Run a check now (``fn(*args)``, recorded as ``name`` or the function's name); record
    ok / the error; details a check returns are kept. Used as a decorator without args."""
    name = name or fn.__name__
    start = time.time()
    try:
        info = fn(*args) or {}
        results[name] = {"ok": True, **info}
    except Exception as exc:  # recorded for the test to show
        results[name] = {"ok": False, "error": f"{type(exc).__name__}: {exc}",
                         "traceback": traceback.format_exc()[-3000:]}
    results[name]["seconds"] = round(time.time() - start, 2)
    save()
    return fn


import bpy  # noqa: E402  (after the import blocker)

ADDON = "bl_ext.user_default.promptgs"


def install():
    bpy.ops.extensions.package_install_files(filepath=config["zip"], repo="user_default",
                                             enable_on_install=True)
    assert ADDON in bpy.context.preferences.addons, "the extension is not enabled"
    return {"modules": sorted(m for m in sys.modules if m.startswith(ADDON))}


def addon(name: str):
    return sys.modules[f"{ADDON}.{name}"]


def run_until_idle(timeout: float = 300.0, on_events=None) -> None:
    """Drive the add-on's drain-and-apply step as its timer would (timers never fire here)."""
    training = addon("training")
    deadline = time.time() + timeout
    while time.time() < deadline:
        busy = training.drain_and_apply(bpy.context)
        if on_events is not None and on_events():
            return
        if not busy:
            return
        time.sleep(0.05)
    raise TimeoutError("the trainer run did not finish in time")


def drain_until(condition, timeout: float = 60.0, what: str = "the condition") -> None:
    """Drive the follower (as its timer would) until ``condition()``; a timeout names
    ``what`` and the shown run's state."""
    training = addon("training")
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            record = training.shown_record(bpy.context.scene)
            shown = f" ({record.status}: {record.message})" if record is not None else ""
            raise TimeoutError(f"timed out waiting for {what}{shown}")
        training.drain_and_apply(bpy.context)
        time.sleep(0.02)


def process_tree(pid: int) -> list[int]:
    """``pid`` and every process below it (read from /proc here, not with the add-on's code)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                text = (entry / "stat").read_text()
            except OSError:
                continue
            parents[int(entry.name)] = int(text[text.rindex(")") + 2:].split()[1])
    tree, todo = [], [pid]
    while todo:
        current = todo.pop()
        tree.append(current)
        todo += [child for child, parent in parents.items() if parent == current]
    return tree


def process_gone(pid: int) -> bool:
    """Whether the process has exited (a zombie waiting for its parent counts as gone)."""
    if not Path("/proc/self/stat").exists():  # no /proc (macOS): ask the kernel
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        except OSError:
            pass
        return False
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return text[text.rindex(")") + 2:].split()[0] == "Z"


def cancel_and_wait(pids: list[int], gone_within: float) -> tuple[float, list[int]]:
    """Press Cancel, follow the run to its end, wait up to ``gone_within`` s for every one
    of ``pids`` to exit: (seconds from the press, the pids still running)."""
    start = time.time()
    bpy.ops.promptgs.cancel()
    run_until_idle(60)
    deadline = time.time() + gone_within
    while not all(process_gone(pid) for pid in pids) and time.time() < deadline:
        time.sleep(0.05)
    return time.time() - start, [pid for pid in pids if not process_gone(pid)]


def delete_selected_points(obj, select) -> None:
    """Delete points as a user does: select them, Edit Mode, Delete (a points-only mesh on
    4.2–5.0, a point cloud from 5.1 on)."""
    for other in bpy.context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    if obj.type == "MESH":
        obj.data.vertices.foreach_set("select", select)
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.delete(type="VERT")
    else:
        attr = obj.data.attributes.get(".selection") or obj.data.attributes.new(".selection", "BOOLEAN", "POINT")
        attr.data.foreach_set("value", select)
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.pointcloud.delete()
    bpy.ops.object.mode_set(mode="OBJECT")


def forbidden_modules() -> list[str]:
    return sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)


def finish() -> None:
    """Raise when a check failed, so ``blender --python-exit-code 1`` exits non-zero."""
    failed = [name for name, outcome in results.items() if not outcome["ok"]]
    if failed:
        raise RuntimeError("failed checks: " + ", ".join(failed))
