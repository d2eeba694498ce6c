"""The add-on's face in Blender: its settings (stored with the scene), the Tessera
panel in Render properties, File > Export > Tessera scene, and the two render
operators.

A render from the button is modal: the export runs first on Blender's main thread
(Blender's data may only be read there), then the job (farm or local ``tessera``)
runs in a thread while a timer shows its progress in the status bar; Esc cancels it.
Called from a script (``bpy.ops.render.tessera_render()``, or in ``--background``)
the same operator runs to the end before returning. Whatever fails ends in one report
of one line, never a traceback."""

import os
import re
import shutil
import tempfile
import threading

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from . import evaluate
from .job import Cancelled, JobError, RenderJob, Settings, one_line

STILL_IMAGE = "Tessera Render"
ANIMATION_IMAGE = "Tessera Animation"

#: Every report the add-on made, newest last: (level, text). Scripts and tests read it.
REPORTS = []


def _report(op, level, text):
    REPORTS.append((level, text))
    op.report({level}, text)


def _report_warnings(op, warnings):
    if warnings:
        _report(op, "WARNING", "Tessera: shown differently: " + "; ".join(warnings))


class TesseraSettings(bpy.types.PropertyGroup):
    address: StringProperty(
        name="Coordinator",
        description="The coordinator's HTTP address (http://host:port, https:// with TLS); "
                    "empty renders with the tessera command on this machine")
    token_file: StringProperty(
        name="Token file", subtype="FILE_PATH",
        description="File holding the coordinator's client token (--client-token-file)")
    tls_fingerprint: StringProperty(
        name="TLS fingerprint",
        description="SHA-256 of the coordinator's certificate, as it prints it with --tls-auto")
    tessera_path: StringProperty(
        name="tessera command", default="tessera", subtype="FILE_PATH",
        description="The tessera program, for renders on this machine")
    aa: IntProperty(
        name="Samples per side", default=2, min=1, max=16,
        description="Antialiasing: N gives N x N samples per pixel (the scene's aa)")
    sampler: EnumProperty(
        name="Sampler", default="grid",
        items=[("grid", "Grid", "The regular N x N grid, the reference"),
               ("jittered", "Jittered", "One random point in each of the N x N cells"),
               ("adaptive", "Adaptive", "4 samples, then more only where they disagree, up to N x N")])
    target_error: FloatProperty(
        name="Target error", default=0.0, min=0.0, max=255.0,
        description="Adaptive sampling: stop a pixel once its estimated error is below this "
                    "many 8-bit levels (0: off)")
    max_depth: IntProperty(
        name="Reflection depth", default=10, min=0, max=64,
        description="How many mirror bounces a ray may take (the scene's max_depth)")


def _settings(scene):
    s = scene.tessera
    name = "%s/%s" % (bpy.path.display_name_from_filepath(bpy.data.filepath) or "untitled",
                      scene.name)
    return Settings(address=s.address, token_file=bpy.path.abspath(s.token_file) if s.token_file else "",
                    tls_fingerprint=s.tls_fingerprint,
                    tessera_path=bpy.path.abspath(s.tessera_path) if os.sep in s.tessera_path
                    else s.tessera_path,
                    sampler=s.sampler, target_error=s.target_error if s.sampler == "adaptive" else 0.0,
                    name=name)


def _image_settings(scene):
    return {"aa": scene.tessera.aa, "max_depth": scene.tessera.max_depth}


def _export(scene, directory, animation):
    """(scene path, export.Exported, Tessera frames or None)."""
    if animation:
        exported = evaluate.export_animation(scene, directory, image=_image_settings(scene))
        frames = (1, scene.frame_end - scene.frame_start + 1)
    else:
        exported = evaluate.export_still(scene, directory, image=_image_settings(scene))
        frames = None
    return os.path.join(directory, "scene.json"), exported, frames


