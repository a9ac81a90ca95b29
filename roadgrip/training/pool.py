"""A pool of training processes: small models train fastest one thread each, several at a time."""

import concurrent.futures as cf
import multiprocessing


def _one_thread():
    import torch

    torch.set_num_threads(1)


def training_pool(workers: int) -> cf.ProcessPoolExecutor:
    """`workers` spawned processes, each holding torch to one thread."""
    return cf.ProcessPoolExecutor(
        max_workers=workers, mp_context=multiprocessing.get_context("spawn"), initializer=_one_thread
    )
