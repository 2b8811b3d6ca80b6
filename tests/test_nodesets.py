"""Node sets against a brute-force reference written with explicit loops over a tiny grid."""

import numpy as np
import pytest

from pixmuscle.errors import InputError
from pixmuscle.model.nodesets import GEOMETRIC_SETS, compute_node_sets, index_volume
from pixmuscle.model.tissues import BONE, NODE_TISSUES


def brute_force_sets(labels, masks=None):
    """Reference: loops over every voxel and its 6 face neighbours (fine for a tiny volume)."""
    I, J, K = labels.shape
    nodes = [(i, j, k) for i in range(I) for j in range(J) for k in range(K) if labels[i, j, k] in NODE_TISSUES]
    index = {p: n for n, p in enumerate(nodes)}
    sets = {name: set() for name in GEOMETRIC_SETS}
    for axis, name in enumerate("xyz"):
        lo = min(p[axis] for p in nodes)
        hi = max(p[axis] for p in nodes)
        sets[f"{name}_min"] = {index[p] for p in nodes if p[axis] == lo}
        sets[f"{name}_max"] = {index[p] for p in nodes if p[axis] == hi}
    for p in nodes:
        for axis in range(3):
            for step in (-1, 1):
                q = list(p)
                q[axis] += step
                inside = 0 <= q[0] < I and 0 <= q[1] < J and 0 <= q[2] < K
                if inside and labels[tuple(q)] == BONE:
                    sets["bone_surface"].add(index[p])
                if not inside or (labels[tuple(q)] not in NODE_TISSUES and labels[tuple(q)] != BONE):
                    sets["outer_surface"].add(index[p])
    for name, m in (masks or {}).items():
        sets[name] = {index[p] for p in nodes if m[p]}
    return np.array(nodes, dtype=np.int64).reshape(-1, 3), sets


def check_against_reference(labels, masks=None):
    ijk, ref = brute_force_sets(labels, masks)
    got = compute_node_sets(ijk, labels.shape, labels, masks)
    assert set(got) == set(ref)
    for name in ref:
        assert got[name].dtype == np.int64
        assert np.all(np.diff(got[name]) > 0), name
        assert set(got[name].tolist()) == ref[name], name


def test_hand_checkable_volume():
    # 4×4×3: muscle block with one bone voxel inside and one background hole on the top slice
    labels = np.ones((4, 4, 3), dtype=np.int16)
    labels[1, 1, 1] = BONE
    labels[2, 2, 2] = 0
    labels[3, 0, 0] = 3
    ijk, ref = brute_force_sets(labels)
    # hand check of the brute force itself: the 6 face neighbours of the bone voxel
    bone_nb = {(0, 1, 1), (2, 1, 1), (1, 0, 1), (1, 2, 1), (1, 1, 0), (1, 1, 2)}
    idx = {tuple(p): n for n, p in enumerate(ijk.tolist())}
    assert ref["bone_surface"] == {idx[p] for p in bone_nb}
    # in a 4×4×3 block every node is on the box surface except (1..2, 1..2, 1); of those,
    # (1,1,1) is bone and (1,2,1), (2,1,1) touch nothing empty; (2,2,1) touches the hole above
    interior = {idx[(1, 2, 1)], idx[(2, 1, 1)]}
    assert ref["outer_surface"] == set(range(len(ijk))) - interior
    check_against_reference(labels)


@pytest.mark.parametrize("seed", range(5))
def test_random_volumes(seed):
    rng = np.random.default_rng(seed)
    labels = rng.choice([0, 1, 2, 3, 4], p=[0.2, 0.35, 0.15, 0.15, 0.15], size=(5, 6, 4)).astype(np.int16)
    masks = {"tendon": rng.random((5, 6, 4)) < 0.3}
    check_against_reference(labels, masks)


def test_bone_mask_equals_labels():
    rng = np.random.default_rng(7)
    labels = rng.choice([0, 1, 4], size=(4, 5, 3))
    ijk = np.argwhere(labels == 1)
    a = compute_node_sets(ijk, labels.shape, labels)
    b = compute_node_sets(ijk, labels.shape, labels == BONE)
    c = compute_node_sets(ijk, labels.shape, None)
    for k in a:
        assert np.array_equal(a[k], b[k])
    assert c["bone_surface"].size == 0


def test_index_volume_and_errors():
    ijk = np.array([[0, 0, 0], [1, 2, 0]])
    vol = index_volume(ijk, (2, 3, 1), pad=1)
    assert vol.shape == (4, 5, 3)
    assert vol[1, 1, 1] == 0 and vol[2, 3, 1] == 1 and (vol >= 0).sum() == 2
    with pytest.raises(InputError, match="share a voxel"):
        index_volume(np.array([[0, 0, 0], [0, 0, 0]]), (2, 2, 2))
    with pytest.raises(InputError, match="outside the grid"):
        compute_node_sets(np.array([[2, 0, 0]]), (2, 2, 2))
    with pytest.raises(InputError, match="clashes"):
        compute_node_sets(ijk, (2, 3, 1), None, {"z_min": np.ones((2, 3, 1), bool)})
    with pytest.raises(InputError, match="expected shape"):
        compute_node_sets(ijk, (2, 3, 1), None, {"m": np.ones((2, 3, 2), bool)})
    with pytest.raises(InputError, match="bone voxel"):
        compute_node_sets(ijk, (2, 3, 1), np.ones((2, 3, 1), bool))
