"""Sparse symmetric positive definite solves shared by the compass and pose solvers."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

try:  # sparse LDL^T with an AMD ordering (pip wheel)
    import qdldl as _qdldl
except ImportError:
    _qdldl = None

__all__ = ["SolveError", "spd_solve"]


class SolveError(ArithmeticError):
    """The normal equations could not be factorised (a floating part or a degenerate measurement)."""


def spd_solve(h: sp.spmatrix, b: np.ndarray, *, upper: bool = False) -> np.ndarray:
    """Solve ``h x = b`` for a sparse symmetric positive definite ``h`` (with ``upper``, given by its upper
    triangle alone).

    QDLDL (sparse LDL^T, AMD ordering) when installed; otherwise SuperLU in symmetric mode (no pivoting off the diagonal, a minimum-degree ordering of
    ``A^T + A``) is a sparse LDL^T in all but name: it keeps the fill of a Cholesky factor.
    """
    h = sp.csc_matrix(h)
    b = np.asarray(b, dtype=float)
    if _qdldl is not None:
        try:
            ldl = _qdldl.Solver(h, upper=upper)
            x = ldl.solve(b) if b.ndim == 1 else np.column_stack([ldl.solve(c) for c in b.T])
        except (ValueError, RuntimeError) as exc:
            raise SolveError(f"singular normal equations ({exc})") from None
        if not np.all(np.isfinite(x)):
            raise SolveError("normal equations are singular or badly conditioned")
        return x
    if upper:
        h = sp.csc_matrix(h + sp.triu(h, 1).T)
    try:
        lu = splu(h, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise SolveError(f"singular normal equations ({exc})") from None
    x = lu.solve(np.asarray(b, dtype=float))
    if not np.all(np.isfinite(x)):
        raise SolveError("normal equations are singular or badly conditioned")
    return x
