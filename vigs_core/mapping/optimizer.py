"""Adam over the rows of a Gaussian map, with state that follows rows being added and removed.

Per parameter tensor ``x`` (N, ...) with gradient ``g``: ``m <- b1 m + (1 - b1) g``,
``v <- b2 v + (1 - b2) g^2``, ``x <- x - lr (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)``
(Kingma and Ba 2015, Alg. 1). The step count ``t`` is kept per row, so Gaussians created later get the
same bias correction as fresh parameters, and rows without gradient (not seen in the rendered view)
are left untouched, as in sparse Adam.
"""
from __future__ import annotations

import numpy as np
import torch


class RowAdam:
    """Adam for a dict of row-aligned tensors ``{name: (N, ...)}`` with per-name learning rates.

    Args:
        lrs: learning rate per parameter name.
        betas: Adam's ``(b1, b2)``.
        eps: Adam's epsilon.
        compiled: on CPU, update the rows in one compiled kernel (:mod:`vigs_core.mapping.adam_numba`; needs
            numba) instead of gathering and scattering them with tensor operations.
    """

    def __init__(self, lrs: dict[str, float], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15,
                 compiled: bool = False):
        self.lrs = dict(lrs)
        self.compiled = compiled
        self.betas = betas
        self.eps = eps
        self.m: dict[str, torch.Tensor] = {}
        self.v: dict[str, torch.Tensor] = {}
        self.t: torch.Tensor | None = None

    def _ensure(self, params: dict[str, torch.Tensor]) -> None:
        n = next(iter(params.values())).shape[0]
        if self.t is None:
            device = next(iter(params.values())).device
            self.t = torch.zeros(0, dtype=torch.int64, device=device)
            for k, p in params.items():
                self.m[k] = p.new_zeros((0,) + p.shape[1:])
                self.v[k] = p.new_zeros((0,) + p.shape[1:])
        if self.t.shape[0] != n:
            raise RuntimeError(f"optimiser tracks {self.t.shape[0]} rows but the parameters have {n}")

    def add_rows(self, count: int, like: dict[str, torch.Tensor]) -> None:
        """Append ``count`` fresh rows (zero moments) shaped like the tensors in ``like``."""
        if self.t is None:
            self._ensure({k: v[:0] for k, v in like.items()})
        for k, p in like.items():
            self.m[k] = torch.cat((self.m[k], p.new_zeros((count,) + p.shape[1:])))
            self.v[k] = torch.cat((self.v[k], p.new_zeros((count,) + p.shape[1:])))
        self.t = torch.cat((self.t, self.t.new_zeros(count)))

    def keep_rows(self, keep: torch.Tensor) -> None:
        """Keep only the rows where the bool mask ``keep`` (N,) is true."""
        if self.t is None:
            return
        for k in self.m:
            self.m[k] = self.m[k][keep]
            self.v[k] = self.v[k][keep]
        self.t = self.t[keep]

    def reset_rows(self, rows: torch.Tensor) -> None:
        """Forget the moments of ``rows`` (bool mask (N,)), e.g. after the rows were moved rigidly."""
        if self.t is None:
            return
        for k in self.m:
            self.m[k][rows] = 0.0
            self.v[k][rows] = 0.0
        self.t[rows] = 0

    @torch.no_grad()
    def step(self, params: dict[str, torch.Tensor], touched: torch.Tensor, grads: dict[str, torch.Tensor]) -> None:
        """One Adam update of ``params`` on the rows ``touched`` (int64 (M,)), given the gradients of those
        rows ``grads[name]`` (M, ...); parameters without an entry in ``grads`` are left as they are."""
        self._ensure(params)
        for k, g in grads.items():
            want = (touched.shape[0],) + params[k].shape[1:]
            if tuple(g.shape) != want:
                raise ValueError(f"gradient of {k!r} has shape {tuple(g.shape)}, need {want}")
        b1, b2 = self.betas
        self.t[touched] += 1
        if self._compiled(params, grads):
            from vigs_core.mapping.adam_numba import adam_rows

            rows = touched.numpy()

            def arrays(tensors: dict[str, torch.Tensor], n: int) -> tuple:   # (n, C) views, in the order of grads
                return tuple(tensors[k].numpy().reshape(n, -1) for k in grads)

            n = self.t.shape[0]
            adam_rows(arrays(params, n), arrays(self.m, n), arrays(self.v, n),
                      arrays({k: g.contiguous() for k, g in grads.items()}, len(rows)),
                      np.array([self.lrs[k] for k in grads]), self.t.numpy(), rows, b1, b2, self.eps)
            return
        t = self.t[touched].to(next(iter(params.values())).dtype)
        c1 = 1.0 - b1**t
        c2 = 1.0 - b2**t
        for k, g in grads.items():
            p = params[k]
            m = self.m[k][touched].mul_(b1).add_(g, alpha=1.0 - b1)
            v = self.v[k][touched].mul_(b2).addcmul_(g, g, value=1.0 - b2)
            self.m[k][touched] = m
            self.v[k][touched] = v
            shape = (-1,) + (1,) * (p.dim() - 1)
            update = (m / c1.view(shape)) / ((v / c2.view(shape)).sqrt_().add_(self.eps))
            p[touched] -= self.lrs[k] * update

    def _compiled(self, params: dict[str, torch.Tensor], grads: dict[str, torch.Tensor]) -> bool:
        """Whether :meth:`step` takes the compiled path (:mod:`vigs_core.mapping.adam_numba`): ``compiled`` set, some
        gradient given, and every tensor a contiguous CPU tensor without gradient (numpy views of them are updated in
        place) of one dtype (the kernel takes them as one tuple)."""
        tensors = [params[k] for k in grads] + [self.m[k] for k in grads] + [self.v[k] for k in grads]
        return self.compiled and bool(grads) and len({x.dtype for x in tensors}) == 1 and all(
            x.device.type == "cpu" and x.is_contiguous() and not x.requires_grad for x in tensors)
