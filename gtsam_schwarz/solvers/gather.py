"""Fixed-pattern submatrix extraction: symbolic positions once, numbers by one gather afterwards."""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import scipy.sparse as sp

from ..util.gathered import is_gathered
from ..util.sparse import as_csr, row_entries, vertex_pattern


class SparsityPattern:
    """A CSR pattern (indptr, indices) to recognise matrices whose symbolic work can be reused."""

    def __init__(self, A: sp.csr_matrix):
        self.shape = A.shape
        # read-only pattern arrays (the linearizer's fixed pattern of H) are kept, not copied (at
        # 91 125 3D poses 90 MB), and the same objects again match without comparing their contents
        frozen = not (A.indptr.flags.writeable or A.indices.flags.writeable)
        self.indptr = A.indptr if frozen else A.indptr.copy()
        self.indices = A.indices if frozen else A.indices.copy()
        self._same = (A.indptr, A.indices) if frozen else None

    def matches(self, A: sp.spmatrix) -> bool:
        if not (isinstance(A, sp.csr_matrix) and A.shape == self.shape):
            return False
        same = self._same
        if same is not None and A.indptr is same[0] and A.indices is same[1]:
            return True  # the same read-only arrays: no O(nnz) check of their order (262k poses: 5 ms)
        if not A.has_sorted_indices:
            return False
        if np.array_equal(A.indptr, self.indptr) and np.array_equal(A.indices, self.indices):
            if not (A.indptr.flags.writeable or A.indices.flags.writeable):
                self._same = (A.indptr, A.indices)
            return True
        return False


_shared: list = [None]  # the last pattern built: the gathers of one matrix share one copy of it


def pattern_of(A: sp.csr_matrix) -> SparsityPattern:
    """A's pattern, shared with the previous gather's when equal (one copy per matrix, not per gather)."""
    last = _shared[0]
    if last is None or not last.matches(A):
        last = _shared[0] = SparsityPattern(A)
    return last


class Gather:
    """B = extract(A) for an extraction that copies entries (submatrix, block diagonal, …).

    The pattern of B and the position in ``A.data`` of each of its entries are found once per
    sparsity pattern of A; afterwards new numbers cost one gather ``A.data[src]``. For a
    :class:`~gtsam_schwarz.util.gathered.GatheredCSR` A the positions are composed once with A's index
    (then they point into A's source) and B's numbers are one gather from the source.
    """

    def __init__(self, extract):
        self.extract = extract
        self.pattern = None
        self.forgotten = None  # the pattern of A whose positions :meth:`forget` dropped
        self.composed = None   # the index array that ``src`` was composed with (None: positions in A.data)

    def forget(self) -> None:
        """Drop the positions and B's pattern (memory); the next call finds them anew. ``forgotten``
        keeps which A they were for (a caller's factorization of B may still fit the next A)."""
        self.forgotten = self.pattern or self.forgotten
        self.pattern = self.src = self.indices = self.indptr = self.composed = None

    def renew(self, A: sp.spmatrix) -> tuple[sp.csr_matrix, bool]:
        """:meth:`prepare` for A, and whether A has the pattern of the positions held before (or last
        forgotten): a factorization of an earlier B then still fits the new one."""
        before = self.pattern or self.forgotten
        A = self.prepare(A)
        self.forgotten = None
        return A, before is not None and (self.pattern is before or before.matches(A))

    def prepare(self, A: sp.spmatrix) -> sp.csr_matrix:
        """The positions for A's pattern (found unless known; B's numbers are not kept); returns A as
        the sorted CSR matrix that :meth:`__call__` reads."""
        A = as_csr(A)
        if not A.has_sorted_indices:
            A = A.sorted_indices()
        gathered = is_gathered(A)
        if (self.pattern is None or not self.pattern.matches(A)
                or (self.composed is not None and self.composed is not (A.index if gathered else None))):
            self.src, self.indices, self.indptr, self.shape = self._positions(A)
            self.pattern = pattern_of(A)
            self.composed = None
        if gathered and self.composed is None:   # positions into A's source from now on
            self.src, self.composed = A.compose(self.src), A.index
        return A

    def __call__(self, A: sp.spmatrix) -> sp.csr_matrix:
        A = self.prepare(A)
        # every result shares the (read-only) index arrays: only its numbers are new
        data = A.take_source(self.src) if self.composed is not None else A.data[self.src]
        B = sp.csr_matrix((data, self.indices, self.indptr), shape=self.shape, copy=False)
        B.has_sorted_indices = True
        return B

    def _positions(self, A: sp.csr_matrix):
        """(position in A.data of every entry of B, B's indices, indptr, shape)."""
        # 1 + each entry's position as A's numbers (int32 where they fit: a 4th of float64's
        # time to create, half its memory; extractions copy entries, they do not add them)
        itype = np.int32 if A.nnz < 2**31 - 1 else np.int64
        pos = sp.csr_matrix((np.arange(1, A.nnz + 1, dtype=itype), A.indices, A.indptr), shape=A.shape)
        B = sp.csr_matrix(self.extract(pos))
        del pos
        B.sort_indices()
        return B.data.astype(itype) - 1, B.indices, B.indptr, B.shape


