"""ERA (Juang 1994; paper 000 footnote 1): exact Markov parameters give the exact system back."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.errors import IdentificationError
from hammer_ros.identification.era import eigensystem_realization, era_linear_model
from hammer_ros.identification.linear import LinearModel, root_rss_error
from hammer_ros.reproduce.cls import G2


def test_exact_markov_parameters_of_g1_give_its_poles_and_zeros(g1):
    model = era_linear_model(g1.markov_parameters(31), order=3, delay=1)  # h_0 .. h_30: mu = 30
    assert root_rss_error(g1.poles, model.poles) < 1e-10
    assert root_rss_error(g1.zeros, model.zeros) < 1e-10
    np.testing.assert_allclose(model.b, g1.b, atol=1e-12)
    np.testing.assert_allclose(model.a, g1.a, atol=1e-12)
    assert model.delay == 1


def test_g2_order_5_and_the_realisation_reproduces_every_markov_parameter():
    h = G2.markov_parameters(31)
    realisation = eigensystem_realization(h, order=5)
    assert realisation.A.shape == (5, 5) and realisation.B.shape == (5, 1) and realisation.C.shape == (1, 5)
    np.testing.assert_allclose(realisation.markov_parameters(31), h, atol=1e-12)
    model = realisation.to_linear_model(delay=1)
    assert root_rss_error(G2.poles, model.poles) < 1e-9
    assert root_rss_error(G2.zeros, model.zeros) < 1e-9
    # the Hankel singular values drop to rounding level after the true order
    s = realisation.hankel_singular_values
    assert s[4] > 1e-3 * s[0] and s[5] < 1e-12 * s[0]


def test_direct_feedthrough_and_longer_delay():
    feedthrough = LinearModel([0.5, -0.2, 0.1], [1.0, -0.6, 0.25])  # d = 0: D = h_0 = 0.5
    model = era_linear_model(feedthrough.markov_parameters(20), order=2)
    np.testing.assert_allclose(model.b, feedthrough.b, atol=1e-12)
    np.testing.assert_allclose(model.a, feedthrough.a, atol=1e-12)

    delayed = LinearModel([0.0, 0.0, 1.0, 0.3], [1.0, -0.9, 0.2, 0.05])  # d = 2
    model = era_linear_model(delayed.markov_parameters(25), order=3, delay=2)
    assert model.delay == 2 and model.zeros.size == 1
    assert root_rss_error(delayed.zeros, model.zeros) < 1e-9
    assert root_rss_error(delayed.poles, model.poles) < 1e-9


def test_hankel_size_and_rank_errors_name_the_problem(g1):
    with pytest.raises(IdentificationError, match="order 3 needs a Hankel matrix"):
        eigensystem_realization(g1.markov_parameters(5), order=3)  # 4 parameters: 2 x 2 at most
    with pytest.raises(IdentificationError, match="Markov parameters"):
        eigensystem_realization(g1.markov_parameters(10), order=2, rows=8, columns=8)
    with pytest.raises(IdentificationError, match="rank"):
        eigensystem_realization(np.zeros(20), order=1)


def test_transfer_function_and_roots_as_numpy_computes_them():
    """The direct LAPACK eigenvalues, the characteristic polynomial and the poles/zeros of a
    ``LinearModel`` are np.linalg.eigvals, np.poly and the sorted np.roots of the padded
    polynomials (trailing zeros: roots at the origin, cancelled in pairs)."""
    from hammer_ros.identification.linear import characteristic_polynomial, eigenvalues

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 5, 8):
        for _ in range(20):
            a = rng.normal(size=(n, n))
            np.testing.assert_allclose(eigenvalues(a), np.linalg.eigvals(a), rtol=1e-13, atol=1e-13)
            assert np.iscomplexobj(eigenvalues(a)) == np.iscomplexobj(np.linalg.eigvals(a))
            np.testing.assert_allclose(characteristic_polynomial(a), np.poly(a), rtol=1e-12, atol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        eigenvalues(np.array([[np.nan, 0.0], [0.0, 1.0]]))

    def reference(model):  # np.roots of the equal-length polynomials, common roots at 0 cancelled, sorted
        length = max(model.a.size, model.b.size)
        z = list(np.roots(np.pad(model.b, (0, length - model.b.size))).astype(complex)) if np.any(model.b) else []
        p = list(np.roots(np.pad(model.a, (0, length - model.a.size))).astype(complex))
        while 0j in z and 0j in p:
            z.remove(0j)
            p.remove(0j)
        out = []
        for r in (np.array(z, dtype=complex), np.array(p, dtype=complex)):
            r = np.where(np.abs(r.imag) < 1e-12, r.real + 0j, r)
            out.append(r[np.lexsort((r.imag, r.real))])
        return out

    for b, a in (([0.0, 1.0, -0.5], [1.0, -1.5, 0.7]), ([0.0, 0.0, 2.0], [1.0, 0.0, 0.0]),
                 ([1.0, 0.0], [1.0, -0.9, 0.2, 0.0]), ([0.0], [1.0, 0.5]), ([0.0, 1.0, -2.0, 1.0], [1.0, -1.5, 0.56]),
                 (rng.normal(size=4), [1.0, *rng.normal(size=5)])):
        model = LinearModel(np.array(b), np.array(a))
        zeros, poles = reference(model)
        np.testing.assert_allclose(model.zeros, zeros, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(model.poles, poles, rtol=1e-13, atol=1e-13)
        assert model.poles is not model.poles  # copies: a caller cannot change the cached roots


def test_direct_lapack_calls_as_numpy_computes_them():
    """ERA's SVD and the engine's symmetric eigenvalues are np.linalg.svd and np.linalg.eigvalsh (the
    same LAPACK routines without numpy's wrappers); the cached Hankel indices cannot be changed."""
    from hammer_ros.identification.era import _hankel_indices, _svd
    from hammer_ros.identification.linear import symmetric_eigenvalues

    rng = np.random.default_rng(10)
    for shape in ((15, 15), (16, 15), (4, 9), (1, 1)):
        m = rng.normal(size=shape)
        for got, expected in zip(_svd(m), np.linalg.svd(m), strict=True):
            np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)
    for n in (1, 2, 7, 12):
        m = rng.normal(size=(n, n))
        m = m + m.T
        np.testing.assert_allclose(symmetric_eigenvalues(m), np.linalg.eigvalsh(m), rtol=1e-12, atol=1e-13)
        lower_only = np.tril(m) + np.triu(np.full((n, n), 1e3), 1)  # eigvalsh reads the lower triangle
        np.testing.assert_allclose(symmetric_eigenvalues(lower_only), np.linalg.eigvalsh(lower_only), rtol=1e-12,
                                   atol=1e-12)
    first, second = _hankel_indices(3, 2)
    np.testing.assert_array_equal(first, [[1, 2], [2, 3], [3, 4]])
    np.testing.assert_array_equal(second, first + 1)
    assert _hankel_indices(3, 2)[0] is first and not first.flags.writeable and not second.flags.writeable


def test_stability_is_every_pole_inside_the_unit_circle():
    """``is_stable``: a Python bool, True when every pole has modulus below 1 (also without poles)."""
    assert LinearModel.from_zeros_poles([0.5], [0.9, 0.2 + 0.3j, 0.2 - 0.3j]).is_stable() is True
    assert LinearModel.from_zeros_poles([], [1.0, 0.2]).is_stable() is False
    assert LinearModel.from_zeros_poles([], [-0.3 + 0.99j, -0.3 - 0.99j]).is_stable() is False
    assert LinearModel(np.array([1.0]), np.array([1.0])).is_stable() is True  # no poles
