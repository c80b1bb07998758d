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


def _vdp_rk4(x, u, theta, dt, substeps):
    """One sample of x1' = x2, x2' = theta x2 (1 - x1^2) - x1 + u (the family's docstring) by
    classical RK4 with u held, written out here."""
    def f(s):
        return np.array([s[1], theta * s[1] * (1.0 - s[0] ** 2) - s[0] + u])
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def test_the_plant_integrates_each_sample_with_the_theta_of_its_start_away_from_rest():
    """Pins the step at which the plant core (Plant.step) applies the schedule, away from the
    equilibrium (where every theta gives the same state): x0 = (1, 0.5), inputs 0.5 sin(0.3 k),
    dt = 0.05 s, a step 0.5 -> 1.5 at 30 s (step 600; 600 x 0.05 is 30.000000000000004) and a
    ramp to 0.8 over [31, 32] s (steps 620..640). Independent answer: the van der Pol equations
    integrated here by RK4, the sample from step k to k + 1 with theta(k dt) read off the
    schedule by hand. The same integration with the step one sample early or late differs by
    far more than the tolerance."""
    dt, substeps, n = 0.05, 10, 660
    plant = Plant(PlantConfig(theta=(0.5,), dt=dt, x0=(1.0, 0.5),
                              theta_schedule=(30.0, 30.0, 1.5, 31.0, 32.0, 0.8)))
    assert plant.config.substeps == substeps
    inputs = 0.5 * np.sin(0.3 * np.arange(n))

    def theta_by_hand(k, change=600):
        if k < change:
            return 0.5
        return 1.5 if k <= 620 else (0.8 if k >= 640 else 1.5 - 0.7 * (k - 620) / 20)

    def by_hand(change):
        x, out = np.array([1.0, 0.5]), []
        for k in range(n):
            x = _vdp_rk4(x, inputs[k], theta_by_hand(k, change), dt, substeps)
            out.append(x)
        return np.array(out)

    got = np.array([plant.step([u]) for u in inputs])
    assert np.abs(got).max() < 5.0      # bounded: no escape, no clipping (|u| <= 1)
    want = by_hand(600)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    for shifted in (599, 601):
        assert np.abs(by_hand(shifted) - want)[595:].max() > 1e-4
