"""glTF 2.0 animations and skins, evaluated: node world matrices at a time of a clip,
morph weights, and skin joint matrices.

Everything works on the JSON ``document`` and the decoded accessors of
:attr:`.scene.Scene.carried` (accessor index -> (values (count, width) in the
accessor's own dtype, record, role)); animation sampler inputs and outputs and
skins' inverse bind matrices are always among them.

The rules of the glTF 2.0 specification followed here (sections "Animations", "Skins",
"Transformations"):

- a node's local matrix is ``matrix`` or ``T * R * S`` (an animated node has no
  ``matrix``); its world matrix is its parent's world times its local matrix;
- a channel targets a node's ``translation``, ``rotation`` (unit quaternion, x y z w),
  ``scale`` or ``weights`` (one float per morph target of the node's mesh);
- samplers interpolate ``LINEAR`` (rotations by spherical linear interpolation
  along the shortest arc), ``STEP`` or ``CUBICSPLINE`` (per keyframe an
  in-tangent, a value and an out-tangent; Hermite between keyframes, tangents
  scaled by the interval's length); before the first keyframe and after the last
  the value is clamped to the first or last;
- a joint matrix is ``inverse(world(mesh node)) @ world(joint) @ inverseBindMatrix``
  so the skinned vertices stay in the mesh node's local space (identity inverse
  bind matrices when the skin has none).
"""

from __future__ import annotations

import numpy as np

from ..mesh import MeshError

# glTF component types of normalized integers and their divisor (the specification's
# "Accessor Data Types"): a signed value c maps to max(c / scale, -1), an unsigned one
# to c / scale (rotations and morph weights may be stored so).
_NORMALIZED_SCALE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_PATH_WIDTHS = {"translation": 3, "rotation": 4, "scale": 3}
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")


# --------------------------------------------------------------------------
# 1. Accessors and quaternions
# --------------------------------------------------------------------------

def accessor_floats(carried: dict, index: int) -> np.ndarray:
    """(count, width) float64 values of carried accessor ``index``, normalized
    integers mapped as the spec says."""
    if index not in carried:
        raise MeshError(f"accessor {index!r} is not among the animation and skin data read")
    values, record, _ = carried[index]
    values = np.asarray(values)
    if record.get("normalized"):
        scale = _NORMALIZED_SCALE[record["componentType"]]
        return np.maximum(values / scale, -1.0)
    return values.astype(np.float64)


