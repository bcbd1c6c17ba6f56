"""Where scene tasks run: in this process, a local process pool, or Ray. Same function, same bytes."""

from __future__ import annotations

import multiprocessing
import queue
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Iterable, Iterator

from nuplan_occ.pipeline.runner import EventSink, SceneResult, run_scene
from nuplan_occ.pipeline.scene import SceneTask


class ExecutorError(RuntimeError):
    """The executor could not be started (e.g. Ray not installed or the cluster unreachable)."""


def _run_with_queue(task: SceneTask, pipeline: list, events_queue) -> SceneResult:
    return run_scene(task, pipeline, events_queue.put if events_queue is not None else None)


def run_local(tasks: list[SceneTask], pipeline: list, workers: int, events: EventSink) -> Iterator[SceneResult]:
    """Yield results as scenes finish, each built by `pipeline`'s stages; workers == 1 runs in this process."""
    if workers <= 1:
        for task in tasks:
            yield run_scene(task, pipeline, events)
        return
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager, ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        events_queue = manager.Queue()
        pending = {pool.submit(_run_with_queue, task, pipeline, events_queue) for task in tasks}
        while pending:
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            _drain(events_queue, events)
            for future in done:
                yield future.result()
        _drain(events_queue, events)


def _drain(events_queue, events: EventSink) -> None:
    while True:
        try:
            events(events_queue.get_nowait())
        except queue.Empty:
            return


def run_ray(tasks: list[SceneTask], pipeline: list, workers: int, address: str | None,
            events: EventSink) -> Iterator[SceneResult]:
    """Yield results as scenes finish on Ray: an existing cluster at `address`, else a local Ray with
    `workers` CPUs. One task per scene, one CPU each; only completion events reach the progress bar."""
    try:
        import ray
    except ImportError as exc:
        raise ExecutorError("--executor ray needs Ray: pip install 'nuplan-occ[ray]'") from exc
    started_here = not ray.is_initialized()
    if started_here:
        init = {"address": address} if address else {"num_cpus": max(1, workers), "include_dashboard": False}
        ray.init(log_to_driver=False, configure_logging=False, **init)
    try:
        remote = ray.remote(num_cpus=1, max_retries=2)(run_scene)
        pending = {remote.remote(task, pipeline): task for task in tasks}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                task = pending.pop(ref)
                result = ray.get(ref)
                events((task.log_name, task.scene_name, "done"))
                yield result
    finally:
        if started_here:
            ray.shutdown()


def execute(tasks: list[SceneTask], pipeline: list, executor: str, workers: int, ray_address: str | None,
            events: EventSink) -> Iterable[SceneResult]:
    """Build every task with `pipeline`'s stages on the named executor ("local" or "ray")."""
    if executor == "local":
        return run_local(tasks, pipeline, workers, events)
    if executor == "ray":
        return run_ray(tasks, pipeline, workers, ray_address, events)
    raise ExecutorError(f"unknown executor {executor!r} (choose local or ray)")
