"""The installable zip, as a user installs it: `build-zip`'s archive installed with
Blender's add-on installer into a scripts directory of its own ($BLENDER_USER_SCRIPTS,
set by run-tests), enabled, and used for a farm render with the Python client it
vendors (nothing from this checkout on sys.path).

  BLENDER_USER_SCRIPTS=DIR blender --background --factory-startup --python-exit-code 1 \
      --python zip_test.py -- ZIP
"""

import os
import shutil
import sys
import tempfile

import addon_utils
import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
zip_path = sys.argv[sys.argv.index("--") + 1]
scripts = os.environ.get("BLENDER_USER_SCRIPTS")
assert scripts, "set BLENDER_USER_SCRIPTS to an empty directory"

assert bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True) == {"FINISHED"}
addon_utils.enable("tessera_blender", default_set=True)
import tessera_blender  # noqa: E402

where = os.path.dirname(os.path.realpath(tessera_blender.__file__))
assert where.startswith(os.path.realpath(scripts)), where
assert hasattr(bpy.types.Scene, "tessera"), "the add-on did not register"

sys.path.insert(0, HERE)                 # the test's farm helper only
from farm import Farm, tessera_bin  # noqa: E402

work = tempfile.mkdtemp(prefix="tessera-zip-")
farm = Farm(tessera_bin(), work)
try:
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = 64, 48
    sc.tessera.address, sc.tessera.token_file = farm.url, farm.token_file
    assert bpy.ops.render.tessera_render() == {"FINISHED"}
    assert tuple(bpy.data.images["Tessera Render"].size) == (64, 48)
    client = sys.modules["tessera_client"].__file__
    assert os.path.realpath(client).startswith(os.path.join(where, "vendor")), client
finally:
    farm.stop()
    shutil.rmtree(work, ignore_errors=True)
print("zip test: installed from %s, rendered on a farm with the vendored client" % os.path.basename(zip_path))
