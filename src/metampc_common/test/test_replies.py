"""Replies: a repeated request id gets the first answer and the request runs once; an empty id
runs every time; a repeat of a call still running waits for its answer."""
import asyncio
from concurrent.futures import Future
from types import SimpleNamespace

import pytest

from metampc_common.replies import Replies


def request(request_id=''):
    return SimpleNamespace(request_id=request_id)


def counting():
    runs = []

    def handler(req, response):
        runs.append(req.request_id)
        return f'answer {len(runs)}'
    return handler, runs


def test_a_repeated_id_gets_the_first_answer_and_runs_once():
    handler, runs = counting()
    callback = Replies(Future).wrap(handler)
    assert callback(request('a'), None) == 'answer 1'
    assert callback(request('a'), None) == 'answer 1'
    assert callback(request('b'), None) == 'answer 2'
    assert runs == ['a', 'b']


def test_an_empty_id_runs_every_time():
    handler, runs = counting()
    replies = Replies(Future)
    callback = replies.wrap(handler)
    assert [callback(request(), None) for _ in range(3)] == ['answer 1', 'answer 2', 'answer 3']
    assert replies.repeats == 0


def test_a_failed_first_call_fails_its_repeats_alike_without_running_again():
    runs = []

    def handler(req, response):
        runs.append(1)
        raise RuntimeError('refused')
    callback = Replies(Future).wrap(handler)
    for _ in range(2):
        with pytest.raises(RuntimeError, match='refused'):
            callback(request('a'), None)
    assert runs == [1]


def test_only_the_latest_ids_are_kept():
    handler, runs = counting()
    callback = Replies(Future, keep=2).wrap(handler)
    for rid in ('a', 'b', 'c', 'a'):    # 'a' was forgotten when 'c' came: run again
        callback(request(rid), None)
    assert runs == ['a', 'b', 'c', 'a']


def test_a_repeat_of_a_running_coroutine_awaits_its_answer():
    """The learner's meta_train and adapt are coroutines in a reentrant group: the repeat
    comes while the first still trains and must get its answer, not train again."""
    release = asyncio.Event()
    runs = []

    async def handler(req, response):
        runs.append(req.request_id)
        await release.wait()
        return f'model v{len(runs)}'

    async def scenario():
        callback = Replies(asyncio.get_running_loop().create_future).wrap_async(handler)
        first = asyncio.ensure_future(callback(request('m'), None))
        await asyncio.sleep(0)
        repeat = asyncio.ensure_future(callback(request('m'), None))
        await asyncio.sleep(0)
        assert not repeat.done()
        release.set()
        return await first, await repeat

    assert asyncio.run(scenario()) == ('model v1', 'model v1')
    assert runs == ['m']


def test_exactly_keep_answers_are_kept():
    """keep 2: ids a, b, a, b run twice (a and b), the repeats answered from the first."""
    handler, runs = counting()
    replies = Replies(Future, keep=2)
    callback = replies.wrap(handler)
    assert [callback(request(rid), None) for rid in 'abab'] == [
        'answer 1', 'answer 2', 'answer 1', 'answer 2']
    assert runs == ['a', 'b'] and replies.repeats == 2
