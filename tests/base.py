"""Shared helpers for numerical tests, in the manner of kornia's ``BaseTester``.

* :func:`assert_close` picks tolerances from the dtype (float16/32/64).
* :func:`gradcheck` runs :func:`torch.autograd.gradcheck` in float64 on copies
  of the inputs that require gradients.
* ``DTYPES`` parametrises a test over float32 and float64.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pytest
import torch

__all__ = ["DTYPES", "TOLERANCES", "BaseTester", "assert_close", "gradcheck"]

# (rtol, atol) per dtype, as in kornia's testing module
TOLERANCES = {
    torch.float16: (1e-3, 1e-3),
    torch.bfloat16: (1e-2, 1e-2),
    torch.float32: (1e-4, 1e-5),
    torch.float64: (1e-7, 1e-7),
}
DTYPES = pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])


def assert_close(
    actual: Any, expected: Any, rtol: float | None = None, atol: float | None = None
) -> None:
    """``torch.testing.assert_close`` with dtype-aware default tolerances."""
    actual_t = torch.as_tensor(actual)
    expected_t = torch.as_tensor(expected, dtype=actual_t.dtype)
    d_rtol, d_atol = TOLERANCES.get(actual_t.dtype, (0.0, 0.0))
    torch.testing.assert_close(
        actual_t,
        expected_t,
        rtol=d_rtol if rtol is None else rtol,
        atol=d_atol if atol is None else atol,
    )


def gradcheck(
    fn: Callable[..., Any],
    inputs: Sequence[Any],
    requires_grad: Sequence[bool] | None = None,
    **kwargs: Any,
) -> bool:
    """Float64 ``gradcheck`` of ``fn(*inputs)``.

    Tensor inputs are cast to float64; those flagged in ``requires_grad``
    (default: every floating tensor) get ``requires_grad=True``.
    """
    prepared = []
    for i, x in enumerate(inputs):
        if isinstance(x, torch.Tensor) and x.is_floating_point():
            x = x.detach().to(torch.float64)
            flag = True if requires_grad is None else requires_grad[i]
            x.requires_grad_(flag)
        prepared.append(x)
    kwargs.setdefault("eps", 1e-6)
    kwargs.setdefault("atol", 1e-5)
    kwargs.setdefault("rtol", 1e-3)
    return torch.autograd.gradcheck(fn, tuple(prepared), **kwargs)


class BaseTester:
    """Mix-in giving test classes the helpers above as methods."""

    @staticmethod
    def assert_close(
        actual: Any, expected: Any, rtol: float | None = None, atol: float | None = None
    ) -> None:
        assert_close(actual, expected, rtol, atol)

    @staticmethod
    def gradcheck(fn: Callable[..., Any], inputs: Sequence[Any], **kwargs: Any) -> bool:
        return gradcheck(fn, inputs, **kwargs)