def _index(value, count: int, what: str) -> int:
    """``value`` as an index into ``count`` items, else a MeshError "{what} {value}, which
    does not exist" (a bool, a string or a float is no index)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or not 0 <= value < count:
        raise MeshError(f"{what} {value!r:.40}, which does not exist")
    return int(value)


def keyframe_times(carried: dict, index, what: str) -> np.ndarray:
    """(k,) float64 keyframe times of a sampler's ``input`` accessor: finite and never
    decreasing (the spec asks for strictly increasing; repeated times, which some
    exporters write, sample as a step), else a MeshError naming ``what``."""
    times = accessor_floats(carried, index).ravel()
    if not np.isfinite(times).all():
        raise MeshError(f"{what} has keyframe times that are not finite numbers")
    if (np.diff(times) < 0).any():
        raise MeshError(f"{what} has keyframe times that are not increasing")
    return times


def skin_joints(skin: dict, number: int, nodes: int) -> np.ndarray:
    """(J,) int64 node indices of ``skin``'s joints (skin ``number`` of a document of
    ``nodes`` nodes), else a MeshError: none, or one that is not a node."""
    joints = skin.get("joints") if isinstance(skin, dict) else None
    if not isinstance(joints, list) or not joints:
        raise MeshError(f"skin {number} has no list of joints")
    for joint in joints:
        _index(joint, nodes, f"skin {number} names as a joint node")
    return np.asarray(joints, dtype=np.int64)


def quaternion_matrix(q) -> np.ndarray:
    """(3, 3) rotation of the quaternion ``q`` (x, y, z, w), normalised first
    (the identity for a zero quaternion)."""
    x, y, z, w = np.asarray(q, dtype=np.float64)
    norm = x * x + y * y + z * z + w * w
    if norm == 0.0:
        return np.eye(3)
    s = 2.0 / norm
    return np.array([
        [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)]])


def slerp(q0, q1, s: float) -> np.ndarray:
    """Spherical linear interpolation from unit quaternion ``q0`` to ``q1`` (x y z w)
    at ``s`` in [0, 1], along the shorter arc (q and -q are the same rotation);
    the result is normalised."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        # nearly parallel: sin(theta) ~ 0 would divide by noise; lerp is exact to ~1e-7
        out = q0 + s * (q1 - q0)
    else:
        theta = np.arccos(min(dot, 1.0))
        out = (np.sin((1.0 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)
    norm = np.linalg.norm(out)
    return out / norm if norm > 0 else out


def trs_matrix(translation=(0, 0, 0), rotation=(0, 0, 0, 1), scale=(1, 1, 1)) -> np.ndarray:
    """(4, 4) float64 ``T @ R @ S`` of a glTF node's translation, rotation (x y z w), scale."""
    matrix = np.eye(4)
    matrix[:3, :3] = quaternion_matrix(rotation) * np.asarray(scale, dtype=np.float64)[None, :]
    matrix[:3, 3] = translation
    return matrix


# --------------------------------------------------------------------------
# 2. Samplers
# --------------------------------------------------------------------------

def sample(times, values, time: float, interpolation: str = "LINEAR", *,
           rotation: bool = False) -> np.ndarray:
    """One animation sampler's value at ``time``.

    Parameters
    ----------
    times : (k,) float
        Keyframe times, seconds, increasing.
    values : (k, w) float, or (3k, w) for CUBICSPLINE
        The output per keyframe; for CUBICSPLINE in-tangent, value, out-tangent
        per keyframe, in that order (appendix "Interpolation").
    time : float
        Seconds; clamped to [times[0], times[-1]].
    interpolation : "LINEAR", "STEP" or "CUBICSPLINE"
    rotation : bool
        The values are quaternions: LINEAR slerps, and every result is normalised.

    Returns
    -------
    (w,) float64
    """
    times = np.asarray(times, dtype=np.float64).ravel()
    values = np.asarray(values, dtype=np.float64)
    k = len(times)
    if interpolation not in INTERPOLATIONS:
        raise MeshError(f"unknown animation interpolation {interpolation!r}")
    if not np.isfinite(time):
        raise MeshError(f"an animation time must be a finite number of seconds, got {time}")
    cubic = interpolation == "CUBICSPLINE"
    if k == 0 or len(values) != (3 * k if cubic else k):
        raise MeshError(f"an animation sampler has {k} keyframes but {len(values)} outputs")
    keys = values[1::3] if cubic else values
    if time <= times[0] or k == 1:
        out = keys[0]
    elif time >= times[-1]:
        out = keys[-1]
    else:
        i = int(np.searchsorted(times, time, side="right")) - 1
        dt = times[i + 1] - times[i]
        s = (time - times[i]) / dt if dt > 0 else 0.0
        if interpolation == "STEP":
            out = keys[i]
        elif interpolation == "LINEAR":
            out = (slerp(keys[i], keys[i + 1], s) if rotation
                   else (1.0 - s) * keys[i] + s * keys[i + 1])
        else:
            # Hermite basis; b = out-tangent of key i, a = in-tangent of key i + 1,
            # both per second, hence times the interval to become per unit s
            s2, s3 = s * s, s * s * s
            out_tangent, in_tangent = values[3 * i + 2], values[3 * (i + 1)]
            out = ((2 * s3 - 3 * s2 + 1) * keys[i] + (s3 - 2 * s2 + s) * dt * out_tangent
                   + (-2 * s3 + 3 * s2) * keys[i + 1] + (s3 - s2) * dt * in_tangent)
    out = np.array(out, dtype=np.float64)
    if rotation:
        norm = np.linalg.norm(out)
        out = out / norm if norm > 0 else np.array([0.0, 0.0, 0.0, 1.0])
    return out


def _animation(document: dict, clip: int) -> dict:
    animations = document.get("animations", ())
    if isinstance(clip, bool) or not isinstance(clip, (int, np.integer)) \
            or not 0 <= clip < len(animations):
        raise MeshError(f"animation {clip!r} does not exist ({len(animations)} in the file)")
    return animations[clip]


def clip_channels(document: dict, carried: dict, time: float, clip) -> dict:
    """``{(node, path): value}`` of every channel of animation ``clip`` at ``time``
    (path "translation" (3,), "rotation" (4,), "scale" (3,) or "weights" (T,));
    ``{}`` for ``clip`` None (the rest pose). Later channels win on a repeated target."""
    if clip is None:
        return {}
    animation = _animation(document, clip)
    samplers = animation.get("samplers", ())
    nodes = document.get("nodes", ())
    found = {}
    for number, channel in enumerate(animation.get("channels", ())):
        target = channel.get("target", {})
        node, path = target.get("node"), target.get("path")
        if node is None or path not in (*_PATH_WIDTHS, "weights"):
            continue        # no node (an extension's target) or pointer paths: nothing to pose
        _index(node, len(nodes), f"channel {number} of animation {clip} targets node")
        sampler = samplers[_index(channel.get("sampler"), len(samplers),
                                  f"channel {number} of animation {clip} uses sampler")]
        times = keyframe_times(carried, sampler["input"], f"animation {clip}")
        values = accessor_floats(carried, sampler["output"])
        interpolation = sampler.get("interpolation", "LINEAR")
        if path == "weights":
            # one scalar per target per keyframe (times 3 for cubic): regroup per keyframe
            per_key = 3 * len(times) if interpolation == "CUBICSPLINE" else len(times)
            if per_key == 0 or values.size % per_key:
                raise MeshError(f"a weights sampler has {values.size} outputs for "
                                f"{len(times)} keyframes")
            values = values.reshape(per_key, -1)
        elif values.shape[1] != _PATH_WIDTHS[path]:
            raise MeshError(f"a {path} sampler has outputs of {values.shape[1]} components")
        found[int(node), path] = sample(times, values, float(time), interpolation,
                                        rotation=path == "rotation")
    return found


# --------------------------------------------------------------------------
# 3. Node worlds, weights and joints
# --------------------------------------------------------------------------

def _parents(nodes: list) -> np.ndarray:
    parent = np.full(len(nodes), -1, dtype=np.int64)
    for index, node in enumerate(nodes):
        for child in node.get("children", ()):
            if isinstance(child, bool) or not isinstance(child, (int, np.integer)) \
                    or not 0 <= child < len(nodes) or parent[child] != -1 or child == index:
                raise MeshError(f"node {child!r:.40} is a child twice, of itself, or does "
                                "not exist")
            parent[child] = index
    return parent


def node_parents(document: dict) -> np.ndarray:
    """(N,) int64 each node's parent, -1 for a node no other has as a child
    (``MeshError`` on a node that is a child twice, of itself, or not there)."""
    return _parents(document.get("nodes", []))


def check_scene(document: dict, carried: dict) -> None:
    """MeshError (one sentence) unless what the poses and the writer evaluate is sound:
    the node tree (children that are nodes, each with one parent, no cycle), finite
    node transforms, every skin (joints that are nodes, one finite inverse bind
    matrix a joint), node and mesh ``weights`` (one a morph target) and every
    animation channel (a sampler and node that exist, finite increasing times,
    outputs matching them and, for ``weights``, the node's targets), sampled at its
    first keyframe.
    Called by :func:`lodserver.io.scene.load_scene`, so a hostile document is refused
    at upload, not at build."""
    worlds = node_worlds(document, carried)
    if not np.isfinite(worlds).all():
        raise MeshError("a node's transform is not finite")
    for number, skin in enumerate(document.get("skins", ())):
        joints = skin_joints(skin, number, len(worlds))
        if "inverseBindMatrices" in skin:
            flat = accessor_floats(carried, skin["inverseBindMatrices"])
            if flat.shape != (len(joints), 16):
                raise MeshError(f"skin {number} has {flat.shape[0]} inverse bind matrices "
                                f"for {len(joints)} joints")
            if not np.isfinite(flat).all():
                raise MeshError(f"skin {number} has inverse bind matrices that are not finite")
    nodes, meshes = document.get("nodes", ()), document.get("meshes", ())
    targets = {}        # node -> its mesh's morph target count, for nodes whose mesh has some
    for number, node in enumerate(nodes):
        if "mesh" in node:
            mesh = meshes[_index(node["mesh"], len(meshes), f"node {number} uses mesh")]
            count = max((len(p.get("targets") or ()) for p in mesh.get("primitives", ())),
                        default=0)
            for owner, weights in ((f"node {number}", node.get("weights")),
                                   (f"mesh {node['mesh']}", mesh.get("weights"))):
                if weights is None:
                    continue
                given = len(weights) if isinstance(weights, list) else "no list of"
                if given != count:
                    raise MeshError(f"{owner} has {given} morph weights for {count} targets")
            if count:
                targets[number] = count
    for clip in range(len(document.get("animations", ()))):
        first, _ = clip_range(document, carried, clip)
        for (node, path), value in clip_channels(document, carried, first, clip).items():
            # a weights channel of a node whose mesh has no targets moves nothing: ignored
            if path == "weights" and node in targets and len(value) != targets[node]:
                raise MeshError(f"animation {clip} gives node {node} {len(value)} morph "
                                f"weights for {targets[node]} targets")


def node_worlds(document: dict, carried: dict, time: float = 0.0, clip=None) -> np.ndarray:
    """(N, 4, 4) float64 world matrix of every node at ``time`` seconds of animation
    ``clip`` (an index into ``animations``; None: the rest pose, the nodes' own
    transforms). Nodes of no scene are placed by their own parents all the same."""
    nodes = document.get("nodes", [])
    channels = clip_channels(document, carried, time, clip)
    local = np.empty((len(nodes), 4, 4))
    for index, node in enumerate(nodes):
        if "matrix" in node:
            # a node with a matrix is never the target of an animation (section "Transformations")
            local[index] = np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
        else:
            local[index] = trs_matrix(
                channels.get((index, "translation"), node.get("translation", (0, 0, 0))),
                channels.get((index, "rotation"), node.get("rotation", (0, 0, 0, 1))),
                channels.get((index, "scale"), node.get("scale", (1, 1, 1))))
    parent = _parents(nodes)
    world = np.empty_like(local)
    done = np.zeros(len(nodes), dtype=bool)
    for index in range(len(nodes)):
        chain = []
        node = index
        while node != -1 and not done[node]:
            chain.append(node)
            node = parent[node]
            if len(chain) > len(nodes):
                raise MeshError("the node hierarchy has a cycle")
        for node in reversed(chain):
            up = parent[node]
            world[node] = local[node] if up == -1 else world[up] @ local[node]
            done[node] = True
    return world


def node_weights(document: dict, carried: dict, node: int, time: float = 0.0,
                 clip=None) -> np.ndarray:
    """(T,) float64 morph weights of ``node``'s mesh at ``time`` of ``clip``: the
    animated ``weights`` when a channel targets the node, else the node's
    ``weights``, else its mesh's, else zeros (T = the mesh's target count)."""
    record = document["nodes"][node]
    mesh = document["meshes"][record["mesh"]] if "mesh" in record else {}
    primitives = mesh.get("primitives", ())
    count = max((len(p.get("targets", ())) for p in primitives), default=0)
    weights = clip_channels(document, carried, time, clip).get((node, "weights"))
    if weights is None:
        weights = record.get("weights", mesh.get("weights", np.zeros(count)))
    weights = np.asarray(weights, dtype=np.float64).ravel()
    if len(weights) != count:
        raise MeshError(f"node {node} has {len(weights)} morph weights for {count} targets")
    return weights


def joint_matrices(document: dict, carried: dict, skin: int, mesh_node: int,
                   worlds: np.ndarray) -> np.ndarray:
    """(J, 4, 4) float64 joint matrices of ``skin`` for the mesh of node ``mesh_node``:
    ``inverse(worlds[mesh_node]) @ worlds[joint_j] @ inverseBindMatrix_j``, which
    take a bind-pose vertex in the mesh's local space to its skinned place in the
    same space (identity inverse bind matrices when the skin gives none)."""
    skins = document.get("skins", ())
    if not 0 <= skin < len(skins):
        raise MeshError(f"skin {skin!r} does not exist")
    joints = skin_joints(skins[skin], skin, len(worlds))
    if "inverseBindMatrices" in skins[skin]:
        flat = accessor_floats(carried, skins[skin]["inverseBindMatrices"])
        if flat.shape != (len(joints), 16):
            raise MeshError(f"skin {skin} has {flat.shape[0]} inverse bind matrices for "
                            f"{len(joints)} joints")
        if not np.isfinite(flat).all():
            raise MeshError(f"skin {skin} has inverse bind matrices that are not finite")
        inverse_bind = flat.reshape(-1, 4, 4).transpose(0, 2, 1)   # column-major
    else:
        inverse_bind = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
    return np.linalg.inv(worlds[mesh_node]) @ worlds[joints] @ inverse_bind


def clip_range(document: dict, carried: dict, clip: int) -> tuple[float, float]:
    """(first, last) keyframe time of animation ``clip`` over all its samplers, seconds."""
    animation = _animation(document, clip)
    first, last = np.inf, -np.inf
    for sampler in animation.get("samplers", ()):
        times = keyframe_times(carried, sampler["input"], f"animation {clip}")
        if times.size:
            first, last = min(first, float(times.min())), max(last, float(times.max()))
    return (first, last) if first <= last else (0.0, 0.0)


def sample_times(document: dict, carried: dict, count: int) -> list:
    """``count`` (clip, time) pairs spread over every animation: the clips share
    ``count`` as evenly as they can (the first ones take one more), and a clip's
    k times sit at the middles of k equal slices of its range, so a looping clip's
    first and last keyframes (often the same pose) are not both taken. ``[]``
    without animations; fewer clips than ``count`` are sampled when ``count`` is
    smaller than the number of clips (chosen evenly)."""
    clips = len(document.get("animations", ()))
    if clips == 0 or count <= 0:
        return []
    if count < clips:
        chosen = np.unique(np.linspace(0, clips - 1, count).round().astype(int))
        shares = {int(c): 1 for c in chosen}
    else:
        shares = {c: count // clips + (c < count % clips) for c in range(clips)}
    found = []
    for clip, k in shares.items():
        first, last = clip_range(document, carried, clip)
        found.extend((clip, first + (j + 0.5) / k * (last - first)) for j in range(k))
    return found
