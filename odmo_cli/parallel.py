"""CPU threads: torch's intra-op thread count for a block, and independent jobs side by side.

Small recurrent networks (ODMO's decoder, the classifier's GRU) use two cores poorly from inside
one operation; independent jobs (one evaluation set each) use them fully. `parallel_map` runs
such jobs on `workers` Python threads with torch at one thread each: torch and numpy release the
GIL inside their kernels, and a kernel's result does not depend on the thread count here (checked:
the same motions, logits and features at 1 and 2 threads), so the numbers are those of a serial run.
"""

from __future__ import annotations

import contextlib
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

import torch

T = TypeVar("T")
R = TypeVar("R")


@contextlib.contextmanager
def thread_count(threads: int) -> Iterator[None]:
    """torch's intra-op threads set to `threads` (0: unchanged) inside the block, restored after."""
    old = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def default_workers(limit: int = 4) -> int:
    """As many workers as torch would use threads (the cores), at most `limit` (memory: each job
    holds a set of motions)."""
    return max(1, min(torch.get_num_threads(), os.cpu_count() or 1, limit))


def parallel_map(fn: Callable[[T], R], items: Iterable[T], workers: int) -> Iterator[R]:
    """fn over items on `workers` threads (torch at one thread each); results in the items' order."""
    items = list(items)
    if workers <= 1 or len(items) <= 1:
        yield from map(fn, items)
        return
    with thread_count(1), ThreadPoolExecutor(workers) as pool:
        yield from pool.map(fn, items)
