"""The feature NARX's sizes (narx_shape)."""
import pytest

from metampc_model.narx_shape import NarxShape


def test_the_sizes_count_the_lags_features_input_and_constant():
    shape = NarxShape(n_u=2, n_y=3, order=4, features=5, hidden=(6, 7))
    assert shape.n_s == 4 * 3 + 3 * 2            # y_t..y_{t-3}, u_t..u_{t-2}
    assert shape.n_phi == shape.n_s + 5 + 2 + 1
    assert list(shape.feature_shapes().values()) == [(6, 18), (6,), (7, 6), (7,), (5, 7), (5,)]
    assert NarxShape(1, 1, order=1, features=0).feature_shapes() == {}


@pytest.mark.parametrize('kwargs', [dict(order=0), dict(features=-1), dict(hidden=(0,)),
                                    dict(n_u=0)])
def test_bad_sizes_are_refused(kwargs):
    with pytest.raises(ValueError):
        NarxShape(**{**dict(n_u=1, n_y=1), **kwargs})
