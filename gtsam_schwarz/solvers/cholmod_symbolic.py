"""CHOLMOD's symbolic analysis through its C interface: the factor's column counts, no numbers.

scikit-sparse exposes CHOLMOD's analysis only as a permutation, so the cost model used to factorize
a surrogate matrix numerically to count the entries of L (3D survey 45x45x45: 2.8-5.4 s for the
vertex pattern). ``cholmod_analyze`` computes the counts itself (``L->ColCount``, under the ordering
CHOLMOD picks, the one the numeric factorization would use) in a fraction of that (0.24 s at
32x32x32, 0.76 s at 45x45x45; the same counts). Only the stable leading fields of
``cholmod_sparse`` and ``cholmod_factor`` are read, for CHOLMOD 3-5; elsewhere :func:`column_counts`
returns None and the caller factorizes its surrogate.
"""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np
import scipy.sparse as sp

from .openmp import limit_threads

KNOWN_MAJOR_VERSIONS = (3, 4, 5)  # cholmod_sparse and the head of cholmod_factor are the same in these
_COMMON_BYTES = 1 << 20  # room for cholmod_common (a few KiB in these versions)


class _Sparse(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("nz", ctypes.c_void_p),
                ("x", ctypes.c_void_p), ("z", ctypes.c_void_p), ("stype", ctypes.c_int),
                ("itype", ctypes.c_int), ("xtype", ctypes.c_int), ("dtype", ctypes.c_int),
                ("sorted", ctypes.c_int), ("packed", ctypes.c_int)]


class _FactorHead(ctypes.Structure):
    _fields_ = [("n", ctypes.c_size_t), ("minor", ctypes.c_size_t), ("Perm", ctypes.c_void_p),
                ("ColCount", ctypes.c_void_p), ("IPerm", ctypes.c_void_p)]


_STYPE_UPPER, _INT, _PATTERN, _DOUBLE = 1, 0, 0, 0
_NATURAL = 0  # CHOLMOD_NATURAL: the matrix's own order
_lib: list = []  # [the loaded library or None], once


def _library():
    if not _lib:
        lib = None
        limit_threads()
        try:
            name = ctypes.util.find_library("cholmod")
            if name:
                lib = ctypes.CDLL(name)
                lib.cholmod_version.argtypes = [ctypes.c_void_p]
                if lib.cholmod_version(None) // 1000 not in KNOWN_MAJOR_VERSIONS:  # CHOLMOD_VER_CODE: major·1000 + minor
                    lib = None
        except (OSError, AttributeError):
            lib = None
        if lib is not None:
            lib.cholmod_start.argtypes = [ctypes.c_void_p]
            lib.cholmod_finish.argtypes = [ctypes.c_void_p]
            lib.cholmod_analyze.argtypes = [ctypes.POINTER(_Sparse), ctypes.c_void_p]
            lib.cholmod_analyze.restype = ctypes.c_void_p
            lib.cholmod_free_factor.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.c_void_p]
            ptr = ctypes.c_void_p
            if hasattr(lib, "cholmod_analyze_ordering"):  # public since CHOLMOD 1; natural_column_counts needs it
                lib.cholmod_analyze_ordering.argtypes = [ctypes.POINTER(_Sparse), ctypes.c_int, ptr, ptr,
                                                         ctypes.c_size_t, ptr, ptr, ptr, ptr, ptr, ctypes.c_void_p]
        _lib.append(lib)
    return _lib[0]


def available() -> bool:
    return _library() is not None


def _pattern(S: sp.spmatrix):
    """S's CSC arrays (int32) and its upper triangle as a CHOLMOD pattern matrix (arrays kept alive by
    the caller), or None where CHOLMOD's 32-bit interface cannot hold it."""
    S = sp.csc_matrix(S)
    n = S.shape[0]
    if S.nnz >= 2**31 - 1 or n == 0:
        return None
    indptr = np.ascontiguousarray(S.indptr, dtype=np.int32)
    indices = np.ascontiguousarray(S.indices, dtype=np.int32)
    A = _Sparse(n, n, len(indices), indptr.ctypes.data, indices.ctypes.data, None, None, None,
                _STYPE_UPPER, _INT, _PATTERN, _DOUBLE, int(S.has_sorted_indices), 1)
    return A, indptr, indices


def natural_column_counts(S: sp.spmatrix) -> np.ndarray | None:
    """Entries per column of the Cholesky factor of the symmetric pattern S in its own order (no
    fill-reducing permutation): elimination tree and row/column counts only, O(nnz(S)), by
    ``cholmod_analyze_ordering``; None where the library is not usable here."""
    lib = _library()
    held = _pattern(S) if lib is not None and hasattr(lib, "cholmod_analyze_ordering") else None
    if held is None:
        return None
    A, n = held[0], S.shape[0]
    work = np.empty((6, n), dtype=np.int32)   # Perm, Parent, Post, ColCount, First, Level
    work[0] = np.arange(n, dtype=np.int32)    # the identity (the natural ordering does not read it)
    common = ctypes.create_string_buffer(_COMMON_BYTES)
    if not lib.cholmod_start(common):
        return None
    try:
        ok = lib.cholmod_analyze_ordering(ctypes.byref(A), _NATURAL, work[0].ctypes.data, None, 0, work[1].ctypes.data,
                                          work[2].ctypes.data, work[3].ctypes.data, work[4].ctypes.data,
                                          work[5].ctypes.data, common)
    finally:
        lib.cholmod_finish(common)
    counts = work[3].astype(np.int64)
    if not ok or counts.min(initial=1) < 1 or counts.max(initial=1) > n:
        return None
    return counts


def column_counts(S: sp.spmatrix) -> np.ndarray | None:
    """Entries per column of the Cholesky factor of the symmetric pattern S (its upper triangle is
    read; diagonal included) under CHOLMOD's default ordering, from ``cholmod_analyze`` alone; None
    where the library is not usable here (the caller falls back to a numeric factorization)."""
    found = ordering(S)
    return None if found is None else found[0]


def ordering(S: sp.spmatrix) -> tuple[np.ndarray, np.ndarray] | None:
    """(column counts, permutation) of CHOLMOD's analysis of the symmetric pattern S: the factor of
    S[p][:, p] has those column counts in that order (p: the ordering CHOLMOD picks, postordered);
    None where the library is not usable here."""
    lib = _library()
    held = _pattern(S) if lib is not None else None
    if held is None:
        return None
    A, n = held[0], S.shape[0]
    common = ctypes.create_string_buffer(_COMMON_BYTES)
    if not lib.cholmod_start(common):
        return None
    try:
        L = lib.cholmod_analyze(ctypes.byref(A), common)
        if not L:
            return None
        try:
            head = _FactorHead.from_address(L)
            if head.n != n or not head.ColCount or not head.Perm:
                return None
            counts = np.ctypeslib.as_array((ctypes.c_int * n).from_address(head.ColCount)).astype(np.int64)
            perm = np.ctypeslib.as_array((ctypes.c_int * n).from_address(head.Perm)).astype(np.int64)
        finally:
            lib.cholmod_free_factor(ctypes.byref(ctypes.c_void_p(L)), common)
    finally:
        lib.cholmod_finish(common)
    if counts.min(initial=1) < 1 or counts.max(initial=1) > n:
        return None  # not a factor's column counts: a layout this module does not know
    if n and (perm.min() < 0 or perm.max() >= n or np.bincount(perm, minlength=n).max() != 1):
        return None
    return counts, perm
