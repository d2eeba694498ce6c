"""Unit tests of the pure-Python half of the exporter (no Blender needed):
python3 -m unittest discover -s clients/blender/tests -p 'test_*.py'"""

import array
import math
import os
import struct
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from types import SimpleNamespace  # noqa: E402

from tessera_blender import export, job  # noqa: E402


class Fov(unittest.TestCase):
    def test_auto_landscape_measures_width(self):
        # 36 mm across the 320 px width; Tessera wants the 240 px height.
        fov = export.camera_fov(50, 36, 24, "AUTO", 320, 240)
        self.assertAlmostEqual(math.tan(math.radians(fov) / 2), 18 / 50 * 240 / 320)

    def test_auto_portrait_lays_sensor_width_along_height(self):
        a = export.camera_fov(50, 36, 24, "AUTO", 320, 240)
        b = export.camera_fov(50, 36, 24, "AUTO", 240, 320)
        self.assertAlmostEqual(a, b)

    def test_vertical_uses_sensor_height(self):
        fov = export.camera_fov(50, 36, 24, "VERTICAL", 320, 240)
        self.assertAlmostEqual(fov, math.degrees(2 * math.atan(12 / 50)))

    def test_horizontal_portrait(self):
        fov = export.camera_fov(50, 36, 24, "HORIZONTAL", 240, 320)
        self.assertAlmostEqual(fov, math.degrees(2 * math.atan(18 / 50)))


class Axes(unittest.TestCase):
    def test_matrix_swaps_y_and_z(self):
        # Blender: rotate 90 degrees about Z (x -> y), translate (1, 2, 3).
        m = [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]
        a = export.matrix_to_tessera(m)
        # In Tessera axes: x -> z (Blender y is Tessera z); translation (1, 3, 2).
        self.assertEqual(a, [0, 0, -1, 1, 0, 1, 0, 3, 1, 0, 0, 2])

    def test_camera_identity_looks_down(self):
        # Blender's identity camera looks along -Z (down), up +Y.
        m = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]
        pos, look, up = export.camera_vectors(m)
        self.assertEqual(pos, (0, 5, 0))
        self.assertEqual(look, (0, 4, 0))
        self.assertEqual(up, (0, 0, 1))