class Submatrix(Gather):
    """B = A[rows][:, cols] for distinct ``rows`` and ``cols`` (in any order: B's columns in theirs,
    each row's entries sorted): the positions are found from the rows' index ranges and a column map,
    without a position matrix of all of A (3D 45³: the interior blocks' positions took 2.6 s per
    rebuild in the low-memory mode, which drops them)."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n: int, shared: dict | None = None,
                 offsets: np.ndarray | None = None):
        super().__init__(None)
        self.rows = np.asarray(rows)
        # rows and columns of whole vertices of one block size (offsets given): positions by blocks
        self.vertex_sets = _whole_vertices(self.rows, np.asarray(cols), offsets)
        self.offsets = offsets
        self.block = int(offsets[1] - offsets[0]) if self.vertex_sets is not None else 1   # dofs per vertex
        # submatrices of the same rows (A_II and A_IΓ) pass one dict: the rows' entries found for the
        # first are taken by the next instead of found again (600x600 2D poses: 0.4 s per build)
        self.shared = shared
        self.cols, self.n = np.asarray(cols), n
        self.n_cols = len(cols)

    def _column_map(self) -> np.ndarray:
        """Each of A's columns' place among ``cols`` (−1: not one), for the entrywise positions only:
        made when asked, not kept (an n-long array per gather: 1M 2D poses, the extension's pieces'
        A_II and A_IΓ held 137 MiB of them beside the build and CG while the block path never read them)."""
        col_map = np.full(self.n, -1, dtype=np.int32 if self.n_cols < 2**31 - 1 else np.int64)
        col_map[self.cols] = np.arange(self.n_cols)
        return col_map

    def _positions(self, A: sp.csr_matrix):
        if self.vertex_sets is not None:
            P = submatrix_positions(A, *self.vertex_sets, self.offsets, self.block)
            if P is not None:
                return P.data, P.indices, P.indptr, P.shape
        itype = np.int32 if A.nnz < 2**31 - 1 else np.int64
        held = self.shared
        # the same pattern arrays (scipy's csr_matrix(A) views A's indices through a new array object)
        key = (A.indptr.ctypes.data, A.indices.ctypes.data, A.indices.size, A.indptr.size)
        if held and held["rows"] is self.rows and held["key"] == key and held["at"].dtype == itype:
            at, ranges, columns = held["at"], held["ranges"], held["columns"]
            held.clear()
        else:
            at, ranges = row_entries(A, self.rows, itype)  # the rows' entries, row after row
            columns = A.indices[at]
            if held is not None:
                held.clear()
                held.update(rows=self.rows, key=key, pattern=(A.indptr, A.indices), at=at, ranges=ranges,
                            columns=columns)
        local = self._column_map()[columns]
        del columns
        keep = local >= 0
        kept = np.zeros(len(at) + 1, dtype=np.int64)  # entries kept before each position
        np.cumsum(keep, out=kept[1:])
        indptr = kept[ranges].astype(itype)
        at, local = at[keep], local[keep]
        if np.any(np.diff(self.cols) < 0):   # columns in an order of their own: each row's entries sorted by it
            P = sp.csr_matrix((at, local, indptr), shape=(len(self.rows), self.n_cols))
            P.has_sorted_indices = False
            P.sort_indices()
            at, local, indptr = P.data, P.indices, P.indptr
        return at, local, indptr, (len(self.rows), self.n_cols)


def _whole_vertices(rows: np.ndarray, cols: np.ndarray, offsets: np.ndarray | None):
    """(row vertices, column vertices) where ``rows`` and ``cols`` are the dofs of whole vertices in
    order and every vertex has the same number of dofs; else None."""
    if offsets is None or len(offsets) < 2:
        return None
    dims = np.diff(offsets)
    d = int(dims[0])
    if d < 2 or not np.all(dims == d) or len(rows) % d or len(cols) % d:
        return None
    vertex = []
    for dofs in (rows, cols):
        v = dofs[::d] // d
        if not np.array_equal(dofs, (v[:, None] * d + np.arange(d)).ravel()):
            return None
        vertex.append(v)
    return vertex[0], vertex[1]


# -- positions by vertex blocks (a matrix made of whole d×d blocks, as H) ------------------------

_VERTEX_LEVEL: dict = {"users": 0, "entry": None}   # (key, A's pattern arrays, result) while shared
_VERTEX_LOCK = threading.Lock()


@contextlib.contextmanager
def sharing_vertex_level():
    """Within: extractions from the same A share its vertex level (:func:`vertex_level`), also across
    threads (the one-level chunks' positions found on the side thread while the extension runs);
    dropped when the last user leaves."""
    with _VERTEX_LOCK:
        _VERTEX_LEVEL["users"] += 1
    try:
        yield
    finally:
        with _VERTEX_LOCK:
            _VERTEX_LEVEL["users"] -= 1
            if not _VERTEX_LEVEL["users"]:
                _VERTEX_LEVEL["entry"] = None


def vertex_level(A: sp.csr_matrix, offsets: np.ndarray):
    """A's vertex pattern V (its numbers: 1 + each vertex entry's number) and where each block starts
    in its dof rows, or None when A is not made of whole blocks. Kept within
    :func:`sharing_vertex_level`: the one-level chunks and the extension's groups read the same A
    (1M 2D poses, 7 chunks: ~0.7 s each for this part); a second thread asking for it meanwhile
    waits for the first one's instead of forming it again."""
    key = (A.indptr.ctypes.data, A.indices.ctypes.data, A.indptr.size, A.indices.size, offsets.ctypes.data, offsets.size)
    with _VERTEX_LOCK:
        if _VERTEX_LEVEL["users"]:
            entry = _VERTEX_LEVEL["entry"]
            if entry is not None and entry[0] == key:
                return entry[2]
            result = _vertex_level(A, offsets)   # formed under the lock: another user of the same A waits
            _VERTEX_LEVEL["entry"] = (key, (A.indptr, A.indices, offsets), result)
            return result
    return _vertex_level(A, offsets)


