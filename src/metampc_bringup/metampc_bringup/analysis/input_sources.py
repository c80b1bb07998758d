"""Which recorded ControlInputs are the controller's answers, and which came from elsewhere.

Anything may publish on ``u`` and a recording does not say which publisher sent a message, but
the controller publishes each answer as a pair: its ControlInput of step k and right after it
the MpcStatus of step k. :func:`controller_inputs` walks inputs and statuses in recorded order
and pairs each input with the earliest unpaired status of its step at most
:data:`PAIRING_WINDOW` statuses away; inputs left unpaired are *foreign*. In: the recorded
steps of both topics; out: a mask [n_inputs]. Without any status recorded every input counts
as the controller's. See docs/recording.md (metrics). No rclpy here.
"""
from collections import deque
from typing import Deque, Dict, Sequence, Tuple

import numpy as np

PAIRING_WINDOW = 100    # statuses recorded between a controller's input and its status, at most


def controller_inputs(input_order: Sequence[int], input_steps: Sequence[int],
                      status_order: Sequence[int], status_steps: Sequence[int],
                      window: int = PAIRING_WINDOW) -> np.ndarray:
    """Mask [n_inputs] of the inputs paired with a status (see the module docstring).

    Args:
        input_order, status_order: each message's rank in the recorded order of both streams
            together (together a permutation of 0..n_inputs + n_statuses - 1).
        input_steps, status_steps: their `step` fields.
        window: the most statuses recorded between an input and the status it pairs with.
    """
    n_in = len(input_steps)
    if len(status_steps) == 0:
        return np.ones(n_in, dtype=bool)
    paired = np.zeros(n_in, dtype=bool)
    # The merged recorded order: kind (0 input, 1 status) and index in its stream.
    n = n_in + len(status_steps)
    kinds, indices = np.zeros(n, dtype=np.int8), np.zeros(n, dtype=np.int64)
    kinds[np.asarray(status_order, dtype=np.int64)] = 1
    indices[np.asarray(input_order, dtype=np.int64)] = np.arange(n_in)
    indices[np.asarray(status_order, dtype=np.int64)] = np.arange(len(status_steps))
    steps = (np.asarray(input_steps, dtype=np.int64).tolist(),
             np.asarray(status_steps, dtype=np.int64).tolist())
    # Unpaired messages per side (inputs, statuses): their indices by step, oldest first; and
    # (step, index, statuses recorded before it) in recorded order, to drop those that fell
    # out of the window.
    waiting: Tuple[Dict[int, Deque[int]], ...] = ({}, {})
    queue: Tuple[Deque[Tuple[int, int, int]], ...] = (deque(), deque())
    statuses = 0
    for kind, index in zip(kinds.tolist(), indices.tolist()):
        for side in (0, 1):
            while queue[side] and queue[side][0][2] < statuses - window:
                step, i, _ = queue[side].popleft()
                pending = waiting[side].get(step)
                if pending and pending[0] == i:
                    _pop(waiting[side], step)
        step = steps[kind][index]
        if step in waiting[1 - kind]:
            i = _pop(waiting[1 - kind], step)
            paired[index if kind == 0 else i] = True
        else:
            waiting[kind].setdefault(step, deque()).append(index)
            queue[kind].append((step, index, statuses))
        statuses += kind
    return paired


def _pop(waiting: Dict[int, Deque[int]], step: int) -> int:
    """The oldest waiting message of `step`, removed (and its step once none waits)."""
    pending = waiting[step]
    got = pending.popleft()
    if not pending:
        del waiting[step]
    return got
