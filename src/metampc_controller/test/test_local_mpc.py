"""The latent MPC linearised at the current state every tick (local_mpc)."""
import numpy as np
import pytest

from metampc_bringup.studies.nonlinear_regime import collect, track
from metampc_common.excitation import ExcitationConfig
from metampc_controller.local_mpc import LINEARISATION_FAILED, LocalLinearMpc
from metampc_controller.mpc import MpcConfig
from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_model.latent_model import LatentModel
from metampc_plant.integrate import rk4_sample
from metampc_plant.registry import get_family
from metampc_controller.references import make_reference
from metampc_plant.simulator import PlantConfig

CONFIG = MpcConfig(horizon=20, q=(1.0, 0.0), r=0.05, u_min=-1.0, u_max=1.0)


class TrueVanDerPol:
    """The plant's own sampled map x+ = F(x, u) (RK4, 10 sub-steps) as a locally linear model,
    its Jacobian by central differences; state s = x = y."""

    def __init__(self, theta: float):
        self.family, self.theta = get_family('vanderpol'), np.array([[theta]])

    def step(self, x, u):
        return rk4_sample(self.family, x[None], np.atleast_1d(u)[None], self.theta, 0.1, 10)[0]

    def linearise(self, s, u):
        eps = 1e-6
        a = np.stack([(self.step(s + eps * e, u) - self.step(s - eps * e, u)) / (2 * eps)
                      for e in np.eye(2)], axis=1)
        b = ((self.step(s, u + eps) - self.step(s, u - eps)) / (2 * eps))[:, None]
        return LatentModel(a, b, np.eye(2), self.step(s, u) - a @ s - b @ u, np.zeros(2))

    @staticmethod
    def state(u_hist, y_hist):
        return y_hist[-1]


PLANT = PlantConfig(family='vanderpol', dt=0.1, substeps=10, u_min=(-1.0,), u_max=(1.0,))


def _cost(planner, theta, setpoints, model=None):
    ref = make_reference('setpoint_sequence', setpoints=setpoints, segment=7.5, outputs=(0,),
                         n_y=2)
    return track(planner, PLANT, (theta,), (0.0, 0.0), ref, int(len(setpoints) * 75), (0,),
                 None if model is None else model.state)


def test_on_the_true_model_it_holds_the_set_points_where_the_nmpc_does():
    """theta* 1.5, the paper's first two set-points (the step to -0.5 is where every fixed
    linear model fell into the limit cycle): the cost within 1.15 of the true-model NMPC's
    (measured 1.131 here, 1.122 over the whole reference, 2026-12-08: docs/nonlinear.md)."""
    model = TrueVanDerPol(1.5)
    local = _cost(LocalLinearMpc(CONFIG, model), 1.5, (0.8, -0.5), model)
    fam = get_family('vanderpol')
    nmpc = _cost(Nmpc(NmpcConfig(**CONFIG.shared(), dt=0.1), fam, (1.5,)), 1.5, (0.8, -0.5))
    assert local <= 1.15 * nmpc
    # while one linear model fitted by least squares on 300 open-loop samples (which lie on
    # the limit cycle, so the fit averages the damping over it) falls into the limit cycle
    exc = ExcitationConfig(u_min=(-1.0,), u_max=(1.0,))
    u, y = collect(exc, PLANT, (1.5,), (0.5, 0.0), 300, 0)
    reg = np.hstack([y[:-1], u[1:], np.ones((len(u) - 1, 1))])
    w = np.linalg.lstsq(reg, y[1:], rcond=None)[0].T
    fixed = LatentModel(w[:, :2], w[:, 2:3], np.eye(2), w[:, 3], np.zeros(2))

    class Fixed:
        def linearise(self, s, u):
            return fixed
    assert _cost(LocalLinearMpc(CONFIG, Fixed()), 1.5, (0.8, -0.5), model) > 3 * local


class _Failing:
    def __init__(self, fail_after):
        self.calls, self.fail_after = 0, fail_after
        self.inner = TrueVanDerPol(1.0)

    def linearise(self, s, u):
        self.calls += 1
        if self.calls > self.fail_after:
            a = np.full((2, 2), np.nan)
            return LatentModel(a, np.ones((2, 1)), np.eye(2), np.zeros(2), np.zeros(2))
        return self.inner.linearise(s, u)


