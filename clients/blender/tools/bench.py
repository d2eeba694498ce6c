"""The add-on's figures (docs/blender.md, "Figures"): export time and file sizes of a
large scene, and the time from "Render on Tessera" to the image on a local farm
against `tessera render` of the same export.

  blender --background --factory-startup --python clients/blender/tools/bench.py -- \
      [--levels 4] [--copies 40] [--size 1280x720] [--aa 2] [--workers 2]

The scene: a subdivided monkey (Subdivision at render level LEVELS) and COPIES linked
duplicates of it (instances of one mesh file), a subdivided, displaced ground, a
mirror sphere and a point light. The farm is a coordinator and WORKERS workers of
one thread each on 127.0.0.1, started here (as `tessera up` does); `tessera render`
uses all cores."""

import math
import os
import shutil
import subprocess
import sys
import tempfile
import time

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tests"))
import tessera_blender  # noqa: E402
from farm import Farm, tessera_bin  # noqa: E402
from tessera_blender import evaluate, ui  # noqa: E402


def arg(name, default):
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    return argv[argv.index(name) + 1] if name in argv else default


def build(levels, copies, size):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = size
    sc.render.resolution_percentage = 100
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=200, y_subdivisions=200, size=40)
    ground = bpy.context.active_object
    tex = bpy.data.textures.new("waves", "CLOUDS")
    disp = ground.modifiers.new("displace", "DISPLACE")
    disp.texture, disp.strength = tex, 0.6
    bpy.ops.mesh.primitive_monkey_add(location=(0, 0, 1.5))
    monkey = bpy.context.active_object
    sub = monkey.modifiers.new("subdivision", "SUBSURF")
    sub.levels, sub.render_levels = 1, levels
    for k in range(copies):
        twin = monkey.copy()
        a = 2 * math.pi * k / max(1, copies)
        r = 5 + 2 * (k % 3)
        twin.location = (r * math.cos(a), r * math.sin(a), 1.2)
        twin.rotation_euler = (0, 0, a)
        sc.collection.objects.link(twin)
    bpy.ops.mesh.primitive_uv_sphere_add(location=(0, -3, 1), segments=64, ring_count=32)
    mat = bpy.data.materials.new("mirror")
    mat.use_nodes = True
    mat.node_tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0
    bpy.context.active_object.data.materials.append(mat)
    bpy.ops.object.light_add(type="POINT", location=(4, -6, 9))
    bpy.ops.object.camera_add(location=(0, -16, 7), rotation=(math.radians(68), 0, 0))
    sc.camera = bpy.context.active_object
    return sc


def main():
    tessera = tessera_bin()
    levels, copies = int(arg("--levels", "4")), int(arg("--copies", "40"))
    size = tuple(int(v) for v in arg("--size", "1280x720").split("x"))
    workers = int(arg("--workers", "2"))
    tessera_blender.register()
    sc = build(levels, copies, size)
    sc.tessera.aa = int(arg("--aa", "2"))
    work = tempfile.mkdtemp(prefix="tessera-bench-")
    farm = None
    try:
        d = os.path.join(work, "export")
        t = time.monotonic()
        ex = evaluate.export_still(sc, d, image=ui._image_settings(sc))
        export_s = time.monotonic() - t
        files = [os.path.join(d, o["file"]) for o in ex.scene["objects"]]
        distinct = sorted(set(files))
        triangles = 0
        for f in distinct:
            with open(f, "rb") as fh:
                head = fh.read(400).split(b"end_header")[0].decode()
            triangles += int(head.split("element face ")[1].split()[0])
        print("scene: %d objects, %d mesh files, %d distinct triangles, %.1f MB of PLY, "
              "scene.json %d bytes" % (len(files), len(distinct), triangles,
                                        sum(os.path.getsize(f) for f in distinct) / 1e6,
                                        os.path.getsize(os.path.join(d, "scene.json"))))
        t = time.monotonic()
        evaluate._render_depsgraph(sc, lambda engine, depsgraph: None)
        evaluation_s = time.monotonic() - t
        print("export: %.2f s, of which Blender's evaluation of the scene for a render "
              "(modifiers applied) %.2f s (measured alone)" % (export_s, evaluation_s))
        t = time.monotonic()
        subprocess.run([tessera, "render", os.path.join(d, "scene.json"), "-o",
                        os.path.join(work, "local.png")], check=True, stdout=subprocess.DEVNULL)
        local_s = time.monotonic() - t
        print("tessera render of the export: %.2f s" % local_s)
        farm = Farm(tessera, os.path.join(work, "farm"), workers=workers, threads=1)
        sc.tessera.address, sc.tessera.token_file = farm.url, farm.token_file
        for attempt in ("first (uploads the meshes)", "again (meshes already stored)"):
            t = time.monotonic()
            assert bpy.ops.render.tessera_render() == {"FINISHED"}
            button_s = time.monotonic() - t
            same = bytes(bpy.data.images[ui.STILL_IMAGE].packed_file.data) == \
                open(os.path.join(work, "local.png"), "rb").read()
            print("Render on Tessera, %s: %.2f s from the button to the image (%.2fx tessera "
                  "render), byte-identical: %s" % (attempt, button_s, button_s / local_s, same))
    finally:
        if farm is not None:
            farm.stop()
        tessera_blender.unregister()
        shutil.rmtree(work, ignore_errors=True)


main()
