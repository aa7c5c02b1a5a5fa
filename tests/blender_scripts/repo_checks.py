"""Installing the extension from the repository index tools/build_extension.py writes, as
a user does with *Get Extensions > Repositories > + > Add Remote Repository* (see
test_blender_addon.py): a fresh profile, the index by ``file://`` URL."""

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))
from harness import bpy, check, config, finish  # noqa: E402


@check
def installed_from_the_repository_index():
    bpy.context.preferences.system.use_online_access = True  # a remote repository asks for it
    url = config["index_url"]
    assert bpy.ops.preferences.extension_repo_add(name="PromptGS", remote_url=url, type="REMOTE",
                                                  use_sync_on_startup=False) == {"FINISHED"}
    repos = bpy.context.preferences.extensions.repos
    index = next(i for i, repo in enumerate(repos) if repo.remote_url == url)
    repo = repos[index]
    assert bpy.ops.extensions.repo_sync(repo_directory=repo.directory, repo_index=index) == {"FINISHED"}
    assert bpy.ops.extensions.package_install(repo_directory=repo.directory, repo_index=index, pkg_id="promptgs",
                                              enable_on_install=True) == {"FINISHED"}
    module = f"bl_ext.{repo.module}.promptgs"
    assert module in bpy.context.preferences.addons, [a.module for a in bpy.context.preferences.addons]
    assert hasattr(bpy.ops.promptgs, "train") and hasattr(bpy.types.Scene, "promptgs")
    manifest = open(os.path.join(repo.directory, "promptgs", "blender_manifest.toml")).read()
    assert f'version = "{config["version"]}"' in manifest
    return {"module": module, "repo_directory": repo.directory}


finish()
