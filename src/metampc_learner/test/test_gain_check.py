"""The gain check (gain_check.gain_verdict) on latent models built by hand."""
import numpy as np

from metampc_learner.gain_check import gain_verdict
from metampc_model.latent_model import LatentModel


def _latent(a, b, c):
    a, b, c = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (a, b, c))
    return LatentModel(A=a, B=b, C=c, e=np.zeros(a.shape[0]), d=np.zeros(c.shape[0]))


def test_a_model_of_the_right_sign_passes_whatever_its_size():
    reference = _latent(0.5, 1.0, 1.0)                       # gain 2
    verdict = gain_verdict(_latent(0.9, 3.0, 1.0), reference, [0])     # gain 30
    assert verdict.ok and verdict.reason.startswith('gain check passed')
    np.testing.assert_allclose(verdict.eigs, [2.0 / 30.0])


def test_a_model_of_the_wrong_sign_is_refused_with_the_eigenvalue():
    verdict = gain_verdict(_latent(0.5, -1.0, 1.0), _latent(0.5, 1.0, 1.0), [0])
    assert not verdict.ok
    np.testing.assert_allclose(verdict.eigs, [-1.0])
    assert 'disagrees in sign' in verdict.reason and verdict.reason.endswith('= -1)')


def test_one_direction_of_two_wrong_is_refused():
    a = 0.5 * np.eye(2)
    b = np.array([[1.0, 0.4], [0.3, 1.0]])
    flipped = b @ np.diag([1.0, -1.0])                       # the second input's effect negated
    verdict = gain_verdict(_latent(a, flipped, np.eye(2)), _latent(a, b, np.eye(2)), [0, 1])
    assert not verdict.ok and np.min(verdict.eigs.real) < 0.0 < np.max(verdict.eigs.real)


def test_only_the_tracked_outputs_count():
    a, c = 0.5 * np.eye(2), np.eye(2)
    reference = _latent(a, [[1.0], [1.0]], c)
    model = _latent(a, [[2.0], [-5.0]], c)                    # the untracked output's sign wrong
    assert gain_verdict(model, reference, [0]).ok
    assert not gain_verdict(model, reference, [1]).ok


def test_a_latent_integrator_is_left_unchecked():
    verdict = gain_verdict(_latent(1.0, -1.0, 1.0), _latent(0.5, 1.0, 1.0), [0])
    assert verdict.ok and verdict.eigs.size == 0
    assert verdict.reason == 'gain check: unchecked, the model: the latent model has a pole ' \
                             'at 1: no finite steady-state gain'


def test_an_arx_that_found_no_effect_of_the_input_refuses_the_model():
    """An ARX with b = 0 has gain 0: eig(G_arx G_m^+) is exactly 0, which is not > 0 (no sign
    to agree with): the model is refused, whatever its own gain."""
    verdict = gain_verdict(_latent(0.9, 3.0, 1.0), _latent(0.5, 0.0, 1.0), [0])
    np.testing.assert_array_equal(verdict.eigs, [0.0])
    assert not verdict.ok and 'disagrees in sign' in verdict.reason
