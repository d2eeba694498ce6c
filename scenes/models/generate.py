#!/usr/bin/env python3
"""Writes the mesh files of the example scenes, byte for byte the same on every run.

    python3 scenes/models/generate.py      # from the checkout, or from this directory

- knot.obj: a (2, 3) torus knot (a trefoil) as a tube of 144 x 12 quads, with the
  tube's exact normals as `vn` lines, for smooth shading.
- icosphere.obj: a unit icosahedron subdivided twice (320 triangles), vertices shared
  and no normals: smooth shading computes them from the faces.
- gem.ply: a cut gem of 8-fold symmetry (an octagonal table, crown, girdle and
  pavilion), binary little-endian, its table one 8-sided face.

Only the standard library is used; numbers are written with 5 decimals.
"""

import math
import os
import struct

HERE = os.path.dirname(os.path.abspath(__file__))


def fmt(x):
    s = f"{x:.5f}"
    return "0.00000" if s == "-0.00000" else s


def norm(v):
    length = math.sqrt(sum(c * c for c in v))
    return [c / length for c in v]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def knot(segments=144, sides=12, tube=0.38):
    """The torus knot r = 2 + cos 3t, (r cos 2t, r sin 2t, -sin 3t), its axis along y
    once written (x, z, y), as a tube of radius `tube`."""

    def point(t):
        r = 2.0 + math.cos(3 * t)
        return [r * math.cos(2 * t), -math.sin(3 * t), r * math.sin(2 * t)]

    def tangent(t):
        r = 2.0 + math.cos(3 * t)
        dr = -3 * math.sin(3 * t)
        return norm([dr * math.cos(2 * t) - 2 * r * math.sin(2 * t),
                     -3 * math.cos(3 * t),
                     dr * math.sin(2 * t) + 2 * r * math.cos(2 * t)])

    vertices, normals = [], []
    for i in range(segments):
        t = 2 * math.pi * i / segments
        c, d = point(t), tangent(t)
        # A frame across the tube that closes on itself: u from the tangent and the
        # position (never parallel on this curve), v completing it.
        u = norm(cross(d, c))
        v = cross(d, u)
        for j in range(sides):
            a = 2 * math.pi * j / sides
            n = [math.cos(a) * u[k] + math.sin(a) * v[k] for k in range(3)]
            vertices.append([c[k] + tube * n[k] for k in range(3)])
            normals.append(n)
    lines = ["# a (2, 3) torus knot: %d x %d quads with their normals" % (segments, sides)]
    lines += ["v %s %s %s" % tuple(fmt(x) for x in p) for p in vertices]
    lines += ["vn %s %s %s" % tuple(fmt(x) for x in n) for n in normals]
    for i in range(segments):
        for j in range(sides):
            quad = [i * sides + j, ((i + 1) % segments) * sides + j,
                    ((i + 1) % segments) * sides + (j + 1) % sides, i * sides + (j + 1) % sides]
            lines.append("f " + " ".join("%d//%d" % (q + 1, q + 1) for q in quad))
    return "\n".join(lines) + "\n"


def icosphere(levels=2):
    g = (1 + math.sqrt(5)) / 2
    vertices = [norm(v) for v in [
        [-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0],
        [0, -1, g], [0, 1, g], [0, -1, -g], [0, 1, -g],
        [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]]]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
             [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
             [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
             [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    for _ in range(levels):
        middle = {}

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in middle:
                vertices.append(norm([(vertices[a][k] + vertices[b][k]) / 2 for k in range(3)]))
                middle[key] = len(vertices) - 1
            return middle[key]

        refined = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            refined += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = refined
    lines = ["# an icosphere: %d triangles, no normals" % len(faces)]
    lines += ["v %s %s %s" % tuple(fmt(x) for x in p) for p in vertices]
    lines += ["f %d %d %d" % tuple(i + 1 for i in f) for f in faces]
    return "\n".join(lines) + "\n"


def gem(n=8):
    """A cut gem of radius 1 at the girdle: an n-sided table at y = 0.42, star, bezel
    (kite) and upper girdle facets on the crown, a girdle band, and a pavilion down to
    the culet at y = -0.9."""
    vertices = []

    def ring(radius, y, turn):
        start = len(vertices)
        for i in range(n):
            a = 2 * math.pi * (i + turn) / n
            vertices.append([radius * math.cos(a), y, radius * math.sin(a)])
        return lambda i: start + i % n

    table = ring(0.56, 0.42, 0.0)
    star = ring(0.8, 0.27, 0.5)
    girdle = ring(1.0, 0.05, 0.0)
    lower = ring(1.0, -0.05, 0.0)
    vertices.append([0.0, -0.9, 0.0])
    culet = len(vertices) - 1
    faces = [[table(i) for i in range(n)]]
    for i in range(n):
        faces.append([table(i), table(i + 1), star(i)])
        faces.append([table(i + 1), star(i), girdle(i + 1), star(i + 1)])
        faces.append([girdle(i), girdle(i + 1), star(i)])
        faces.append([girdle(i), girdle(i + 1), lower(i + 1), lower(i)])
        faces.append([lower(i), lower(i + 1), culet])
    header = ("ply\nformat binary_little_endian 1.0\ncomment a cut gem, %d-fold\n"
              "element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
              "element face %d\nproperty list uchar int vertex_indices\nend_header\n"
              % (n, len(vertices), len(faces)))
    body = b"".join(struct.pack("<3f", *v) for v in vertices)
    body += b"".join(struct.pack("<B%di" % len(f), len(f), *f) for f in faces)
    return header.encode("ascii") + body


def main():
    files = {
        "knot.obj": knot().encode("ascii"),
        "icosphere.obj": icosphere().encode("ascii"),
        "gem.ply": gem(),
    }
    for name, data in files.items():
        with open(os.path.join(HERE, name), "wb") as f:
            f.write(data)
        print("%s: %d bytes" % (name, len(data)))


if __name__ == "__main__":
    main()