class Ply(unittest.TestCase):
    def test_layout_and_dedupe(self):
        data = export.ply_bytes([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
        head, body = data.split(b"end_header\n")
        self.assertIn(b"binary_little_endian", head)
        self.assertEqual(len(body), 3 * 12 + 13)
        self.assertEqual(struct.unpack("<Biii", body[36:]), (3, 0, 1, 2))
        with tempfile.TemporaryDirectory() as d:
            s = export.MeshStore(d)
            self.assertEqual(s.add(data), s.add(bytes(data)))
            self.assertEqual(len(os.listdir(os.path.join(d, "meshes"))), 1)


class _Collection(list):
    def foreach_get(self, attr, out):
        """As Blender's: fills a typed array of the right length in place."""
        values = [c for item in self for c in getattr(item, attr)]
        assert len(values) == len(out)
        out[:] = array.array(out.typecode, values) if isinstance(out, array.array) else values


def _fake_mesh(verts, tris, smooth, split=None, auto_smooth=False, faces=None):
    """A mesh of the given loop triangles; its faces (polygons) are ``faces`` (vertex
    lists; by default the triangles themselves)."""
    faces = faces or tris
    starts = [sum(len(f) for f in faces[:i]) for i in range(len(faces))]
    loops = [SimpleNamespace(vertices=t, split_normals=[c for n in (split or [])[i * 3:i * 3 + 3] for c in n])
             for i, t in enumerate(tris)]
    return SimpleNamespace(
        calc_loop_triangles=lambda: None, calc_normals_split=lambda: None,
        use_auto_smooth=auto_smooth, has_custom_normals=False, edges=_Collection(),
        vertices=_Collection(SimpleNamespace(co=v) for v in verts),
        polygons=_Collection(SimpleNamespace(use_smooth=[s], loop_start=[starts[i]],
                                             loop_total=[len(faces[i])])
                             for i, s in enumerate(smooth)),
        loops=_Collection(SimpleNamespace(vertex_index=[v]) for f in faces for v in f),
        loop_triangles=_Collection(loops))


VERTS = [(0.5, -1.0, 2.0), (1.0, 0.0, 0.25), (0.0, 1.5, -3.0), (2.0, 2.0, 2.0)]
TRIS = [(0, 1, 2), (2, 1, 3)]


class MeshPly(unittest.TestCase):
    def test_flat_faces_give_the_mesh_as_it_is(self):
        data, shading = export.mesh_ply(_fake_mesh(VERTS, TRIS, [False, False]))
        self.assertEqual(shading, "flat")
        self.assertEqual(data, export.ply_bytes([export.to_tessera(v) for v in VERTS], TRIS))

    def test_smooth_faces_give_the_same_file_shaded_smooth(self):
        data, shading = export.mesh_ply(_fake_mesh(VERTS, TRIS, [True, True]))
        self.assertEqual(shading, "smooth")
        self.assertEqual(data, export.ply_bytes([export.to_tessera(v) for v in VERTS], TRIS))

    def test_a_flat_face_beside_smooth_ones_gets_vertices_of_its_own(self):
        n, a, b = (0.0, 0.0, 1.0), (0.0, 0.6, 0.8), (0.6, 0.0, 0.8)
        # Triangle 0 flat (its face normal at each corner); triangle 1 smooth.
        split = [n, n, n, a, b, a]
        data, shading = export.mesh_ply(_fake_mesh(VERTS, TRIS, [False, True], split))
        self.assertEqual(shading, "smooth")
        corners = [VERTS[0], VERTS[1], VERTS[2], VERTS[2], VERTS[1], VERTS[3]]
        self.assertEqual(data, export.ply_bytes([export.to_tessera(v) for v in corners],
                                                [(0, 1, 2), (3, 4, 5)]))

    def test_corners_with_the_same_normal_share_their_vertex(self):
        n, a = (0.0, 0.0, 1.0), (0.0, 0.6, 0.8)
        # Auto smooth: vertices 1 and 2 smooth across the edge, 0 and 3 on sharp edges.
        split = [n, a, a, a, a, n]
        data, _ = export.mesh_ply(_fake_mesh(VERTS, TRIS, [True, True], split, auto_smooth=True))
        self.assertEqual(data, export.ply_bytes([export.to_tessera(v) for v in VERTS], TRIS))


class MeshKey(unittest.TestCase):
    def test_equal_meshes_have_equal_keys_and_other_faces_other_keys(self):
        a = export.mesh_key(_fake_mesh(VERTS, TRIS, [False, False]))
        self.assertEqual(a, export.mesh_key(_fake_mesh(VERTS, TRIS, [False, False])))
        self.assertNotEqual(a, export.mesh_key(_fake_mesh(VERTS, TRIS, [True, True])))
        other = [(0, 1, 3), (0, 3, 2)]
        self.assertNotEqual(a, export.mesh_key(_fake_mesh(VERTS, other, [False, False])))
        moved = [VERTS[0], VERTS[1], VERTS[2], (2.0, 2.0, 2.5)]
        self.assertNotEqual(a, export.mesh_key(_fake_mesh(moved, TRIS, [False, False])))

    def test_meshes_split_by_corner_normals_are_not_keyed(self):
        self.assertIsNone(export.mesh_key(_fake_mesh(VERTS, TRIS, [False, True])))
        self.assertIsNone(export.mesh_key(_fake_mesh(VERTS, TRIS, [True, True], auto_smooth=True)))

    def test_sharp_edges_split_normals_without_auto_smooth_from_blender_4_1(self):
        mesh = _fake_mesh(VERTS, TRIS, [True, True])
        del mesh.use_auto_smooth                      # Blender 4.1 and later
        mesh.edges = _Collection([SimpleNamespace(use_edge_sharp=[False])])
        self.assertIsNotNone(export.mesh_key(mesh))
        mesh.edges.append(SimpleNamespace(use_edge_sharp=[True]))
        self.assertIsNone(export.mesh_key(mesh))

    def test_a_known_key_is_not_converted_again(self):
        with tempfile.TemporaryDirectory() as d:
            store = export.MeshStore(d)
            data, shading = export.mesh_ply(_fake_mesh(VERTS, TRIS, [False, False]))
            key = export.mesh_key(_fake_mesh(VERTS, TRIS, [False, False]))
            self.assertIsNone(store.known(key))
            written = store.add(data, key, shading)
            self.assertEqual(store.known(key), written)
            self.assertIsNone(store.known(None))


def _light(kind, colour=(1.0, 0.5, 0.25), energy=1000.0):
    return SimpleNamespace(name="L", data=SimpleNamespace(type=kind, color=colour, energy=energy))


# A light at Blender (1, 2, 3) pointing straight down (local -Z is world -Z).
_AT = [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]


class Rules(unittest.TestCase):
    def test_point_light_colour_times_watts_over_1000(self):
        warnings = []
        e = export.light_entry(_light("POINT", energy=500.0), _AT, warnings.append)
        self.assertEqual(e, {"position": "1.0 3.0 2.0", "color": "0.5 0.25 0.125"})
        self.assertEqual(warnings, [])

    def test_spot_and_area_become_point_lights_with_a_warning(self):
        for kind, words in (("SPOT", "spot cone"), ("AREA", "area light")):
            warnings = []
            e = export.light_entry(_light(kind), _AT, warnings.append)
            self.assertEqual(e["position"], "1.0 3.0 2.0")
            self.assertEqual(len(warnings), 1)
            self.assertIn(words, warnings[0])
            self.assertIn("used a point light", warnings[0])

    def test_sun_is_a_far_point_light_against_its_direction(self):
        warnings = []
        e = export.light_entry(_light("SUN", energy=2.0), _AT, warnings.append)
        # Pointing down (Blender -Z): the light sits up (Tessera +y), far away.
        self.assertEqual(e["position"], "-0.0 10000.0 -0.0")
        self.assertEqual(e["color"], "2.0 1.0 0.5")
        self.assertIn("sun light", warnings[0])

    def test_mirror_coefficient(self):
        self.assertEqual(export.mirror_coefficient(1.0, 0.5), 1.0)
        self.assertEqual(export.mirror_coefficient(0.3, 0.5), 0.3)
        self.assertEqual(export.mirror_coefficient(0.0, 0.02), 0.5)
        self.assertEqual(export.mirror_coefficient(0.0, 0.5), 0.0)

    def test_a_metal_reflects_and_is_not_lit_as_well(self):
        self.assertEqual(export.surface((0.8, 0.6, 0.4, 1.0), 1.0, 0.2), ((0.0, 0.0, 0.0), 1.0))
        rgb, special = export.surface((0.8, 0.6, 0.4, 1.0), 0.25, 0.2)
        self.assertEqual(special, 0.25)
        self.assertEqual(rgb, (0.8 * 0.75, 0.6 * 0.75, 0.4 * 0.75))
        self.assertEqual(export.surface((0.8, 0.6, 0.4), 0.0, 0.5), ((0.8, 0.6, 0.4), 0.0))

    def test_colours_are_encoded_as_srgb(self):
        self.assertEqual(export.linear_to_srgb(0.0), 0.0)
        self.assertAlmostEqual(export.linear_to_srgb(1.0), 1.0)
        self.assertAlmostEqual(export.linear_to_srgb(0.214), 0.5, places=3)

    def test_image_settings_take_aa_and_depth(self):
        self.assertEqual(export.image_settings((320, 240), {"aa": 3, "max_depth": 4}),
                         {"width": 320, "height": 240, "aa": 3, "max_depth": 4})
        self.assertEqual(export.image_settings((8, 6)),
                         {"width": 8, "height": 6, "aa": 1, "max_depth": 10})


class Animation(unittest.TestCase):
    def test_keys_interpolated_exactly_are_dropped(self):
        keys = [(1, [0.0]), (2, [0.5]), (3, [1.0]), (4, [3.0])]
        self.assertEqual(export.reduce_keys(keys), [(1, [0.0]), (3, [1.0]), (4, [3.0])])

    def test_tracks_only_for_what_changes(self):
        tracks = export.build_tracks([(1, {"a": "0 0 0", "b": 1.0}), (2, {"a": "0 0 0", "b": 2.0})])
        self.assertEqual(tracks, [{"target": "b", "keys": [{"frame": 1, "value": 1.0},
                                                           {"frame": 2, "value": 2.0}]}])


class Job(unittest.TestCase):
    def test_errors_are_one_line(self):
        self.assertEqual(job.one_line("\n  refused: too big\n  details\n"), "refused: too big")
        self.assertEqual(job.one_line(""), "failed")

    def test_a_file_named_by_its_hash_is_named_by_its_objects(self):
        j = job.RenderJob(job.Settings(), "s.json", "out",
                          mesh_names={"meshes/7081647b260b32ce.ply": ["Monkey", "Twin"]})
        text = j._name_files("sha256:7081647b260b32ce" + "0" * 48 + " (75487 bytes) is over")
        self.assertEqual(text, "the mesh of Monkey, Twin (meshes/7081647b260b32ce.ply) (75487 bytes) is over")

    def test_a_missing_tessera_command_is_one_error(self):
        with tempfile.TemporaryDirectory() as d:
            j = job.RenderJob(job.Settings(tessera_path=os.path.join(d, "nope")), "s.json", d)
            with self.assertRaises(job.JobError) as e:
                j.run()
            self.assertIn("cannot run", str(e.exception))


if __name__ == "__main__":
    unittest.main()
