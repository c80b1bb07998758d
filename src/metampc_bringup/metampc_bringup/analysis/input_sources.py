"""Which recorded ControlInputs are the controller's answers, and which came from elsewhere.

Anything may publish on ``u`` and a recording does not say which publisher sent a message, but
the controller publishes each answer as a pair: its ControlInput of step k and the MpcStatus of
step k, both stamped with y_k's stamp (which never repeats: sim-time stamps never go back, even
across resets). :func:`controller_inputs` pairs each input with an unpaired status of the same
(step, stamp), the earliest input first; inputs left unpaired are *foreign*. In: both topics'
keys; out: a mask [n_inputs]. Without any status recorded every input counts as the
controller's. See docs/recording.md (metrics). No rclpy here.
"""
import numpy as np


def controller_inputs(input_steps: np.ndarray, input_stamps: np.ndarray,
                      status_steps: np.ndarray, status_stamps: np.ndarray) -> np.ndarray:
    """Mask [n_inputs] of the inputs paired with a status (see the module docstring).

    Args:
        input_steps, input_stamps: [n_inputs] step and header stamp (s) of each input, in
            recorded order (of inputs with the same key, the earliest recorded pairs first).
        status_steps, status_stamps: [n_statuses] the same of each status, in any order.
    """
    n_in = len(input_steps)
    if len(status_steps) == 0:
        return np.ones(n_in, dtype=bool)
    keys = np.empty(n_in + len(status_steps), dtype=[('step', np.int64), ('stamp', np.float64)])
    keys['step'] = np.concatenate([input_steps, status_steps])
    keys['stamp'] = np.concatenate([input_stamps, status_stamps])
    _, ids = np.unique(keys, return_inverse=True)
    ids = ids.ravel()
    statuses = np.bincount(ids[n_in:], minlength=ids.max() + 1)
    # Each input's rank among the inputs of its key, in recorded order (a stable sort keeps it).
    by_key = np.argsort(ids[:n_in], kind='stable')
    sorted_ids = ids[:n_in][by_key]
    first = np.searchsorted(sorted_ids, sorted_ids, side='left')
    rank = np.empty(n_in, dtype=np.int64)
    rank[by_key] = np.arange(n_in) - first
    return rank < statuses[ids[:n_in]]
