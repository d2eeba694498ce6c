"""Render on Tessera: send the open scene to a Tessera farm (or a local `tessera`)
and load the image back. Skeleton: see ../NOTES.md for what is done and what is not."""

bl_info = {
    "name": "Tessera",
    "author": "Tessera contributors",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "Properties > Render > Tessera; File > Export > Tessera scene",
    "description": "Render the scene on a Tessera render farm",
    "category": "Render",
}

import os
import shutil
import subprocess
import sys
import tempfile

try:
    import bpy
    from bpy.props import StringProperty, PointerProperty
    from bpy_extras.io_utils import ExportHelper
except ImportError:          # imported outside Blender (unit tests of export.py)
    bpy = None

from . import export

if bpy is not None:

    class TesseraSettings(bpy.types.PropertyGroup):
        address: StringProperty(
            name="Coordinator",
            description="The coordinator's HTTP address (host:port or URL); empty renders "
                        "with the tessera command on this machine")
        token_file: StringProperty(name="Token file", subtype="FILE_PATH")
        tls_fingerprint: StringProperty(
            name="TLS fingerprint",
            description="SHA-256 of the coordinator's certificate, as --tls-auto prints it")
        tessera_path: StringProperty(
            name="tessera", default="tessera",
            description="The tessera command, for local renders")

    def _report_warnings(op, warnings):
        if warnings:
            op.report({"WARNING"}, "Tessera: not exported as in Blender: " + "; ".join(warnings))

    class TESSERA_OT_export(bpy.types.Operator, ExportHelper):
        """Write the scene as a Tessera scene file and its PLY meshes"""
        bl_idname = "export_scene.tessera"
        bl_label = "Export Tessera scene"
        filename_ext = ".json"

        def execute(self, context):
            directory, name = os.path.split(self.filepath)
            depsgraph = context.evaluated_depsgraph_get()
            _, warnings = export.export_scene(context.scene, depsgraph, directory, name)
            _report_warnings(self, warnings)
            return {"FINISHED"}

    class TESSERA_OT_render(bpy.types.Operator):
        """Render the current frame on Tessera and load the image"""
        bl_idname = "render.tessera_render"
        bl_label = "Render on Tessera"

        def execute(self, context):
            settings = context.scene.tessera
            work = tempfile.mkdtemp(prefix="tessera-blender-")
            depsgraph = context.evaluated_depsgraph_get()
            _, warnings = export.export_scene(context.scene, depsgraph, work)
            scene_path = os.path.join(work, "scene.json")
            out = os.path.join(work, "render.png")
            try:
                if settings.address:
                    client = _client(settings)
                    wm = context.window_manager
                    wm.progress_begin(0, 1)
                    job = client.submit(scene_path)
                    client.wait(job.id)
                    client.image(job.id, out)
                    wm.progress_end()
                else:
                    exe = shutil.which(settings.tessera_path) or settings.tessera_path
                    r = subprocess.run([exe, "render", scene_path, "-o", out],
                                       capture_output=True, text=True)
                    if r.returncode != 0:
                        self.report({"ERROR"}, "Tessera: " + (r.stderr.strip() or "render failed"))
                        return {"CANCELLED"}
            except Exception as e:  # one readable report, whatever went wrong
                self.report({"ERROR"}, "Tessera: %s" % e)
                return {"CANCELLED"}
            img = bpy.data.images.get("Tessera Render")
            if img is not None:
                bpy.data.images.remove(img)
            img = bpy.data.images.load(out)
            img.name = "Tessera Render"
            img.pack()
            shutil.rmtree(work, ignore_errors=True)
            _report_warnings(self, warnings)
            return {"FINISHED"}

    def _client(settings):
        here = os.path.dirname(os.path.abspath(__file__))
        for p in (os.path.join(here, "vendor"),
                  os.path.join(here, "..", "..", "python", "src")):
            if os.path.isdir(p) and p not in sys.path:
                sys.path.append(p)
        from tessera_client import Client
        return Client(settings.address, token_file=settings.token_file or None,
                      tls_fingerprint=settings.tls_fingerprint or None)

    class TESSERA_PT_render(bpy.types.Panel):
        bl_label = "Tessera"
        bl_space_type = "PROPERTIES"
        bl_region_type = "WINDOW"
        bl_context = "render"

        def draw(self, context):
            s = context.scene.tessera
            col = self.layout.column()
            col.prop(s, "address")
            col.prop(s, "token_file")
            col.prop(s, "tls_fingerprint")
            col.prop(s, "tessera_path")
            col.operator(TESSERA_OT_render.bl_idname, icon="RENDER_STILL")

    def _menu_export(self, context):
        self.layout.operator(TESSERA_OT_export.bl_idname, text="Tessera scene (.json)")

    _classes = (TesseraSettings, TESSERA_OT_export, TESSERA_OT_render, TESSERA_PT_render)

    def register():
        for c in _classes:
            bpy.utils.register_class(c)
        bpy.types.Scene.tessera = PointerProperty(type=TesseraSettings)
        bpy.types.TOPBAR_MT_file_export.append(_menu_export)

    def unregister():
        bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
        del bpy.types.Scene.tessera
        for c in reversed(_classes):
            bpy.utils.unregister_class(c)
