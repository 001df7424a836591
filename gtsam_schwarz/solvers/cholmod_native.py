"""CHOLMOD's simplicial factorization through its C interface, without Python's GIL.

scikit-sparse holds the GIL through every CHOLMOD call, so two factorizations or solves never run
at once (two 400² grid Laplacians: 1.68 s one after the other, 1.91 s on two threads). ctypes
releases it: the one-level part's chunks (simplicial factors: CHOLMOD's own choice for them, no
BLAS involved) can be factorized and solved on two threads, beside the coarse correction's scipy
products. Each thread has its own ``cholmod_common``. Options are set in the common's leading
fields (``supernodal``, the first ordering method), whose offsets are checked against CHOLMOD's
defaults after ``cholmod_start``; where they do not match (another CHOLMOD layout),
:func:`available` is False and callers use scikit-sparse.
"""

from __future__ import annotations

import ctypes
import threading

import numpy as np
import scipy.sparse as sp

from ..util.threads import WORKERS, run_all
from . import cholmod_symbolic as _sym
from .base import SingularLocalMatrixError, check_finite
from .sparse import _csc

_COMMON_BYTES = 1 << 20
_SIMPLICIAL, _NATURAL, _PATTERN, _REAL, _A = 0, 0, 0, 1, 0   # CHOLMOD_SIMPLICIAL, _NATURAL, _PATTERN, _REAL, _A
# offsets in cholmod_common (CHOLMOD 3-5, 64-bit): its leading scalars, then the first ordering method
_SUPERNODAL, _NMETHODS, _METHOD0_ORDERING = 48, 168, 316
_DEFAULTS = ((8, ctypes.c_double, 1.2), (16, ctypes.c_double, 1.2), (24, ctypes.c_size_t, 5),
             (32, ctypes.c_size_t, 8), (40, ctypes.c_double, 40.0), (48, ctypes.c_int, 1),
             (80, ctypes.c_double, 0.8), (104, ctypes.c_size_t, 4), (168, ctypes.c_int, 0),
             (200, ctypes.c_double, 10.0), (216, ctypes.c_double, 1.0), (256, ctypes.c_size_t, 200))


class _Dense(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("d", ctypes.c_size_t), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("xtype", ctypes.c_int), ("dtype", ctypes.c_int)]


_state: dict = {}
_local = threading.local()


def _library():
    """The CHOLMOD library with this module's prototypes, or None (checked once)."""
    if "lib" not in _state:
        lib = _sym._library()
        try:
            if lib is not None:
                vp, sparse = ctypes.c_void_p, ctypes.POINTER(_sym._Sparse)
                lib.cholmod_analyze.argtypes, lib.cholmod_analyze.restype = [sparse, vp], vp
                lib.cholmod_factorize.argtypes, lib.cholmod_factorize.restype = [sparse, vp, vp], ctypes.c_int
                lib.cholmod_solve.argtypes = [ctypes.c_int, vp, ctypes.POINTER(_Dense), vp]
                lib.cholmod_solve.restype = ctypes.POINTER(_Dense)
                lib.cholmod_free_dense.argtypes = [ctypes.POINTER(ctypes.POINTER(_Dense)), vp]
                lib.cholmod_free_factor.argtypes = [ctypes.POINTER(vp), vp]
                lib.cholmod_change_factor.argtypes = [ctypes.c_int] * 5 + [vp, vp]
                lib.cholmod_change_factor.restype = ctypes.c_int
                if not _layout_known(lib):
                    lib = None
        except AttributeError:
            lib = None
        _state["lib"] = lib
    return _state["lib"]


def _layout_known(lib) -> bool:
    """Whether a fresh common holds CHOLMOD's defaults at the offsets this module writes near."""
    common = ctypes.create_string_buffer(_COMMON_BYTES)
    if not lib.cholmod_start(common):
        return False
    try:
        base = ctypes.addressof(common)
        return all(abs(kind.from_address(base + at).value - value) < 1e-12 for at, kind, value in _DEFAULTS)
    finally:
        lib.cholmod_finish(common)


def available() -> bool:
    return _library() is not None


def _common(natural: bool):
    """This thread's common set for simplicial factors (natural ordering or CHOLMOD's default)."""
    commons = getattr(_local, "commons", None)
    if commons is None:
        commons = _local.commons = {}
    common = commons.get(natural)
    if common is None:
        common = ctypes.create_string_buffer(_COMMON_BYTES)
        if not _library().cholmod_start(common):
            raise MemoryError("cholmod_start failed")
        base = ctypes.addressof(common)
        ctypes.c_int.from_address(base + _SUPERNODAL).value = _SIMPLICIAL
        if natural:
            ctypes.c_int.from_address(base + _NMETHODS).value = 1
            ctypes.c_int.from_address(base + _METHOD0_ORDERING).value = _NATURAL
        commons[natural] = common
    return common


def _matrix(K: sp.csc_matrix):
    """K (CSC, symmetric, both triangles stored) as a CHOLMOD matrix reading its upper triangle."""
    indptr = np.ascontiguousarray(K.indptr, dtype=np.int32)
    indices = np.ascontiguousarray(K.indices, dtype=np.int32)
    data = np.ascontiguousarray(K.data, dtype=np.float64)
    n = K.shape[0]
    A = _sym._Sparse(n, n, len(indices), indptr.ctypes.data, indices.ctypes.data, None, data.ctypes.data, None,
                     1, 0, _REAL, 0, int(K.has_sorted_indices), 1)
    return A, (indptr, indices, data)


