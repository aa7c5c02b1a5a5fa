"""Shared set-up for scripts run inside a bpy subprocess by tests/test_blender_*.py.

``python SCRIPT CONFIG.json RESULTS.json`` (bpy module) or
``blender -b --factory-startup --python-exit-code 1 --python SCRIPT -- CONFIG.json RESULTS.json``
(a Blender binary): CONFIG holds paths prepared by the test;
each check's outcome goes to RESULTS as ``{name: {"ok": bool, "error": str, ...}}``.
Imports of torch and promptgs_engine are blocked for the whole process, so any attempt
by the add-on fails loudly and is recorded.
"""

import json
import sys
import time
import traceback

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


def forbidden_modules() -> list[str]:
    return sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)


def finish() -> None:
    """Raise when a check failed, so ``blender --python-exit-code 1`` exits non-zero."""
    failed = [name for name, outcome in results.items() if not outcome["ok"]]
    if failed:
        raise RuntimeError("failed checks: " + ", ".join(failed))
