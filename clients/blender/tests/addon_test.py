"""The add-on end to end, headless, against the real `tessera` (PATH or $TESSERA):

  blender --background --factory-startup --python-exit-code 1 --python addon_test.py

- a scene built by script (checker floor, metallic sphere, a subdivided monkey and
  its linked duplicate, a glass cube, a point and a sun light, a camera) exported
  through File > Export; meshes deduplicated;
- "Render on Tessera" on this machine and on a local farm (a coordinator and a worker
  started here on 127.0.0.1): the image loaded into Blender is byte for byte the PNG
  `tessera render` makes of the exported scene;
- "Render animation" on the farm: one sequence job, its frames byte for byte
  `tessera render --frames`, loaded as an image sequence;
- each error path ends in exactly one report of one line: coordinator down, wrong
  token, missing token file, a mesh over the coordinator's file limit, a tessera
  command that does not exist; an unsupported material and light give one warning
  naming the objects and what was used instead;
- Esc (the job's cancel) cancels the job on the farm.
Exit status 1 on the first failure."""

import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import traceback

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)
import tessera_blender  # noqa: E402
from farm import TOKEN, Farm, tessera_bin  # noqa: E402
from tessera_blender import job as tjob, ui  # noqa: E402

def build_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 160, 120, 100

    def material(name, colour=(0.8, 0.8, 0.8), metallic=0.0, roughness=0.5):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        bsdf = m.node_tree.nodes["Principled BSDF"]
        bsdf.inputs["Base Color"].default_value = colour + (1.0,)
        bsdf.inputs["Metallic"].default_value = metallic
        bsdf.inputs["Roughness"].default_value = roughness
        return m, bsdf

    bpy.ops.mesh.primitive_plane_add(size=12, location=(0, 0, 0))
    floor = bpy.context.active_object
    floor.name = "Floor"
    m, bsdf = material("Checker")
    checker = m.node_tree.nodes.new("ShaderNodeTexChecker")
    m.node_tree.links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    floor.data.materials.append(m)

    bpy.ops.mesh.primitive_uv_sphere_add(location=(-1.6, 0.5, 1), segments=32, ring_count=16)
    sphere = bpy.context.active_object
    sphere.name = "Chrome"
    sphere.data.materials.append(material("Chrome", metallic=1.0, roughness=0.1)[0])
    for poly in sphere.data.polygons:        # smooth but for a flat cap: corner normals
        poly.use_smooth = poly.center.z < 0.9

    bpy.ops.mesh.primitive_monkey_add(location=(1.2, 0, 1))
    monkey = bpy.context.active_object
    monkey.name = "Monkey"
    monkey.modifiers.new("subdivision", "SUBSURF").render_levels = 1
    for poly in monkey.data.polygons:        # smooth: vertex normals
        poly.use_smooth = True
    monkey.data.materials.append(material("Red", colour=(0.8, 0.05, 0.05))[0])
    twin = monkey.copy()                 # a linked duplicate with the same modifier
    twin.name = "MonkeyTwin"
    twin.location = (3.2, 1.5, 1)
    sc.collection.objects.link(twin)

    bpy.ops.mesh.primitive_cube_add(location=(0, 2.5, 0.5), size=1)
    glass = bpy.context.active_object
    glass.name = "GlassCube"
    gm = bpy.data.materials.new("Glass")
    gm.use_nodes = True
    nodes = gm.node_tree.nodes
    nodes.remove(nodes["Principled BSDF"])
    g = nodes.new("ShaderNodeBsdfGlass")
    g.inputs["Color"].default_value = (0.2, 0.6, 0.9, 1.0)
    gm.node_tree.links.new(g.outputs["BSDF"], nodes["Material Output"].inputs["Surface"])
    glass.data.materials.append(gm)
    # A collection instance of the glass cube's mesh: an instance, sharing its file.
    props = bpy.data.collections.new("Props")
    props.objects.link(bpy.data.objects.new("PropCube", glass.data))
    holder = bpy.data.objects.new("PropInstance", None)
    holder.instance_type, holder.instance_collection = "COLLECTION", props
    holder.location = (-3.2, 2.5, 0.5)
    sc.collection.objects.link(holder)
    # A volume: rendered by Blender, no surface for Tessera.
    bpy.ops.object.volume_add(location=(4, 4, 1))
    bpy.context.active_object.name = "Fog"
    # A second view layer: Blender renders each; the first one is exported.
    sc.view_layers.new("Second")

    bpy.ops.object.light_add(type="POINT", location=(2, -3, 5))
    bpy.context.active_object.data.energy = 1000
    bpy.ops.object.light_add(type="SUN", location=(0, 0, 8))
    bpy.context.active_object.name = "Sun"
    bpy.context.active_object.data.energy = 0.3

    bpy.ops.object.camera_add(location=(0.5, -9, 4.5), rotation=(1.15, 0, 0.05))
    sc.camera = bpy.context.active_object
    sc.tessera.aa = 2
    return sc


