"""JobSlot: one job at a time, its latest progress, cancellation at the next step."""
import threading
import time

import pytest

from metampc_learner.job_slot import JobCancelled, JobSlot
from metampc_learner.progress import Progress


def test_one_job_at_a_time_with_its_latest_progress():
    slot = JobSlot()
    assert slot.current() is None and slot.release(True) is None
    assert slot.claim()
    assert not slot.claim() and slot.busy_reason() == 'busy: another request is being set up'
    status = slot.describe('meta_train', 'imaml', 10)
    assert (status.phase, status.method, status.progress.iteration, status.progress.total) == (
        'meta_train', 'imaml', 0, 10)
    slot.report(Progress(3, 10, 0.5, 0.01, skipped=1, cg_residual=0.2))
    time.sleep(0.05)
    now = slot.current()
    assert (now.progress.iteration, now.progress.loss, now.progress.skipped) == (3, 0.5, 1)
    assert now.progress.elapsed >= 0.05, 'elapsed is measured from describe(), not reported'
    assert slot.busy_reason().startswith('busy: meta_train (imaml) running, step 3/10, ')
    final = slot.release(True)
    assert (final.phase, final.progress.iteration) == ('done', 3)
    assert slot.current() is None and slot.claim()
    slot.describe('adapt', 'maml', 5)
    assert slot.release(False).phase == 'failed'


def test_cancel_stops_a_running_job_at_its_next_report():
    slot = JobSlot()
    assert slot.cancel(0.0), 'no job: nothing to wait for'
    slot = JobSlot()
    assert slot.claim()
    slot.describe('meta_train', 'imaml', 10**6)
    ended = []

    def job():
        try:
            for it in range(1, 10**6):
                time.sleep(0.01)
                slot.report(Progress(it, 10**6, 0.0, 0.0))
        except JobCancelled as err:
            ended.append(str(err))
        finally:
            slot.release(False)

    worker = threading.Thread(target=job)
    worker.start()
    time.sleep(0.1)
    assert slot.cancel(5.0)
    worker.join(5.0)
    assert ended == ['cancelled: the learner is shutting down']
    assert not slot.claim(), 'no new job after cancel'
    with pytest.raises(JobCancelled):
        slot.report(Progress(1, 1, 0.0, 0.0))


def test_cancel_gives_up_on_a_job_that_never_reports():
    slot = JobSlot()
    assert slot.claim()
    t0 = time.monotonic()
    assert not slot.cancel(0.2)
    assert 0.2 <= time.monotonic() - t0 < 2.0
