"""The shipped Cascaded Tanks file: its SHA-256 (the README's), its shape and columns read
again with the csv module, and a clear error for an altered or missing copy."""
import csv
import hashlib

import numpy as np
import pytest

from metampc_plant.cascaded_tanks_data import (DataError, load_cascaded_tanks, SHA256,
                                               shipped_file)

README_SHA256 = 'ef2388ed822f3aef4aa80d6b0f2b466dd80b361786b3eafc7a2957c31ea323a7'


def test_the_shipped_file_is_the_benchmarks():
    raw = shipped_file().read_bytes()
    assert hashlib.sha256(raw).hexdigest() == README_SHA256 == SHA256
    assert len(raw) == 30014


def test_records_are_the_files_columns_1024_samples_at_4_s():
    rows = list(csv.reader(shipped_file().read_text().splitlines()))
    assert rows[0] == ['uEst', 'uVal', 'yEst', 'yVal', 'Ts', '']
    body = [r for r in rows[1:] if r]
    assert len(body) == 1024 and body[0][4] == '4' and all(r[4] == '' for r in body[1:])
    columns = {name: np.array([float(r[i]) for r in body]) for i, name in enumerate(rows[0][:4])}
    data = load_cascaded_tanks()
    assert data.ts == 4.0
    for name, array in (('uEst', data.u_est), ('uVal', data.u_test), ('yEst', data.y_est),
                        ('yVal', data.y_test)):
        assert array.shape == (1024,) and array.dtype == np.float64
        assert np.array_equal(array, columns[name]), name
    # The description's estimation record: pump voltages within 0..10 V, the level reaching
    # the sensors' 10 V ceiling when the tanks overflow.
    assert 0.0 < data.u_est.min() and data.u_est.max() < 10.0
    assert data.y_est.max() == 10.0 and np.sum(data.y_est == 10.0) == 47


def test_an_altered_or_missing_file_is_refused(tmp_path):
    raw = bytearray(shipped_file().read_bytes())
    raw[100] = ord('9') if raw[100] != ord('9') else ord('8')
    altered = tmp_path / 'dataBenchmark.csv'
    altered.write_bytes(bytes(raw))
    with pytest.raises(DataError, match=r'SHA-256 [0-9a-f]{64} is not the benchmark'):
        load_cascaded_tanks(altered)
    with pytest.raises(DataError, match='No such file'):
        load_cascaded_tanks(tmp_path / 'missing.csv')
