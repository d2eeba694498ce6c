"""Mask test: the exporter's geometry and camera against Blender's own render.

Run:  blender --background --factory-startup --python-exit-code 1 \
          --python clients/blender/tests/mask_test.py [-- --keep DIR] [-- --case NAME]

Builds a scene by script (rotated, non-uniformly scaled and negatively scaled
objects, a linked duplicate, a sphere, a modifier), gives every object one flat
colour, and for each camera case renders it twice: with Tessera (ambient 1, no
lights, aa 1: every pixel is exactly its object's colour) and with Workbench (flat
object colours, AA off, Raw view transform, no dither). Each object's silhouette is
compared by IoU; an object must reach 0.99 wherever it covers at least 1% of the
image in either render. Exit status 1 if any case fails.
"""

import json
import math
import os
import shutil
import subprocess
import sys
import tempfile

import bpy
from mathutils import Euler, Matrix, Vector

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
from tessera_blender import evaluate, pngread  # noqa: E402

PALETTE = {
    "CubeRot": (230, 40, 40),
    "CubeNonUniform": (40, 200, 40),
    "MonkeyMirrored": (40, 60, 230),
    "MonkeyLinked": (220, 220, 40),
    "Sphere": (40, 210, 210),
    "CylinderBevel": (210, 40, 210),
    "Torus": (240, 140, 20),
    # Render settings, not the viewport's: a Subdivision of viewport level 0 and render
    # level 2 (a rounded cube in the render) with an Array shown only in renders, an
    # object hidden in the viewport but rendered, one shown but not rendered.
    "RenderOnlyModifiers": (150, 90, 255),
    "HiddenInViewport": (255, 170, 200),
    "NotRendered": (120, 255, 120),
}


def argv_after_dashes():
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []


