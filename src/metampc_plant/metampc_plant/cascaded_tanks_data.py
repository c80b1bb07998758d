"""The Cascaded Tanks benchmark's data (Schoukens, Mattsson, Wigren, Noel 2016), shipped here.

``data/cascaded_tanks/dataBenchmark.csv`` (source, citation, licence: the README beside it):
an estimation and a test record of 1024 samples each, Ts = 4 s, pump voltage u and lower-tank
level y in volts; u[k] is held over [k Ts, (k+1) Ts) and y[k] measured at k Ts (the file's
order). :func:`load_cascaded_tanks` refuses a file whose SHA-256 differs (one-line
:class:`DataError`). The test record is for the final evaluation only: nothing may be
fitted or chosen on it. Pure numpy, no rclpy.
"""
from dataclasses import dataclass
import hashlib
from importlib.resources.abc import Traversable
from importlib.resources import files
from pathlib import Path
from typing import Optional, Union

import numpy as np

SHA256 = 'ef2388ed822f3aef4aa80d6b0f2b466dd80b361786b3eafc7a2957c31ea323a7'
TS = 4.0    # s


class DataError(ValueError):
    """The data file is missing, altered or not the benchmark's."""


@dataclass(frozen=True)
class CascadedTanksData:
    """The benchmark's two records, float64 arrays of shape (1024,), volts.

    Attributes:
        u_est, y_est: the estimation record (the file's uEst, yEst).
        u_test, y_test: the test record (the file's uVal, yVal; the benchmark's "test data").
        ts: sample time, s.
    """

    u_est: np.ndarray
    y_est: np.ndarray
    u_test: np.ndarray
    y_test: np.ndarray
    ts: float


def shipped_file() -> Traversable:
    """The shipped CSV file (``read_bytes()`` reads it, also from a zipped install)."""
    return files('metampc_plant') / 'data' / 'cascaded_tanks' / 'dataBenchmark.csv'


def load_cascaded_tanks(path: Optional[Union[str, Path]] = None) -> CascadedTanksData:
    """Both records from `path` (default: the shipped file).

    Raises:
        DataError: the file is unreadable or its SHA-256 is not :data:`SHA256` (the file
            whose 1024 rows of uEst, uVal, yEst, yVal the tests check).
    """
    path = Path(path) if path is not None else shipped_file()
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise DataError(f'cascaded tanks data {path}: {err.strerror or err}') from None
    digest = hashlib.sha256(raw).hexdigest()
    if digest != SHA256:
        raise DataError(f'cascaded tanks data {path}: SHA-256 {digest} is not the benchmark '
                        f"file's {SHA256}")
    # Columns uEst, uVal, yEst, yVal, Ts (4 on the first row only), each row ending in ','.
    table = np.array([line.split(',')[:4] for line in raw.decode('ascii').splitlines()[1:]
                      if line], dtype=np.float64)
    u_est, u_test, y_est, y_test = (np.ascontiguousarray(c) for c in table.T)
    return CascadedTanksData(u_est=u_est, y_est=y_est, u_test=u_test, y_test=y_test, ts=TS)


__all__ = ['SHA256', 'TS', 'DataError', 'CascadedTanksData', 'shipped_file',
           'load_cascaded_tanks']
