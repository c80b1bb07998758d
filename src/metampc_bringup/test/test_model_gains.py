"""Steady-state gains and slowest poles (analysis.model_gains) against closed forms."""
import os
import subprocess
import sys

import numpy as np
import pytest

from metampc_bringup.analysis.model_gains import compare, plant_gain, plant_poles, time_constant
from metampc_model.latent_model import LatentModel
from metampc_plant.families.quadruple_tank import (AREA, FAMILY as TANK, GRAVITY, OUTLET, PUMP,
                                                   SENSOR)
from metampc_plant.steady_state import steady_state

THETA = (0.7, 0.6)
U0 = (3.0, 2.6)


def _latent(a, b, c):
    a, b, c = (np.atleast_2d(np.asarray(v, dtype=float)) for v in (a, b, c))
    return LatentModel(A=a, B=b, C=c, e=np.full(a.shape[0], 0.3), d=np.full(c.shape[0], -1.0))


def test_the_tank_gain_is_johanssons():
    # At rest a3 s3 = (1 - g2) k2 v2, a4 s4 = (1 - g1) k1 v1, so a1 s1 = g1 k1 v1 + (1 - g2) k2 v2
    # and h1 = s1^2 / (2 g): d y1 / d v1 = SENSOR s1 g1 k1 / (g a1), and so on.
    (g1, g2), (v1, v2), (k1, k2), (a1, a2) = THETA, U0, PUMP, OUTLET[:2]
    s1 = (g1 * k1 * v1 + (1 - g2) * k2 * v2) / a1
    s2 = (g2 * k2 * v2 + (1 - g1) * k1 * v1) / a2
    expected = SENSOR / GRAVITY * np.array([[s1 * g1 * k1 / a1, s1 * (1 - g2) * k2 / a1],
                                            [s2 * (1 - g1) * k1 / a2, s2 * g2 * k2 / a2]])
    np.testing.assert_allclose(plant_gain(TANK, THETA, U0), expected, rtol=1e-6)


def test_the_tank_poles_are_its_outlets_time_constants():
    # The linearised tank is triangular: pole i is -a_i g / (A_i s(h_i)) at the steady state.
    h = steady_state(TANK, THETA, U0)
    rates = [a * GRAVITY / (area * np.sqrt(2 * GRAVITY * hi))
             for a, area, hi in zip(OUTLET, AREA, h)]
    expected = np.sort(np.exp(-5.0 * np.asarray(rates)))[::-1]
    np.testing.assert_allclose(plant_poles(TANK, THETA, U0, 5.0), expected, rtol=1e-6)
    assert time_constant(expected[0], 5.0) == pytest.approx(1.0 / min(rates))
    assert time_constant(1.0, 5.0) == float('inf')


def test_a_model_with_the_plants_gain_has_ratio_one_and_a_wrong_sign_shows():
    g_p = plant_gain(TANK, THETA, U0)
    right = compare(_latent(0.5 * np.eye(2), 0.5 * g_p, np.eye(2)), TANK, THETA, U0, 5.0)
    np.testing.assert_allclose(right.ratio_eigs, [1.0, 1.0], atol=1e-9)
    assert right.model_pole == pytest.approx(0.5)
    assert right.plant_pole == pytest.approx(plant_poles(TANK, THETA, U0, 5.0)[0])
    flipped = compare(_latent(0.5 * np.eye(2), 0.5 * g_p @ np.diag([1.0, -1.0]), np.eye(2)),
                      TANK, THETA, U0, 5.0)
    assert np.min(flipped.ratio_eigs.real) < 0.0      # integral action diverges there


def test_the_script_refuses_a_folder_without_a_report(tmp_path):
    script = os.path.join(os.path.dirname(__file__), '..', '..', '..', 'scripts',
                          'model_gains.py')
    done = subprocess.run([sys.executable, script, str(tmp_path)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and 'no readable report.json' in done.stderr, done.stderr
