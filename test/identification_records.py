"""Records made by known models, the independent reference of the identification tests
(src/metampc_plant/test/test_arx.py, test_greybox.py, test_validation.py)."""
import numpy as np

from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.identification.arx import Arx
from metampc_plant.identification.greybox import simulate_family
from metampc_plant.registry import get_family

ARX_TRUE = Arx(a=np.array([1.2, -0.5]), b=np.array([0.3, 0.15]), nk=1, c=0.4)
TANKS = get_family('cascaded_tanks')
TANKS_TRUE = np.array(TANKS.nominal_theta) * np.array([1.1, 0.9, 1.1, 0.95, 1.15])
TANKS_X0 = np.array([8.0, 5.0])


def arx_record(model: Arx, u: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """y[k] = sum a_i y[k-i] + sum b_j u[k-nk-j] + c + noise[k], written out sample by sample,
    zero before the start."""
    y = np.zeros(len(u))
    for k in range(len(u)):
        past = sum(a * y[k - i] for i, a in enumerate(model.a, 1) if k - i >= 0)
        inputs = sum(b * u[k - model.nk - j] for j, b in enumerate(model.b)
                     if k - model.nk - j >= 0)
        y[k] = past + inputs + model.c + noise[k]
    return y


def tanks_record():
    """(u (200, 1), x (200, 2), y (200, 1)): samples 100..299 of the estimation record's input
    (the upper tank overflows near sample 45 of them, so k5 shows) and the member TANKS_TRUE
    from TANKS_X0, RK4 at 2 substeps."""
    u = load_cascaded_tanks().u_est[100:300, None]
    x, y = simulate_family(TANKS, TANKS_TRUE[None], TANKS_X0[None], u, 2)
    return u, x[0], y[0]
