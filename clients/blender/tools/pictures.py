"""The README's Blender-vs-Tessera picture: one demo scene rendered by Cycles and by
Tessera (through the add-on's exporter), side by side.

Run:  blender --background --factory-startup --python clients/blender/tools/pictures.py -- OUTDIR

tessera is taken from $TESSERA, else PATH, else this checkout's target/release/tessera.

Builds the scene by script: a checker floor (Principled BSDF, Checker Texture into Base
Color, 1-unit squares in object coordinates, so they match Tessera's checkerboard of
unit squares square for square), a mirror sphere (Metallic 1), Suzanne (smooth,
Subdivision modifier, red non-metal), a blue cube, a 1000 W point light and a camera.

Writes to OUTDIR:
  blender-cycles.png       Cycles, CPU, 64 samples, no denoising, 640x400
  scene/scene.json         the add-on's export (File > Export > Tessera scene), with meshes/
  tessera.png              tessera render scene/scene.json -o tessera.png --aa 3
  blender-vs-tessera.png   the two side by side (Blender left, Tessera right)
and prints the timings and the exported files' sizes.

The lighting differs on purpose and cannot match: Tessera's point lights have no
distance fall-off (the exporter maps a light's power as colour x W / 1000), it adds an
ambient term of 0.2 and shades with its own model (Whitted-style). The geometry, the
camera and the checker squares match.
"""

import array
import math
import os
import shutil
import subprocess
import sys
import time

import bpy
from mathutils import Vector

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
import tessera_blender  # noqa: E402

W, H = 640, 400
GAP = 8                     # white pixels between the two pictures


def die(msg):
    print("pictures: %s" % msg, file=sys.stderr, flush=True)
    sys.exit(1)


def tessera_exe():
    cand = os.environ.get("TESSERA") or shutil.which("tessera")
    if not cand:
        repo = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
        cand = os.path.join(repo, "target", "release", "tessera")
    if not os.access(cand, os.X_OK):
        die("no tessera executable (set $TESSERA or put tessera on PATH): %s" % cand)
    return os.path.abspath(cand)


def principled(name, base, metallic=0.0, roughness=0.5):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = tuple(base) + (1.0,)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    mat.diffuse_color = tuple(base) + (1.0,)
    return mat, bsdf


def look_at(ob, target):
    d = Vector(target) - ob.location
    ob.rotation_euler = d.to_track_quat("-Z", "Y").to_euler()


def build_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene

    # Floor: a 24 x 24 plane at z = 0. Object coordinates and checker scale 1 give unit
    # squares in world x, y; Blender's Color1 falls where floor(x) + floor(y) is odd,
    # which is where Tessera's checkerboard is white.
    bpy.ops.mesh.primitive_plane_add(size=24, location=(0, 0, 0))
    floor = bpy.context.active_object
    floor.name = "Floor"
    mat, bsdf = principled("Checker", (0.8, 0.8, 0.8), roughness=0.6)
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    coords = nodes.new("ShaderNodeTexCoord")
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = 1.0
    checker.inputs["Color1"].default_value = (0.8, 0.8, 0.8, 1.0)
    checker.inputs["Color2"].default_value = (0.02, 0.02, 0.02, 1.0)
    links.new(coords.outputs["Object"], checker.inputs["Vector"])
    links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    floor.data.materials.append(mat)

    # Mirror sphere.
    bpy.ops.mesh.primitive_uv_sphere_add(segments=96, ring_count=48, radius=1.0,
                                         location=(-2.4, 0.6, 1.0))
    sphere = bpy.context.active_object
    sphere.name = "MirrorSphere"
    bpy.ops.object.shade_smooth()
    sphere.data.materials.append(principled("Mirror", (0.9, 0.9, 0.9), 1.0, 0.05)[0])

    # Suzanne: smooth, subdivided, red plastic, looking at the camera.
    bpy.ops.mesh.primitive_monkey_add(size=1.6, location=(0.1, -0.2, 1.05))
    monkey = bpy.context.active_object
    monkey.name = "Suzanne"
    monkey.rotation_euler = (math.radians(-10), 0, math.radians(-15))
    bpy.ops.object.shade_smooth()
    sub = monkey.modifiers.new("Subdivision", "SUBSURF")
    sub.levels, sub.render_levels = 2, 2
    monkey.data.materials.append(principled("Red", (0.8, 0.04, 0.03), 0.0, 0.35)[0])

    # Cube.
    bpy.ops.mesh.primitive_cube_add(size=1.4, location=(2.5, 0.7, 0.7),
                                    rotation=(0, 0, math.radians(30)))
    cube = bpy.context.active_object
    cube.name = "Cube"
    cube.data.materials.append(principled("Blue", (0.05, 0.2, 0.7), 0.0, 0.5)[0])

    # Light: a 1000 W point light up and to the left of the camera.
    bpy.ops.object.light_add(type="POINT", location=(-3.0, -4.0, 6.0))
    light = bpy.context.active_object
    light.name = "Light"
    light.data.energy = 1000.0
    light.data.shadow_soft_size = 0.1

    # Camera.
    bpy.ops.object.camera_add(location=(1.2, -9.5, 3.6))
    cam = bpy.context.active_object
    cam.name = "Camera"
    cam.data.lens = 35
    look_at(cam, (0.0, 0.3, 0.85))
    sc.camera = cam

    world = bpy.data.worlds.new("World")
    world.color = (0.01, 0.01, 0.01)      # nearly black, as Tessera's background
    sc.world = world
    # 'Standard' (not Filmic): colours as the exporter reads them (it sRGB-encodes the
    # base colours, Tessera writes its values with no curve).
    sc.view_settings.view_transform = "Standard"

    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.image_settings.color_depth = "8"
    r.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = 64
    sc.cycles.use_denoising = False
    return sc


