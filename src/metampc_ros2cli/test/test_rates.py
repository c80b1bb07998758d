"""The statistics of `ros2 topic hz` and `bw` against hand-computed values."""
from metampc_ros2cli.rates import BandwidthWindow, RateWindow


def test_a_steady_10_hz_stream_reports_once_a_second():
    window = RateWindow()
    lines = [window.add(10 ** 9 + k * 10 ** 8) for k in range(32)]
    printed = [line for line in lines if line]
    # the first message starts the window, the second sets the print mark, then one report
    # per second of message time (at k = 11 and 21 and 31)
    assert [k for k, line in enumerate(lines) if line] == [11, 21, 31]
    assert printed[0] == ('average rate: 10.000\n\tmin: 0.100s max: 0.100s std dev: 0.00000s '
                          'window: 11')


def test_jitter_gives_the_population_standard_deviation_and_the_window_bounds_it():
    window = RateWindow(window=4)
    t = 0
    for dt in (1, 100, 200, 100, 200, 100, 200, 1000):     # ms
        t += dt * 10 ** 6
        window.add(t)
    rate, low, high, std, n = window.stats()
    held = [200, 100, 200, 1000]
    mean = sum(held) / 4
    assert n == 4 and abs(low - 0.1) < 1e-12 and abs(high - 1.0) < 1e-12
    assert abs(rate - 1e3 / mean) < 1e-9
    assert abs(std - (sum((x - mean) ** 2 for x in held) / 4) ** 0.5 * 1e-3) < 1e-9


def test_a_clock_that_goes_back_restarts_the_window():
    window = RateWindow()
    for k in range(5):
        window.add((k + 10) * 10 ** 8)
    window.add(10 ** 8)
    assert not window.intervals


def test_bandwidth_uses_kilobytes_above_1000_bytes_per_second():
    window = BandwidthWindow()
    for k in range(11):
        window.add(k * 10 ** 8, 200)
    line = window.report(10 ** 9 + 10 ** 8)     # 11 x 200 B over 1.1 s = 2000 B/s
    assert line == ('2.00 KB/s from 11 messages\n\tMessage size mean: 0.20 KB min: 0.20 KB '
                    'max: 0.20 KB')
    assert BandwidthWindow().report(5) is None