class SimplicialCholesky:
    """A simplicial LDLᵀ factor of a fixed pattern (analysis once, numbers by :meth:`refactor`),
    whose factorizations and solves release the GIL. ``natural``: K's own order (already
    fill-reducing), else CHOLMOD's default ordering."""

    releases_gil = True   # factorizations and solves run side by side on the local threads
    SUPERNODAL_SWITCH = 40.0  # CHOLMOD's default: supernodal where flops / nnz(L) reach this

    def __init__(self, K: sp.spmatrix, what: str = "local matrix", natural: bool = False, factor: bool = True):
        self.what, self.natural = what, natural
        K = _csc(K)   # a symmetric CSR matrix's transpose: its CSC arrays, no conversion
        self.n = K.shape[0]
        if self.n >= 2**31 - 1 or K.nnz >= 2**31 - 1:
            raise ValueError("CHOLMOD's 32-bit interface cannot hold this matrix")
        self._L = None
        self._analyze(K)
        if factor:
            self.refactor(K)

    def _analyze(self, K: sp.csc_matrix) -> None:
        A, held = _matrix(K)
        L = _library().cholmod_analyze(ctypes.byref(A), _common(self.natural))
        del held
        if not L:
            raise MemoryError(f"CHOLMOD could not analyze {self.what}")
        self._L = ctypes.c_void_p(L)
        self._numeric = False

    @property
    def has_numeric(self) -> bool:
        """Whether the factor holds numbers (not after :meth:`release_numeric`)."""
        return self._L is not None and self._numeric

    def column_counts(self) -> np.ndarray:
        """Entries per column of the factor L (D on its diagonal), from the analysis."""
        head = _sym._FactorHead.from_address(self._L.value)
        return np.ctypeslib.as_array((ctypes.c_int * self.n).from_address(head.ColCount)).astype(np.int64)

    def supernodal_preferred(self) -> bool:
        """Whether CHOLMOD's automatic choice would make this factor supernodal (flops per entry of L
        from the analysis' column counts; there its BLAS kernels beat a simplicial factor)."""
        counts = self.column_counts().astype(np.float64)
        return bool(np.sum(counts * counts) >= self.SUPERNODAL_SWITCH * max(np.sum(counts), 1.0))

    def refactor(self, K: sp.spmatrix) -> "SimplicialCholesky":
        K = _csc(K)
        check_finite(K, self.what)
        A, held = _matrix(K)
        lib = _library()
        lib.cholmod_factorize(ctypes.byref(A), self._L, _common(self.natural))
        del held
        self._numeric = True
        head = _sym._FactorHead.from_address(self._L.value)
        if head.minor < self.n:
            raise SingularLocalMatrixError(f"{self.what} is not positive definite (pivot {head.minor})")
        return self

    def solve(self, b: np.ndarray, pool=None) -> np.ndarray:
        """x with K x = b (b: (n,) or (n, k)); ``pool`` (:func:`~gtsam_schwarz.util.threads.local_threads`):
        the columns of b in as many blocks as it has workers, solved side by side (the same numbers)."""
        b = np.asarray(b, dtype=np.float64)
        B = np.asfortranarray(b.reshape(self.n, -1))
        out = np.empty(B.shape, order="F")
        k = B.shape[1]
        parts = min(k, WORKERS) if pool is not None else 1
        if parts > 1:
            cuts = np.linspace(0, k, parts + 1).astype(int)
            run_all(pool, [lambda c0=c0, c1=c1: self._solve_into(B[:, c0:c1], out[:, c0:c1])
                           for c0, c1 in zip(cuts[:-1], cuts[1:])])
        else:
            self._solve_into(B, out)
        return out.reshape(b.shape, order="F") if b.ndim > 1 else out.reshape(-1)

    def _solve_into(self, B: np.ndarray, out: np.ndarray) -> None:
        """out = K⁻¹ B for F-contiguous (n, k) blocks B and out."""
        D = _Dense(self.n, B.shape[1], B.size, self.n, B.ctypes.data, None, _REAL, 0)
        lib = _library()
        common = _common(self.natural)
        X = lib.cholmod_solve(_A, self._L, ctypes.byref(D), common)
        if not X:
            raise MemoryError(f"CHOLMOD could not solve with {self.what}")
        try:
            x = np.ctypeslib.as_array((ctypes.c_double * B.size).from_address(X.contents.x))
            out[...] = x.reshape(B.shape, order="F")
        finally:
            lib.cholmod_free_dense(ctypes.byref(X), common)

    __call__ = solve

    def release_numeric(self) -> None:
        """Free the factor's numbers and keep its analysis (the next :meth:`refactor` fills it again)."""
        if self._L is not None and self._numeric:
            if not _library().cholmod_change_factor(_PATTERN, 0, 0, 1, 1, self._L, _common(self.natural)):
                raise MemoryError(f"CHOLMOD could not release the numbers of {self.what}")
            self._numeric = False

    def __del__(self):
        L, self._L = getattr(self, "_L", None), None
        if L is not None and _library() is not None:
            _library().cholmod_free_factor(ctypes.byref(L), _common(self.natural))
