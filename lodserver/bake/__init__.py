"""Far levels made by merging parts and baking their look (issue 28).

Where edge collapse stops above a level's face budget, :func:`level.merged_level`
remeshes the whole surface by vertex clustering (``simplify.cluster``) to
within 10% of the budget, then gives it an atlas (``atlas.py``) whose textures
are sampled from the full-detail surface (``surface.py``, ``textures.py``,
``normalmap.py``): one primitive, one material.
"""
