"""The shipped plant families against their equations, written out again in
test/family_equations.py and integrated by scipy (DOP853, rtol 1e-12): each one-step
prediction of the plant core within 1e-6. The equations there are copied from
docs/families.md, not imported, so a slip in a family's code shows up as a mismatch.
"""
from family_equations import OUTPUT_GAIN, one_step
import numpy as np
import pytest

from metampc_plant.family import PlantFamily, Signal, ThetaComponent
from metampc_plant.registry import family_names, get_family, UnknownFamily
from metampc_plant.simulator import Plant, PlantConfig

SHIPPED = ('cascaded_tanks', 'duffing', 'pendulum', 'quadruple_tank', 'vanderpol')
# RK4 integrates these to 1e-6 everywhere; the cascaded tanks' spill at the rims is a kink,
# tested on its own (test_cascaded_tanks.py: 1e-6 away from the rims, 1e-3 V across them).
SMOOTH = tuple(name for name in SHIPPED if name != 'cascaded_tanks')


def held_inputs(family: PlantFamily, n: int, rng: np.random.Generator, hold: int = 5):
    """Uniform levels within the family's bounds, each held `hold` samples: (n, n_u)."""
    levels = rng.uniform(family.u_min, family.u_max, size=(-(-n // hold), family.n_u))
    return np.repeat(levels, hold, axis=0)[:n]


def test_the_shipped_families_are_registered():
    assert set(SHIPPED) <= set(family_names())
    with pytest.raises(UnknownFamily, match="unknown plant family 'tank'; installed: "
                                            'cascaded_tanks, duffing'):
        get_family('tank')


@pytest.mark.parametrize('name', SMOOTH)
def test_one_step_error_against_scipy_below_1e6(name):
    family = get_family(name)
    rng = np.random.default_rng(7)
    worst = 0.0
    for theta in family.sample_theta(rng, 3):
        plant = Plant(PlantConfig(family=name, theta=tuple(theta)))
        x = rng.uniform(family.x0_low, family.x0_high)
        plant.reset(x0=x)
        gain = OUTPUT_GAIN.get(name, np.eye(family.n_x))
        for u in held_inputs(family, 60, rng):
            x_ref = one_step(name, plant.x, u, theta, plant.config.dt)
            y = plant.step(u)
            assert not plant.diverged
            worst = max(worst, np.abs(plant.x - x_ref).max(), np.abs(y - gain @ x_ref).max())
    assert worst < 1e-6, f'{name}: worst one-step error {worst:.2e}'


@pytest.mark.parametrize('name', SHIPPED)
def test_prior_is_seeded_and_within_its_support(name):
    family = get_family(name)
    draws = family.sample_theta(np.random.default_rng(3), 2000)
    assert draws.shape == (2000, family.n_theta)
    assert np.array_equal(draws, family.sample_theta(np.random.default_rng(3), 2000))
    for j, comp in enumerate(family.theta):
        if comp.distribution == 'uniform':
            assert comp.a <= draws[:, j].min() and draws[:, j].max() <= comp.b
            assert abs(draws[:, j].mean() - comp.nominal) < 0.05 * (comp.b - comp.a)
        else:
            assert abs(draws[:, j].mean() - comp.a) < 0.1 and abs(draws[:, j].std() - comp.b) < 0.1
    labels = [s.label() for s in family.states + family.inputs + family.outputs]
    assert len(set(labels)) >= family.n_x and all(labels)


def test_quadruple_tank_targets_are_minimum_phase_or_not():
    # g1 + g2 > 1: minimum phase; < 1: a right-half-plane zero. Theta = U(0.3, 0.8)^2 holds
    # both: P(g1 + g2 <= 1) is the triangle g1 + g2 - 0.6 <= 0.4 of the 0.5 x 0.5 square.
    draws = get_family('quadruple_tank').sample_theta(np.random.default_rng(0), 4000)
    share = np.mean(draws.sum(axis=1) > 1.0)
    assert 0.64 < share < 0.72   # 1 - 0.4^2 / 2 / 0.25 = 0.68; std of the share 0.007


class Falling(PlantFamily):
    """x' = u, the least a family has to write."""

    def rhs(self, x, u, theta):
        return (u[0],)


def test_a_bad_family_definition_is_one_clear_error():
    with pytest.raises(ValueError, match='u_min needs 1 values'):
        Falling(name='bad', title='', states=(Signal('x'),), inputs=(Signal('u'),),
                outputs=(Signal('x'),), theta=(ThetaComponent('k'),), u_min=(), u_max=(1.0,),
                state_bound=1.0, x0=(0.0,), x0_low=(0.0,), x0_high=(0.0,), dt=0.1,
                noise_states=(), reference=(0.0,), tracked=(0,))
    with pytest.raises(ValueError, match='distribution must be one of'):
        ThetaComponent('k', distribution='lognormal')
