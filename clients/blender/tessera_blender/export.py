"""Blender scene -> Tessera scene (docs/scene-format.md).

The first half of this module is pure Python (no bpy): axis mapping, matrices,
camera field of view, binary PLY writing, colour and light rules. It can be unit
tested with any Python 3. The second half (``export_scene``) takes bpy objects and
imports nothing itself: it only calls methods on what it is given.

Axes. Blender is right-handed with Z up; Tessera's camera is x right, y up,
z forward (r = normalize(up x f), a left-handed frame). The mapping is the swap
(x, y, z) -> (x, z, y): a reflection, which turns Blender's right-handed frames into
Tessera's left-handed ones, so a camera's right/up/forward map to Tessera's
right/up/forward and images are not mirrored.
"""

import array
import collections
import hashlib
import json
import math
import os
import struct
import sys

# --------------------------------------------------------------------------- math


def to_tessera(v):
    """A Blender point or direction (x, y, z) in Tessera's axes: (x, z, y)."""
    return (v[0], v[2], v[1])


def matrix_to_tessera(m):
    """A Blender 4x4 world matrix (rows; anything indexable m[i][j]) as Tessera's
    ``transform.matrix``: the 12 numbers of the 3x4 [A | t], row by row, for vertices
    already written in Tessera's axes. A' = P A P, t' = P t with P the y/z swap."""
    p = (0, 2, 1)
    out = []
    for i in range(3):
        for j in range(3):
            out.append(float(m[p[i]][p[j]]))
        out.append(float(m[p[i]][3]))
    return out


