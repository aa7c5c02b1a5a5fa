"""*Set Up Trainer* for real (see test_blender_train.py): the installed extension makes a
fresh Python environment with torch and the engine, built from a copy of this checkout,
and that environment trains the toy scene from the panel."""

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from harness import addon, bpy, check, config, finish, forbidden_modules, install, run_until_idle  # noqa: E402

TMP = Path(config["tmp"])
ADDON = "bl_ext.user_default.promptgs"


def prefs():
    return bpy.context.preferences.addons[ADDON].preferences


@check
def set_up_trainer_makes_the_environment():
    install()
    p = prefs()
    p.setup_folder, p.setup_base, p.setup_source = str(TMP / "trainer-env"), config["base_python"], config["source"]
    p.setup_torch = "CPU"
    p.torch_index = config["torch_index"]  # '' here: pip's own configuration has the CPU wheel
    p.output_dir = str(TMP / "runs")
    assert not p.python
    bpy.ops.promptgs.setup_trainer()
    jobs = bpy.context.window_manager.promptgs_run
    stages, lines = [], 0
    deadline = time.time() + config["timeout"]
    training = addon("training")
    while training.drain_and_apply(bpy.context):
        if not stages or stages[-1] != jobs.setup_stage:
            stages.append(jobs.setup_stage)
            print(f"{time.strftime('%H:%M:%S')} {jobs.setup_stage} {jobs.setup_progress:.2f}", flush=True)
        lines += 1
        assert time.time() < deadline, f"set-up still at {jobs.setup_stage}: {jobs.setup_message}"
        time.sleep(0.2)
    assert jobs.setup_status == "DONE", (jobs.setup_status, jobs.setup_message, jobs.setup_log)
    python = TMP / "trainer-env" / "bin" / "python"
    assert p.python == str(python) and python.is_file(), p.python
    assert "backends: cpu" in p.probe_result, p.probe_result
    assert training.notices[-1][0] == "INFO" and "Trainer Python set to" in training.notices[-1][1]
    return {"stages": stages, "probe": p.probe_result, "python": p.python, "log": jobs.setup_log}


@check
def the_environment_trains_the_toy_scene():
    bpy.ops.promptgs.import_colmap(directory=config["toy"])
    settings = bpy.context.scene.promptgs
    settings.preset, settings.iterations, settings.snapshot_every = "CUSTOM", 30, 10
    settings.strategy, settings.backend = "3dgs", "cpu"
    bpy.ops.promptgs.train()
    run_until_idle(config["timeout"])
    record = addon("training").shown_record(bpy.context.scene)
    assert record.status == "DONE", (record.status, record.message, record.error_lines)
    job = json.loads(Path(record.job_path).read_text())
    assert Path(record.result_ply).is_file() and job["dataset"] == config["toy"]
    obj = bpy.data.objects["PromptGS Gaussians"]
    n = addon("display").point_count(obj)
    header = Path(record.result_ply).read_bytes()[:400].decode("latin-1")
    assert f"element vertex {n}\n" in header, (n, header[:200])
    return {"message": record.message, "n_gaussians": n, "run": record.folder}


@check
def never_imports_torch_or_engine():
    assert not forbidden_modules(), forbidden_modules()


finish()
