"""The operations routes: public liveness (``/health``), readiness in detail and Prometheus ``/metrics`` for admins and the
operator token."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from ..accounts.caller import require_operator
from ..schemas import HealthDetailOut, HealthOut
from .health import HealthMonitor
from .metrics import CONTENT_TYPE_LATEST, Metrics

router = APIRouter(tags=["operations"])


async def _metrics(request: Request) -> Metrics:  # async: resolving it takes no thread of the shared pool
    return request.app.state.metrics


async def _monitor(request: Request) -> HealthMonitor:
    return request.app.state.health


#: A route's ``recorded: MetricsDep``: this API process's metrics (``create_app`` holds them).
MetricsDep = Annotated[Metrics, Depends(_metrics)]
#: A route's ``monitor: MonitorDep``: the health monitor (``create_app`` holds it).
MonitorDep = Annotated[HealthMonitor, Depends(_monitor)]


@router.get("/health", tags=["operations"], response_model=HealthOut, responses={503: {"model": HealthOut}})
async def health(monitor: MonitorDep):
    """Public liveness: ``ok``, ``degraded`` (no evaluation worker alive: submissions would wait) or ``error``
    (503: the database cannot be read). Nothing else: host names, process ids and queue counts are in
    ``/health/detail`` for admins and the monitoring token."""
    status, body = await _health(monitor)
    return JSONResponse({"status": body["status"]}, status_code=status)


@router.get(
    "/health/detail",
    tags=["operations"],
    response_model=HealthDetailOut,
    response_model_exclude_unset=True,
    responses={503: {"model": HealthDetailOut}},
)
async def health_detail(request: Request, monitor: MonitorDep):
    """Readiness in detail (an admin's token or session, or the operator token): database, queue counts, live
    workers. Answered on the event loop from the state a background thread reads every 0.25 s (``age_ms`` old;
    ``db_ms``: how long that read took), so that a probe never waits behind the database while uploads are copied
    in; a killed worker on this host drops out at once."""
    await run_in_threadpool(require_operator, request)
    status, body = await _health(monitor)
    return JSONResponse(body, status_code=status)


@router.get(
    "/metrics",
    tags=["operations"],
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
)
def metrics(request: Request, recorded: MetricsDep):
    """Prometheus metrics (admins and the operator token): request latency of this API process, queue depth and
    oldest job age, worker liveness, scoring time."""
    require_operator(request)
    return Response(recorded.render(), media_type=CONTENT_TYPE_LATEST)


async def _health(monitor: HealthMonitor) -> tuple[int, dict]:
    snap = monitor.current()
    if snap is None:
        snap = await run_in_threadpool(monitor.refresh)
    return monitor.answer(snap)
