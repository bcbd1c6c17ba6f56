"""Jacobi-preconditioned conjugate gradient on a torch sparse CSR matrix.

torch has no CPU sparse solver; index tensors are int32 (CSR mat-vecs run faster on int32 indices than
on int64).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch


@dataclass(frozen=True)
class PCGResult:
    """Solution x, iterations used, final relative residual ||r|| / ||b||."""

    x: torch.Tensor
    iterations: int
    relative_residual: float


def to_torch_csr(matrix: sp.spmatrix, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """A scipy sparse matrix as a torch sparse CSR tensor with int32 indices."""
    csr = matrix.tocsr()
    csr.sort_indices()
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.from_numpy(csr.indptr.astype(np.int32, copy=False)),
            torch.from_numpy(csr.indices.astype(np.int32, copy=False)),
            torch.from_numpy(csr.data.astype(np.float32 if dtype == torch.float32 else np.float64, copy=False)),
            size=csr.shape,
            check_invariants=False,
        )


def jacobi_pcg(
    matrix: torch.Tensor, diagonal: torch.Tensor, rhs: torch.Tensor, tolerance: float, max_iter: int
) -> PCGResult:
    """Solve matrix @ x = rhs for SPD `matrix` (torch CSR), preconditioned by 1 / `diagonal`.

    Stops when ||r|| <= tolerance * ||rhs|| or after max_iter iterations; starts from x = 0.
    """
    inv_diag = torch.where(diagonal > 0, 1.0 / diagonal, torch.ones_like(diagonal))
    x = torch.zeros_like(rhs)
    r = rhs.clone()
    b_norm = float(torch.linalg.vector_norm(rhs))
    if b_norm == 0.0:
        return PCGResult(x=x, iterations=0, relative_residual=0.0)
    z = inv_diag * r
    p = z.clone()
    rz = torch.dot(r, z)
    iterations = 0
    rel = 1.0
    while iterations < max_iter:
        ap = torch.mv(matrix, p)
        step = rz / torch.dot(p, ap)
        x.add_(step * p)
        r.sub_(step * ap)
        iterations += 1
        rel = float(torch.linalg.vector_norm(r)) / b_norm
        if rel <= tolerance:
            break
        z = inv_diag * r
        rz_next = torch.dot(r, z)
        p.mul_(rz_next / rz).add_(z)
        rz = rz_next
    return PCGResult(x=x, iterations=iterations, relative_residual=rel)
