"""The plain-Python broadcast_shapes agrees with torch.broadcast_shapes."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchslq._shapes import broadcast_shapes

dims = st.lists(st.sampled_from([1, 2, 3, 5]), min_size=0, max_size=4)


@settings(max_examples=300, deadline=None)
@given(st.lists(dims, min_size=1, max_size=4))
def test_broadcast_shapes_matches_torch(shapes):
    try:
        expected = torch.broadcast_shapes(*shapes)
    except RuntimeError:
        with pytest.raises(RuntimeError):
            broadcast_shapes(*shapes)
        return
    assert broadcast_shapes(*shapes) == expected
    assert isinstance(broadcast_shapes(*shapes), torch.Size)


def test_zero_size_dims_and_scalars():
    assert broadcast_shapes((0, 1), (1, 3)) == torch.broadcast_shapes((0, 1), (1, 3))
    assert broadcast_shapes((), ()) == torch.Size([])
    with pytest.raises(RuntimeError):
        broadcast_shapes((0,), (2,))
