"""Unit tests of the pure-Python half of the exporter (no Blender needed):
python3 -m unittest discover -s clients/blender/tests -p 'test_*.py'"""

import math
import os
import struct
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from tessera_blender import export  # noqa: E402


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


if __name__ == "__main__":
    unittest.main()
