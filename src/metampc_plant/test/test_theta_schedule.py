"""theta_schedule: steps and ramps of theta over plant time, checked against np.interp on the
schedule's breakpoints, the exact step a change lands at, and the refusals."""
import numpy as np
import pytest

from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig
from metampc_plant.theta_schedule import ThetaSchedule

VDP = get_family('vanderpol')


def test_steps_and_ramps_against_interpolation_of_the_breakpoints():
    schedule = ThetaSchedule.parse([10, 10, -0.5, 20, 40, 1.5, 50, 50, 0.0], VDP, [0.5])
    # The same function by np.interp: a step is two breakpoints at (almost) one time.
    eps = 1e-9
    xs = [0, 10 - eps, 10, 20, 40, 50 - eps, 50, 60]
    fs = [0.5, 0.5, -0.5, -0.5, 1.5, 1.5, 0.0, 0.0]
    for t in np.linspace(0, 60, 1201):
        assert schedule.theta_at(t)[0] == pytest.approx(np.interp(t, xs, fs), abs=1e-12), t
    assert schedule.boundaries_passed(9.99) == 0 and schedule.boundaries_passed(10) == 2
    assert schedule.boundaries_passed(30) == 3 and schedule.boundaries_passed(60) == 6
    assert schedule.flat() == (10, 10, -0.5, 20, 40, 1.5, 50, 50, 0.0)


def test_a_vector_theta_ramps_every_component():
    duffing = get_family('duffing')
    schedule = ThetaSchedule.parse([0, 10, 0.5, -1.0, 1.5], duffing, [0.1, 1.0, 0.5])
    assert schedule.theta_at(5.0) == pytest.approx((0.3, 0.0, 1.0))
    assert schedule.theta_at(12.0) == (0.5, -1.0, 1.5)


def test_the_plant_changes_theta_at_the_exact_step():
    """A step at t = 30 s with dt = 0.05 s: the sample from step 600 on is integrated with the
    new theta (600 x 0.05 is 30.000000000000004 in floats: the plant time is rounded to ns)."""
    plant = Plant(PlantConfig(theta=(0.5,), dt=0.05, theta_schedule=(30.0, 30.0, -0.5)))
    thetas = [plant.theta[0]]
    for _ in range(602):
        plant.step([0.0])
        thetas.append(plant.theta[0])   # theta(k dt) after step k
    assert thetas[599] == 0.5 and thetas[600] == -0.5
    # The sample from step 600 on was integrated with -0.5: the same as a plant reset there.
    twin = Plant(PlantConfig(theta=(0.5,), dt=0.05))
    for _ in range(600):
        twin.step([0.0])
    x600 = twin.x
    twin.reset(theta=[-0.5], x0=x600)
    plant_b = Plant(PlantConfig(theta=(0.5,), dt=0.05, theta_schedule=(30.0, 30.0, -0.5)))
    for _ in range(601):
        y = plant_b.step([0.0])
    assert np.array_equal(y, twin.step([0.0]))
    # A reset restarts the episode's schedule; another one replaces it.
    plant.reset(x0=[1.0, 0.0])
    assert plant.theta == (0.5,) and plant.time == 0.0
    plant.reset(schedule=[0.0, 0.0, 1.0])
    plant.step([0.0])
    assert plant.theta == (1.0,)


@pytest.mark.parametrize('flat, match', [
    ([30.0, 30.0], 'rows of 3 values'),
    ([30.0, 20.0, 1.0], 't_start <= t_end'),
    ([10.0, 20.0, 1.0, 15.0, 15.0, 0.0], 'need 20 <= t_start'),
    ([-1.0, 0.0, 1.0], 'need 0 <= t_start'),
    ([5.0, 5.0, float('nan')], 'must be finite'),
    ([5.0, 5.0, 4.5], r'theta = 4.5 lies outside the range \[-4, 4\] of family vanderpol'),
])
def test_bad_schedules_are_refused_naming_the_row(flat, match):
    with pytest.raises(ValueError, match=match):
        ThetaSchedule.parse(flat, VDP, [0.0])


def test_a_uniform_prior_bounds_the_schedule():
    pendulum = get_family('pendulum')
    with pytest.raises(ValueError, match=r'l = 2 lies outside the range \[0.5, 1.5\]'):
        ThetaSchedule.parse([1, 1, 1.0, 2.0, 0.1], pendulum, pendulum.nominal_theta)
    with pytest.raises(ValueError, match='theta_schedule'):
        PlantConfig(family='pendulum', theta_schedule=(1, 1, 1.0, 2.0, 0.1)).resolved()
