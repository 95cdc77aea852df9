"""The descriptor matcher of the Rust core against a numpy brute-force reference."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from dhptam import _core
from dhptam.errors import InputError


def _reference(
    q: npt.NDArray, t: npt.NDArray, max_distance: float, ratio: float, mutual: bool
) -> list[tuple[int, int]]:
    if q.dtype == np.uint8:
        bits = np.unpackbits(q[:, None, :] ^ t[None, :, :], axis=2)
        d = bits.sum(axis=2).astype(np.float64)
    else:
        d = np.linalg.norm(q[:, None, :].astype(np.float64) - t[None, :, :], axis=2)
    out = []
    for i in range(len(q)):
        order = np.argsort(d[i], kind="stable")
        j = int(order[0])
        second = d[i, order[1]] if len(order) > 1 else np.inf
        if d[i, j] > max_distance or (ratio < 1.0 and not d[i, j] < ratio * second):
            continue
        if mutual and int(np.argmin(d[:, j])) != i:
            continue
        out.append((i, j))
    return out


def _unit(rng: np.random.Generator, n: int, dim: int) -> npt.NDArray[np.float32]:
    x = rng.normal(size=(n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.mark.parametrize("mutual", [True, False])
@pytest.mark.parametrize("ratio", [0.8, 1.0])
def test_float_matches_equal_the_reference(mutual: bool, ratio: float) -> None:
    rng = np.random.default_rng(4)
    train = _unit(rng, 300, 128)
    query = train[rng.permutation(300)[:200]] + rng.normal(scale=0.08, size=(200, 128)).astype(np.float32)
    query = np.ascontiguousarray(query / np.linalg.norm(query, axis=1, keepdims=True), dtype=np.float32)
    pairs, dist = _core.match_descriptors(query, train, 1.0, ratio, mutual)
    assert [tuple(p) for p in pairs.tolist()] == _reference(query, train, 1.0, ratio, mutual)
    assert len(pairs) > 150
    np.testing.assert_allclose(
        dist, np.linalg.norm(query[pairs[:, 0]] - train[pairs[:, 1]], axis=1), atol=1e-5
    )


def test_binary_matches_equal_the_reference() -> None:
    rng = np.random.default_rng(5)
    train = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    query = train.copy()
    flips = (
        rng.integers(0, 256, size=query.shape, dtype=np.uint8)
        & rng.integers(0, 256, size=query.shape, dtype=np.uint8)
        & rng.integers(0, 256, size=query.shape, dtype=np.uint8)
    )
    query ^= flips
    pairs, dist = _core.match_descriptors(query, train, 80.0, 0.9, True)
    assert [tuple(p) for p in pairs.tolist()] == _reference(query, train, 80.0, 0.9, True)
    assert len(pairs) > 150
    assert dist.dtype == np.float32


def test_descriptors_are_read_in_place_and_bad_arrays_are_named() -> None:
    d = _unit(np.random.default_rng(0), 10, 64)
    assert _core._buffer_address(d) == d.__array_interface__["data"][0]
    with pytest.raises(InputError, match="query"):
        _core.match_descriptors(d.astype(np.float64), d, 1.0)
    with pytest.raises(InputError, match="non-contiguous"):
        _core.match_descriptors(d[:, ::2], d[:, ::2], 1.0)
    with pytest.raises(InputError, match="train descriptors"):
        _core.match_descriptors(d, np.zeros((3, 32), np.uint8), 1.0)