def build_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene

    def add(op, name, loc, rot=(0, 0, 0), scale=(1, 1, 1), **kw):
        op(location=loc, **kw)
        ob = bpy.context.active_object
        ob.name = name
        ob.rotation_euler = Euler([math.radians(a) for a in rot])
        ob.scale = scale
        return ob

    add(bpy.ops.mesh.primitive_cube_add, "CubeRot", (-3, 0, 1.5), (30, 20, 45), (0.7, 0.7, 0.7))
    add(bpy.ops.mesh.primitive_cube_add, "CubeNonUniform", (0, 0.5, 1.6), (0, 10, 30), (1.3, 0.4, 0.6))
    mk = add(bpy.ops.mesh.primitive_monkey_add, "MonkeyMirrored", (3, 0, 1.5), (90, 0, 20), (-1, 1, 1))
    dup = mk.copy()                      # a linked duplicate: shares the mesh data
    dup.name = "MonkeyLinked"
    sc.collection.objects.link(dup)
    dup.location = (-3, 1, -1.4)
    dup.rotation_euler = Euler([math.radians(a) for a in (70, 0, -30)])
    dup.scale = (0.9, 0.9, 0.9)
    add(bpy.ops.mesh.primitive_uv_sphere_add, "Sphere", (0, 0, -1.5), segments=48, ring_count=24)
    cyl = add(bpy.ops.mesh.primitive_cylinder_add, "CylinderBevel", (3, -0.5, -1.6), (60, 0, 0), (0.8, 0.8, -0.7))
    bev = cyl.modifiers.new("bevel", "BEVEL")
    bev.width = 0.25
    bev.segments = 3
    add(bpy.ops.mesh.primitive_torus_add, "Torus", (0, -2, 0.1), (70, 30, 0), (0.6, 0.6, 0.6))
    ro = add(bpy.ops.mesh.primitive_cube_add, "RenderOnlyModifiers", (-6.0, 1, -2.8), (0, 0, 15), (0.9, 0.9, 0.9))
    sub = ro.modifiers.new("subdivision", "SUBSURF")
    sub.levels, sub.render_levels = 0, 2
    arr = ro.modifiers.new("array", "ARRAY")
    arr.show_viewport = False
    arr.relative_offset_displace = (1.3, 0, 0)
    hv = add(bpy.ops.mesh.primitive_ico_sphere_add, "HiddenInViewport", (5.2, 2, 2.8), subdivisions=3)
    hv.hide_viewport = True
    nr = add(bpy.ops.mesh.primitive_cube_add, "NotRendered", (5.5, 1, -3.2), (10, 20, 30), (1.3, 1.3, 1.3))
    nr.hide_render = True

    for ob in sc.objects:
        ob.color = tuple(c / 255 for c in PALETTE[ob.name]) + (1.0,)

    cam_data = bpy.data.cameras.new("Camera")
    cam = bpy.data.objects.new("Camera", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam

    sc.render.engine = "BLENDER_WORKBENCH"
    sh = sc.display.shading
    sh.light = "FLAT"
    sh.color_type = "OBJECT"
    sh.show_object_outline = False
    sh.show_cavity = False
    sh.show_shadows = False
    sc.display.render_aa = "OFF"
    sc.view_settings.view_transform = "Raw"      # object colour * 255, no curve
    sc.view_settings.look = "None"
    sc.display_settings.display_device = "sRGB"
    sc.render.dither_intensity = 0.0             # default 1 adds +-1 noise
    sc.render.film_transparent = False
    world = bpy.data.worlds.new("World")
    world.color = (0, 0, 0)
    sc.world = world
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGB"
    sc.render.image_settings.color_depth = "8"
    return sc


def place_camera(cam, position, target, roll_deg):
    direction = Vector(target) - Vector(position)
    quat = direction.to_track_quat("-Z", "Y")
    rot = quat.to_matrix().to_4x4() @ Matrix.Rotation(math.radians(roll_deg), 4, "Z")
    cam.matrix_world = Matrix.Translation(position) @ rot


CASES = [
    # name, lens mm, sensor fit, width, height, camera position, roll, sensor w, sensor h
    ("50mm-landscape-auto", 50, "AUTO", 320, 240, (0.5, -19, 1.0), 0, 36, 24),
    ("50mm-portrait-auto", 50, "AUTO", 240, 320, (0.5, -19, 1.0), 0, 36, 24),
    ("50mm-landscape-vertical", 50, "VERTICAL", 320, 240, (0.5, -14, 1.0), 0, 36, 24),
    ("50mm-portrait-horizontal", 50, "HORIZONTAL", 240, 320, (0.5, -19, 1.0), 0, 36, 24),
    ("50mm-portrait-vertical", 50, "VERTICAL", 240, 320, (0.5, -25, 1.0), 0, 36, 24),
    ("18mm-landscape-auto", 18, "AUTO", 320, 240, (1.0, -7.5, 2.0), 0, 36, 24),
    ("35mm-rolled-high", 35, "AUTO", 320, 240, (-6, -10, 7), 25, 36, 24),
    ("28mm-close-up", 28, "AUTO", 320, 240, (0.3, -9.5, 0.8), 5, 36, 24),
    ("85mm-square-below", 85, "AUTO", 240, 240, (4, -26, -5), -10, 36, 24),
]


def iou_report(tess_png, blend_png):
    w1, h1, a = pngread.read_png(tess_png)
    w2, h2, b = pngread.read_png(blend_png)
    assert (w1, h1) == (w2, h2), ((w1, h1), (w2, h2))
    names = list(PALETTE)
    cols = [PALETTE[n] for n in names]

    def classify(rows):
        out = []
        unknown = 0
        for row in rows:
            for p in row:
                k = -1
                for i, c in enumerate(cols):
                    if max(abs(p[0] - c[0]), abs(p[1] - c[1]), abs(p[2] - c[2])) <= 8:
                        k = i
                        break
                if k < 0 and max(p) > 8:
                    unknown += 1
                out.append(k)
        return out, unknown

    ca, ua = classify(a)
    cb, ub = classify(b)
    n = w1 * h1
    res = {}
    for i, name in enumerate(names):
        inter = sum(1 for x, y in zip(ca, cb) if x == i and y == i)
        union = sum(1 for x, y in zip(ca, cb) if x == i or y == i)
        ta = sum(1 for x in ca if x == i)
        tb = sum(1 for y in cb if y == i)
        res[name] = {"iou": inter / union if union else 1.0, "tessera_px": ta, "blender_px": tb,
                     "coverage": max(ta, tb) / n}
    return res, {"unclassified_tessera": ua, "unclassified_blender": ub}


def animation_case(sc, tessera, work, failures):
    """Frames 1..4 of an animation (a moving, turning cube, a growing linked duplicate,
    a camera moving and zooming, interpolated by Blender's Bezier curves) exported as
    one animated scene and rendered with tessera render --frames."""
    cam = sc.camera
    cam.data.sensor_fit = "AUTO"
    sc.render.resolution_x, sc.render.resolution_y = 320, 240
    place_camera(cam, (0.5, -19, 1.0), (0, 0, 0), 0)
    cube = sc.objects["CubeRot"]
    monkey = sc.objects["MonkeyLinked"]
    sc.frame_start, sc.frame_end = 1, 4
    for f, (x, rz, s, cx, lens) in enumerate([(-3, 45, 0.9, 0.5, 50), (-2, 80, 1.0, 1.5, 45),
                                               (-1.5, 120, 1.1, 2.0, 40), (-1, 170, 1.2, 2.5, 38)], 1):
        cube.location.x = x
        cube.rotation_euler.z = math.radians(rz)
        monkey.scale = (s, s, s)
        cam.location.x = cx
        cam.data.lens = lens
        cube.keyframe_insert("location", frame=f)
        cube.keyframe_insert("rotation_euler", frame=f)
        monkey.keyframe_insert("scale", frame=f)
        cam.keyframe_insert("location", frame=f)
        cam.data.keyframe_insert("lens", frame=f)
    d = os.path.join(work, "animation")
    os.makedirs(d, exist_ok=True)
    colors = {k: tuple(c / 255 for c in v) for k, v in PALETTE.items()}
    scene, warnings, _ = evaluate.export_animation(sc, d, object_colors=colors, flat=True)
    subprocess.run([tessera, "render", os.path.join(d, "scene.json"), "--frames", "all",
                    "-o", os.path.join(d, "tessera")], check=True, stdout=subprocess.DEVNULL)
    tracks = [t["target"] for t in scene["animation"]["tracks"]]
    result = {"case": "animation", "tracks": tracks, "frames": [], "warnings": warnings}
    for f in range(1, 5):
        sc.frame_set(f)
        bpng = os.path.join(d, "blender_%04d.png" % f)
        sc.render.filepath = bpng
        bpy.ops.render.render(write_still=True)
        res, extra = iou_report(os.path.join(d, "tessera", "frame_%04d.png" % f), bpng)
        worst = min([r["iou"] for r in res.values() if r["coverage"] >= 0.01] or [1.0])
        for obj, r in res.items():
            if r["coverage"] >= 0.01 and r["iou"] < 0.99:
                failures.append(("animation frame %d" % f, obj, r))
        print("animation frame %d       min IoU %.4f  " % (f, worst) + " ".join(
            "%s=%.4f" % (o, r["iou"]) for o, r in res.items() if r["coverage"] >= 0.01), extra if any(extra.values()) else "")
        result["frames"].append(res)
    print("animation tracks:", tracks, warnings if warnings else "")
    sc.frame_set(1)
    return result


def main():
    args = argv_after_dashes()
    keep = args[args.index("--keep") + 1] if "--keep" in args else None
    only = args[args.index("--case") + 1] if "--case" in args else None
    tessera = os.environ.get("TESSERA") or shutil.which("tessera")
    if not tessera:
        print("mask_test: no tessera on PATH (or $TESSERA)")
        sys.exit(2)
    sc = build_scene()
    cam = sc.camera
    work = keep or tempfile.mkdtemp(prefix="tessera-mask-")
    os.makedirs(work, exist_ok=True)
    failures = []
    summary = []
    for (name, lens, fit, w, h, pos, roll, sw, shh) in CASES:
        if only and name != only:
            continue
        cam.data.lens = lens
        cam.data.sensor_fit = fit
        cam.data.sensor_width = sw
        cam.data.sensor_height = shh
        sc.render.resolution_x, sc.render.resolution_y = w, h
        sc.render.resolution_percentage = 100
        place_camera(cam, pos, (0, 0, 0), roll)
        bpy.context.view_layer.update()
        d = os.path.join(work, name)
        os.makedirs(d, exist_ok=True)
        colors = {k: tuple(c / 255 for c in v) for k, v in PALETTE.items()}
        scene, warnings, _ = evaluate.export_still(sc, d, object_colors=colors, flat=True)
        tpng = os.path.join(d, "tessera.png")
        bpng = os.path.join(d, "blender.png")
        subprocess.run([tessera, "render", os.path.join(d, "scene.json"), "-o", tpng],
                       check=True, stdout=subprocess.DEVNULL)
        sc.render.filepath = bpng
        bpy.ops.render.render(write_still=True)
        res, extra = iou_report(tpng, bpng)
        files = sorted({o["file"] for o in scene["objects"]})
        line = "%-26s fov %.3f  meshes %d/%d  " % (name, scene["camera"]["fov"], len(files), len(scene["objects"]))
        worst = 1.0
        for obj, r in res.items():
            if r["coverage"] >= 0.01:
                worst = min(worst, r["iou"])
                if r["iou"] < 0.99:
                    failures.append((name, obj, r))
        line += "min IoU %.4f  " % worst + " ".join(
            "%s=%.4f" % (o, r["iou"]) if r["coverage"] >= 0.01 else "%s=(%.2f%%)" % (o, 100 * r["coverage"])
            for o, r in res.items())
        print(line, extra if any(extra.values()) else "", warnings if warnings else "")
        summary.append({"case": name, "fov": scene["camera"]["fov"], "objects": res, "extra": extra,
                        "warnings": warnings})
    if not only or only == "animation":
        summary.append(animation_case(sc, tessera, work, failures))
    with open(os.path.join(work, "results.json"), "w") as f:
        json.dump(summary, f, indent=1)
    if not keep:
        shutil.rmtree(work)
    if failures:
        for f in failures:
            print("FAIL", f)
        sys.exit(1)
    print("mask test: all %d cases pass (IoU >= 0.99 for every object covering >= 1%%)" % len(summary))


main()
