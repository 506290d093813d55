"""Asking several computers at once, following their work, and naming who did not answer.

Every command that asks the fleet (``ps``, ``doctor --all``, ``down --all``, ``up --all``,
``update --all``, ``build --all``) does it through these: :func:`ask_each` sends one request
to every host at the same time and sorts what came back into answers and
:class:`~msctl.launcher.fleet.Silence`\\ s; :func:`rounds` asks the hosts that are still busy
again, all at once, until each is settled or the time is up; :func:`progress` is the one rich
view of it. Plain threads and no rich at import: ``msctl ps`` imports this (see
:mod:`msctl.quick`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Hashable, Iterable, Sequence
from typing import Any, NamedTuple, TypeVar

T = TypeVar("T")
R = TypeVar("R")
K = TypeVar("K", bound=Hashable)


class Replies(NamedTuple):
    """What one request to several hosts brought back, by the key each was asked under.

    Attributes:
        answers: Each host that answered and its answer.
        silent: Each host that did not, and why (what its ``ask`` returned instead).
    """

    answers: dict[Any, Any]
    silent: dict[Any, Any]


def at_once(work: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[work(item) for item in items]``, every call in its own thread at the same time.

    For asking a fleet: one after another, loaded computers took the sum of their answer
    times, and a slow one ate the time the others had. Plain threads, because
    concurrent.futures imports logging, which ``msctl ps`` has no use for.

    Raises:
        Exception: The first exception a call raised, after every call ended.
    """
    import threading

    results: list[Any] = [None] * len(items)
    failures: list[BaseException] = []

    def run(index: int, item: T) -> None:
        try:
            results[index] = work(item)
        except BaseException as exc:  # handed to the caller's thread below
            failures.append(exc)

    threads = [
        threading.Thread(target=run, args=(i, item), daemon=True) for i, item in enumerate(items)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failures:
        raise failures[0]
    return results


def ask_each(
    keys: Iterable[K], ask: Callable[[K], Any], is_silence: Callable[[Any], bool]
) -> Replies:
    """Ask every host at once; sort the results into answers and silences, in asking order.

    Args:
        keys: Each host to ask (a host name, or its supervisor's namespace).
        ask: Asks one host; returns its answer, or what says why it did not answer.
        is_silence: Whether a result of ``ask`` is a silence rather than an answer.
    """
    keys = list(keys)
    answers: dict[Any, Any] = {}
    silent: dict[Any, Any] = {}
    for key, result in zip(keys, at_once(ask, keys), strict=True):
        (silent if is_silence(result) else answers)[key] = result
    return Replies(answers, silent)


def rounds(
    keys: Iterable[K],
    look: Callable[[K], Any],
    settle: Callable[[dict[K, Any]], Collection[K]],
    deadline: float,
    pause: float,
) -> list[K]:
    """Ask the hosts still busy, all at once, round after round, until each is settled.

    Args:
        keys: The hosts to follow.
        look: Asks one host how far it got (its answer, or what it raised as a value).
        settle: Given one round's results, shows them and returns the hosts now settled
            (done, failed or named unreachable): they are not asked again.
        deadline: When to stop asking (a monotonic time); one round is asked at least.
        pause: Seconds between two rounds.

    Returns:
        The hosts still busy at the deadline.
    """
    waiting = list(keys)
    while waiting:  # one round at least, even with the deadline gone by
        results = dict(zip(waiting, at_once(look, waiting), strict=True))
        settled = settle(results)
        waiting = [key for key in waiting if key not in settled]
        if not waiting or time.monotonic() >= deadline:
            break
        time.sleep(pause)
    return waiting


def progress(*columns: Any, bar_width: int | None = 40) -> Any:
    """The one rich view of a fleet's work: a description, a bar, ``columns``, the time.

    ``columns`` are rich text columns (``"{task.completed}/{task.total} healthy"``); the
    view writes to stderr and disappears when done (the command prints its summary).
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from msctl.console import err

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(bar_width=bar_width),
        *(TextColumn(c) if isinstance(c, str) else c for c in columns),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    )
