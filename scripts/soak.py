#!/usr/bin/env python3
"""Real-time soak: a realtime plant and the latent-MPC controller for a long run; one JSON line.

The set-up is :mod:`metampc_bringup.realtime_soak` (its docstring), the measures those of
:mod:`metampc_bringup.soak_metrics`, the measured soaks in docs/faults.md. Reported (after a
warm-up that is left out): deadline misses, controller tick and solve time and the response
time seen by the observer (ms percentiles), dropped messages, the nodes' own stop-line
counters, RSS and CPU share of the plant and the controller, the load average at start and
end. soak.png and the node logs go to --out.

Goals (issue 10): deadline misses <= 0.1 % and memory growth <= 5 % at 100 Hz for 10 minutes.

    python scripts/soak.py                           # 100 Hz for 10 minutes
    python scripts/soak.py --duration 60 --out /tmp/soak1
    python scripts/soak.py --rate 50 --weights runs/x/ckpt/adapted_imaml_v5.pt --dt 0.1

The controller's timer runs at --controller-rate (default twice --rate); at the plant's own
rate every answer can come late (try ``--controller-rate 100``).
"""
import argparse
import json
import sys
import tempfile

from metampc_bringup.realtime_soak import soak, SoakConfig


def parse_args(argv=None) -> SoakConfig:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rate', type=float, default=100.0, help='plant rate, Hz')
    parser.add_argument('--duration', type=float, default=600.0, help='measured time, s')
    parser.add_argument('--warmup', type=float, default=30.0,
                        help='s left out at the start (start-up, first model)')
    parser.add_argument('--controller-rate', type=float,
                        help='controller timer rate, Hz (default: 2 x --rate)')
    parser.add_argument('--dt', type=float,
                        help='plant sample time, s (default: 1/rate: real time)')
    parser.add_argument('--weights', help='checkpoint to control with (default: the '
                                          'hand-built linearised model)')
    parser.add_argument('--theta', type=float, default=0.5, help='plant damping')
    parser.add_argument('--horizon', type=int, default=20, help='MPC horizon N')
    parser.add_argument('--seed', type=int, default=0, help='measurement noise seed')
    parser.add_argument('--out', help='folder for logs and soak.png (default: a new temp dir)')
    args = vars(parser.parse_args(argv))
    cfg = SoakConfig(**args)
    try:
        cfg.validate()
    except ValueError as err:
        parser.error(str(err))
    return cfg


def main(argv=None) -> int:
    cfg = parse_args(argv)
    cfg.out = cfg.out or tempfile.mkdtemp(prefix='metampc-soak-')
    try:
        report = soak(cfg)
    except KeyboardInterrupt:
        print(f'soak: interrupted; nodes stopped, logs in {cfg.out}', file=sys.stderr)
        return 130
    except RuntimeError as err:
        print(f'soak: {err}', file=sys.stderr)
        return 1
    print(json.dumps(report))
    return 0


if __name__ == '__main__':
    sys.exit(main())