def _norm(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def camera_vectors(m):
    """position, look_at and up (Tessera axes) for a Blender camera world matrix.
    A Blender camera looks along its local -Z with local +Y up; scale is ignored."""
    pos = (m[0][3], m[1][3], m[2][3])
    fwd = _norm((-m[0][2], -m[1][2], -m[2][2]))
    up = _norm((m[0][1], m[1][1], m[2][1]))
    pos_t = to_tessera(pos)
    fwd_t = to_tessera(fwd)
    look = tuple(pos_t[i] + fwd_t[i] for i in range(3))
    return pos_t, look, to_tessera(up)


def sensor_fit_axis(sensor_fit, width, height, aspect_x=1.0, aspect_y=1.0):
    """'HORIZONTAL' or 'VERTICAL': the axis Blender's sensor size measures.
    AUTO takes the longer side (after pixel aspect), as Blender does."""
    if sensor_fit == 'AUTO':
        return 'HORIZONTAL' if width * aspect_x >= height * aspect_y else 'VERTICAL'
    return sensor_fit


def camera_fov(lens, sensor_width, sensor_height, sensor_fit, width, height,
               aspect_x=1.0, aspect_y=1.0):
    """Tessera's ``fov`` (degrees across the *shorter* image side) for a Blender
    perspective camera: focal length ``lens`` (mm), sensor size (mm) and fit.
    The fit chooses the side the sensor size measures: AUTO the longer side,
    HORIZONTAL the width, VERTICAL the height. AUTO and HORIZONTAL use
    sensor_width, VERTICAL sensor_height (Blender's BKE_camera_sensor_size): in a
    portrait image AUTO thus lays sensor_width along the *height*.
    Non-square pixels are not representable in Tessera: the caller warns."""
    axis = sensor_fit_axis(sensor_fit, width, height, aspect_x, aspect_y)
    sensor = sensor_height if sensor_fit == 'VERTICAL' else sensor_width
    half_fit = sensor / (2.0 * lens)          # tan of half the angle across the fit side
    w, h = width * aspect_x, height * aspect_y
    fit_len = w if axis == 'HORIZONTAL' else h
    half_short = half_fit * min(w, h) / fit_len
    return math.degrees(2.0 * math.atan(half_short))


def linear_to_srgb(c):
    """Blender colours are scene-linear; Tessera writes its values without a curve,
    so they are display (sRGB) values. Colours are encoded once on export."""
    c = max(0.0, float(c))
    if c <= 0.0031308:
        return 12.92 * c
    return 1.055 * c ** (1.0 / 2.4) - 0.055


# A Blender point light of this power (W) becomes a Tessera light of its colour.
# Tessera's point lights have no distance fall-off (docs/scene-format.md, step 5:
# colour += C * Lc * cos), so the rule is only a scale: Lc = colour * power / 1000.
LIGHT_REFERENCE_WATTS = 1000.0


def light_color(color, energy):
    k = float(energy) / LIGHT_REFERENCE_WATTS
    return tuple(max(0.0, float(c)) * k for c in color[:3])


def mirror_coefficient(metallic, roughness):
    """Tessera's 'special' for a Principled BSDF: metallic in (0, 1] is the mirror
    fraction; a non-metal with roughness <= 0.05 is taken as a mirror of 0.5
    (clear varnish); otherwise 0 (matte)."""
    m = min(1.0, max(0.0, float(metallic)))
    if m > 0.0:
        return m
    if roughness <= 0.05:
        return 0.5
    return 0.0


def surface(base, metallic, roughness):
    """Tessera's (r g b, special) for a Principled BSDF's base colour (linear),
    metallic and roughness. Tessera adds a mirror's reflection to the lit colour,
    untinted: a metal's diffuse part is base x (1 - metallic), so a chrome ball
    (metallic 1) is a pure mirror, not a lit white ball with a reflection on top;
    the tint of a coloured metal's reflection cannot be shown."""
    special = mirror_coefficient(metallic, roughness)
    m = min(1.0, max(0.0, float(metallic)))
    return tuple(float(c) * (1.0 - m) for c in base[:3]), special


def fmt(v):
    """Numbers as the shortest text that reads back to the same double."""
    return " ".join(repr(float(x)) for x in v)


# ---------------------------------------------------------------------------- PLY


def ply_header(vertices, triangles):
    return (
        "ply\nformat binary_little_endian 1.0\n"
        "element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
        "element face %d\nproperty list uchar int vertex_indices\nend_header\n"
        % (vertices, triangles)
    ).encode("ascii")


def ply_bytes(vertices, triangles):
    """Binary little-endian PLY: float x y z per vertex; faces as uchar count + int
    indices. ``vertices`` in Tessera axes; ``triangles`` index triples. (The reference
    for ``mesh_ply``, which writes the same bytes from Blender's arrays.)"""
    header = ply_header(len(vertices), len(triangles))
    body = bytearray()
    vs = struct.Struct("<fff")
    fs = struct.Struct("<Biii")
    for v in vertices:
        body += vs.pack(*v)
    for t in triangles:
        body += fs.pack(3, *t)
    return header + bytes(body)


class MeshStore:
    """Writes each distinct PLY once, named by the SHA-256 of its bytes. A mesh seen
    before under the same ``mesh_key`` is not converted again (a hundred linked
    duplicates of a million triangles are read once, not a hundred times)."""

    def __init__(self, directory, subdir="meshes"):
        self.directory = directory
        self.subdir = subdir
        self.files = {}
        self.by_key = {}

    def known(self, key):
        """(file, shading) of a mesh added under ``key`` (None: not known, or no key)."""
        return self.by_key.get(key) if key is not None else None

    def add(self, data, key=None, shading="flat"):
        """Writes ``data`` unless a file with its bytes exists; returns (file, shading)."""
        digest = hashlib.sha256(data).hexdigest()
        name = "%s/%s.ply" % (self.subdir, digest[:16])
        if digest not in self.files:
            path = os.path.join(self.directory, name)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "wb") as f:
                f.write(data)
            self.files[digest] = name
        written = (self.files[digest], shading)
        if key is not None:
            self.by_key[key] = written
        return written


# --------------------------------------------------------------------------- bpy


