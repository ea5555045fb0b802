"""Sparse symmetric positive definite solves shared by the compass and pose solvers."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

__all__ = ["SolveError", "spd_solve"]


class SolveError(ArithmeticError):
    """The normal equations could not be factorised (a floating part or a degenerate measurement)."""


def spd_solve(h: sp.spmatrix, b: np.ndarray) -> np.ndarray:
    """Solve ``h x = b`` for a sparse symmetric positive definite ``h``.

    SuperLU in symmetric mode (no pivoting off the diagonal, a minimum-degree ordering of
    ``A^T + A``) is a sparse LDL^T in all but name: it keeps the fill of a Cholesky factor.
    """
    h = sp.csc_matrix(h)
    try:
        lu = splu(h, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise SolveError(f"singular normal equations ({exc})") from None
    x = lu.solve(np.asarray(b, dtype=float))
    if not np.all(np.isfinite(x)):
        raise SolveError("normal equations are singular or badly conditioned")
    return x