class TESSERA_OT_export(bpy.types.Operator, ExportHelper):
    """Write the scene as Blender renders it as a Tessera scene file and its PLY meshes,
    for tessera render or tessera submit"""
    bl_idname = "export_scene.tessera"
    bl_label = "Export Tessera scene"
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={"HIDDEN"})
    animation: BoolProperty(
        name="Animation", default=False,
        description="The frame range as one animated scene (else the current frame)")

    def execute(self, context):
        directory, name = os.path.split(bpy.path.abspath(self.filepath))
        scene = context.scene
        try:
            os.makedirs(directory or ".", exist_ok=True)
            if self.animation:
                exported = evaluate.export_animation(scene, directory, name,
                                                     image=_image_settings(scene))
            else:
                exported = evaluate.export_still(scene, directory, name,
                                                 image=_image_settings(scene))
        except Exception as e:  # one report, never a traceback
            _report(self, "ERROR", "Tessera: export failed: %s" % one_line(e))
            return {"CANCELLED"}
        _report_warnings(self, exported.warnings)
        return {"FINISHED"}


def _animation_paths(scene, count):
    """Where a sequence's frames go: Blender's own output path (Output properties),
    numbered by Blender frame as its animation renders are: PREFIX0001.png..."""
    prefix = bpy.path.abspath(scene.render.filepath or "//")
    directory = prefix.endswith(("/", os.sep)) or prefix == "" or os.path.isdir(prefix)
    # Absolute (an unsaved file's "//" is the current directory), as reports name it.
    prefix = os.path.join(os.path.abspath(prefix), "") if directory else os.path.abspath(prefix)
    prefix = re.sub(r"#+$", "", prefix)
    return [prefix + "%04d.png" % (scene.frame_start + i) for i in range(count)]


