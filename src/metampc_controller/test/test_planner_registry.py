"""The planners by name: one clear error for an unknown name, and every planner of the
registry answers with the one result type, its fields checked against independent answers."""
import numpy as np
import pytest

from metampc_controller.controller_core import ControllerCore
from metampc_controller.controller_params import ControllerConfig, PLANNERS
from metampc_controller.mpc import MpcConfig
from metampc_controller.planner import PlanResult
from metampc_controller.planner_registry import planner_kind, REGISTRY, TrueModel
from metampc_model.latent_model import LatentModel
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig

N = 8
CONFIG = MpcConfig(horizon=N, q=(1.0, 0.2), r=0.05, u_min=-0.7, u_max=0.9, offset_free='none',
                   time_limit=30.0)     # what the solver answers, not how fast
Y_REF = np.tile([0.4, 0.0], (N, 1))


def test_an_unknown_planner_is_one_clear_error():
    """The registry's look-up, and a core built in code with that name (the node's parse
    refuses it before: choices). Before, the core took any other name for the NMPC and
    answered 'no_plant_info' forever."""
    message = r"^unknown planner 'pid' \(known: latent_mpc, nmpc\)$"
    with pytest.raises(ValueError, match=message):
        planner_kind('pid')
    with pytest.raises(ValueError, match=message):
        ControllerCore(ControllerConfig(planner='pid'))
    assert PLANNERS == tuple(REGISTRY) == ('latent_mpc', 'nmpc')   # the parameter's choices


def _latent_model() -> LatentModel:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 3))
    return LatentModel(A=0.8 * a / np.max(np.abs(np.linalg.eigvals(a))), B=rng.normal(size=(3, 1)),
                       C=rng.normal(size=(2, 3)), e=rng.normal(size=3) * 0.1,
                       d=np.array([0.05, -0.02]))


def _check_filled(res: PlanResult, n_u: int, n_y: int) -> None:
    assert type(res) is PlanResult
    assert res.u_plan.shape == (N, n_u) and res.y_pred.shape == (N, n_y)
    np.testing.assert_array_equal(res.u, res.u_plan[0])
    assert res.status == 'solved' and res.iterations > 0 and res.solve_time > 0.0
    assert np.isfinite(res.cost) and not res.fallback
    assert np.all((res.u_plan >= -0.7) & (res.u_plan <= 0.9))
    assert np.abs(res.u_plan).max() > 1e-3     # it did plan something


def test_the_latent_mpc_by_name_answers_a_plan_result_of_its_model():
    """y_pred is the model's own rollout of u_plan from z_t (eq. (mpc)'s prediction)."""
    model = _latent_model()
    planner = REGISTRY['latent_mpc'].build(ControllerConfig(mpc=CONFIG), model)
    z, u = np.array([0.3, -0.2, 0.1]), np.array([0.1])
    res = planner.solve(z, u, Y_REF, model.C @ z + model.d, 0)
    _check_filled(res, 1, 2)
    ys = []
    for u_k in res.u_plan:
        z = model.A @ z + model.B @ u_k + model.e
        ys.append(model.C @ z + model.d)
    np.testing.assert_allclose(res.y_pred, ys, atol=1e-12)


def test_the_nmpc_by_name_answers_a_plan_result_of_the_plant():
    """Built from the controller's MpcConfig: its horizon, weights and bounds (one
    declaration), plant_info's dt and the controller's nmpc_tail. y_pred is the plant
    simulator's response to u_plan (same RK4, 2 substeps), the cost J of eq. (mpc) with Q on
    all N outputs recomputed from it (no tail)."""
    family = get_family('vanderpol')
    model = TrueModel(family, (0.5,), 0.1)
    planner = REGISTRY['nmpc'].build(ControllerConfig(mpc=CONFIG), model)
    cfg = planner.config
    assert (cfg.horizon, cfg.q, cfg.r, cfg.u_min, cfg.u_max, cfg.dt, cfg.tail) == (
        N, CONFIG.q, CONFIG.r, CONFIG.u_min, CONFIG.u_max, 0.1, 0)
    tailed = REGISTRY['nmpc'].build(ControllerConfig(mpc=CONFIG, nmpc_tail=3), model)
    assert tailed.config.tail == 3      # the controller's nmpc_tail
    y, u = np.array([0.2, -0.1]), np.array([0.1])
    res = planner.solve(None, u, Y_REF, y, 0)        # the state from y (y = x here)
    _check_filled(res, 1, 2)
    plant = Plant(PlantConfig(theta=(0.5,), dt=0.1, substeps=2, x0=tuple(y)))
    ys = np.array([plant.step(u_k) for u_k in res.u_plan])
    np.testing.assert_allclose(res.y_pred, ys, atol=1e-12)
    err = ys - Y_REF
    du = np.diff(np.concatenate([u, res.u_plan[:, 0]]))
    assert res.cost == pytest.approx(np.sum(err ** 2 * [1.0, 0.2]) + 0.05 * np.sum(du ** 2),
                                     rel=1e-12)
