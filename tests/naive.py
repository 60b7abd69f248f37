"""Slow, obviously right reference versions that the compiled kernels are checked against."""

from __future__ import annotations

from collections import Counter, defaultdict

import numpy as np


def plane_error(positions, faces, vertex, point):
    """Sum over the faces at ``vertex`` of area x squared distance from ``point`` to the face plane."""
    total = 0.0
    for face in faces:
        if vertex not in face:
            continue
        a, b, c = (np.asarray(positions[i], float) for i in face)
        normal = np.cross(b - a, c - a)
        double_area = np.linalg.norm(normal)
        if double_area == 0:
            continue
        distance = np.dot(normal / double_area, np.asarray(point) - a)
        total += 0.5 * double_area * distance * distance
    return total


def edge_face_counts(faces):
    """{(min, max): number of faces using that edge}."""
    counts = Counter()
    for face in faces:
        for k in range(3):
            a, b = int(face[k]), int(face[(k + 1) % 3])
            counts[(min(a, b), max(a, b))] += 1
    return counts


def fans(faces, n):
    """Edge-connected fans around each vertex, by flood fill over its faces."""
    around = defaultdict(list)
    for f, face in enumerate(faces):
        for v in face:
            around[int(v)].append(f)
    out = np.zeros(n, dtype=np.int64)
    for v, fs in around.items():
        unseen = set(fs)
        while unseen:
            out[v] += 1
            stack = [unseen.pop()]
            while stack:
                f = stack.pop()
                link = set(int(x) for x in faces[f]) - {v}
                for g in list(unseen):
                    if link & (set(int(x) for x in faces[g]) - {v}):
                        unseen.remove(g)
                        stack.append(g)
    return out
