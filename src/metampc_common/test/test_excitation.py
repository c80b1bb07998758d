"""Excitation signals: within their bounds, of the right shape and structure, and seeded."""
import re

import numpy as np
import pytest

from metampc_common.excitation import excitation, ExcitationConfig, KINDS

# Bounds that are not symmetric and not exactly representable, to catch rounding past them.
BOUNDS = [(-1.0, 1.0), (0.1, 0.7), (-0.3, -0.3)]
UNIT = dict(u_min=(-1.0,), u_max=(1.0,))


@pytest.mark.parametrize('kind', KINDS)
@pytest.mark.parametrize('lo,hi', BOUNDS)
def test_within_bounds_and_shaped(kind, lo, hi):
    u = excitation(ExcitationConfig(kind=kind, u_min=(lo,), u_max=(hi,)), 5, 1000, 0.1, seed=3)
    assert u.shape == (5, 1000, 1)
    assert np.isfinite(u).all()
    assert u.min() >= lo and u.max() <= hi


@pytest.mark.parametrize('kind', KINDS)
def test_each_input_within_its_own_bounds_and_independent(kind):
    cfg = ExcitationConfig(kind=kind, u_min=(0.0, -3.0), u_max=(10.0, -1.0))
    u = excitation(cfg, 4, 600, 5.0, seed=2)
    assert u.shape == (4, 600, 2)
    assert 0.0 <= u[..., 0].min() and u[..., 0].max() <= 10.0
    assert -3.0 <= u[..., 1].min() and u[..., 1].max() <= -1.0
    scaled = (u - np.array([5.0, -2.0])) / np.array([5.0, 1.0])
    assert not np.array_equal(scaled[..., 0], scaled[..., 1]), 'inputs drawn independently'


@pytest.mark.parametrize('kind', KINDS)
def test_seeded(kind):
    cfg = ExcitationConfig(kind=kind, **UNIT)
    a = excitation(cfg, 3, 500, 0.1, seed=7)
    assert np.array_equal(a, excitation(cfg, 3, 500, 0.1, seed=7))
    assert not np.array_equal(a, excitation(cfg, 3, 500, 0.1, seed=8))
    assert not np.array_equal(a[0], a[1]), 'systems of a batch get different signals'


def test_hold_structure():
    cfg = ExcitationConfig(kind='random_hold', hold_s=0.5, **UNIT)
    u = excitation(cfg, 2, 100, 0.1, seed=0)
    blocks = u.reshape(2, 20, 5)  # 0.5 s / 0.1 s = 5 samples per level
    assert (blocks == blocks[:, :, :1]).all()
    prbs = excitation(ExcitationConfig(kind='prbs', u_min=(-0.4,), u_max=(0.9,)), 2, 100, 0.1, 0)
    assert set(np.unique(prbs)) <= {-0.4, 0.9}


def test_multisine_spans_its_range():
    cfg = ExcitationConfig(kind='multisine', u_min=(-0.5,), u_max=(1.5,))
    u = excitation(cfg, 1, 2000, 0.05, 1)
    # Scaled so that its largest excursion touches one of the bounds.
    assert u.max() == pytest.approx(1.5) or u.min() == pytest.approx(-0.5)


def test_empty_and_invalid():
    assert excitation(ExcitationConfig(kind='multisine', **UNIT), 2, 0, 0.1, 0).shape == (2, 0, 1)
    for cfg in (ExcitationConfig(kind='chirp', **UNIT),
                ExcitationConfig(u_min=(1.0,), u_max=(-1.0,)),
                ExcitationConfig(u_min=(0.0,), u_max=(1.0, 2.0)),
                ExcitationConfig(u_min=(0.0,), u_max=(float('inf'),)),
                ExcitationConfig(hold_s=0.0, **UNIT), ExcitationConfig()):
        with pytest.raises(ValueError):
            excitation(cfg, 1, 10, 0.1, 0)
    with pytest.raises(ValueError):
        excitation(ExcitationConfig(**UNIT), 1, 10, 0.0, 0)


@pytest.mark.parametrize('kind', KINDS)
def test_a_band_is_an_excitation_of_its_own_bounds(kind):
    # center +- amplitude x half the range is the same signal as bounds set to that band.
    band = ExcitationConfig(kind=kind, u_min=(0.0, -3.0), u_max=(10.0, -1.0), amplitude=0.4,
                            center=(3.0, -2.5))
    assert [b.tolist() for b in band.band()] == [[1.0, -2.9], [5.0, -2.1]]
    as_bounds = ExcitationConfig(kind=kind, u_min=(1.0, -2.9), u_max=(5.0, -2.1))
    np.testing.assert_allclose(excitation(band, 3, 400, 5.0, seed=4),
                               excitation(as_bounds, 3, 400, 5.0, seed=4), rtol=0, atol=1e-12)
    # The whole range about the middle (the defaults): the bounds themselves, bit for bit.
    whole = ExcitationConfig(kind=kind, u_min=(0.1,), u_max=(0.7,))
    assert [b.tolist() for b in whole.band()] == [[0.1], [0.7]]


@pytest.mark.parametrize('center, amplitude, error', [
    ((3.0,), 0.7, 'leaves the input bounds'),           # 3 - 3.5 < 0
    ((9.0,), 0.4, 'leaves the input bounds'),           # 9 + 2 > 10
    ((3.0, 3.0), 0.2, 'excitation_center needs one value per input (1)'),
])
def test_a_band_outside_the_bounds_is_refused(center, amplitude, error):
    cfg = ExcitationConfig(u_min=(0.0,), u_max=(10.0,), amplitude=amplitude, center=center)
    with pytest.raises(ValueError, match=re.escape(error)):
        excitation(cfg, 1, 10, 5.0, 0)
    # The edge itself is inside: 3 +- 0.6 x 5 = [0, 6].
    edge = ExcitationConfig(u_min=(0.0,), u_max=(10.0,), amplitude=0.6, center=(3.0,))
    assert [b.tolist() for b in edge.band()] == [[0.0], [6.0]]
