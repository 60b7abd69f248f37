"""Scenes: a glTF document kept whole, each of its meshes a part with its own levels.

The stage between the progressive mesh and the service: which uploads are
scenes and reading them (``load.py``), one triangle budget over the parts
(``budget.py``), building the parts (``build.py``), the stored asset
(``asset.py``, ``artefact.py``) and the scene written back as GLB with the
parts at their levels (``write.py``). Reading and writing the glTF document
itself is ``io`` (``io/scene.py``, ``io/scene_glb.py``).
"""
