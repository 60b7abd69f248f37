"""Liveness and readiness for load balancers, orchestrators and the container HEALTHCHECK.

``/healthz`` (liveness): the process answers and its kernels are warm; it reads
one flag, so it answers however busy or cut off the server is. Restart a server
only on this one.

``/readyz`` (readiness): besides the kernels, the catalogue and the store can be
used now. A balancer routes on it: a server whose database or object store is
down answers 503 here, as every mesh route then would, and gets no traffic until
they are back. Restarting it would not help.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from functools import partial

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from ..deps import JobsDep

router = APIRouter(tags=["health"])
log = logging.getLogger(__name__)

# A dependency that has not answered a probe within this many seconds counts as down.
PROBE_SECONDS = 2.0
# An answer is reused this long, so that any number of balancers polling cost at
# most one probe of each dependency per period.
FRESH_SECONDS = 1.5
_NO_STORE = {"Cache-Control": "no-store"}


class Readiness:
    """Whether the catalogue and the store can be used, probed cheaply and rarely.

    Parameters
    ----------
    probes : {name: callable(timeout=seconds)}
        One call per dependency that raises when it cannot be used (``ping`` of
        the catalogue and of the blob store); ``name`` goes into the message.
        Its own timeouts are given twice the deadline: the deadline answers
        first, and the probe's thread still ends soon after.

    Each probe runs in a daemon thread of its own (never on the event loop,
    never queued behind the requests' threads, never holding up the process's
    exit), at most one per dependency at a time: a probe still running from an
    earlier check, because its dependency hangs, is waited for again rather
    than started twice. Requests arriving together share one round.
    """

    def __init__(self, probes: dict[str, Callable[..., None]], *,
                 deadline: float = PROBE_SECONDS, fresh: float = FRESH_SECONDS):
        self._probes = {name: partial(probe, timeout=2 * deadline)
                        for name, probe in probes.items()}
        self._deadline, self._fresh = deadline, fresh
        self._running: dict[str, asyncio.Future] = {}
        self._answer: tuple[float, str | None] | None = None
        self._round = asyncio.Lock()

    async def problem(self) -> str | None:
        """None when every dependency answered, else one sentence naming the first
        that did not (no URL, host or path: the details go to the log)."""
        if (answer := self._fresh_answer()) is not None:
            return answer[1]
        async with self._round:
            if (answer := self._fresh_answer()) is not None:
                return answer[1]
            problem = await self._probe_all()
            self._answer = (time.monotonic(), problem)
            return problem

    def _fresh_answer(self):
        if self._answer is not None and time.monotonic() - self._answer[0] < self._fresh:
            return self._answer
        return None

    async def _probe_all(self) -> str | None:
        for name, probe in self._probes.items():
            running = self._running.get(name)
            if running is None or running.done():
                self._running[name] = _in_thread(name, probe)
        futures = dict(self._running)
        done, _ = await asyncio.wait(futures.values(), timeout=self._deadline)
        problems = []
        for name, future in futures.items():
            if future not in done:
                problems.append((f"the {name} did not answer within {self._deadline:g} s", ""))
            elif (error := future.exception()) is not None:
                problems.append((f"the {name} cannot be used right now", f": {error}"))
        problem = problems[0][0] if problems else None
        before = self._answer[1] if self._answer is not None else None
        if problem != before:       # the log says when the answer changes, not every time
            if problems:
                log.warning("not ready: %s", "; ".join(reason + detail
                                                       for reason, detail in problems))
            else:
                log.warning("ready again: the %s answer", " and the ".join(self._probes))
        return problem



def _in_thread(name: str, probe: Callable[[], None]) -> asyncio.Future:
    """A future of the running loop settled by ``probe()`` run in a daemon thread."""
    loop = asyncio.get_running_loop()
    future = loop.create_future()

    def settle(error: BaseException | None) -> None:
        if not future.done():
            if error is None:
                future.set_result(None)
            else:
                future.set_exception(error)

    def run() -> None:
        try:
            probe()
            error = None
        except Exception as exc:     # noqa: BLE001 (any failure means "not ready")
            error = exc
        try:
            loop.call_soon_threadsafe(settle, error)
        except RuntimeError:         # the loop closed meanwhile: nobody is waiting
            pass

    threading.Thread(target=run, name=f"lodserver-readiness-{name}", daemon=True).start()
    return future


@router.get("/healthz", responses={503: {"description": "Up, but the kernels are still "
                                         "warming: do not route builds here yet."}})
async def healthz(jobs: JobsDep) -> JSONResponse:
    """``{"status": "ok", "ready": true}`` once the numba kernels are warm
    (``LODSERVER_WARM_KERNELS``), else 503 with ``"ready": false``.

    It reads one flag on the event loop, no store or disk, so it answers at
    once however busy the server is (a worker thread could be all taken).
    """
    ready = jobs.ready.is_set()
    return JSONResponse({"status": "ok", "ready": ready}, status_code=200 if ready else 503)


@router.get("/readyz", responses={503: {"description": "The kernels are still warming, or "
                                        "the catalogue or the store cannot be used: route "
                                        "no requests here; the message says which."}})
async def readyz(request: Request, jobs: JobsDep) -> JSONResponse:
    """``{"status": "ok", "ready": true}`` when the kernels are warm and the
    catalogue and the store answered a probe within ``PROBE_SECONDS``; else 503
    with ``"ready": false`` and a one-sentence ``message``.

    A probe's answer is reused for ``FRESH_SECONDS``, and the probes run in
    threads of their own, so polling it costs nothing and it answers within
    ``PROBE_SECONDS`` however the dependencies fail.
    """
    if not jobs.ready.is_set():
        problem = "the numba kernels are still loading"
    else:
        problem = await request.app.state.readiness.problem()
    if problem is None:
        return JSONResponse({"status": "ok", "ready": True}, headers=_NO_STORE)
    return JSONResponse({"status": "unavailable", "ready": False, "message": problem},
                        status_code=503, headers=_NO_STORE)