MESH_LIKE = {"MESH", "CURVE", "SURFACE", "FONT", "META"}
# Objects a render shows that Tessera's model has no surface for.
UNSHOWN = {"VOLUME": "a volume", "POINTCLOUD": "a point cloud", "CURVES": "hair curves",
           "GPENCIL": "a grease pencil drawing", "GREASEPENCIL": "a grease pencil drawing"}


def _viewport_colour(mat):
    return tuple(mat.diffuse_color[:3])


def _material_info(obj, warn):
    """(rgb linear, special) from the object's first material. What the model cannot
    show is warned, naming the object, the material and what was used instead."""
    mat = obj.active_material if obj.material_slots else None
    if len(obj.material_slots) > 1:
        warn("%s: %d material slots: the first material's colour is used for the whole object"
             % (obj.name, len(obj.material_slots)))
    if mat is None:
        return (0.8, 0.8, 0.8), 0.0
    if not mat.use_nodes or mat.node_tree is None:
        return surface(_viewport_colour(mat), mat.metallic, mat.roughness)
    tree = mat.node_tree
    out = tree.get_output_node("ALL") if hasattr(tree, "get_output_node") else None
    surf = out.inputs["Surface"].links[0].from_node if out and out.inputs["Surface"].links else None
    where = "%s: material %s" % (obj.name, mat.name)
    if surf is None or surf.type != "BSDF_PRINCIPLED":
        kind = surf.bl_label if surf is not None else "no surface"
        colour = surf.inputs.get("Color") if surf is not None else None
        if colour is not None and not colour.links and hasattr(colour, "default_value"):
            warn("%s: %s cannot be shown: used its Color input as a matte colour" % (where, kind))
            return tuple(colour.default_value[:3]), 0.0
        warn("%s: %s cannot be shown: used the material's viewport colour, matte" % (where, kind))
        return _viewport_colour(mat), 0.0
    inputs = surf.inputs
    base = inputs["Base Color"]
    metallic, roughness = inputs["Metallic"].default_value, inputs["Roughness"].default_value
    # Input names are Blender 3.x's; 4.x renamed some (looked up defensively).
    transmission = inputs.get("Transmission") or inputs.get("Transmission Weight")
    if transmission is not None and transmission.default_value > 0:
        warn("%s: transmission (glass) cannot be shown: rendered opaque" % where)
    emission = inputs.get("Emission") or inputs.get("Emission Color")
    strength = inputs.get("Emission Strength")
    if emission is not None and strength is not None and strength.default_value > 0 \
            and any(c > 0 for c in emission.default_value[:3]):
        warn("%s: emission cannot be shown: only the base colour is used" % where)
    if base.links:
        node = base.links[0].from_node
        if node.type == "TEX_CHECKER":
            return (1.0, 1.0, 1.0), 2.0
        warn("%s: base colour from %s cannot be shown: used the material's viewport colour"
             % (where, node.bl_label))
        return surface(_viewport_colour(mat), metallic, roughness)
    return surface(base.default_value, metallic, roughness)


# Where a sun light is put: this far from the origin, against its direction. With no
# fall-off in Tessera's model, a point light far away lights like the sun.
SUN_DISTANCE = 1.0e4


def light_entry(ob, matrix, warn):
    """A Blender light as Tessera's point light (position, colour), or None. Point
    lights map by the documented rule; spot and area lights become point lights at
    their place; a sun becomes a point light far away along its direction."""
    light = ob.data
    position = (matrix[0][3], matrix[1][3], matrix[2][3])
    colour = light_color(light.color, light.energy)
    if light.type == "SPOT":
        warn("light %s: spot cone cannot be shown: used a point light at its place" % ob.name)
    elif light.type == "AREA":
        warn("light %s: area light cannot be shown: used a point light at its centre" % ob.name)
    elif light.type == "SUN":
        direction = _norm((-matrix[0][2], -matrix[1][2], -matrix[2][2]))
        position = tuple(-c * SUN_DISTANCE for c in direction)
        # A sun's strength is in W/m^2 (1 to 10 for daylight), not in watts.
        colour = tuple(max(0.0, float(c)) * float(light.energy) for c in light.color[:3])
        warn("light %s: sun light cannot be shown: used a point light %g units away along"
             " its direction, colour x strength" % (ob.name, SUN_DISTANCE))
    elif light.type != "POINT":
        warn("light %s: %s light cannot be shown: left out" % (ob.name, light.type))
        return None
    return {"position": fmt(to_tessera(position)), "color": fmt(colour)}


