"""The native linearizer's gather index: entry (a, b) of every assigned block takes base + coef[a, b]."""

import numpy as np
import pytest

from gtsam_schwarz.linearization.native_kernels import BlockPattern


def _reference(P: BlockPattern, assignments, fill: int) -> np.ndarray:
    """The index entry by entry, from the pattern's dof-level positions."""
    src = np.full(P.nnz, fill, dtype=np.int64)
    for rows, cols, base, coef in assignments:
        dr, dc = coef.shape
        r = (P.offsets[rows][:, None, None] + np.arange(dr)[None, :, None]) + 0 * np.arange(dc)[None, None, :]
        c = (P.offsets[cols][:, None, None] + np.arange(dc)[None, None, :]) + 0 * np.arange(dr)[None, :, None]
        src[P.entry_positions(r.ravel(), c.ravel())] = (np.asarray(base)[:, None, None] + coef[None]).ravel()
    return src


@pytest.mark.parametrize("bsr_max", [0, 10**9])
@pytest.mark.parametrize("dims", [[3] * 40, [6] * 25, [3, 6] * 15])
@pytest.mark.parametrize("all_blocks", [True, False])
def test_source_index_is_the_entrywise_assignment(monkeypatch, dims, all_blocks, bsr_max):
    """Uniform (laid out by BSR→CSR, or scattered above BSR_INDEX_MAX) and mixed block sizes, every
    block assigned or some left to ``fill``, int32 and int64: the same index as writing every entry at
    its CSR position."""
    from gtsam_schwarz.linearization import native_kernels
    monkeypatch.setattr(native_kernels, "BSR_INDEX_MAX", bsr_max)
    rng = np.random.default_rng(len(dims))
    dims = np.asarray(dims)
    nv = len(dims)
    u = rng.integers(0, nv, 60)
    v = rng.integers(0, nv, 60)
    keep = u != v
    u, v = u[keep], v[keep]
    P = BlockPattern(dims, np.r_[u, np.arange(nv)], np.r_[v, np.arange(nv)])
    pairs = np.unique(np.stack([np.minimum(u, v), np.maximum(u, v)], 1), axis=0)
    if not all_blocks:
        pairs = pairs[::2]
    assignments = []
    size = 0
    for d_lo in np.unique(dims):   # one assignment per (row dim, col dim): coef's shape is fixed
        for d_hi in np.unique(dims):
            sel = (dims[pairs[:, 0]] == d_lo) & (dims[pairs[:, 1]] == d_hi)
            lo, hi = pairs[sel, 0], pairs[sel, 1]
            base = size + 100 * np.arange(len(lo))
            coef = np.arange(d_lo * d_hi).reshape(d_lo, d_hi)
            assignments += [(lo, hi, base, coef), (hi, lo, base, coef.T + 50)]
            size += 100 * len(lo) + 1
    for d in np.unique(dims):
        diag = np.flatnonzero(dims == d)
        if not all_blocks:
            diag = diag[::2]
        assignments.append((diag, diag, size + 100 * np.arange(len(diag)), np.arange(d * d).reshape(d, d)))
        size += 100 * len(diag) + 1
    ref = _reference(P, assignments, fill=size)
    for dtype in (np.int32, np.int64):
        src = P.source_index(assignments, fill=size, dtype=dtype)
        assert src.dtype == dtype and np.array_equal(src, ref)


@pytest.mark.parametrize("dims", [[3] * 30, [3, 6] * 10])
def test_the_wide_row_pointers_are_held_only_for_mixed_block_sizes(dims):
    """indptr in 64 bits: kept where the mixed layout reads it, made when asked for uniform blocks (one
    n-long array less beside a solve), the same numbers either way."""
    dims = np.asarray(dims)
    nv = len(dims)
    u, v = np.arange(nv - 1), np.arange(1, nv)
    P = BlockPattern(dims, np.r_[u, np.arange(nv)], np.r_[v, np.arange(nv)])
    assert (P._indptr_wide is None) == P.uniform
    assert P._indptr64.dtype == np.int64
    np.testing.assert_array_equal(P._indptr64, P.indptr)
    r = P.offsets[u]
    c = P.offsets[v]
    pos = P.entry_positions(r, c)
    rows = np.repeat(np.arange(P.n), np.diff(P.indptr))
    np.testing.assert_array_equal(rows[pos], r)
    np.testing.assert_array_equal(P.indices[pos], c)
