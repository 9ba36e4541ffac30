"""Laplacian-preconditioned vertex updates ("large steps", Nicolet et al. 2021).

Adam on the raw canonical vertices moves every coordinate at its own full step size, which grows thin
spikes wherever the views say little (mostly along depth). Optimising ``u = (I + lambda L) X`` instead
and mapping back ``X = (I + lambda L)^{-1} u`` spreads each step over the surface: the update stays
smooth while the shape can still move far. We keep ``X`` as the parameter and do this exactly: the
gradient handed to Adam is the one of ``u`` (``(I + lambda L)^{-1} dE/dX``, the matrix is symmetric),
and Adam's step on ``u`` is mapped back to ``X`` by the same solve.

``L`` is the combinatorial graph Laplacian ``D - A`` of the mesh edges (scale-free, as in the paper);
the system is small (the canonical mesh has a few thousand vertices), so it is factorised densely once
per mesh with a float64 Cholesky and reused every step.

Plain Adam divides every entry of u's step by its own gradient scale, which undoes much of the smoothing
(its first step moves every vertex by the learning rate); the paper's remedy, used here for the vertex
group (``uniform=True`` in :class:`Adam`), divides by one scale per parameter, the largest.
"""

from __future__ import annotations

import torch


def graph_laplacian(edges: torch.Tensor, num_verts: int, dtype=torch.float64) -> torch.Tensor:
    """Dense combinatorial Laplacian ``L = D - A`` ``(N, N)`` of undirected ``edges (E, 2)`` (each once)."""
    e = edges.to(torch.int64).cpu()
    L = torch.zeros(num_verts, num_verts, dtype=dtype)
    L[e[:, 0], e[:, 1]] = -1.0
    L[e[:, 1], e[:, 0]] = -1.0
    L.diagonal().copy_(-L.sum(1))
    return L


class LargeSteps:
    """``M = I + lambda L`` factorised once; ``solve(g)`` = ``M^{-1} g`` for ``g (N, 3)``."""

    max_vertices = 20000  # dense float64 factor: 3.2 GB at this size; beyond it refuse rather than thrash

    def __init__(self, edges: torch.Tensor, num_verts: int, lam: float, device: torch.device | str = "cpu"):
        if lam <= 0:
            raise ValueError(f"LargeSteps: lambda must be > 0, got {lam}")
        if num_verts > self.max_vertices:
            raise ValueError(f"LargeSteps: {num_verts} vertices is over the dense limit {self.max_vertices}; "
                             f"set motion.large_steps=0 (and coarse.large_steps=0) or use fewer vertices")
        M = torch.eye(num_verts, dtype=torch.float64) + lam * graph_laplacian(edges, num_verts)
        self.num_verts = num_verts
        self.lam = float(lam)
        self.factor = torch.linalg.cholesky(M).to(device)

    def solve(self, g: torch.Tensor) -> torch.Tensor:
        """``(I + lambda L)^{-1} g`` in the dtype of ``g``."""
        return torch.cholesky_solve(g.to(self.factor.dtype), self.factor).to(g.dtype)


class Adam(torch.optim.Adam):
    """torch's Adam; a param group with ``uniform=True`` is stepped with one second-moment scale per
    parameter (the largest entry's, Nicolet et al.'s AdamUniform) so a smooth gradient gives a smooth step.
    State keys and formats are torch's, so state dicts, checkpoints and state carry-over work unchanged."""

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        groups = self.param_groups
        uniform = [g for g in groups if g.get("uniform")]
        if len(uniform) < len(groups):
            self.param_groups = [g for g in groups if not g.get("uniform")]
            try:
                super().step()
            finally:
                self.param_groups = groups
        for g in uniform:
            b1, b2 = g["betas"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if len(st) == 0:
                    st["step"] = torch.tensor(0.0)
                    st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["step"] += 1
                t = float(st["step"])
                st["exp_avg"].lerp_(p.grad, 1 - b1)
                st["exp_avg_sq"].mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                m_hat = st["exp_avg"] / (1 - b1 ** t)
                scale = (st["exp_avg_sq"].max() / (1 - b2 ** t)).sqrt() + g["eps"]
                p.add_(m_hat / scale, alpha=-g["lr"])
        return loss


def preconditioned_step(param: torch.Tensor, pre: LargeSteps, step) -> None:
    """Run optimiser ``step()`` as Adam on ``u = M X`` for the vertex parameter ``param`` (its ``.grad`` set).

    The gradient of u is ``M^{-1} dE/dX`` (M symmetric); the optimiser's move of u maps back to X as
    ``M^{-1}`` times it. Other parameters in the optimiser step as usual.
    """
    param.grad = pre.solve(param.grad)
    old = param.data.clone()
    step()
    param.data.copy_(old + pre.solve(param.data - old))
