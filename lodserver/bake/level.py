"""A far level made by merging: the whole surface clustered to a face budget.

``merged_level(full, budget)`` is what ``--reach merge`` draws where edge
collapse stops above the budget: vertex clustering of the full-detail mesh
(which joins parts and closes gaps smaller than a cell) on the continuous
cell size that lands within :data:`REACH_WINDOW` of the budget
(``simplify.cluster.cluster_within``).
"""

from __future__ import annotations

from ..mesh import Mesh
from ..simplify.cluster import cluster_within

# How far a merged level may land from its face budget (a fraction of it).
REACH_WINDOW = 0.1


def merged_level(full: Mesh, budget: int) -> Mesh:
    """``full`` remeshed by vertex clustering to ``budget`` faces (within
    :data:`REACH_WINDOW` where the grid allows it): positions (k, 3), faces (f, 3)."""
    return cluster_within(Mesh(full.positions, full.faces), budget, REACH_WINDOW)