def test_a_failed_linearisation_shifts_the_previous_plan_and_is_counted():
    planner = LocalLinearMpc(CONFIG, _Failing(fail_after=1))
    ref = np.tile([0.8, 0.0], (20, 1))
    first = planner.solve(np.zeros(2), np.zeros(1), ref, np.zeros(2), 0)
    assert not first.fallback
    second = planner.solve(np.array([0.1, 0.0]), first.u, ref, np.array([0.1, 0.0]), 1)
    assert second.fallback and second.status == LINEARISATION_FAILED
    np.testing.assert_array_equal(second.u_plan[:-1], first.u_plan[1:])
    assert planner.failed_linearisations == 1
    third = planner.solve(np.array([np.nan, 0.0]), second.u, ref, None, 2)
    assert third.fallback and np.all(np.isfinite(third.u_plan))
    assert np.all(np.abs(third.u_plan) <= 1.0) and planner.failed_linearisations == 2


def test_a_first_tick_failure_holds_the_input_within_bounds():
    planner = LocalLinearMpc(CONFIG, _Failing(fail_after=0))
    res = planner.solve(np.zeros(2), np.array([3.0]), np.zeros((20, 2)), None, 0)
    assert res.fallback
    np.testing.assert_array_equal(res.u_plan, np.ones((20, 1)))


@pytest.mark.parametrize('form', ['state', 'none'])
def test_the_planner_plans_without_an_offset_free_estimator(form):
    from dataclasses import replace
    planner = LocalLinearMpc(replace(CONFIG, offset_free=form), TrueVanDerPol(1.0))
    assert planner.config.offset_free == 'none'


def test_new_constants_move_the_prediction_as_a_rollout_of_the_new_model_does():
    """set_constants (the rebuild-free path): the plan's prediction is a rollout of the model
    with the new e under the returned plan (fails if the data vector kept the old e)."""
    from dataclasses import replace as swap
    from metampc_controller.mpc import LatentMpc
    model = TrueVanDerPol(0.5).linearise(np.array([0.2, 0.1]), np.zeros(1))
    mpc = LatentMpc(swap(CONFIG, offset_free='none'))
    mpc.set_model(model)
    e_new = model.e + np.array([0.01, -0.02])
    mpc.set_constants(e_new, model.d)
    z0, ref = np.array([0.3, -0.1]), np.tile([0.5, 0.0], (20, 1))
    res = mpc.solve(z0, np.zeros(1), ref)
    moved = swap(model, e=e_new)
    z, pred = z0, []
    for u in res.u_plan:
        z = moved.step(z, u)
        pred.append(moved.output(z))
    np.testing.assert_allclose(res.y_pred, np.array(pred), atol=1e-9)
    with pytest.raises(ValueError, match='offset-free'):
        on = LatentMpc(swap(CONFIG, offset_free='state'))
        on.set_model(model)
        on.set_constants(e_new, model.d)


def test_a_linear_model_is_set_up_once_and_a_tolerance_skips_small_moves():
    class Linear:
        def __init__(self):
            self.fixed = TrueVanDerPol(0.5).linearise(np.zeros(2), np.zeros(1))

        def linearise(self, s, u):
            return self.fixed
    planner = LocalLinearMpc(CONFIG, Linear())
    for k in range(5):
        planner.solve(np.full(2, 0.1 * k), np.zeros(1), np.zeros((20, 2)), None, k)
    assert planner.rebuilds == 1
    model = TrueVanDerPol(1.0)
    exact, loose = LocalLinearMpc(CONFIG, model), LocalLinearMpc(CONFIG, model, 0.05)
    for k in range(5):
        for planner in (exact, loose):
            planner.solve(np.array([0.5 + 0.001 * k, 0.0]), np.zeros(1), np.zeros((20, 2)),
                          None, k)
    assert exact.rebuilds == 5 and loose.rebuilds == 1
    with pytest.raises(ValueError, match='rebuild_tol'):
        LocalLinearMpc(CONFIG, model, -1.0)
