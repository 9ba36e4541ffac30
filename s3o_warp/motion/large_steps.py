"""The joint phase's shape step: Laplacian-preconditioned vertex steps with a uniform second moment.

Nicolet et al. 2021 ("Large Steps in Inverse Rendering of Geometry") step on ``u = (I + lam L) x`` instead of the
vertices ``x``, with ``L`` the mesh's combinatorial (umbrella) Laplacian: the gradient with respect to ``u`` is
``(I + lam L)^-1`` times the vertices' gradient, a smoothed gradient, and the step in ``u`` maps back to the
vertices through the same solve. Their Adam divides every entry by the *largest* second moment instead of its own,
so a vertex with a small gradient moves little. Plain per-entry Adam moves every vertex by about the learning rate
whatever its gradient's size, and on the joint phase's noisy silhouette, colour and coverage gradients each vertex
random-walks about half an edge an epoch (docs/results.md, "From every side").

:class:`FitAdam` is torch's Adam for every group but the one named ``shape``, which it steps this way. It keeps the
moments in ``u`` in the optimiser's state (``exp_avg``, ``exp_avg_sq``, ``step``: checkpoints carry them as Adam's)
and never stores ``u``: the step ``delta_u`` moves the vertices by ``(I + lam L)^-1 delta_u``, so anything else that
writes the vertices (a resampling, a roll-back) needs no ``u`` to be kept in step. The factor of ``I + lam L`` is
computed once per mesh (scipy's sparse LU; the faces change only at a resampling).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from s3o_warp.kernels._warp import cached
from s3o_warp.ops import mesh_edges


def umbrella_laplacian(faces: torch.Tensor, num_verts: int) -> sp.csc_matrix:
    """The combinatorial Laplacian ``L = D - A`` of the mesh's edge graph (``D`` the valences), (V, V) float64."""
    e = mesh_edges(faces).cpu().numpy()
    i = np.concatenate([e[:, 0], e[:, 1]])
    j = np.concatenate([e[:, 1], e[:, 0]])
    A = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(num_verts, num_verts)).tocsr()
    return (sp.diags(np.asarray(A.sum(1)).ravel()) - A).tocsc()


class SmoothingSolve:
    """``x -> (I + lam L)^-1 x`` for (V, k) tensors: one sparse LU of ``I + lam L`` (float64), applied on the CPU."""

    def __init__(self, faces: torch.Tensor, num_verts: int, lam: float):
        self.lam, self.num_verts = float(lam), int(num_verts)
        M = sp.identity(num_verts, format="csc") + self.lam * umbrella_laplacian(faces, num_verts)
        self._solve = spla.factorized(M.tocsc())

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        b = x.detach().to("cpu", torch.float64).numpy()
        out = np.stack([self._solve(np.ascontiguousarray(b[:, k])) for k in range(b.shape[1])], axis=1)
        return torch.from_numpy(out).to(device=x.device, dtype=x.dtype)


def smoothing_solve(faces: torch.Tensor, num_verts: int, lam: float) -> SmoothingSolve:
    """The :class:`SmoothingSolve` of a mesh, factored once per faces tensor (and ``lam``)."""
    return cached(faces, f"large_steps_{num_verts}_{lam!r}", lambda: SmoothingSolve(faces, num_verts, lam))


class FitAdam(torch.optim.Adam):
    """torch's Adam, except for the parameter group named ``shape`` (the canonical vertices, (V, 3)), which takes
    Laplacian-preconditioned steps with a uniform second moment (module docstring).

    Args:
        groups: parameter groups as for Adam, each with a ``name``.
        faces: the canonical mesh's (F, 3) faces (the shape group's only parameter is its vertices).
        lam: ``lam`` of ``I + lam L``, > 0.
    """

    def __init__(self, groups, faces: torch.Tensor, lam: float, **kw):
        super().__init__(groups, **kw)
        if not lam > 0:
            raise ValueError(f"FitAdam: lam must be > 0, got {lam}")
        self.faces, self.lam = faces, float(lam)

    def _shape_groups(self):
        return [g for g in self.param_groups if g.get("name") == "shape"]

    @torch.no_grad()
    def step(self, closure=None):
        shape = self._shape_groups()
        held = [(p, p.grad) for g in shape for p in g["params"]]
        for p, _ in held:  # Adam skips parameters without a gradient
            p.grad = None
        try:
            loss = super().step(closure)
        finally:
            for p, grad in held:
                p.grad = grad
        for g in shape:
            for p in g["params"]:
                if p.grad is not None:
                    self._shape_step(p, g)
        return loss

    def _shape_step(self, p: torch.Tensor, group: dict) -> None:
        if p.dim() != 2:
            raise ValueError(f"FitAdam: the shape group's parameter must be the mesh's (V, 3) vertices, got {tuple(p.shape)}")
        solve = smoothing_solve(self.faces, p.shape[0], self.lam)
        b1, b2 = group["betas"]
        st = self.state[p]
        if len(st) == 0:
            st["step"] = torch.tensor(0.0)
            st["exp_avg"] = torch.zeros_like(p)
            st["exp_avg_sq"] = torch.zeros_like(p)
        st["step"] += 1
        t = float(st["step"])
        g_u = solve(p.grad)
        st["exp_avg"].mul_(b1).add_(g_u, alpha=1 - b1)
        st["exp_avg_sq"].mul_(b2).addcmul_(g_u, g_u, value=1 - b2)
        m_hat = st["exp_avg"] / (1 - b1**t)
        v_max = (st["exp_avg_sq"].max() / (1 - b2**t)).sqrt()
        p.add_(solve(-group["lr"] * m_hat / (v_max + group["eps"])))
