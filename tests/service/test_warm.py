"""The warm-up compiles what an upload runs: after it, a real build compiles nothing.

numba types a read-only array apart from a writable one, so a kernel called
with both is compiled twice; the parse workers send meshes back through
multiprocessing's pickle (protocol 4), which used to bring them back writable
while the warm-up's were read-only. The check runs in a fresh process, so
kernels compiled by other tests in this one cannot hide a miss.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# In the child: every kernel's signatures after the warm-up, then after an upload's
# builds (the sample with its UVs, and a Loop-subdivided copy with normals past the
# partitioned run's size, both through multiprocessing's pickle); what is new.
CHILD = r"""
import json, sys
import numpy as np
from multiprocessing.reduction import ForkingPickler
from numba.core.registry import CPUDispatcher
import trimesh
from lodserver.build import build
from lodserver.io import load_mesh
from lodserver.mesh import Attributes, Mesh
from lodserver.scene.build import build_asset
from lodserver.service.warm import warm_up

def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("lodserver"):
            for value in list(vars(module).values()):
                if isinstance(value, CPUDispatcher):
                    key = f"{value.py_func.__module__}.{value.py_func.__qualname__}"
                    found[key] = {str(s) for s in value.signatures}
    return found

warm_up()
before = signatures()
sample = sys.argv[1]
mesh, _ = load_mesh(sample, root=sample.rsplit("/", 1)[0])
positions, faces = trimesh.remesh.subdivide_loop(mesh.positions, mesh.faces, iterations=3)
normals = trimesh.Trimesh(positions, faces, process=False).vertex_normals
large = Mesh(positions, faces, Attributes((("NORMAL", 3),), normals, faces))
for upload in (mesh, large):
    upload = ForkingPickler.loads(ForkingPickler.dumps(upload))
    asset = build_asset(upload, build=build, options={})
    pm = asset.parts[0].pm
    pm.at(pm.base_vertices)
after = signatures()
new = {name: sorted(sigs - before.get(name, set())) for name, sigs in after.items()
       if sigs - before.get(name, set())}
print(json.dumps({"new": new, "vertices": int(large.vertex_count)}))
"""


def test_after_the_warm_up_an_uploads_build_compiles_nothing(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", CHILD, str(ROOT / "tests/data/spot.obj")],
                          capture_output=True, text=True, env=env, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    from lodserver.simplify.parts import PARALLEL_MIN_VERTICES
    assert found["vertices"] >= PARALLEL_MIN_VERTICES    # the partitioned run was built
    assert found["new"] == {}, "compiled after the warm-up: " + json.dumps(found["new"])


def test_an_unpickled_mesh_keeps_its_arrays_read_only():
    from multiprocessing.reduction import ForkingPickler

    import numpy as np

    from lodserver.mesh import Attributes, Mesh

    faces = np.array([[0, 1, 2]])
    mesh = Mesh(np.eye(3), faces, Attributes((("TEXCOORD_0", 2),), np.zeros((3, 2)), faces),
                face_material=None)
    back = ForkingPickler.loads(ForkingPickler.dumps(mesh))
    for array in (back.positions, back.faces, back.attributes.values, back.attributes.corners):
        assert not array.flags.writeable
    assert np.array_equal(back.positions, mesh.positions)
