"""Steady-state gain of the latent model and the agreement of two gains (steady_gain)."""
import numpy as np
import pytest

from metampc_model.latent_model import LatentModel
from metampc_model.steady_gain import agreement, steady_gain


def _latent(a, b, c):
    a, b, c = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (a, b, c))
    return LatentModel(A=a, B=b, C=c, e=np.full(a.shape[0], 0.3), d=np.full(c.shape[0], -1.0))


def test_the_model_gain_is_where_the_model_comes_to_rest():
    latent = _latent([[0.9, 0.2], [0.0, 0.5]], [[1.0, 0.0], [0.5, 2.0]], [[1.0, 0.0],
                                                                          [0.3, 1.0]])

    def rest(u):             # iterate eq. (z_next) to its fixed point, then eq. (haty)
        z = np.zeros(2)
        for _ in range(2000):
            z = latent.A @ z + latent.B @ u + latent.e
        return latent.C @ z + latent.d
    by_rest = np.stack([rest(np.eye(2)[j]) - rest(np.zeros(2)) for j in range(2)], axis=1)
    np.testing.assert_allclose(steady_gain(latent), by_rest, rtol=1e-10)
    assert steady_gain(_latent(0.9, 2.0, 0.5))[0, 0] == pytest.approx(10.0)


def test_a_latent_integrator_has_no_gain():
    with pytest.raises(ValueError, match='pole at 1'):
        steady_gain(_latent(1.0, 1.0, 1.0))


def test_agreement_on_the_tracked_outputs_leaves_out_an_output_without_gain():
    # A pendulum's gain: angle per torque, and its velocity, which has none at rest.
    reference = np.array([[0.8], [0.0]])
    wrong = np.array([[-4.0], [1e-9]])             # 5x too strong and the wrong sign
    right = np.array([[4.0], [-1e-9]])
    np.testing.assert_allclose(agreement(reference, wrong, [0]), [-0.2], rtol=1e-12)
    np.testing.assert_allclose(agreement(reference, right, [0]), [0.2], rtol=1e-12)
    # On all outputs the velocity adds an eigenvalue ~0 whose sign is rounding: a sign test
    # must not read it.
    both = sorted(agreement(reference, right).real, key=abs)
    assert abs(both[0]) < 1e-9 and both[1] == pytest.approx(0.2, rel=1e-6)
    g = np.array([[2.0, 0.5], [0.3, 1.5]])
    np.testing.assert_allclose(agreement(g, g), [1.0, 1.0], atol=1e-12)
    flipped = agreement(g, g @ np.diag([1.0, -1.0]))        # one input's effect negated
    assert np.min(flipped.real) < 0.0 < np.max(flipped.real)
    np.testing.assert_allclose(np.sort(agreement(g, 2.0 * g).real), [0.5, 0.5])
