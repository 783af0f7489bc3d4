"""The operations routes: public liveness (``/health``), readiness in detail and Prometheus ``/metrics`` for admins and the
operator token."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from ..accounts.caller import require_operator
from ..schemas import HealthDetailOut, HealthOut
from .metrics import CONTENT_TYPE_LATEST

router = APIRouter(tags=["operations"])


@router.get("/health", tags=["operations"], response_model=HealthOut, responses={503: {"model": HealthOut}})
async def health(request: Request):
    """Public liveness: ``ok``, ``degraded`` (no evaluation worker alive: submissions would wait) or ``error``
    (503: the database cannot be read). Nothing else: host names, process ids and queue counts are in
    ``/health/detail`` for admins and the monitoring token."""
    status, body = await _health(request)
    return JSONResponse({"status": body["status"]}, status_code=status)


@router.get(
    "/health/detail",
    tags=["operations"],
    response_model=HealthDetailOut,
    response_model_exclude_unset=True,
    responses={503: {"model": HealthDetailOut}},
)
async def health_detail(request: Request):
    """Readiness in detail (an admin's token or session, or the operator token): database, queue counts, live
    workers. Answered on the event loop from the state a background thread reads every 0.25 s (``age_ms`` old;
    ``db_ms``: how long that read took), so that a probe never waits behind the database while uploads are copied
    in; a killed worker on this host drops out at once."""
    await run_in_threadpool(require_operator, request)
    status, body = await _health(request)
    return JSONResponse(body, status_code=status)


@router.get(
    "/metrics",
    tags=["operations"],
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
)
def metrics(request: Request):
    """Prometheus metrics (admins and the operator token): request latency of this API process, queue depth and
    oldest job age, worker liveness, scoring time."""
    require_operator(request)
    return Response(request.app.state.metrics.render(), media_type=CONTENT_TYPE_LATEST)


async def _health(request: Request) -> tuple[int, dict]:
    monitor = request.app.state.health
    snap = monitor.current()
    if snap is None:
        snap = await run_in_threadpool(monitor.refresh)
    return monitor.answer(snap)
