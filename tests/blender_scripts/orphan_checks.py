"""A Blender that dies while it trains (see test_blender_train.py): the installed extension
starts a real training (CONFIG["nproc"] processes), writes the trainer's processes to
TMP/trainer_pids.json, and then only waits, for the test to kill this process."""

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from harness import addon, bpy, check, config, install, process_tree  # noqa: E402

TMP = Path(config["tmp"])


@check
def training_started():
    install()
    preferences = bpy.context.preferences.addons["bl_ext.user_default.promptgs"].preferences
    preferences.python, preferences.output_dir = config["python"], str(TMP / "runs")
    bpy.ops.promptgs.import_colmap(directory=config["dataset"], images=config["images"])
    settings = bpy.context.scene.promptgs
    settings.preset, settings.iterations, settings.snapshot_every = "CUSTOM", 100000, 50
    settings.strategy, settings.backend, settings.nproc = "3dgs", "cpu", config["nproc"]
    bpy.ops.promptgs.train()
    training = addon("training")
    record = training.shown_record(bpy.context.scene)
    deadline = time.time() + config["timeout"]
    while training.view(record).step == 0:
        assert time.time() < deadline, (record.status, record.message, record.error_lines)
        training.drain_and_apply(bpy.context)
        time.sleep(0.1)
    pids = process_tree(training.current_run().pid)
    (TMP / "trainer_pids.tmp").write_text(json.dumps(pids))
    (TMP / "trainer_pids.tmp").rename(TMP / "trainer_pids.json")  # whole when the test sees it
    return {"pids": pids}


if not (TMP / "trainer_pids.json").is_file():
    sys.exit(1)  # the check failed: its error is in the results
while True:  # the follower is not needed: the test kills this process
    time.sleep(1.0)
