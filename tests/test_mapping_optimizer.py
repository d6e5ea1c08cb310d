"""RowAdam: the compiled CPU step equals the tensor-operation step; fresh rows get Adam's first step."""
from __future__ import annotations

import torch

from vigs_core.mapping.optimizer import RowAdam

LRS = {"means": 1e-2, "opacity_logits": 5e-2}


def _run(compiled: bool):
    """Four steps on overlapping random rows, then three rows appended and one step on two of them and row 0."""
    g = torch.Generator().manual_seed(1)
    params = {"means": torch.randn(50, 3, generator=g), "opacity_logits": torch.randn(50, generator=g)}
    adam = RowAdam(LRS, compiled=compiled)
    adam.add_rows(50, params)
    for step in range(4):
        rows = torch.randperm(50, generator=g)[: 20 + 5 * step]  # rows with different step counts
        grads = {k: torch.randn((len(rows),) + v.shape[1:], generator=g) for k, v in params.items()}
        adam.step(params, rows, grads)
    adam.add_rows(3, {k: v[:3] for k, v in params.items()})
    params = {k: torch.cat((v, torch.full_like(v[:3], 0.5))) for k, v in params.items()}
    adam.step(params, torch.tensor([0, 51, 52]), {k: torch.ones((3,) + v.shape[1:]) for k, v in params.items()})
    return params, adam


def test_compiled_step_equals_the_tensor_step():
    ref, ref_adam = _run(compiled=False)
    got, adam = _run(compiled=True)
    for k in ref:
        assert torch.allclose(got[k], ref[k], rtol=1e-5, atol=1e-6)
        assert torch.allclose(adam.m[k], ref_adam.m[k], rtol=1e-5, atol=1e-7)
        assert torch.allclose(adam.v[k], ref_adam.v[k], rtol=1e-5, atol=1e-9)
        # a fresh row's first step moves it by its learning rate against the gradient (m / sqrt(v) = 1)
        assert torch.allclose(got[k][51:], torch.full_like(got[k][51:], 0.5 - LRS[k]))
        assert torch.equal(got[k][50], torch.full_like(got[k][50], 0.5))  # not in the step: untouched
    assert torch.equal(adam.t, ref_adam.t) and adam.t[50:].tolist() == [0, 1, 1]


def test_compiled_step_takes_mixed_dtypes_and_no_gradients():
    """The kernel takes one tuple of one dtype: other parameter sets take the tensor step, with the same result."""
    params = {"means": torch.randn(6, 3, dtype=torch.float64), "opacity_logits": torch.randn(6)}
    results = []
    for compiled in (False, True):
        p = {k: v.clone() for k, v in params.items()}
        adam = RowAdam(LRS, compiled=compiled)
        adam.add_rows(6, p)
        adam.step(p, torch.tensor([1, 4]), {k: torch.ones((2,) + v.shape[1:], dtype=v.dtype) for k, v in p.items()})
        adam.step(p, torch.tensor([2]), {})   # no gradients: only the step count moves
        results.append((p, adam.t.tolist()))
    for k in params:
        assert torch.equal(results[0][0][k], results[1][0][k])
    assert results[0][1] == results[1][1] == [0, 1, 1, 0, 1, 0]