FAILURES = []


def check(cond, what):
    if not cond:
        FAILURES.append(what)
        print("FAIL:", what)
    else:
        print("ok:", what)


def run_op(**kw):
    """Runs Render on Tessera; returns (result or the RuntimeError's text, reports)."""
    del ui.REPORTS[:]
    try:
        result = bpy.ops.render.tessera_render(**kw)
    except RuntimeError as e:
        result = str(e)
    return result, list(ui.REPORTS)


def one_error(reports, must_contain):
    errors = [t for level, t in reports if level == "ERROR"]
    return (len(reports) == 1 and len(errors) == 1 and "\n" not in errors[0]
            and "Traceback" not in errors[0] and must_contain in errors[0].lower(), reports)


def still_bytes():
    img = bpy.data.images.get(ui.STILL_IMAGE)
    return bytes(img.packed_file.data) if img is not None and img.packed_file else None


def main():
    tessera = tessera_bin()
    work = tempfile.mkdtemp(prefix="tessera-addon-")
    tessera_blender.register()
    sc = build_scene()
    farms = []
    try:
        # -- export, and the reference images made by tessera render of the export
        export_dir = os.path.join(work, "export")
        del ui.REPORTS[:]
        t = time.monotonic()
        res = bpy.ops.export_scene.tessera(filepath=os.path.join(export_dir, "scene.json"))
        export_s = time.monotonic() - t
        check(res == {"FINISHED"}, "File > Export finishes")
        meshes = os.listdir(os.path.join(export_dir, "meshes"))
        check(len(meshes) == 4, "6 mesh objects, a linked duplicate and a collection instance sharing"
              " files: 4 PLY files (%d)"
              % len(meshes))
        warnings = [t for level, t in ui.REPORTS if level == "WARNING"]
        check(len(ui.REPORTS) == 1 and len(warnings) == 1
              and "GlassCube: material Glass: Glass BSDF cannot be shown: used its Color input" in warnings[0]
              and "light Sun: sun light cannot be shown: used a point light" in warnings[0]
              and "Fog: a volume cannot be shown: left out" in warnings[0],
              "one warning names the glass cube, the sun, the volume and what was used instead: %r"
              % ui.REPORTS)
        from tessera_blender import evaluate, export
        ex = evaluate.export_still(sc, os.path.join(work, "rules"))
        colour = {}
        for obj in ex.scene["objects"]:
            for name in ex.mesh_users[obj["file"]]:
                colour[name] = [float(c) for c in obj["color"].split()]
        red = export.linear_to_srgb(0.8), export.linear_to_srgb(0.05)
        check(len(ex.scene["objects"]) == 6 and ex.mesh_users[
            [o for o in ex.scene["objects"] if "PropInstance" in ex.mesh_users[o["file"]]][0]["file"]]
            == ["GlassCube", "PropInstance"], "the collection instance shares the cube's file: %r"
            % ex.mesh_users)
        check(colour["Floor"][3] == 2.0, "a Checker Texture into Base Color is special 2")
        check(colour["Chrome"] == [0.0, 0.0, 0.0, 1.0], "Metallic 1 is a pure mirror of 1: %r" % colour["Chrome"])
        shading = {n: o.get("shading", "flat") for o in ex.scene["objects"] for n in ex.mesh_users[o["file"]]}
        check(shading == {"Floor": "flat", "Chrome": "smooth", "Monkey": "smooth", "MonkeyTwin": "smooth",
                          "GlassCube": "flat", "PropInstance": "flat"}, "smooth-shaded objects are exported smooth: %r" % shading)
        want = [red[0], red[1], red[1], 0.0]
        check(all(abs(a - b) < 1e-6 for a, b in zip(colour["Monkey"], want)),
              "a base colour is written sRGB-encoded, matte: %r" % colour["Monkey"])
        check(len(ex.scene["lights"]) == 2 and "1.0 1.0 1.0" in [l["color"] for l in ex.scene["lights"]],
              "a 1000 W white point light is Tessera's white 1: %r" % ex.scene["lights"])
        reference = os.path.join(work, "reference.png")
        subprocess.run([tessera, "render", os.path.join(export_dir, "scene.json"), "-o", reference],
                       check=True, stdout=subprocess.DEVNULL)
        with open(reference, "rb") as f:
            reference_bytes = f.read()
        print("export: %.3f s, %d bytes of PLY" % (export_s, sum(
            os.path.getsize(os.path.join(export_dir, "meshes", m)) for m in meshes)))

        # -- local render
        sc.tessera.tessera_path = tessera
        result, reports = run_op()
        check(result == {"FINISHED"}, "local render finishes: %r %r" % (result, reports))
        check(still_bytes() == reference_bytes, "local render: the image is tessera render's, byte for byte")
        img = bpy.data.images[ui.STILL_IMAGE]
        check(tuple(img.size) == (160, 120), "the image is 160x120")

        # -- farm render
        farm = Farm(tessera, os.path.join(work, "farm"))
        farms.append(farm)
        sc.tessera.address = farm.url
        sc.tessera.token_file = farm.token_file
        bpy.data.images.remove(bpy.data.images[ui.STILL_IMAGE])
        t = time.monotonic()
        result, reports = run_op()
        print("farm render: %.3f s from the button to the image" % (time.monotonic() - t))
        check(result == {"FINISHED"}, "farm render finishes: %r %r" % (result, reports))
        check(still_bytes() == reference_bytes, "farm render: the image is tessera render's, byte for byte")

        # -- a farm with TLS: pinned by its certificate's fingerprint
        secure = Farm(tessera, os.path.join(work, "tls-farm"), tls=True)
        farms.append(secure)
        sc.tessera.address, sc.tessera.token_file = secure.url, secure.token_file
        sc.tessera.tls_fingerprint = secure.fingerprint
        result, reports = run_op()
        check(result == {"FINISHED"} and still_bytes() == reference_bytes,
              "farm render over TLS: tessera render's image: %r" % (reports,))
        sc.tessera.tls_fingerprint = "ab" * 32
        result, reports = run_op()
        check(one_error(reports, "fingerprint")[0], "a wrong TLS fingerprint: one error: %r" % (reports,))
        sc.tessera.address, sc.tessera.token_file = farm.url, farm.token_file
        sc.tessera.tls_fingerprint = ""

        # -- animation on the farm: one sequence job
        cube = sc.objects["GlassCube"]
        sc.frame_start, sc.frame_end = 1, 3
        for f, x in ((1, -1.0), (3, 1.0)):
            cube.location.x = x
            cube.keyframe_insert("location", frame=f)
        sc.render.filepath = os.path.join(work, "frames", "shot_")
        result, reports = run_op(animation=True)
        check(result == {"FINISHED"}, "farm animation finishes: %r %r" % (result, reports))
        anim_dir = os.path.join(work, "anim-export")
        bpy.ops.export_scene.tessera(filepath=os.path.join(anim_dir, "scene.json"), animation=True)
        subprocess.run([tessera, "render", os.path.join(anim_dir, "scene.json"), "--frames", "all",
                        "-o", os.path.join(anim_dir, "frames")], check=True, stdout=subprocess.DEVNULL)
        for f in (1, 2, 3):
            with open(os.path.join(anim_dir, "frames", "frame_%04d.png" % f), "rb") as a:
                want = a.read()
            got_path = os.path.join(work, "frames", "shot_%04d.png" % f)
            got = open(got_path, "rb").read() if os.path.exists(got_path) else None
            check(got == want, "animation frame %d is tessera render --frames' byte for byte" % f)
        seq = bpy.data.images.get(ui.ANIMATION_IMAGE)
        check(seq is not None and seq.source == "SEQUENCE", "the frames are loaded as an image sequence")
        with open(os.path.join(work, "frames", "shot_0001.png"), "rb") as a, \
                open(os.path.join(work, "frames", "shot_0003.png"), "rb") as b:
            check(a.read() != b.read(), "the animation moves (frames 1 and 3 differ)")

        # -- error paths: one report each, of one line
        sc.tessera.token_file = os.path.join(work, "wrong.token")
        with open(sc.tessera.token_file, "w") as f:
            f.write("0" * 32 + "\n")
        result, reports = run_op()
        check(one_error(reports, "wrong client token")[0], "wrong token: one error: %r" % (reports,))
        sc.tessera.token_file = os.path.join(work, "no-such.token")
        result, reports = run_op()
        check(one_error(reports, "token file")[0], "missing token file: one error: %r" % (reports,))
        sc.tessera.token_file = farm.token_file
        sc.tessera.address = "http://127.0.0.1:1"
        result, reports = run_op()
        check(one_error(reports, "cannot reach")[0] and result != {"FINISHED"},
              "coordinator down: one error: %r" % (reports,))
        small = Farm(tessera, os.path.join(work, "small-farm"), ["--max-file-bytes", "40000"])
        farms.append(small)
        sc.tessera.address, sc.tessera.token_file = small.url, small.token_file
        result, reports = run_op()
        check(one_error(reports, "the mesh of monkey, monkeytwin")[0] and "limit" in reports[0][1],
              "a mesh over the file limit: one error: %r" % (reports,))
        sc.tessera.address = ""
        sc.tessera.tessera_path = os.path.join(work, "no-such-tessera")
        result, reports = run_op()
        check(one_error(reports, "no-such-tessera")[0], "tessera command missing: one error: %r" % (reports,))
        sc.tessera.tessera_path = tessera
        # The smallest image Blender allows (its own render refuses so few pixels).
        sc.render.resolution_x, sc.render.resolution_y = 5, 4
        result, reports = run_op()
        check(result == {"FINISHED"} and tuple(bpy.data.images[ui.STILL_IMAGE].size) == (5, 4),
              "a 5x4 image renders: %r %r" % (result, reports))
        sc.render.resolution_x, sc.render.resolution_y = 160, 120
        sc.camera = None
        result, reports = run_op()
        check(one_error(reports, "no camera")[0], "no camera: one error: %r" % (reports,))

        # -- cancel (Esc) cancels the job on the farm
        sc.camera = bpy.data.objects["Camera"]
        sc.render.resolution_x, sc.render.resolution_y = 1920, 1080
        sc.tessera.aa = 8
        d = os.path.join(work, "cancel")
        os.makedirs(d)
        evaluate.export_still(sc, d, image={"aa": 8})
        settings = tjob.Settings(address=farm.url, token_file=farm.token_file)
        job = tjob.RenderJob(settings, os.path.join(d, "scene.json"), os.path.join(d, "out"))
        errors = []
        runner = threading.Thread(target=lambda: errors.append(_catch(job.run)))
        runner.start()
        deadline = time.monotonic() + 20
        while job.job_id is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        job.cancel.set()
        runner.join(10)
        check(not runner.is_alive() and errors and errors[0].startswith("cancelled (job"),
              "cancel ends the job: %r" % errors)
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(HERE)), "python", "src"))
        from tessera_client import Client
        state = Client(farm.url, token=TOKEN, use_env=False).job(job.job_id).state
        check(state == "cancelled", "the farm's job is cancelled (%s)" % state)
    except Exception:
        traceback.print_exc()
        FAILURES.append("exception")
    finally:
        for farm in farms:
            farm.stop()
        tessera_blender.unregister()
        shutil.rmtree(work, ignore_errors=True)
    if FAILURES:
        print("addon test: %d failures" % len(FAILURES))
        sys.exit(1)
    print("addon test: all checks pass")


def _catch(fn):
    try:
        fn()
        return None
    except tjob.JobError as e:
        return str(e)


main()
