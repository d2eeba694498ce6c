"""Tessera for Blender: render the open scene on a Tessera farm (or with the tessera
command on this machine) and load the image back; export it as a Tessera scene.

``export`` maps Blender's scene to Tessera's (pure math, testable without Blender),
``evaluate`` gets the scene as Blender renders it, ``job`` runs a render away from
Blender's main thread, ``ui`` is the panel, the settings and the operators."""

bl_info = {
    "name": "Tessera",
    "author": "Tessera contributors",
    "version": (1, 0, 0),
    "blender": (3, 4, 0),
    "location": "Properties > Render > Tessera; File > Export > Tessera scene",
    "description": "Render the scene on a Tessera render farm",
    "category": "Render",
}

try:
    import bpy  # noqa: F401
except ImportError:  # imported outside Blender (unit tests of export.py and job.py)
    bpy = None

if bpy is not None:
    from . import ui

    def register():
        ui.register()

    def unregister():
        ui.unregister()