def _vertex_level(A: sp.csr_matrix, offsets: np.ndarray):
    dims = np.diff(offsets)
    nv = len(dims)
    V = vertex_pattern(A, offsets)
    V.sort_indices()
    vrow = np.repeat(np.arange(nv), np.diff(V.indptr))
    if int(np.sum(dims[vrow] * dims[V.indices])) != A.nnz:
        return None
    # where block (u, v) starts in each dof row of u: the widths of the blocks before it in the row
    width = dims[V.indices]
    before = np.cumsum(width) - width
    col_start = before - before[V.indptr[vrow]]
    V.data = np.arange(1, V.nnz + 1, dtype=float)  # 1 + the vertex entry's number
    return V, col_start


def submatrix_positions(A: sp.csr_matrix, row_vertices: np.ndarray, col_vertices: np.ndarray,
                        offsets: np.ndarray, d: int) -> sp.csr_matrix | None:
    """Positions in A.data of A[rows][:, cols] for rows and columns made of whole vertices of one block
    size d (in the order of the vertices given), as a CSR pattern; None where A is not made of whole
    blocks. The vertex-level submatrix is expanded as a BSR pattern (1M 2D poses, the extension's
    interior blocks: ~7 passes over 25M entries found them before)."""
    level = vertex_level(A, offsets)
    if level is None:
        return None
    V, col_start = level
    Vs = sp.csr_matrix(V[row_vertices][:, col_vertices])
    Vs.sort_indices()
    return block_positions(A, Vs, Vs.data.astype(np.int64) - 1, row_vertices, offsets, col_start, d)


def block_positions(A: sp.csr_matrix, Bv: sp.csr_matrix, entry: np.ndarray, vert: np.ndarray,
                       offsets: np.ndarray, col_start: np.ndarray, d: int) -> sp.csr_matrix:
    """For d×d blocks everywhere: entry (a, b) of the kept block (u, v) sits in A's dof row
    offsets[u] + a at col_start + b; these positions form a BSR matrix on Bv's pattern, turned into
    CSR by scipy (three passes over the entries instead of seven)."""
    m, mc = Bv.shape[0] * d, Bv.shape[1] * d
    itype = np.int32 if max(A.nnz, Bv.nnz * d * d, m, mc) < 2**31 - 1 else np.int64
    u = vert[np.repeat(np.arange(Bv.shape[0]), np.diff(Bv.indptr))]   # the vertex of every kept block's row
    first = (A.indptr[offsets[u][:, None] + np.arange(d)] + col_start[entry][:, None]).astype(itype)   # (nb, d)
    src = first[:, :, None] + np.arange(d, dtype=itype)   # (nb, d, d): positions in A.data
    del first
    P = sp.bsr_matrix((src, Bv.indices.astype(itype), Bv.indptr.astype(itype)), shape=(m, mc), blocksize=(d, d))
    del src
    P = P.tocsr()
    P.has_sorted_indices = True
    return P