def size_of(path):
    if os.path.isdir(path):
        return sum(os.path.getsize(os.path.join(d, f))
                   for d, _, fs in os.walk(path) for f in fs)
    return os.path.getsize(path)


def side_by_side(left, right, out):
    """Blender's image API: both loaded (bottom row first, RGBA floats of the 8-bit
    values), copied into one new 8-bit image, saved as PNG."""
    a = bpy.data.images.load(left, check_existing=False)
    b = bpy.data.images.load(right, check_existing=False)
    (wa, ha), (wb, hb) = tuple(a.size), tuple(b.size)
    if ha != hb:
        die("the two pictures differ in height: %d and %d" % (ha, hb))
    pa = array.array("f", bytes(4 * wa * ha * 4))
    pb = array.array("f", bytes(4 * wb * hb * 4))
    a.pixels.foreach_get(pa)
    b.pixels.foreach_get(pb)
    w = wa + GAP + wb
    canvas = array.array("f", [1.0]) * (w * ha * 4)
    for y in range(ha):
        canvas[y * w * 4:(y * w + wa) * 4] = pa[y * wa * 4:(y + 1) * wa * 4]
        canvas[(y * w + wa + GAP) * 4:(y + 1) * w * 4] = pb[y * wb * 4:(y + 1) * wb * 4]
    canvas[3::4] = array.array("f", [1.0]) * (w * ha)
    img = bpy.data.images.new("side-by-side", w, ha, alpha=False, float_buffer=False)
    img.pixels.foreach_set(canvas)
    img.filepath_raw = out
    img.file_format = "PNG"
    img.save()
    return w, ha


def main():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) != 1:
        die("usage: blender --background --factory-startup --python pictures.py -- OUTDIR")
    out = os.path.abspath(argv[0])
    os.makedirs(out, exist_ok=True)
    exe = tessera_exe()
    tessera_blender.register()
    sc = build_scene()

    cycles_png = os.path.join(out, "blender-cycles.png")
    sc.render.filepath = cycles_png
    t = time.monotonic()
    bpy.ops.render.render(write_still=True)
    t_cycles = time.monotonic() - t
    if not os.path.exists(cycles_png):
        die("Cycles wrote no %s" % cycles_png)

    scene_dir = os.path.join(out, "scene")
    shutil.rmtree(scene_dir, ignore_errors=True)
    scene_json = os.path.join(scene_dir, "scene.json")
    t = time.monotonic()
    res = bpy.ops.export_scene.tessera(filepath=scene_json)
    t_export = time.monotonic() - t
    if res != {"FINISHED"} or not os.path.exists(scene_json):
        die("export returned %s" % sorted(res))

    tessera_png = os.path.join(out, "tessera.png")
    t = time.monotonic()
    r = subprocess.run([exe, "render", scene_json, "-o", tessera_png, "--aa", "3"],
                       capture_output=True, text=True)
    t_tessera = time.monotonic() - t
    if r.returncode != 0:
        die("tessera render failed (%d): %s" % (r.returncode, r.stderr.strip()))

    both = os.path.join(out, "blender-vs-tessera.png")
    w, h = side_by_side(cycles_png, tessera_png, both)

    meshes = os.path.join(scene_dir, "meshes")
    print("pictures: Cycles render (CPU, %d samples, %dx%d): %.2f s"
          % (sc.cycles.samples, W, H, t_cycles))
    print("pictures: export (export_scene.tessera): %.2f s; scene.json %d bytes, "
          "%d mesh files %d bytes"
          % (t_export, size_of(scene_json),
             len(os.listdir(meshes)) if os.path.isdir(meshes) else 0,
             size_of(meshes) if os.path.isdir(meshes) else 0))
    print("pictures: tessera render --aa 3: %.2f s" % t_tessera)
    print("pictures: wrote %s (%dx%d), %s, %s" % (both, w, h, cycles_png, tessera_png))


main()
