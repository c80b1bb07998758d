"""The simulator core (van der Pol, the paper's family) against references: scipy's RK45, the
closed form at theta = 0, itself (batch vs single, seeded noise)."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from metampc_plant.families.vanderpol import FAMILY as VDP
from metampc_plant.integrate import rk4_components, rk4_sample
from metampc_plant.simulator import BatchPlant, Plant, PlantConfig, simulate

DT = 0.05
N_SAMPLES = 400  # 20 s at DT


def held_inputs(n: int, seed: int, hold: int = 10, amplitude: float = 0.5) -> np.ndarray:
    """Piecewise-constant inputs in [-amplitude, amplitude], each level held `hold` samples."""
    levels = np.random.default_rng(seed).uniform(-amplitude, amplitude, -(-n // hold))
    return np.repeat(levels, hold)[:n]


def reference(theta: float, x0, u: np.ndarray, dt: float) -> np.ndarray:
    """solve_ivp (RK45, rtol 1e-10, atol 1e-12), restarted at every sample since u jumps."""
    x = np.asarray(x0, dtype=float)
    out = [x]
    for u_k in u:
        sol = solve_ivp(lambda _t, z: [z[1], theta * z[1] * (1 - z[0] ** 2) - z[0] + u_k],
                        (0.0, dt), x, method='RK45', rtol=1e-10, atol=1e-12)
        x = sol.y[:, -1]
        out.append(x)
    return np.array(out)


def test_default_substeps_match_rk45_within_1e6():
    thetas = [-1.5, -0.5, 0.0, 0.7, 2.0]
    x0 = np.array([[0.5, -0.3]] * len(thetas))
    u = np.tile(held_inputs(N_SAMPLES, seed=1), (len(thetas), 1))
    cfg = PlantConfig(dt=DT)  # default substeps
    u_out, y, valid = simulate(thetas, x0, u, cfg)
    assert valid.all()
    np.testing.assert_array_equal(u_out[:, 1:, 0], u)
    for b, theta in enumerate(thetas):
        ref = reference(theta, x0[b], u[b], DT)
        err = np.abs(y[b] - ref).max()
        assert err <= 1e-6, f'theta={theta}: max abs error {err:.2e} vs RK45'


def test_theta_zero_is_the_harmonic_oscillator():
    # x1'' = -x1 + u: with u held over a sample, the state rotates about (u, 0) by dt rad.
    u = held_inputs(N_SAMPLES, seed=2, hold=7)
    plant = Plant(PlantConfig(theta=(0.0,), dt=DT, x0=(1.0, -0.5)))
    c, s = np.cos(DT), np.sin(DT)
    x = np.array([1.0, -0.5])
    worst = 0.0
    for u_k in u:
        d = x[0] - u_k
        x = np.array([u_k + c * d + s * x[1], -s * d + c * x[1]])
        worst = max(worst, np.abs(plant.step([u_k]) - x).max())
    assert worst <= 1e-9


def test_batch_equals_single_simulations_bit_for_bit():
    thetas = [-1.5, -0.5, 0.0, 0.7, 2.0, -1.2]
    x0 = np.array([[0.5, -0.3], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.5], [2.0, 0.0], [2.5, 2.5]])
    u = np.stack([held_inputs(200, seed=b, amplitude=1.5) for b in range(len(thetas))])
    cfg = PlantConfig(dt=DT, state_bound=5.0)
    _, y_batch, valid = simulate(thetas, x0, u, cfg)
    assert not valid[-1].all(), 'the last system should escape (it starts outside its cycle)'
    for b, theta in enumerate(thetas):
        plant = Plant(PlantConfig(theta=(theta,), dt=DT, x0=tuple(x0[b]), state_bound=5.0))
        y_single = np.array([plant.output()] + [plant.step([u_k]) for u_k in u[b]])
        assert np.array_equal(y_batch[b], y_single), f'system {b} (theta={theta}) differs'
        assert plant.diverged == (not valid[b, -1])


def test_scalar_and_vector_kernels_agree_bit_for_bit():
    rng = np.random.default_rng(3)
    x, u, theta = rng.normal(size=(50, 2)), rng.normal(size=(50, 1)), rng.normal(size=(50, 1))
    batch = rk4_sample(VDP, x, u, theta, 0.1, 7)
    single = [[float(v) for v in rk4_components(VDP, tuple(x[b]), (float(u[b, 0]),),
                                                (float(theta[b, 0]),), 0.1, 7)]
              for b in range(50)]
    assert batch.shape == (50, 2)
    assert np.array_equal(batch, np.array(single))


def test_single_plant_equals_a_batch_of_one_with_noise():
    cfg = PlantConfig(theta=(0.7,), dt=DT, x0=(0.2, 0.1), process_noise_std=0.1,
                      measurement_noise_std=0.05, seed=11)
    u = held_inputs(300, seed=4, amplitude=2.0)
    plant, batch = Plant(cfg), BatchPlant(np.array([cfg.theta]), cfg, np.array([cfg.x0]))
    for u_k in u:
        assert np.array_equal(plant.step([u_k]), batch.step(np.array([[u_k]]))[0])


def test_noise_is_seeded():
    def run(seed):
        cfg = PlantConfig(theta=(1.0,), dt=DT, process_noise_std=0.1,
                          measurement_noise_std=0.1, seed=seed)
        plant = Plant(cfg)
        return np.array([plant.step([0.1]) for _ in range(50)])
    assert np.array_equal(run(5), run(5))
    assert not np.allclose(run(5), run(6))


def test_noise_levels_change_live_from_the_next_step_on():
    """Plant.set_noise (a live parameter change): the measurement noise of every later output
    is the new std times the next normal numbers of the seeded stream, as if it had been the
    level from the start; the outputs before are untouched."""
    clean = Plant(PlantConfig(theta=(0.7,), dt=DT, x0=(0.2, 0.1)))
    noisy = Plant(PlantConfig(theta=(0.7,), dt=DT, x0=(0.2, 0.1), measurement_noise_std=0.05,
                              seed=3))
    normals = np.random.default_rng(3).standard_normal((31, 2))     # y_0, then 30 steps
    stds = [0.05] * 11 + [0.2] * 20
    errors = []
    for k in range(30):
        if k == 10:
            noisy.set_noise(0.0, 0.2)
        errors.append(noisy.step([0.3]) - clean.step([0.3]))
    np.testing.assert_allclose(errors, np.array(stds[1:])[:, None] * normals[1:], atol=1e-12)
    assert noisy.config.measurement_noise_std == 0.2


@pytest.mark.parametrize('simulator', ['single', 'batch'])
def test_process_noise_variance_is_std_squared_times_dt(simulator):
    """Process noise is a Wiener increment of intensity process_noise_std: the x2 noise of one
    sample has variance std**2 * dt. The noise of each step is what is left after subtracting
    the noiseless RK4 sample from the same state; its mean square over N = 20000 steps is an
    estimate of that variance with a relative standard error of sqrt(2 / N) = 1 %."""
    std, dt, theta, n = 0.3, 0.05, 1.0, 20000
    # One RK4 step per sample: the noise does not depend on it, and it is 10x cheaper.
    cfg = PlantConfig(theta=(theta,), dt=dt, substeps=1, x0=(1.0, 0.0), process_noise_std=std,
                      seed=3)
    if simulator == 'single':
        plant, noise = Plant(cfg), []
        for _ in range(n):
            x1, x2 = rk4_components(VDP, tuple(plant.x), (0.0,), (theta,), dt, cfg.substeps)
            y = plant.step([0.0])
            assert y[0] == x1, 'x1 carries no noise'
            noise.append(y[1] - x2)
        assert not plant.diverged
    else:
        batch = 500     # 40 steps of 500 systems
        sim = BatchPlant(np.full(batch, theta), cfg)
        noise = []
        for _ in range(n // batch):
            free = rk4_sample(VDP, sim.x, np.zeros((batch, 1)), sim.theta, dt, cfg.substeps)
            y = sim.step(np.zeros(batch))
            assert np.array_equal(y[:, 0], free[:, 0]), 'x1 carries no noise'
            noise.extend(y[:, 1] - free[:, 1])
        assert not sim.diverged.any()
    noise = np.asarray(noise)
    assert noise.size == n
    # 5 % is 5 standard errors; scaling by dt instead of sqrt(dt) would give 5 % of std**2 dt.
    assert abs(np.mean(noise ** 2) / (std ** 2 * dt) - 1.0) < 0.05
    assert abs(noise.mean()) < 5 * std * np.sqrt(dt / n), 'zero mean'


@pytest.mark.parametrize('state_bound', [10.0, 1e300], ids=['leaves-box', 'non-finite'])
def test_escaping_state_is_flagged_never_nan(state_bound):
    # theta < 0: the limit cycle is unstable and a state outside it escapes in finite time;
    # with a huge bound the state overflows to inf/NaN before it leaves the box.
    cfg = PlantConfig(dt=0.1, state_bound=state_bound)
    u = np.zeros((2, 300))
    _, y, valid = simulate([-1.5, -1.5], np.array([[2.5, 0.0], [0.5, 0.0]]), u, cfg)
    assert np.isfinite(y).all()
    assert valid[1].all(), 'the system inside its cycle stays valid'
    first_bad = int(np.argmin(valid[0]))
    assert 0 < first_bad and not valid[0, first_bad:].any()
    # Frozen at the last valid sample from then on, inside the box.
    assert (y[0, first_bad:] == y[0, first_bad - 1]).all()
    assert np.abs(y[0]).max() <= state_bound

    plant = Plant(PlantConfig(theta=(-1.5,), dt=0.1, x0=(2.5, 0.0), state_bound=state_bound))
    outputs = [plant.step([0.0]) for _ in range(300)]
    assert plant.diverged and np.isfinite(outputs).all()
    plant.reset(theta=(0.5,), x0=(0.1, 0.0))
    assert not plant.diverged and plant.step_index == 0 and plant.theta == (0.5,)


def test_saturation_and_non_finite_inputs():
    plant = Plant(PlantConfig(u_min=(-0.5,), u_max=(0.8,)))
    assert plant.saturate([2.0]) == ((0.8,), True)
    assert plant.saturate([-2.0]) == ((-0.5,), True)
    assert plant.saturate([0.1]) == ((0.1,), False)
    for bad in ([float('nan')], [float('inf')], [0.1, 0.2]):
        with pytest.raises(ValueError):
            plant.step(bad)
    with pytest.raises(ValueError):
        BatchPlant([0.0], PlantConfig()).step(np.array([np.nan]))


@pytest.mark.parametrize('field,value,match', [
    ('dt', -0.1, 'dt'), ('dt', float('inf'), 'dt'),
    ('substeps', 0, 'substeps'), ('substeps', 2.5, 'substeps'),
    ('theta', (float('nan'),), 'theta'), ('theta', (0.1, 0.2), 'theta of family vanderpol'),
    ('x0', (0.0,), 'x0'), ('x0', (0.0, float('nan')), 'x0'), ('x0', (11.0, 0.0), 'x0'),
    ('u_max', (-1.5,), 'u_min <= u_max'), ('u_min', (-2.0,), 'outside those of family'),
    ('u_max', (1.0, 1.0), 'u_max of family'),
    ('process_noise_std', -1.0, 'noise'), ('measurement_noise_std', float('nan'), 'noise'),
    ('state_bound', -1.0, 'state_bound'), ('family', 'vanderpool', 'unknown plant family'),
    ('seed', -1, 'seed')])
def test_bad_config_is_rejected(field, value, match):
    with pytest.raises(ValueError, match=match):
        PlantConfig(**{field: value}).validate()


def test_the_paper_prior_is_seeded_standard_normal():
    a = VDP.sample_theta(np.random.default_rng(0), 10000)
    assert a.shape == (10000, 1)
    assert np.array_equal(a, VDP.sample_theta(np.random.default_rng(0), 10000))
    assert np.array_equal(a[:, 0], np.random.default_rng(0).standard_normal(10000))
    assert abs(a.mean()) < 0.05 and abs(a.std() - 1.0) < 0.05
