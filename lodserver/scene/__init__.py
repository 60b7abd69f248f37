"""Scenes: a glTF document kept whole, each of its meshes a part with its own levels.

The stage between the progressive mesh and the service. Every stored asset is
a scene of parts (``asset.py``: a single mesh is the scene of one part without
a document). Here: which uploads are scenes and reading them (``load.py``), one
triangle budget over the parts (``budget.py``), building the parts
(``build.py``), the stored asset as one artefact (``artefact.py``), the scene
written back as GLB with its parts at their levels (``write.py``) or, by the
pipeline, as chains (``export.py``). Reading and writing the glTF document
itself is ``io`` (``io/scene.py``, ``io/scene_glb.py``).
"""
