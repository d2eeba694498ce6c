"""The scene as Blender *renders* it, exported.

``context.evaluated_depsgraph_get()`` is the viewport's depsgraph: modifiers shown only
in the viewport, viewport subdivision levels, objects hidden in the viewport but
rendered... all come out as the viewport shows them, not as a render would. Blender
builds a render depsgraph only for a render engine, so the export briefly registers
one: ``bpy.ops.render.render()`` with it hands ``render(depsgraph)`` the depsgraph a
render uses (mode RENDER: render visibility, ``show_render`` modifiers, render
levels), and for an animation ``RenderEngine.frame_set`` moves that depsgraph from
frame to frame. The engine is registered only during the export, so it never shows in
the engine list, and the scene's engine and resolution are restored afterwards."""

import bpy

from . import export

ENGINE_ID = "TESSERA_EXPORT"
#: The side of the (empty, square) render the export runs in, in pixels.
RENDER_SIDE = 32


class ExportFailed(Exception):
    """The scene could not be exported; one line saying why."""


class _Request:
    def __init__(self, call):
        self.call = call
        self.result = None
        self.error = None
        self.ran = False


_pending = None


class _ExportEngine(bpy.types.RenderEngine):
    bl_idname = ENGINE_ID
    bl_label = "Tessera (export)"
    bl_use_postprocess = False

    def render(self, depsgraph):
        request = _pending
        # Blender calls render once per view layer: the first one is exported.
        if request is None or request.ran:
            return
        request.ran = True
        try:
            request.result = request.call(self, depsgraph)
        except Exception as e:  # handed back to the caller, outside the render
            request.error = e


def _render_depsgraph(scene, call):
    """Calls ``call(engine, depsgraph)`` with the render depsgraph of ``scene`` (its
    current frame) and returns what it returns."""
    global _pending
    if scene.camera is None:
        raise ExportFailed("the scene has no camera (set one in Scene properties)")
    request = _Request(call)
    r = scene.render
    saved = (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.use_border)
    frame = scene.frame_current
    bpy.utils.register_class(_ExportEngine)
    _pending = request
    try:
        r.engine = ENGINE_ID
        # The export reads the size before; the render Blender starts for the engine
        # (which draws nothing) need not be the image's: a small square, of a size
        # Blender accepts whatever the image's (it refuses images of a few pixels).
        r.resolution_x = r.resolution_y = RENDER_SIDE
        r.resolution_percentage = 100
        r.use_border = False
        bpy.ops.render.render(write_still=False)
    finally:
        _pending = None
        r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage, r.use_border = saved
        bpy.utils.unregister_class(_ExportEngine)
        if scene.frame_current != frame:
            scene.frame_set(frame)
    if not request.ran:
        raise ExportFailed("Blender did not start the export (is a render already running?)")
    if request.error is not None:
        raise request.error
    return request.result


def image_size(scene):
    r = scene.render
    return (max(1, int(r.resolution_x * r.resolution_percentage / 100)),
            max(1, int(r.resolution_y * r.resolution_percentage / 100)))


def export_still(scene, directory, name="scene.json", image=None, object_colors=None,
                 flat=False):
    """The current frame as rendered, written to ``directory/name`` with its PLY files.
    Returns an ``export.Exported``."""
    size = image_size(scene)

    def call(engine, depsgraph):
        return export.export_scene(scene, depsgraph, directory, name, object_colors, flat,
                                   size=size, image=image)

    return _render_depsgraph(scene, call)


def export_animation(scene, directory, name="scene.json", image=None, object_colors=None,
                     flat=False, frame_start=None, frame_end=None):
    """The frame range as rendered, as one animated scene. Returns an ``export.Exported``."""
    size = image_size(scene)

    def call(engine, depsgraph):
        def goto(frame):
            engine.frame_set(frame, 0.0)
            return depsgraph

        return export.export_animation(scene, goto, directory, name, object_colors, flat,
                                       frame_start, frame_end, size=size, image=image)

    return _render_depsgraph(scene, call)