def _show(context, image):
    """Shows ``image`` in the image editors of the open windows."""
    wm = getattr(context, "window_manager", None)
    for window in (wm.windows if wm else []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image


def _load_still(context, path):
    new = bpy.data.images.load(path, check_existing=False)
    new.pack()
    old = bpy.data.images.get(STILL_IMAGE)
    if old is not None:
        old.user_remap(new)
        bpy.data.images.remove(old)
    new.name = STILL_IMAGE
    new.filepath = ""
    _show(context, new)
    return new


def _load_sequence(context, paths):
    old = bpy.data.images.get(ANIMATION_IMAGE)
    new = bpy.data.images.load(paths[0], check_existing=False)
    new.source = "SEQUENCE"
    if old is not None:
        old.user_remap(new)
        bpy.data.images.remove(old)
    new.name = ANIMATION_IMAGE
    _show(context, new)
    return new


class TESSERA_OT_render(bpy.types.Operator):
    """Render on Tessera (the farm in the Tessera panel, or this machine) and load the
    image into Blender"""
    bl_idname = "render.tessera_render"
    bl_label = "Render on Tessera"
    animation: BoolProperty(
        name="Animation", default=False, options={"SKIP_SAVE"},
        description="The frame range as one sequence job, loaded as an image sequence")

    _running = False

    @classmethod
    def description(cls, context, properties):
        if properties.animation:
            return "Render the frame range on Tessera as one sequence job, loaded as an image sequence"
        return "Render the current frame on Tessera and load the image into Blender"

    def _prepare(self, context):
        scene = context.scene
        self.work = tempfile.mkdtemp(prefix="tessera-blender-")
        scene_path, exported, frames = _export(scene, self.work, self.animation)
        self.warnings = exported.warnings
        self.count = frames[1] if frames else 1
        self.job = RenderJob(_settings(scene), scene_path, os.path.join(self.work, "out"), frames,
                             exported.mesh_users)
        self.outputs = None
        self.error = None
        self.cancelled = None

    def _run(self):
        try:
            self.outputs = self.job.run()
        except Cancelled as e:
            self.cancelled = str(e)
        except JobError as e:
            self.error = str(e)
        except Exception as e:  # a thread must never die silently
            self.error = one_line(e)

    def _finish(self, context):
        """Loads the images (main thread), reports, and cleans up."""
        try:
            if self.cancelled is not None:
                _report(self, "WARNING", "Tessera: render %s" % self.cancelled)
                return {"CANCELLED"}
            if self.error is not None:
                what = "animation" if self.animation else "render"
                _report(self, "ERROR", "Tessera: %s failed: %s" % (what, self.error))
                return {"CANCELLED"}
            if self.animation:
                paths = _animation_paths(context.scene, self.count)
                os.makedirs(os.path.dirname(paths[0]) or ".", exist_ok=True)
                for src, dst in zip(self.outputs, paths):
                    shutil.move(src, dst)
                _load_sequence(context, paths)
                where = "%d frames in %s" % (len(paths), os.path.dirname(paths[0]))
            else:
                _load_still(context, self.outputs[0])
                where = "image %r" % STILL_IMAGE
            _report_warnings(self, self.warnings)
            _report(self, "INFO", "Tessera: rendered, %s" % where)
            return {"FINISHED"}
        except Exception as e:
            _report(self, "ERROR", "Tessera: could not load the result: %s" % one_line(e))
            return {"CANCELLED"}
        finally:
            shutil.rmtree(self.work, ignore_errors=True)
            TESSERA_OT_render._running = False

    def _start(self, context):
        if TESSERA_OT_render._running:
            _report(self, "ERROR", "Tessera: a render is already running (Esc cancels it)")
            return False
        try:
            self._prepare(context)
        except Exception as e:
            _report(self, "ERROR", "Tessera: export failed: %s" % one_line(e))
            if getattr(self, "work", None):
                shutil.rmtree(self.work, ignore_errors=True)
            return False
        TESSERA_OT_render._running = True
        return True

    def execute(self, context):
        if not self._start(context):
            return {"CANCELLED"}
        self._run()
        return self._finish(context)

    def invoke(self, context, event):
        if not self._start(context):
            return {"CANCELLED"}
        self.thread = threading.Thread(target=self._run, name="tessera-render", daemon=True)
        self.thread.start()
        wm = context.window_manager
        self.timer = wm.event_timer_add(0.25, window=context.window)
        wm.progress_begin(0, 1000)
        wm.modal_handler_add(self)
        self._status(context, "Tessera: starting (Esc cancels)")
        return {"RUNNING_MODAL"}

    def _status(self, context, text):
        if context.workspace is not None:
            context.workspace.status_text_set(text)

    def _end_modal(self, context):
        wm = context.window_manager
        wm.event_timer_remove(self.timer)
        wm.progress_end()
        self._status(context, None)

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS" and not self.job.cancel.is_set():
            self.job.cancel.set()
            self._status(context, "Tessera: cancelling...")
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if self.thread.is_alive():
            fraction, text = self.job.progress()
            if fraction is not None:
                context.window_manager.progress_update(int(fraction * 1000))
            if not self.job.cancel.is_set():
                self._status(context, "Tessera: %s (Esc cancels)" % text)
            return {"RUNNING_MODAL"}
        self._end_modal(context)
        return self._finish(context)


class TESSERA_PT_render(bpy.types.Panel):
    bl_label = "Tessera"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"

    def draw(self, context):
        s = context.scene.tessera
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        col = layout.column()
        col.prop(s, "address")
        sub = col.column()
        sub.active = bool(s.address)
        sub.prop(s, "token_file")
        sub.prop(s, "tls_fingerprint")
        sub = col.column()
        sub.active = not s.address
        sub.prop(s, "tessera_path")
        col.separator()
        scene = context.scene
        w, h = evaluate.image_size(scene)
        col.label(text="%d x %d pixels, frames %d-%d (Output properties)"
                  % (w, h, scene.frame_start, scene.frame_end))
        col.prop(s, "aa")
        col.prop(s, "sampler")
        sub = col.column()
        sub.active = s.sampler == "adaptive"
        sub.prop(s, "target_error")
        col.prop(s, "max_depth")
        col.separator()
        row = col.row(align=True)
        row.enabled = not TESSERA_OT_render._running
        row.operator(TESSERA_OT_render.bl_idname, text="Render on Tessera", icon="RENDER_STILL")
        op = row.operator(TESSERA_OT_render.bl_idname, text="Render animation", icon="RENDER_ANIMATION")
        op.animation = True


def _menu_export(self, context):
    self.layout.operator(TESSERA_OT_export.bl_idname, text="Tessera scene (.json)")


CLASSES = (TesseraSettings, TESSERA_OT_export, TESSERA_OT_render, TESSERA_PT_render)


def register():
    for c in CLASSES:
        bpy.utils.register_class(c)
    bpy.types.Scene.tessera = PointerProperty(type=TesseraSettings)
    bpy.types.TOPBAR_MT_file_export.append(_menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(_menu_export)
    del bpy.types.Scene.tessera
    for c in reversed(CLASSES):
        bpy.utils.unregister_class(c)
