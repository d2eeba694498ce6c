"""Registers the add-on, exports the factory scene through File > Export's operator and
renders it with Render on Tessera (local tessera), headless."""
import os, sys, tempfile
import bpy
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
import tessera_blender
tessera_blender.register()
d = tempfile.mkdtemp(prefix="tessera-addon-")
sc = bpy.context.scene
sc.render.resolution_x, sc.render.resolution_y = 160, 120
assert bpy.ops.export_scene.tessera(filepath=os.path.join(d, "s.json")) == {"FINISHED"}
assert os.path.exists(os.path.join(d, "s.json")) and os.listdir(os.path.join(d, "meshes"))
assert bpy.ops.render.tessera_render() == {"FINISHED"}
img = bpy.data.images["Tessera Render"]
assert tuple(img.size) == (160, 120), tuple(img.size)
tessera_blender.unregister()
print("addon smoke test: ok")
