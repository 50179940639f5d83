"""ERA (Juang 1994; paper 000 footnote 1): exact Markov parameters give the exact system back."""

from __future__ import annotations

import numpy as np
import pytest

from hammer_ros.errors import IdentificationError
from hammer_ros.identification.era import eigensystem_realization, era_linear_model
from hammer_ros.identification.linear import LinearModel, root_rss_error
from hammer_ros.tools.reproduce.cls import G2


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
