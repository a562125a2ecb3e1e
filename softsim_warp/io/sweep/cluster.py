"""Where a sweep's tasks run: a Dask cluster, local or at ``--scheduler``.

:func:`start_cluster` starts a ``distributed.LocalCluster`` of worker processes (one thread each;
``dask_cuda.LocalCUDACluster``, one worker per GPU, for ``--device cuda`` with several GPUs) or joins
an existing cluster; :func:`run_tasks` submits the tasks and hands each one's rows on as it
finishes. A task whose worker dies is rerun elsewhere by the scheduler.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

from ...core.errors import CommandLineError
from ..warp_init import init_warp
from .store import require


@dataclass
class Cluster:
    client: object
    cluster: object | None
    workers: int
    dashboard: str | None
    address: str
    device: str
    """The device name each task uses (``cuda:0`` on a dask-cuda worker, which sees its own GPU)."""

    def close(self):
        try:
            self.client.close(timeout=10)
        except Exception:  # noqa: BLE001 - closing a lost scheduler's client
            pass
        if self.cluster is not None:
            try:
                self.cluster.close(timeout=10)
            except Exception:  # noqa: BLE001
                pass


SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss")
SCHEDULER_EXPECTED = "expected a scheduler address tcp://HOST:PORT (or tls://, ws://, wss://; tcp:// may be left out)"


def check_scheduler_address(address: str) -> str:
    """``--scheduler``'s address as ``scheme://HOST:PORT``, or a one-line error saying what is wrong.

    The form distributed's ``Client`` connects to: ``[SCHEME://]HOST:PORT``, SCHEME one of
    :data:`SCHEDULER_SCHEMES` (tcp when left out), an IPv6 host in brackets, PORT from 1 to 65535.
    Only the form is checked; whether a scheduler answers there is :func:`start_cluster`'s to find.
    """
    text = str(address).strip()
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    if rest.startswith("["):  # [::1]:8786
        host, close, port = rest[1:].partition("]")
        port = port[1:] if close and port.startswith(":") else None
    else:
        host, colon, port = rest.rpartition(":")
        host, port = (host, port) if colon else (rest, None)
    if not text:
        why = "empty"
    elif scheme.lower() not in SCHEDULER_SCHEMES:
        why = f"unknown scheme '{scheme}'"
    elif "/" in rest or any(c.isspace() for c in rest):
        why = "not HOST:PORT after the scheme"
    elif not host:
        why = "no host"
    elif not port:
        why = "no port"
    elif not (port.isdecimal() and 1 <= int(port) <= 65535):
        why = "the port must be an integer from 1 to 65535"
    else:
        return f"{scheme.lower()}://{rest}"  # distributed knows the schemes in lower case
    raise CommandLineError("--scheduler", f"{why}; {SCHEDULER_EXPECTED}", address)


def default_workers(device: str) -> int:
    if device.startswith("cuda"):
        return 1
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def start_cluster(device: str, workers: int | None = None, scheduler: str | None = None, gpus: int = 0) -> Cluster:
    """A Dask client: on ``scheduler``'s cluster, else on a new local cluster of worker processes.

    Locally, each worker is a process with one thread. ``device == "cuda"`` (every GPU) with several
    GPUs starts ``dask_cuda.LocalCUDACluster``, one worker per GPU, each seeing its GPU as cuda:0.
    """
    import logging  # noqa: PLC0415

    distributed = require("distributed")
    dashboard_ok = _has_bokeh()
    if scheduler:
        scheduler = check_scheduler_address(scheduler)
        try:
            client = distributed.Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as e:
            why = str(e).replace(": ", ", ") or type(e).__name__  # the line keeps its four ': '-separated parts
            raise CommandLineError("--scheduler", f"cannot reach the scheduler ({why})", scheduler) from None
        except ValueError as e:  # an address distributed cannot parse after all
            why = str(e).replace(": ", ", ")  # the line keeps its four ': '-separated parts
            raise CommandLineError("--scheduler", f"{SCHEDULER_EXPECTED} ({why})", scheduler) from None
        n = len(client.scheduler_info().get("workers", {}))
        dashboard = client.dashboard_link if dashboard_ok else None
        task_device = "cuda:0" if device == "cuda" else device
        return Cluster(client, None, n, dashboard, scheduler, task_device)
    # preload: this module's dask_setup runs in each local worker process (Ctrl-C is the client's).
    kwargs = {"threads_per_worker": 1, "dashboard_address": ":0" if dashboard_ok else None,
              "silence_logs": logging.ERROR, "preload": [__name__]}
    if device == "cuda" and gpus > 1:
        try:
            from dask_cuda import LocalCUDACluster  # noqa: PLC0415
        except ImportError:
            raise CommandLineError("--device", f"cuda (every GPU, {gpus} here) needs dask-cuda: pip install dask-cuda; "
                                   "or name one GPU, cuda:N", device) from None
        cluster = LocalCUDACluster(n_workers=workers or gpus, **kwargs)
        task_device = "cuda:0"
    else:
        n = workers or default_workers(device)
        cluster = distributed.LocalCluster(n_workers=n, processes=True, scheduler_port=0, **kwargs)
        task_device = "cuda:0" if device == "cuda" else device
    client = distributed.Client(cluster)
    # Warp starts in every worker now, not in its first task (a start-up cost, not a task's).
    client.run(_start_worker)
    n = len(cluster.workers)
    dashboard = client.dashboard_link if dashboard_ok else None
    return Cluster(client, cluster, n, dashboard, cluster.scheduler_address, task_device)


def _start_worker():
    init_warp()


def dask_setup(worker):
    """Preloaded into each local worker process: a Ctrl-C in the terminal (or the terminal closed:
    SIGHUP) reaches every process of the group, and the client alone handles it (it stops, keeps
    the rows and closes the cluster)."""
    import signal  # noqa: PLC0415

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    except ValueError:  # not the main thread: leave it
        pass


def _has_bokeh() -> bool:
    import importlib.util  # noqa: PLC0415

    return importlib.util.find_spec("bokeh") is not None


@dataclass
class Outcome:
    done: int = 0
    failed: int = 0
    lost: list = field(default_factory=list)  # variant ids whose task was lost or raised (no rows)
    errors: list = field(default_factory=list)  # what those tasks raised
    interrupted: bool = False
    scheduler_lost: str | None = None


def run_tasks(cluster: Cluster, fn, specs: list[dict], on_rows, stop_requested=None, progress=None) -> Outcome:
    """Submit ``fn(spec)`` for each spec and hand each finished task's rows to ``on_rows`` as they come.

    A task whose worker died is rerun by the scheduler (up to its ``allowed-failures``); one it gave
    up on, or one that raised outside a variant (a device missing on that worker, say), is reported
    in ``Outcome.lost`` and ``errors`` and gives no rows, so ``--resume`` runs it again: only a
    variant's own failure is a row. Stops early, cancelling what is still queued, when
    ``stop_requested()`` says so or the scheduler is lost.
    """
    distributed = require("distributed")
    client = cluster.client
    outcome = Outcome()
    futures = {}
    # Set when the sweep stops: a running task reads it between chunks of a long frame and ends
    # (stop_check), so its worker is free and the cluster closes at once.
    stop_event = f"softsim-stop-{os.getpid()}-{time.time_ns()}"
    for spec in specs:
        spec = {**spec, "stop_event": stop_event}
        f = client.submit(fn, spec, key=f"softsim-{spec['task']}-{os.getpid()}-{time.time_ns()}", pure=False)
        futures[f.key] = (f, spec)
    pending = {f for f, _ in futures.values()}
    ac = distributed.as_completed(list(pending))
    try:
        while pending:
            if stop_requested is not None and stop_requested():
                outcome.interrupted = True
                try:
                    distributed.Event(stop_event, client=client).set()
                except Exception:  # noqa: BLE001 - a lost scheduler: its tasks are gone anyway
                    pass
                break
            if not ac.has_ready():
                if ac.is_empty():
                    break
                time.sleep(0.05)
                continue
            for f in ac.next_batch(block=False):
                pending.discard(f)
                _, spec = futures.pop(f.key)  # the result is released once read
                ids = [v["id"] for v in spec["variants"]]
                if f.status == "finished":
                    rows = f.result()
                    on_rows(rows)
                    outcome.done += len(rows)
                    outcome.failed += sum(r["status"] == "failed" for r in rows)
                elif f.status == "error":
                    exc = f.exception()
                    outcome.lost += ids
                    outcome.errors.append(f"{type(exc).__name__}: {exc}".strip())
                else:  # cancelled or lost: the scheduler went away
                    outcome.lost += ids
                    outcome.scheduler_lost = f"task {spec['task']} was {f.status}"
                if progress is not None:
                    progress.update(len(ids))
            if outcome.scheduler_lost:
                break
    except (OSError, TimeoutError) as e:  # the connection to the scheduler broke
        outcome.scheduler_lost = str(e) or type(e).__name__
    finally:
        if pending:
            try:
                client.cancel(list(pending), force=True)
            except Exception:  # noqa: BLE001 - a lost scheduler cannot cancel
                pass
    return outcome
