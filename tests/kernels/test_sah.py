"""SAH helpers (MacDonald & Booth 1990): ``kernels/sah.py``."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from rayaccel.kernels.sah import (
    box_half_area,
    box_half_area_py,
    node_half_area,
    node_half_area_py,
    sah_split_cost,
    sah_split_cost_py,
    sah_split_cost_scaled,
    sah_split_cost_scaled_py,
    union_half_area,
    union_half_area_py,
)

coord = st.floats(-1e3, 1e3, allow_nan=False, width=32)


def test_half_area_of_a_box_by_hand():
    # 1 x 2 x 3: xy + yz + zx = 2 + 6 + 3.
    assert box_half_area_py(0.0, 0.0, 0.0, 1.0, 2.0, 3.0) == 11.0
    assert box_half_area(np.float32(0), np.float32(0), np.float32(0),
                         np.float32(1), np.float32(2), np.float32(3)) == 11.0
    # Flat and point boxes have (half) area 0 or the area of their face.
    assert box_half_area_py(1.0, 1.0, 1.0, 1.0, 1.0, 1.0) == 0.0
    assert box_half_area_py(0.0, 0.0, 5.0, 2.0, 3.0, 5.0) == 6.0


@given(st.lists(coord, min_size=12, max_size=12))
def test_row_forms_agree_with_the_scalar_form(values):
    """Same values; compiled forms may fuse a multiply-add (``contract``), so to rounding."""
    a = np.array(values, dtype=np.float32).reshape(2, 2, 3)
    lo = np.minimum(a[:, 0], a[:, 1])
    hi = np.maximum(a[:, 0], a[:, 1])
    for i in range(2):
        expected = box_half_area_py(*lo[i], *hi[i])
        assert node_half_area_py(lo, hi, i) == expected
        assert node_half_area(lo, hi, i) == pytest.approx(expected, rel=1e-12)
    u_lo = np.minimum(lo[0], lo[1])
    u_hi = np.maximum(hi[0], hi[1])
    union = box_half_area_py(*u_lo, *u_hi)
    assert union_half_area_py(lo, hi, 0, 1) == union
    assert union_half_area(lo, hi, 1, 0) == pytest.approx(union, rel=1e-12)
    assert union >= max(node_half_area_py(lo, hi, 0), node_half_area_py(lo, hi, 1))


def test_area_is_float64_from_float32_extents():
    # 2^24 + 1 is not a float32, but the extent of [1, 2^24 + 2] is exact in float64.
    lo = np.float32(1.0)
    hi = np.float32(2.0**24 + 2)
    area = box_half_area(lo, lo, lo, hi, lo + np.float32(1), lo + np.float32(1))
    assert area == 2 * (2.0**24 + 1) + 1


def test_split_cost_formula():
    # C_trav + C_prim (A_L N_L + A_R N_R) / A.
    assert sah_split_cost_py(1.0, 2.0, 3.0, 4, 5.0, 6, 0.25) == 1.0 + 2.0 * (12 + 30) * 0.25
    assert sah_split_cost(1.0, 2.0, 3.0, 4, 5.0, 6, 0.25) == 22.0
    # A flat node (inv_area 0) costs only the traversal step.
    assert sah_split_cost(1.5, 1.0, 3.0, 4, 5.0, 6, 0.0) == 1.5


def test_scaled_split_cost_folds_the_per_node_factor():
    # C_trav + (C_prim / A)(A_L N_L + A_R N_R), the factor computed once per node.
    assert sah_split_cost_scaled_py(1.0, 0.5, 3.0, 4, 5.0, 6) == 1.0 + 0.5 * 42
    assert sah_split_cost_scaled(1.0, 0.5, 3.0, 4, 5.0, 6) == 22.0
    # With C_prim = 1 both forms are the same products in another order.
    assert sah_split_cost_scaled_py(1.0, 1.0 * 0.1, 3.0, 4, 5.0, 6) == sah_split_cost_py(
        1.0, 1.0, 3.0, 4, 5.0, 6, 0.1
    )