def _regroup(data, record, fields, prefix=b""):
    """Each ``record``-byte record of ``data`` rebuilt as ``prefix`` then its
    (offset, size) ``fields`` in the order given, by byte slicing (no Python loop
    over the records)."""
    count = len(data) // record
    out_record = len(prefix) + sum(size for _, size in fields)
    out = bytearray(out_record * count)
    for k, byte in enumerate(prefix):
        out[k::out_record] = bytes([byte]) * count
    at = len(prefix)
    for offset, size in fields:
        for k in range(size):
            out[at + k::out_record] = data[offset + k::record]
        at += size
    return bytes(out)


def _floats(collection, attr, count):
    out = array.array("f", [0.0]) * count
    collection.foreach_get(attr, out)
    return out


def _le(values):
    if sys.byteorder != "little":
        values.byteswap()
    return values.tobytes()


def mesh_ply(mesh):
    """A Blender mesh's triangles as binary PLY, and the shading that shows them as
    Blender does: (bytes, "flat" or "smooth"), or None for a mesh without triangles.

    No normals are written: Blender computes its normals in parallel, so their last
    bits change from one evaluation to the next, and two linked duplicates would no
    longer share a file nor an animation keep its shape. Smoothness is carried by
    which triangles share a vertex, and Tessera computes smooth normals over the
    triangles sharing each vertex (docs/scene-format.md, "Normals and shading"):

    - no face shaded smooth: the mesh's own vertices, flat shading;
    - every face smooth, no auto smooth, no custom normals: the mesh's own vertices,
      smooth shading (the same file as flat: only the object's shading differs);
    - otherwise (mixed faces, auto smooth's sharp edges, custom normals): corners are
      grouped as Blender's split normals group them (a vertex is split wherever its
      corners' normals differ: across sharp edges and around flat faces), smooth
      shading; a flat face then has vertices of its own and stays flat.

    The arrays are copied whole (``foreach_get`` into typed arrays) and regrouped by
    byte slicing, never element by element: a million triangles take a fraction of a
    second, with the same bytes as ``ply_bytes``."""
    mesh.calc_loop_triangles()
    nv, nt = len(mesh.vertices), len(mesh.loop_triangles)
    if nt == 0:
        return None
    kind = _smoothness(mesh)
    tri = array.array("i", [0]) * (3 * nt)
    mesh.loop_triangles.foreach_get("vertices", tri)
    co = _floats(mesh.vertices, "co", 3 * nv)
    if kind == "split":
        co, tri = _split_by_corner_normals(mesh, co, tri)
    vertices = _regroup(_le(co), 12, [(0, 4), (8, 4), (4, 4)])   # (x, y, z) -> (x, z, y)
    faces = _regroup(_le(tri), 12, [(0, 12)], prefix=b"\x03")      # count 3, three indices
    return ply_header(len(co) // 3, nt) + vertices + faces, "flat" if kind == "flat" else "smooth"


def _smoothness(mesh):
    """"flat" (no face smooth), "plain" (every face smooth and nothing splits the
    normals at a vertex) or "split". Sharp edges split normals under auto smooth
    (Blender before 4.1) and always from 4.1 on, where auto smooth is gone."""
    smooth = [False] * len(mesh.polygons)
    mesh.polygons.foreach_get("use_smooth", smooth)
    if not any(smooth):
        return "flat"
    if not all(smooth) or getattr(mesh, "use_auto_smooth", False) \
            or getattr(mesh, "has_custom_normals", False):
        return "split"
    if not hasattr(mesh, "use_auto_smooth"):
        sharp = [False] * len(mesh.edges)
        mesh.edges.foreach_get("use_edge_sharp", sharp)
        if any(sharp):
            return "split"
    return "plain"


def mesh_key(mesh):
    """A digest of everything ``mesh_ply`` reads of a mesh whose vertices are written
    as they are (every face flat, or every face smooth with no auto smooth and no
    custom normals): positions, faces, corners, shading flags. Equal keys give equal
    PLY bytes: the triangles Blender makes of a face depend only on these. None for a
    mesh whose vertices are split by its corner normals (not cached)."""
    kind = _smoothness(mesh)
    if kind == "split":
        return None
    h = hashlib.sha256()
    co = _floats(mesh.vertices, "co", 3 * len(mesh.vertices))
    h.update(b"%d %d %d %s|" % (len(mesh.vertices), len(mesh.polygons), len(mesh.loops),
                                kind.encode()))
    h.update(co.tobytes())
    for collection, attr, count in ((mesh.loops, "vertex_index", len(mesh.loops)),
                                    (mesh.polygons, "loop_start", len(mesh.polygons)),
                                    (mesh.polygons, "loop_total", len(mesh.polygons))):
        values = array.array("i", [0]) * count
        collection.foreach_get(attr, values)
        h.update(values.tobytes())
    return h.digest()


def _split_by_corner_normals(mesh, co, tri):
    """(positions, triangles) with one vertex per (vertex, split normal) pair."""
    if hasattr(mesh, "calc_normals_split"):
        mesh.calc_normals_split()
    normal = _floats(mesh.loop_triangles, "split_normals", 3 * len(tri))
    index = {}
    new_tri = array.array("i", [0]) * len(tri)
    positions = array.array("f")
    for c, v in enumerate(tri):
        key = (v, normal[3 * c], normal[3 * c + 1], normal[3 * c + 2])
        k = index.get(key)
        if k is None:
            k = index[key] = len(index)
            positions.extend(co[3 * v:3 * v + 3])
        new_tri[c] = k
    return positions, new_tri


def _instance_key(inst):
    """A name for an object instance that stays the same from frame to frame."""
    ob = inst.object
    name = ob.original.name if hasattr(ob, "original") else ob.name
    if getattr(inst, "is_instance", False):
        parent = inst.parent.original.name if inst.parent is not None else ""
        return "%s/%s/%s" % (parent, name, tuple(inst.persistent_id))
    return name


def image_settings(size, image=None):
    """The scene's ``image``: the size given, ``aa`` 1 and depth 10 unless ``image``
    (a dict of ``aa``, ``max_depth``) says otherwise."""
    out = {"width": int(size[0]), "height": int(size[1]), "aa": 1, "max_depth": 10}
    for k in ("aa", "max_depth"):
        if image and image.get(k) is not None:
            out[k] = int(image[k])
    return out


def collect(scene, depsgraph, store, warn, object_colors=None, flat=False, size=None,
            image=None):
    """The scene as evaluated by ``depsgraph``: (scene dict, keys) where keys[i] names
    what ``objects[i]`` or ``lights[i]`` came from: ("object", key) / ("light", key).
    Mesh files are written through ``store``. ``size`` is the image's (width, height)
    (the render settings' by default)."""
    r = scene.render
    if size is None:
        size = (int(r.resolution_x * r.resolution_percentage / 100),
                int(r.resolution_y * r.resolution_percentage / 100))
    width, height = size
    out = {"image": image_settings(size, image),
           "ambient": 1.0 if flat else 0.2, "lights": [], "objects": []}
    keys = {"objects": [], "lights": []}
    if r.pixel_aspect_x != r.pixel_aspect_y:
        warn("pixel aspect %g:%g cannot be shown: the image has square pixels of the same size"
             % (r.pixel_aspect_x, r.pixel_aspect_y))

    cam = scene.camera
    if cam is not None:
        camd = cam.data
        cam_eval = cam.evaluated_get(depsgraph)
        pos, look, up = camera_vectors(cam_eval.matrix_world)
        c = {"position": fmt(pos), "look_at": fmt(look), "up": fmt(up)}
        camd = cam_eval.data
        if camd.type == "PERSP":
            c["fov"] = camera_fov(camd.lens, camd.sensor_width, camd.sensor_height,
                                  camd.sensor_fit, width, height,
                                  r.pixel_aspect_x, r.pixel_aspect_y)
        else:
            warn("camera %s: %s projection cannot be shown: used a perspective camera"
                 " with Tessera's default fov" % (cam.name, camd.type))
        if camd.shift_x or camd.shift_y:
            warn("camera %s: lens shift cannot be shown: used the unshifted view" % cam.name)
        out["camera"] = c
    else:
        warn("the scene has no camera")

    for inst in depsgraph.object_instances:
        ob = inst.object
        if ob.type == "LIGHT":
            if flat:
                continue
            entry = light_entry(ob, inst.matrix_world, warn)
            if entry is not None:
                out["lights"].append(entry)
                keys["lights"].append(_instance_key(inst))
            continue
        if ob.type not in MESH_LIKE:
            if ob.type in UNSHOWN:
                warn("%s: %s cannot be shown: left out" % (ob.name, UNSHOWN[ob.type]))
            continue
        key = ob.original.name if hasattr(ob, "original") else ob.name
        mesh = ob.to_mesh()
        try:
            digest = mesh_key(mesh)
            written = store.known(digest)
            if written is None:
                ply = mesh_ply(mesh)
                written = None if ply is None else store.add(ply[0], digest, ply[1])
        finally:
            ob.to_mesh_clear()
        if written is None:
            continue
        file, shading = written
        if object_colors is not None:
            rgb, special = object_colors[key], 0.0
        else:
            rgb, special = _material_info(ob, warn)
            rgb = tuple(linear_to_srgb(c) for c in rgb)
        entry = {"type": "mesh", "file": file, "color": fmt(tuple(rgb) + (special,)),
                 "transform": {"matrix": fmt(matrix_to_tessera(inst.matrix_world))}}
        if shading == "smooth":
            entry["shading"] = "smooth"
        out["objects"].append(entry)
        keys["objects"].append(_instance_key(inst))
    return out, keys


class Exported(collections.namedtuple("Exported", "scene warnings mesh_users")):
    """What an export wrote: the scene dict, the warnings (each once, in order), and
    {mesh file: [names of the objects using it]}."""


def _mesh_users(out, keys):
    users = {}
    for obj, key in zip(out["objects"], keys["objects"]):
        users.setdefault(obj["file"], []).append(key.split("/")[0] if "/" in key else key)
    return users


def _dedupe_warnings(warnings):
    seen, out = set(), []
    for w in warnings:
        if w not in seen:
            seen.add(w)
            out.append(w)
    return out


def export_scene(scene, depsgraph, directory, name="scene.json", object_colors=None,
                 flat=False, size=None, image=None):
    """Writes ``directory/name`` and its PLY files for the scene as evaluated by
    ``depsgraph``. Returns an ``Exported``.

    object_colors: optional {object name: (r, g, b)} used as-is (0..1, Tessera values)
    instead of materials. flat: ambient 1 and no lights (a mask render)."""
    warnings = []
    out, keys = collect(scene, depsgraph, MeshStore(directory), warnings.append, object_colors,
                        flat, size, image)
    with open(os.path.join(directory, name), "w") as f:
        json.dump(out, f, indent=1)
    return Exported(out, _dedupe_warnings(warnings), _mesh_users(out, keys))


def _numbers(v):
    return [float(x) for x in v.split()] if isinstance(v, str) else [float(v)]


def reduce_keys(keys):
    """Drops keys that linear interpolation between their neighbours gives with the
    same bits, as Tessera computes it (v0 + (v1 - v0) * t, each rounded); keys are
    (frame, [numbers]) in frame order."""
    out = list(keys)
    i = 1
    while i + 1 < len(out):
        (f0, a), (f, v), (f1, b) = out[i - 1], out[i], out[i + 1]
        t = (f - f0) / (f1 - f0)
        if all(a[k] + (b[k] - a[k]) * t == v[k] for k in range(len(v))):
            del out[i]
        else:
            i += 1
    return out


def build_tracks(frames_values):
    """frames_values: [(tessera frame, {target: value as written})] in frame order.
    Returns the tracks (linear) of every target whose value changes."""
    tracks = []
    targets = list(frames_values[0][1])
    for target in targets:
        seq = [(f, vals[target]) for f, vals in frames_values if target in vals]
        if all(v == seq[0][1] for _, v in seq):
            continue
        keys = reduce_keys([(f, _numbers(v)) for f, v in seq])
        scalar = not isinstance(seq[0][1], str)
        tracks.append({"target": target, "keys": [
            {"frame": f, "value": (v[0] if scalar else fmt(v))} for f, v in keys]})
    return tracks


def _animated_values(out, keys):
    vals = {}
    cam = out.get("camera", {})
    for k in ("position", "look_at", "up", "fov"):
        if k in cam:
            vals["camera." + k] = cam[k]
    for i, o in enumerate(out["objects"]):
        vals[("objects", keys["objects"][i], "transform.matrix")] = o["transform"]["matrix"]
    for i, l in enumerate(out["lights"]):
        vals[("lights", keys["lights"][i], "position")] = l["position"]
        vals[("lights", keys["lights"][i], "color")] = l["color"]
    return vals


def export_animation(scene, goto, directory, name="scene.json", object_colors=None, flat=False,
                     frame_start=None, frame_end=None, size=None, image=None):
    """Writes an animated Tessera scene: Blender frames frame_start..frame_end
    (the scene's range by default) become Tessera frames 1..N. The static scene is the
    first frame; every changing camera vector, fov, object matrix or light becomes a
    linear track with a key on each frame it cannot be interpolated exactly.
    Changes in shape (a deforming mesh), in the set of objects, and materials are not
    animated: they are warned about. ``goto(frame)`` moves the scene to a Blender
    frame and returns the depsgraph evaluated there; the caller puts the scene back."""
    warnings = []
    warn = warnings.append
    store = MeshStore(directory)
    fs = scene.frame_start if frame_start is None else frame_start
    fe = scene.frame_end if frame_end is None else frame_end
    if fe < fs:
        raise ValueError("the frame range %d-%d is empty" % (fs, fe))
    frames_values = []
    first = first_keys = None
    reshaped = set()
    for bf in range(fs, fe + 1):
        depsgraph = goto(bf)
        out, keys = collect(scene, depsgraph, store, warn, object_colors, flat, size, image)
        if first is None:
            first, first_keys = out, keys
        elif keys != first_keys:
            warn("frame %d: objects or lights appear or disappear; only frame %d's are exported"
                 % (bf, fs))
            continue
        frames_values.append((bf - fs + 1, _animated_values(out, keys)))
        for i, o in enumerate(out["objects"]):
            if o["file"] != first["objects"][i]["file"]:
                reshaped.add(keys["objects"][i])
    tracks = []
    index = {("objects", k): i for i, k in enumerate(first_keys["objects"])}
    index.update({("lights", k): i for i, k in enumerate(first_keys["lights"])})
    for t in build_tracks(frames_values):
        target = t["target"]
        if isinstance(target, tuple):
            kind, key, field = target
            t["target"] = "%s[%d].%s" % (kind, index[(kind, key)], field)
        tracks.append(t)
    for key in sorted(reshaped):
        warn("%s changes shape during the animation: its first frame's shape is used" % key)
    first["animation"] = {"frames": fe - fs + 1, "fps": scene.render.fps / scene.render.fps_base,
                          "tracks": tracks}
    with open(os.path.join(directory, name), "w") as f:
        json.dump(first, f, indent=1)
    return Exported(first, _dedupe_warnings(warnings), _mesh_users(first, first_keys))
