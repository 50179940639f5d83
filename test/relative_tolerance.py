"""Equality of a compiled kernel's outputs to its numpy reference, relative to the reference's scale
(the compiled solves' tests: ``test_compiled_cls.py``, ``test_compiled_plls.py``)."""

from __future__ import annotations

import numpy as np


def assert_close(compiled, reference, name: str, tolerance: float = 1e-9) -> None:
    """Equal to ``tolerance`` relative to the reference's largest magnitude (entry by entry)."""
    compiled, reference = np.asarray(compiled), np.asarray(reference)
    assert compiled.shape == reference.shape, name
    if reference.size:
        scale = max(float(np.max(np.abs(reference))), 1e-300)
        assert np.max(np.abs(compiled - reference)) <= tolerance * scale, (name, compiled, reference)
